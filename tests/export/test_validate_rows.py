"""The round trip's rows can fail: a row left with no samples says "not compared" and does not
pass, and the cross-solver row compares the samples between events, also when a sampled
controller puts a time event on every output point (the VLDM's driver at 100 Hz)."""
import numpy as np
import pytest

from fmubuilder.build import example_fmu
from fmubuilder.export import export_hybrid, validate_hybrid
from fmubuilder.export.validate import Comparison, ValidationReport, _away_from_events, _compare, _Run
from fmubuilder.fmi import read_model_info
from fmubuilder.hybridize.terms import spec_from_fitted_term

STOP = 20.0    # s of the CADC cycle: the car starts moving after a few seconds


def run_with_an_event_at_every_sample(offset=0.0):
    time = np.linspace(0.0, 1.0, 11)
    return _Run(time, {"x": time + offset}, events=[(t, "time") for t in time])


def test_a_row_with_every_sample_at_an_event_is_not_compared_and_does_not_pass():
    row = _compare("cross-solver", 1e-6, lambda: run_with_an_event_at_every_sample(1.0),
                   lambda: run_with_an_event_at_every_sample(), ["x"], event_window=0.025)
    assert row.samples == 0 and not row.compared and not row.passed
    assert row.verdict.startswith("not compared")
    report = ValidationReport(hybrid_fmu="h.fmu", fmpy_problems=[], comparisons=[row])
    assert not report.passed
    assert "not compared" in report.format_table()


def test_the_same_runs_away_from_events_show_their_difference():
    row = _compare("cross-solver", 1e-6, lambda: run_with_an_event_at_every_sample(1.0),
                   lambda: run_with_an_event_at_every_sample(), ["x"])
    assert row.samples == 11 and row.compared and not row.passed
    assert row.signals[0].max_abs == pytest.approx(1.0)


def test_only_samples_near_an_event_are_dropped():
    time = np.arange(0.0, 0.1 + 1e-12, 0.005)       # half the output interval of 0.01 s
    events = np.arange(0.0, 0.1 + 1e-12, 0.01)      # a time event at every output point
    keep = _away_from_events(time, events, 0.25 * 0.01)
    np.testing.assert_array_equal(keep, np.arange(time.size) % 2 == 1)


def test_an_empty_comparison_is_not_a_pass():
    assert not Comparison("nothing", 1.0).passed


@pytest.fixture(scope="module")
def vldm_hybrid(tmp_path_factory):
    """The VLDM with a fitted driving resistance -0.002 * speed in der(speed)."""
    folder = tmp_path_factory.mktemp("vldm_term")
    fmu = example_fmu("vldm")
    fitted = {"channel": "der(speed)", "terms": [{"variable": "speed", "basis": "w", "center": 0.0,
                                                   "coefficient": -0.002}]}
    spec = spec_from_fitted_term(fitted, fmu, read_model_info(fmu).guid, folder)
    return export_hybrid(spec, folder / "hybrid.fmu"), folder / "spec.json"


def test_vldm_cross_solver_row_compares_samples_between_the_drivers_events(vldm_hybrid):
    """The driver's time event every 10 ms sits on every output point; the old row dropped every
    sample and printed 0 'passed'. Now half the samples (the midpoints) are compared and show the
    solvers' real difference."""
    fmu, spec = vldm_hybrid
    report = validate_hybrid(fmu, spec=spec, start_values={"cycle": 1}, stop_time=STOP)
    row = report.comparison("fmpy CVode")
    assert row.compared, report.format_table()
    assert row.samples >= 0.45 * (STOP / 0.01)
    speed = next(s for s in row.signals if s.name == "speed")
    assert speed.max_abs > 0.0, report.format_table()
    # The export rows compare the same arithmetic on both sides: exact up to round-off.
    exact = [c for c in report.comparisons if not c.label.startswith("fmpy CVode")]
    assert all(c.passed for c in exact), report.format_table()


def test_cross_solver_tolerance_grows_with_the_restarts():
    """Every event restarts both adaptive solvers; their difference walks with sqrt(events)."""
    from fmubuilder.export.validate import ADAPTIVE_TOLERANCE_FACTOR, cross_solver_tolerance
    assert cross_solver_tolerance(1e-10, 0) == pytest.approx(ADAPTIVE_TOLERANCE_FACTOR * 1e-10)
    assert cross_solver_tolerance(1e-10, 6000) / cross_solver_tolerance(1e-10, 60) == pytest.approx(10.0)


def test_fmpy_runs_leave_no_extracted_fmu_whether_they_return_or_fail(tmp_path, monkeypatch):
    """fmpy.simulate_fmu removes its extraction only after a run that returns; the round trip's
    fmpy runs extract into a folder of their own, removed however the run ends."""
    import tempfile

    import fmpy
    from fmpy.fmi1 import FMICallException

    from fmubuilder.export.validate import simulate_with_fmpy
    temp = tmp_path / "tmp"
    temp.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(temp))
    fmu = example_fmu("vldm")
    options = dict(stop_time=2.0, solver="Euler", step_size=0.01, output=["speed", "energy"])
    ours = simulate_with_fmpy(fmu, **options)
    assert list(temp.iterdir()) == []
    reference = fmpy.simulate_fmu(str(fmu), **options)     # fmpy's own extraction, removed on return
    assert np.array_equal(ours["time"], reference["time"])
    assert np.array_equal(ours["energy"], reference["energy"]) and np.array_equal(ours["speed"], reference["speed"])
    with pytest.raises(FMICallException):
        simulate_with_fmpy(fmu, stop_time=1.0, start_values={"cycle": 0})     # no such cycle: refused
    assert list(temp.iterdir()) == []
