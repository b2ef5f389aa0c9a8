"""`fmubuilder hybridize` end to end: diagnose, add the effect, export, validate, report.

The DC drive (examples/dc_drive/model.c) runs one hard-coded set-point/load profile and has no
parameter or input to choose another, so the test data are a different time window of that
profile (20.5-30 s: a start from rest and a run up to 200 rad/s, beyond the 150 rad/s of the
training window 0-15 s) logged with a different noise seed. The truth of each variant is known
from the C source: windage enters der(speed) and depends on speed; the extra heating enters
der(temperature) and depends on the current.

The last 20 % of the training window is held out of the fit and chooses the candidate; the test
window is scored once, after the choice. The test errors are checked twice: in the report
(fmubuilder's engine) and independently, by simulating the plain and the hybrid FMU with fmpy and
applying the bench's sensor lag here.
"""
import json
import subprocess
import sys

import numpy as np
import pytest
from fmpy import simulate_fmu
from fmpy.validation import validate_fmu

from fmubuilder import synth
from fmubuilder.build import example_fmu
from fmubuilder.data import read_sidecar
from fmubuilder.examples_zoo import dc_drive_truth_term
from fmubuilder.hybridize import hybridize
from fmubuilder.cli.hybridize import summary

BENCH = dict(signals=("speed", "current", "power", "temperature"),
             noise_std={"speed": 0.1, "current": 0.02, "power": 1.0, "temperature": 0.02})
TRAIN_WINDOW, TRAIN_SEED = (0.0, 15.0), 0
TEST_WINDOW, TEST_SEED = (20.5, 30.0), 1

# truth -> (channel, leading input, measured signals the effect changes beyond the noise)
EFFECTS = {
    "dc_drive_truth_windage": ("der(speed)", "speed", ("current", "power", "temperature")),
    "dc_drive_truth_extra_heating": ("der(temperature)", "current", ("temperature",)),
}
ERROR_KEYS = {"mse", "max_abs", "final"}


def measure(folder, truth, window, seed, start_values=None, bench=BENCH):
    settings = synth.BenchSettings(seed=seed, **bench)
    measurement = synth.measure(example_fmu(truth), start_time=window[0], stop_time=window[1],
                                start_values=start_values, settings=settings)
    label = "_".join(f"{k}{v}" for k, v in (start_values or {}).items())
    path = folder / f"{truth}_{window[0]:g}-{window[1]:g}_{seed}{label}.csv"
    synth.write_measurement(measurement, path)
    return path


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    folder = tmp_path_factory.mktemp("hybridize_data")
    return {truth: (measure(folder, truth, TRAIN_WINDOW, TRAIN_SEED), measure(folder, truth, TEST_WINDOW, TEST_SEED))
            for truth in ("dc_drive", *EFFECTS)}


# NeuralFMU loss evaluations of the hybridize runs here: a fifth of the default's work (one L-BFGS
# step, as 3 take). The checks hold for any budget (the ANN on the term keeps its best validation
# epoch, the term included).
BUDGET = 2


@pytest.fixture(scope="module")
def runs(data, tmp_path_factory):
    """hybridize() on each data set, run once per module on first use."""
    done = {}

    def run(truth):
        if truth not in done:
            folder = tmp_path_factory.mktemp(truth)
            train, test = data[truth]
            done[truth] = hybridize(example_fmu("dc_drive"), train, test, folder / "hybrid.fmu", folder / "report",
                                    budget=BUDGET, progress=False)       # the default candidates
        return done[truth]
    return run


# ---------------------------------------------------------------------------------------
# an independent check of the test errors: fmpy plus the bench's sensor lag


def lagged(time, values, lag):
    """First-order sensor filter lag * y' = u - y, settled at the start, exact for u linear
    between samples (repeated time stamps of events: no time passes)."""
    y = np.empty_like(values)
    y[0] = values[0]
    for k in range(len(time) - 1):
        h = time[k + 1] - time[k]
        if h <= 0:
            y[k + 1] = y[k]
            continue
        slope = (values[k + 1] - values[k]) / h
        decay = np.exp(-h / lag)
        y[k + 1] = values[k + 1] - lag * slope + (y[k] - values[k] + lag * slope) * decay
    return y


def fmpy_mse(fmu, data_csv, signals):
    """MSE of the FMU simulated by fmpy (CVode) against the measured data, per signal."""
    meta = read_sidecar(data_csv)
    measured = np.genfromtxt(data_csv, delimiter=",", names=True)
    result = simulate_fmu(str(fmu), start_time=meta["start_time"], stop_time=meta["stop_time"],
                          start_values=meta["start_values"], relative_tolerance=1e-8, output_interval=0.005,
                          output=list(signals))
    lag = meta["bench"]["lag"]
    errors = {}
    for name in signals:
        model = np.interp(measured["time"], result["time"], lagged(result["time"], result[name], lag))
        errors[name] = float(np.mean((model - measured[name]) ** 2))
    return errors


