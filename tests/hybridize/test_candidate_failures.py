"""One candidate that fails does not sink the run: the others are chosen among as usual, and the
report and the console name the failure with its reason. When no candidate can be built, the run
ends with an error that gives the reasons and points to the report it kept.

The data: the DC drive's windage truth (examples/dc_drive), whose fitted term the choice takes;
the failures are made on purpose by replacing a candidate's builder.
"""
import json

import pytest

from fmubuilder import synth
from fmubuilder.build import example_fmu
from fmubuilder.errors import FmuBuilderError
from fmubuilder.hybridize import hybridize, workflow
from fmubuilder.cli.hybridize import summary

BENCH = dict(signals=("speed", "current", "power", "temperature"),
             noise_std={"speed": 0.1, "current": 0.02, "power": 1.0, "temperature": 0.02})
TRUTH = "dc_drive_truth_windage"
BROKEN = "the network could not be built on purpose"


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    folder = tmp_path_factory.mktemp("failures_data")

    def measure(window, seed):
        settings = synth.BenchSettings(seed=seed, **BENCH)
        measurement = synth.measure(example_fmu(TRUTH), start_time=window[0], stop_time=window[1],
                                    settings=settings)
        return synth.write_measurement(measurement, folder / f"{seed}.csv")
    return measure((0.0, 10.0), 0), measure((20.5, 26.0), 1)


def fail(*args, **kwargs):
    raise RuntimeError(BROKEN)


def run(files, folder):
    return hybridize(example_fmu("dc_drive"), *files, folder / "hybrid.fmu", folder / "report", budget=1,
                     ann_on_term=False, progress=False, jobs=1)


def test_a_failing_candidate_is_reported_and_the_others_are_chosen_among(files, tmp_path, monkeypatch):
    monkeypatch.setattr(workflow, "_neural_candidate", fail)
    result = run(files, tmp_path)
    assert result.hybrid_fmu is not None and result.hybrid_fmu.is_file()
    assert result.report["chosen"] == "fitted term"
    assert result.report["selection"]["failed"] == {"neural": f"RuntimeError: {BROKEN}"}
    assert "neural" not in [m["name"] for m in result.report["models"]]
    markdown = (result.report_dir / "report.md").read_text()
    assert f"Failed: neural; RuntimeError: {BROKEN}." in markdown
    assert f"failed: neural; RuntimeError: {BROKEN}" in summary(result)


def test_when_no_candidate_can_be_built_the_error_gives_the_reasons_and_keeps_the_report(files, tmp_path,
                                                                                          monkeypatch):
    for builder in ("_neural_candidate", "_term_candidate", "_calibrated_candidates"):
        monkeypatch.setattr(workflow, builder, fail)
    with pytest.raises(FmuBuilderError) as error:
        run(files, tmp_path)
    message = str(error.value)
    assert "no candidate could be built" in message
    for name in ("fitted term", "neural", "calibrated"):
        assert f"{name}: RuntimeError: {BROKEN}" in message
    report = tmp_path / "report" / "report.md"
    assert str(report) in message and report.is_file()
    assert "no candidate could be built" in report.read_text()
    assert json.loads((tmp_path / "report" / "report.json").read_text())["selection"]["failed"].keys() == \
        {"fitted term", "neural", "calibrated"}
    assert not (tmp_path / "hybrid.fmu").exists()


def test_a_hybrid_that_fails_its_round_trip_is_not_published(files, tmp_path, monkeypatch):
    checked = workflow._roundtrip

    def failed_round_trip(chosen, test):
        return {**checked(chosen, test), "passed": False}
    monkeypatch.setattr(workflow, "_roundtrip", failed_round_trip)
    monkeypatch.setattr(workflow, "_neural_candidate", fail)        # not needed here: saves its training
    with pytest.raises(FmuBuilderError, match="the chosen fitted term hybrid failed its round trip") as error:
        run(files, tmp_path)
    report = tmp_path / "report" / "report.md"
    assert str(report) in str(error.value)
    assert not (tmp_path / "hybrid.fmu").exists()
    markdown = report.read_text()
    assert "**Shipped: nothing**: the chosen fitted term hybrid failed its round trip" in markdown
    assert "(FAILED: not published)" in markdown
    assert json.loads((tmp_path / "report" / "report.json").read_text())["hybrid_fmu"] is None


def test_an_effect_no_term_form_traced_still_gets_its_neural_fmu(files, tmp_path, monkeypatch):
    """"No formula fits" is where the network is needed most: a significant effect that the trace did
    not pin to one derivative gets the NeuralFMU's search over the derivatives, and the run completes."""
    import fmubuilder.diagnose as diagnose_package
    diagnose = diagnose_package.diagnose

    def untraced(*args, **kwargs):
        diagnosis = diagnose(*args, **kwargs)
        diagnosis.channel, diagnosis.inputs, diagnosis.fitted_term = None, [], None
        return diagnosis
    monkeypatch.setattr(diagnose_package, "diagnose", untraced)
    result = run(files, tmp_path)
    report = json.loads((tmp_path / "report" / "report.json").read_text())
    neural = next(m for m in report["models"] if m["name"] == "neural")
    assert neural["channels"]
    assert "fitted term" not in [m["name"] for m in report["models"]]
    assert "No term form traced" in (tmp_path / "report" / "report.md").read_text()
    assert result.report_dir == tmp_path / "report"


def test_a_builder_keeps_its_own_keyword_arguments():
    """The ANN on the fitted term is built by a function that takes a `name` of its own."""
    from types import SimpleNamespace
    context = SimpleNamespace(failed={}, say=lambda line: None)
    assert workflow._isolated(context, "ANN on the term", lambda name: name, name="inner") == "inner"
    assert workflow._isolated(context, "ANN on the term", fail, name="inner") is None
    assert context.failed == {"ANN on the term": f"RuntimeError: {BROKEN}"}
