"""The fitted term's coefficient refined through the simulation (fmubuilder/hybridize/refine_term.py).

The truths are known: the data come from the DC drive's truth variants, whose missing term and
coefficient are read from their C definition (examples_zoo.dc_drive_truth_term: windage
-WINDAGE / inertia * speed*|speed| in der(speed)). The refinement starts from a term 30 % off and
must land within 2 % of the truth; started at its own optimum it must stay there, and it never
returns a term with a higher training error than the one it was given.
"""
import math

import numpy as np
import pytest

from fmubuilder import synth
from fmubuilder.build import example_fmu
from fmubuilder.examples_zoo import dc_drive_truth_term
from fmubuilder.export import export_hybrid
from fmubuilder.fmi import read_model_info
from fmubuilder.hybridize.evaluate import Scoring, evaluate, read_data
from fmubuilder.hybridize.refine_term import (MAX_SIMULATIONS, refine_scales, scaled_term, term_gates)
from fmubuilder.hybridize.terms import spec_from_fitted_term

NOISE = {"speed": 0.1, "current": 0.02, "power": 1.0, "energy": 1.0, "temperature": 0.02}
SPAN = 12.0     # s: start-up, load steps and the slow-down; 120 samples


@pytest.fixture(scope="module")
def windage_data(tmp_path_factory):
    settings = synth.BenchSettings(seed=5, signals=tuple(NOISE), noise_std=NOISE)
    measurement = synth.measure(example_fmu("dc_drive_truth_windage"), stop_time=SPAN, settings=settings)
    path = tmp_path_factory.mktemp("fitted_term") / "windage.csv"
    synth.write_measurement(measurement, path)
    data = read_data(path, read_model_info(example_fmu("dc_drive")))
    # the generator's noise level of the logged mean of its runs: the residuals' weights
    noise = {name: level / math.sqrt(settings.runs) for name, level in NOISE.items()}
    return data, noise


def start_30_percent_off(truth: dict) -> dict:
    term = {"variable": truth["variable"], "basis": truth["basis"], "center": 0.0,
            "coefficient": 1.3 * truth["coefficient"]}
    return {"channel": truth["channel"], "terms": [term]}


def hybrid_of(fitted: dict, folder):
    """The exported hybrid of a fitted term and its gates."""
    fmu = example_fmu("dc_drive")
    spec = spec_from_fitted_term(scaled_term(fitted, 1.0), fmu, read_model_info(fmu).guid, folder)
    return export_hybrid(spec, folder / "hybrid.fmu"), term_gates(spec)


def objective(hybrid, gates, data, noise, scale):
    """Mean squared residual in noise units, computed here from one simulation of the hybrid."""
    run = evaluate(hybrid, data, {**data.start_values, **{g: scale for g in gates}}, Scoring.accurate(0.001))
    residual = np.concatenate([(run.predicted[s] - data.signals[s]) / noise[s] for s in data.names])
    return float(residual @ residual) / residual.size


def test_the_windage_coefficient_is_recovered_from_a_start_30_percent_off(windage_data, tmp_path):
    data, noise = windage_data
    truth = dc_drive_truth_term("windage")
    fitted = start_30_percent_off(truth)
    hybrid, gates = hybrid_of(fitted, tmp_path)
    assert gates == ["hybrid.speed.p_term"]
    refinement = refine_scales(hybrid, gates, [(data, data.start_values)], noise, 0.001, show=False)
    refined = scaled_term(fitted, refinement.scales[0])["terms"][0]["coefficient"]
    assert refinement.kept
    assert refined == pytest.approx(truth["coefficient"], rel=0.02)
    assert refinement.simulations <= MAX_SIMULATIONS
    # the objective it reports is the one a separate simulation gives, and far below the start's
    assert refinement.objective_after == pytest.approx(objective(hybrid, gates, data, noise, refinement.scales[0]),
                                                       rel=1e-6)
    assert refinement.objective_after < 0.01 * refinement.objective_before


def test_a_term_at_its_optimum_stays_there_and_is_never_worse(windage_data, tmp_path):
    """Refined twice: the second start is already the best scale the data allow (noise only is
    left), so the second refinement keeps it within 0.1 % and does not raise the training error."""
    data, noise = windage_data
    truth = dc_drive_truth_term("windage")
    fitted = start_30_percent_off(truth)
    (tmp_path / "first").mkdir()
    (tmp_path / "second").mkdir()
    first_hybrid, gates = hybrid_of(fitted, tmp_path / "first")
    first = refine_scales(first_hybrid, gates, [(data, data.start_values)], noise, 0.001, show=False)
    second_hybrid, gates = hybrid_of(scaled_term(fitted, first.scales[0]), tmp_path / "second")
    second = refine_scales(second_hybrid, gates, [(data, data.start_values)], noise, 0.001, show=False)
    assert second.scales[0] == pytest.approx(1.0, abs=1e-3)
    assert second.objective_after <= second.objective_before
    assert second.objective_before == pytest.approx(objective(second_hybrid, gates, data, noise, 1.0), rel=1e-6)
    assert second.objective_after == pytest.approx(first.objective_after, rel=1e-3)


def test_a_refinement_without_a_better_point_returns_the_term_unchanged(windage_data, tmp_path):
    """A budget that leaves no room for a step (the unrefined run and one finite difference): the
    term comes back as it was, scale 1, with its own training error."""
    data, noise = windage_data
    truth = dc_drive_truth_term("windage")
    fitted = start_30_percent_off(truth)
    hybrid, gates = hybrid_of(fitted, tmp_path)
    refinement = refine_scales(hybrid, gates, [(data, data.start_values)], noise, 0.001, budget=2, show=False)
    assert not refinement.kept and refinement.scales == [1.0]
    assert refinement.objective_after == refinement.objective_before