# ---------------------------------------------------------------------------------------
# an undeclared effect: found, learned, exported


@pytest.mark.parametrize("truth", list(EFFECTS))
def test_the_report_names_the_channel_and_leading_input(runs, truth):
    channel, leading, _ = EFFECTS[truth]
    diagnosis = runs(truth).report["diagnosis"]
    assert diagnosis["significant"]
    assert diagnosis["channel"] == channel
    assert diagnosis["inputs"][0] == leading
    assert diagnosis["candidates"][0]["channel"] == channel


@pytest.mark.parametrize("truth", list(EFFECTS))
def test_the_test_error_of_the_affected_signals_drops_tenfold(runs, data, truth):
    _, _, affected = EFFECTS[truth]
    result = runs(truth)
    errors = result.report["errors"]["test"]
    for signal in affected:
        assert errors["before"][signal]["mse"] >= 10 * errors["after"][signal]["mse"], signal
    # the same with fmpy and a sensor lag applied here
    test_csv = data[truth][1]
    before = fmpy_mse(example_fmu("dc_drive"), test_csv, affected)
    after = fmpy_mse(result.hybrid_fmu, test_csv, affected)
    for signal in affected:
        assert before[signal] >= 10 * after[signal], (signal, before[signal], after[signal])
        assert after[signal] == pytest.approx(errors["after"][signal]["mse"], rel=0.5), signal


@pytest.mark.parametrize("truth", list(EFFECTS))
def test_the_fitted_term_is_refined_to_the_truth(runs, truth):
    """The term's form is the truth's, and its coefficient, refined through the simulation on the
    training data, is within 2 % of the one in the variant's C definition. (Over the training window
    the current hardly changes sign, so current*|current| is the truth's current^2 there.)"""
    report = runs(truth).report
    model = next(m for m in report["models"] if m["name"] == "fitted term")
    expected = dc_drive_truth_term(truth.removeprefix("dc_drive_truth_"))
    term, = model["fitted_term"]["terms"]
    twins = {"w^2": {"w^2", "w*|w|"}, "w*|w|": {"w*|w|"}}      # the odd form of an own state is exact
    assert term["variable"] == expected["variable"] and term["basis"] in twins[expected["basis"]]
    assert term["coefficient"] == pytest.approx(expected["coefficient"], rel=0.02)
    refinement = model["refinement"]
    assert refinement["objective_after"] <= refinement["objective_before"]
    assert model["description"] == model["fitted_term"]["expression"]
    assert "coefficient refined through the simulation" in (runs(truth).report_dir / "report.md").read_text() \
        or not refinement["kept"]


def test_the_ann_on_the_fitted_term_is_a_default_candidate_no_worse_than_the_term(runs):
    """A default candidate whenever a term is offered that leaves more than the noise (the extra
    heating's term over this short run: 18 times the noise on the validation data): it starts as the
    fitted term and keeps its best validation epoch, the start included, by the training's measure
    (mean MSE / MSE plain), scored like the others (the exported FMUs, fmubuilder's engine); the
    choice takes it only when it beats the term by the noise margin on the choice's own score."""
    report = runs("dc_drive_truth_extra_heating").report
    selection = report["selection"]
    scores = selection["scores"]
    assert "neural on the fitted term" in scores and not selection["not_trained"]
    relative = selection["relative_to_plain"]
    assert relative["neural on the fitted term"] <= relative["fitted term"] * (1 + 1e-6)
    if report["chosen"] == "neural on the fitted term":
        assert scores["neural on the fitted term"] * selection["margin"] < scores["fitted term"]


def test_no_ann_is_trained_on_a_term_at_the_noise_floor(runs, data):
    """The windage's term holds the truth's effect: at the noise floor on the validation data, an ANN on
    it has nothing left to learn and is not trained; the report says why. That the term left nothing
    above the noise is checked on the test data, which decided nothing, against the truth FMU: fmpy
    gives the published hybrid the truth's own MSE on every signal (the noise)."""
    truth = "dc_drive_truth_windage"
    result = runs(truth)
    selection = result.report["selection"]
    assert "neural on the fitted term" not in selection["scores"]
    why = selection["not_trained"]["neural on the fitted term"]
    assert f"scores {selection['scores']['fitted term']:.3g} on the validation data" in why
    assert f"Not trained: neural on the fitted term; {why}." in (result.report_dir / "report.md").read_text()
    assert f"  not trained: neural on the fitted term; {why}" in summary(result)
    assert result.report["chosen"] == "fitted term"
    test_csv = data[truth][1]
    signals = BENCH["signals"]
    truth_mse, hybrid_mse = fmpy_mse(example_fmu(truth), test_csv, signals), fmpy_mse(result.hybrid_fmu, test_csv, signals)
    for signal in signals:
        assert hybrid_mse[signal] <= 1.1 * truth_mse[signal], (signal, hybrid_mse[signal], truth_mse[signal])


