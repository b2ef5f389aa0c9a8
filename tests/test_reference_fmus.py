"""The Modelica Reference FMUs (written by others) through every stage: inspect, the engine against
fmpy's CVode, training a NeuralFMU on data with a known added effect, export, validation, and fmpy's
CVode on the hybrid. Run as a script (`python tests/test_reference_fmus.py`) it prints the table of
stages per FMU. Skips visibly when the FMUs are not found (see tests/reference_fmus.py)."""
from __future__ import annotations

import sys
import tempfile
import zipfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

if __name__ == "__main__":
    sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from tests.reference_fmus import NOT_FOUND, reference_dir  # noqa: E402

STAGES = ("inspect", "simulate vs fmpy CVode", "train", "export", "validate", "fmpy CVode on the hybrid")


@dataclass(frozen=True)
class Case:
    """How to train on one Reference FMU: the channel corrected, the ANN's inputs, the span."""
    target: str
    inputs: tuple[str, ...]
    stop: float
    step: float
    element: float


CASES = {
    "Dahlquist": Case("der(x)", ("x",), 4.0, 0.02, 1.0),
    "VanDerPol": Case("der(x1)", ("x0", "x1"), 3.0, 0.01, 1.0),
    "BouncingBall": Case("der(v)", ("v",), 2.0, 0.005, 1.0),
}


def model_exchange_fmus() -> list[Path]:
    folder = reference_dir()
    if folder is None:
        return []
    found = []
    for path in sorted(folder.glob("*.fmu")):
        with zipfile.ZipFile(path) as archive:
            names = archive.namelist()
            xml = archive.read("modelDescription.xml").decode(errors="replace")
        if "<ModelExchange" in xml and any(n.startswith("binaries/linux64/") and n.endswith(".so") for n in names):
            found.append(path)
    return found


FMUS = model_exchange_fmus()


class NotApplicable(Exception):
    """A stage that does not apply to this FMU (the reason is the message)."""


# -- the stages ---------------------------------------------------------------------------------

def stage_inspect(fmu: Path) -> None:
    from fmubuilder.fmi import read_model_info
    from fmubuilder.inspect_fmu import describe
    import fmpy
    text = describe(fmu)
    info = read_model_info(fmu)
    reference = fmpy.read_model_description(str(fmu), validate=False)
    assert info.n_states == len(reference.derivatives)
    assert info.n_event_indicators == reference.numberOfEventIndicators
    for variable in reference.modelVariables:
        assert variable.name in text


def stage_simulate(fmu: Path) -> None:
    """Engine (DOPRI5) against fmpy's CVode on the default experiment, every numeric output."""
    import fmpy
    from fmubuilder.simulation import simulate
    ours = simulate(fmu, rtol=1e-9, atol=1e-10)
    names = [n for n in ours.names if n != "time"]
    theirs = fmpy.simulate_fmu(str(fmu), fmi_type="ModelExchange", solver="CVode", relative_tolerance=1e-9,
                               output_interval=float(ours.time[1] - ours.time[0]), output=names)
    assert names
    time, values = ours.time, {n: ours[n] for n in names}
    if ours.terminated_early:
        # the model's last event ends the run: the engine records its row after that event,
        # fmpy the row before it; compare the samples before it
        time, values = time[:-1], {n: v[:-1] for n, v in values.items()}
    compare(time, values, theirs, 1e-5)