@pytest.mark.parametrize("truth", list(EFFECTS))
def test_the_hybrid_fmu_is_written_and_valid(runs, truth):
    result = runs(truth)
    assert result.hybrid_fmu is not None and result.hybrid_fmu.is_file()
    assert validate_fmu(str(result.hybrid_fmu)) == []
    report = result.report
    assert report["hybrid_fmu"] == str(result.hybrid_fmu)
    assert report["chosen"] in {m["name"] for m in report["models"]}
    assert report["roundtrip"]["passed"]
    assert report["roundtrip"]["max_rel_error"] < 1e-6


@pytest.mark.parametrize("truth", list(EFFECTS))
def test_report_json_and_markdown(runs, truth):
    result = runs(truth)
    on_disk = json.loads((result.report_dir / "report.json").read_text())
    assert on_disk["hybrid_fmu"] == result.report["hybrid_fmu"]
    diagnosis = on_disk["diagnosis"]
    assert {"significant", "channel", "inputs", "candidates"} <= set(diagnosis)
    assert all({"channel", "inputs", "score"} <= set(c) for c in diagnosis["candidates"])
    for part in ("train", "test"):
        for when in ("before", "after"):
            errors = on_disk["errors"][part][when]
            assert set(errors) == set(BENCH["signals"])
            for values in errors.values():
                assert set(values) == ERROR_KEYS and all(np.isfinite(v) for v in values.values())
    assert isinstance(on_disk["roundtrip"]["max_rel_error"], float)
    markdown = (result.report_dir / "report.md").read_text()
    # one table per role, a row per signal with its unit
    assert markdown.count("| signal | RMS FMU | RMS hybrid | factor |") == 3
    for signal in BENCH["signals"]:
        assert markdown.count(f"| `{signal}` [") == 3, signal
    for plot in on_disk["plots"]:
        assert (result.report_dir / plot).read_bytes().startswith(b"\x89PNG")


def test_a_calibration_worse_on_validation_is_not_chosen(runs):
    """Windage is a missing speed-squared term: a higher viscous friction explains part of it and is
    offered, but the fitted term (or the ANN started from it, which ends at its best validation
    epoch, the term included) is better on the validation data and is chosen."""
    report = runs("dc_drive_truth_windage").report
    scores = report["selection"]["scores"]
    calibrated = [name for name in scores if name.startswith("calibrated ")]
    assert "calibrated viscous_friction" in calibrated
    assert report["chosen"] in ("fitted term", "neural on the fitted term")
    assert all(scores[name] > scores["fitted term"] for name in calibrated)


# ---------------------------------------------------------------------------------------
# the control: the declared model's own data


def test_no_effect_no_hybrid(runs):
    result = runs("dc_drive")
    report = result.report
    assert not report["diagnosis"]["significant"]
    assert result.hybrid_fmu is None and report["hybrid_fmu"] is None
    assert not (result.report_dir.parent / "hybrid.fmu").exists()
    assert report["models"] == [] and report["chosen"] is None
    for part in ("train", "test"):
        assert report["errors"][part]["after"] == report["errors"][part]["before"]
    markdown = (result.report_dir / "report.md").read_text()
    assert "No significant effect" in markdown and "No hybrid FMU was written" in markdown
    assert summary(result).startswith("no hybrid FMU written: no significant effect")


@pytest.mark.parametrize("noise", [dict(noise_model="ar1", noise_rho=0.7),
                                   dict(noise_model="lowpass", noise_filter_tau=0.3, noise_filter_order=2)])
def test_no_effect_in_coloured_noise_no_hybrid(noise, tmp_path):
    """Sensor noise correlated from sample to sample is not an effect: nothing is published."""
    bench = dict(BENCH, **noise)
    train = measure(tmp_path, "dc_drive", TRAIN_WINDOW, 5, bench=bench)
    test = measure(tmp_path, "dc_drive", TEST_WINDOW, 6, bench=bench)
    result = hybridize(example_fmu("dc_drive"), train, test, tmp_path / "hybrid.fmu", tmp_path / "report",
                       progress=False)
    assert not result.report["diagnosis"]["significant"], result.report["diagnosis"]
    assert result.hybrid_fmu is None and not (tmp_path / "hybrid.fmu").exists()
    assert result.report["models"] == []


# ---------------------------------------------------------------------------------------
# VLDM: the first 30 s of the training cycle (CADC road) and of the test cycle (WLTC class 2)


@pytest.mark.slow
def test_vldm_extra_resistance_on_short_windows(tmp_path):
    """A separate validation run (the training cycle logged again, other noise): the diagnosis and
    the fit see the whole training window (about a minute). Without the ANN on the fitted term
    (half of this test's time): the DC drive's runs above check it, and the README's hybridize
    snippet (tests/test_readme.py) builds it on the VLDM."""
    bench = dict(signals=("speed", "power", "energy"))
    train = measure(tmp_path, "vldm_truth_extra_resistance", (0.0, 30.0), 0, {"cycle": 1}, bench)
    validation = measure(tmp_path, "vldm_truth_extra_resistance", (0.0, 30.0), 2, {"cycle": 1}, bench)
    test = measure(tmp_path, "vldm_truth_extra_resistance", (0.0, 30.0), 1, {"cycle": 2}, bench)
    result = hybridize(example_fmu("vldm"), train, test, tmp_path / "hybrid.fmu", tmp_path / "report",
                       validation_csv=validation, budget=BUDGET, ann_on_term=False, progress=False)
    report = result.report
    diagnosis = report["diagnosis"]
    assert diagnosis["significant"] and diagnosis["channel"] == "der(speed)"
    assert diagnosis["inputs"][0] == "speed"
    assert diagnosis["fitted_term"]["terms"][0]["coefficient"] < 0      # a resistance slows the car
    names = {m["name"] for m in report["models"]}
    plain = {"fitted term", "neural"}
    assert plain <= names and all(n.startswith("calibrated ") for n in names - plain)
    assert report["data"]["validation"] == [validation.name] and report["data"]["train"] == [train.name]
    assert validate_fmu(str(result.hybrid_fmu)) == [] and report["roundtrip"]["passed"]
    # the driver holds the speed on the cycle; the energy shows the effect
    errors = report["errors"]
    assert errors["train"]["before"]["energy"]["mse"] >= 10 * errors["train"]["after"]["energy"]["mse"]
    assert errors["test"]["before"]["energy"]["mse"] >= 2 * errors["test"]["after"]["energy"]["mse"]
    before = fmpy_mse(example_fmu("vldm"), test, ["energy"])["energy"]
    after = fmpy_mse(result.hybrid_fmu, test, ["energy"])["energy"]
    assert before >= 2 * after


# ---------------------------------------------------------------------------------------
# command line: one-line errors


def run_cli(*args):
    return subprocess.run([sys.executable, "-m", "fmubuilder.cli", "hybridize", *map(str, args)],
                          capture_output=True, text=True, timeout=300)


def assert_one_line_error(proc, *fragments):
    assert proc.returncode != 0
    assert "Traceback" not in proc.stderr
    lines = [line for line in proc.stderr.strip().splitlines() if line.strip()]
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith("error: ")
    for fragment in fragments:
        assert fragment in lines[0], lines[0]


def test_cli_missing_data_file(data, tmp_path):
    missing = tmp_path / "nothing.csv"
    proc = run_cli(example_fmu("dc_drive"), "--train", missing, "--test", data["dc_drive"][1],
                   "-o", tmp_path / "h.fmu", "--report", tmp_path / "r")
    assert_one_line_error(proc, "nothing.csv")
    assert not (tmp_path / "h.fmu").exists()


def test_cli_unknown_signal_name(data, tmp_path):
    bad = tmp_path / "bad.csv"
    bad.write_text("time,sped\n" + "".join(f"{0.1 * k:.1f},{k}\n" for k in range(50)))
    proc = run_cli(example_fmu("dc_drive"), "--train", data["dc_drive"][0], "--test", bad,
                   "-o", tmp_path / "h.fmu", "--report", tmp_path / "r")
    assert_one_line_error(proc, "bad.csv", "sped")


def test_cli_existing_output_needs_force(data, tmp_path):
    existing = tmp_path / "h.fmu"
    existing.write_bytes(b"keep me")
    proc = run_cli(example_fmu("dc_drive"), "--train", data["dc_drive"][0], "--test", data["dc_drive"][1],
                   "-o", existing, "--report", tmp_path / "r")
    assert_one_line_error(proc, "--force")
    assert existing.read_bytes() == b"keep me"


def test_cli_the_ann_on_the_fitted_term_is_on_unless_switched_off():
    from fmubuilder.cli import build_parser
    base = ["hybridize", "m.fmu", "--train", "a.csv", "--test", "b.csv", "-o", "h.fmu", "--report", "r"]
    assert build_parser().parse_args(base).ann_on_term is True
    assert build_parser().parse_args([*base, "--no-ann-on-term"]).ann_on_term is False