def compare(time, ours: dict, theirs, tolerance: float) -> None:
    """Each signal against fmpy's at the same output times: fmpy's last row at a time (after an
    event, as the engine records it); samples next to a jump are left out (the solvers place a
    state event a little differently), integers and booleans must agree exactly."""
    span = min(time[-1], theirs["time"][-1])
    keep = time <= span
    time = time[keep]
    row = np.searchsorted(theirs["time"], time + 1e-9 * max(abs(span), 1.0), side="right") - 1
    for name, values in ours.items():
        mine = np.asarray(values)[keep]
        other = np.asarray(theirs[name])[row]
        if not np.issubdtype(mine.dtype, np.floating):
            assert np.array_equal(mine, other.astype(mine.dtype)), name
            continue
        away = np.ones(time.size, dtype=bool)
        for j in np.flatnonzero(np.abs(np.diff(mine)) > 0.2 * (np.ptp(mine) + 1e-300)):
            away[max(j - 1, 0): j + 3] = False
        scale = max(np.max(np.abs(other[away])), 1.0)
        error = np.max(np.abs(mine[away] - other[away]))
        assert error <= tolerance * scale, f"{name}: differs by {error:.3g} (tolerance {tolerance * scale:.3g})"


def make_data(fmu: Path, case: Case, folder: Path):
    """Data from the FMU itself plus a known effect: a residual NeuralFMU with fixed random weights
    (the 'truth', simulated by the engine), every state measured."""
    import torch
    from fmubuilder.data import MeasuredData
    from fmubuilder.neural import NeuralFMU, TopologyConfig
    from fmubuilder.neural.system import simulate_hybrid
    torch.manual_seed(1)
    config = TopologyConfig(channels=[case.target], inputs=list(case.inputs), hidden=[4], kind="residual")
    with NeuralFMU(fmu, config) as truth:
        with torch.no_grad():
            for parameter in truth.topology.ann.parameters():
                parameter.normal_(0.0, 0.4)
        states = truth.state_names()
        result = simulate_hybrid(truth, start_time=0.0, stop_time=case.stop, variables=states, solver="rk4",
                                 step_size=case.step / 4, output_interval=case.step)
    return MeasuredData(result.time, {s: np.asarray(result[s], dtype=float) for s in states}, source=f"{fmu.stem} truth")


def stage_train(fmu: Path, folder: Path):
    from fmubuilder.fmi import read_model_info
    from fmubuilder.neural.train import train_neural_fmu
    if read_model_info(fmu).n_states == 0:
        raise NotApplicable("no continuous state to correct")
    case = CASES.get(fmu.stem)
    if case is None:
        raise NotApplicable("no training case written for this FMU")
    data = make_data(fmu, case, folder)
    result = train_neural_fmu(fmu, data, targets=[case.target], inputs=list(case.inputs), hidden=[8], epochs=4,
                              element_length=case.element, step_size=case.step, learning_rate=1e-2,
                              progress=False, output=folder / "trained.neuralfmu")
    losses = [h["loss"] for h in result.history]
    assert len(losses) == 4 and min(losses[1:]) < losses[0], losses
    errors = result.metrics["errors"]
    mse = {s: (errors["before"][s]["mse"], errors["after"][s]["mse"]) for s in data.signals}
    assert sum(after for _, after in mse.values()) < sum(before for before, _ in mse.values()), mse
    return result.model, case, losses


def stage_export(model, folder: Path) -> Path:
    from fmubuilder.export import export_hybrid
    from fmubuilder.hybridize.terms import spec_from_neural
    return export_hybrid(spec_from_neural(model, folder), folder / "hybrid.fmu")


def stage_validate(hybrid: Path, case: Case) -> None:
    from fmubuilder.export import validate_hybrid
    report = validate_hybrid(hybrid, stop_time=case.stop, step_size=case.step)
    assert report.passed and report.comparisons, report.format_table()


def stage_fmpy_cvode(hybrid: Path, model, case: Case) -> None:
    """fmpy's CVode on the hybrid against the engine's DOPRI5 on the trained NeuralFMU."""
    import fmpy
    from fmubuilder.neural.system import simulate_hybrid
    states = model.state_names()
    theirs = fmpy.simulate_fmu(str(hybrid), fmi_type="ModelExchange", solver="CVode", relative_tolerance=1e-9,
                               stop_time=case.stop, output_interval=case.step, output=states)
    ours = simulate_hybrid(model, start_time=0.0, stop_time=case.stop, variables=states, solver="dopri5",
                           rtol=1e-10, output_interval=case.step)
    compare(ours.time, {name: ours[name] for name in states}, theirs, 1e-4)
    plain = fmpy.simulate_fmu(str(model.fmu_path), fmi_type="ModelExchange", solver="CVode", relative_tolerance=1e-9,
                              stop_time=case.stop, output_interval=case.step, output=states)
    with pytest.raises(AssertionError):   # the comparison sees the trained correction
        compare(ours.time, {name: ours[name] for name in states}, plain, 1e-3)


def run_all(fmu: Path, folder: Path) -> dict[str, str]:
    """Every stage on one FMU: {stage: "ok" | "n/a: reason" | "FAILED: reason"} (script mode)."""
    row = {}

    def attempt(stage, function, *args):
        try:
            value = function(*args)
            row[stage] = "ok"
            return value
        except NotApplicable as reason:
            row[stage] = f"n/a: {reason}"
        except Exception as exc:  # noqa: BLE001 - the table reports it
            row[stage] = f"FAILED: {type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}"
        return None

    attempt("inspect", stage_inspect, fmu)
    attempt("simulate vs fmpy CVode", stage_simulate, fmu)
    trained = attempt("train", stage_train, fmu, folder)
    later = STAGES[3:]
    if trained is None:
        reason = row["train"] if row["train"].startswith("n/a") else "n/a: training failed"
        row.update({stage: reason for stage in later})
        return row
    model, case, losses = trained
    row["train"] = f"ok (epoch loss {losses[0]:.3g} -> {min(losses):.3g})"
    try:
        hybrid = attempt("export", stage_export, model, folder)
        if hybrid is None:
            row.update({stage: "n/a: export failed" for stage in later[1:]})
            return row
        attempt("validate", stage_validate, hybrid, case)
        attempt("fmpy CVode on the hybrid", stage_fmpy_cvode, hybrid, model, case)
    finally:
        model.close()
    return row


# -- the tests ----------------------------------------------------------------------------------

def _ids(paths):
    return [p.stem for p in paths]


needs_fmus = pytest.mark.skipif(not FMUS, reason=NOT_FOUND)


@needs_fmus
@pytest.mark.parametrize("fmu", FMUS, ids=_ids(FMUS))
def test_inspect(fmu):
    stage_inspect(fmu)


@needs_fmus
@pytest.mark.parametrize("fmu", FMUS, ids=_ids(FMUS))
def test_engine_agrees_with_fmpy_cvode(fmu):
    stage_simulate(fmu)


@needs_fmus
@pytest.mark.parametrize("fmu", FMUS, ids=_ids(FMUS))
def test_train_export_validate_and_cvode_on_the_hybrid(fmu, tmp_path):
    try:
        model, case, _ = stage_train(fmu, tmp_path)
    except NotApplicable as reason:
        pytest.skip(f"{fmu.stem}: {reason}")
    try:
        hybrid = stage_export(model, tmp_path)
        stage_validate(hybrid, case)
        stage_fmpy_cvode(hybrid, model, case)
    finally:
        model.close()


def test_the_reference_fmus_are_found_or_the_skip_says_why():
    if not FMUS:
        pytest.skip(NOT_FOUND)
    assert {p.stem for p in FMUS} >= set(CASES)


def _table(rows: dict[str, dict[str, str]]) -> str:
    lines = ["| FMU | " + " | ".join(STAGES) + " |", "|---" * (len(STAGES) + 1) + "|"]
    for name, row in rows.items():
        lines.append(f"| {name} | " + " | ".join(row[s] for s in STAGES) + " |")
    return "\n".join(lines)


if __name__ == "__main__":
    if not FMUS:
        sys.exit(f"error: {NOT_FOUND}")
    rows = {}
    for path in FMUS:
        with tempfile.TemporaryDirectory() as scratch:
            rows[path.stem] = run_all(path, Path(scratch))
    print(_table(rows))
