"""--force only overwrites, only a report folder fmubuilder made, and the old outputs stay until the
new ones are complete; --allow-insignificant (not --force) builds a hybrid without a significant effect."""
import pytest

from fmubuilder.build import example_fmu
from fmubuilder.errors import FmuBuilderError
from fmubuilder.files import MANIFEST_NAME, write_manifest
from fmubuilder.hybridize import hybridize, report as report_module

from .test_hybridize import assert_one_line_error, measure, run_cli

OLD_FMU, OLD_REPORT = b"the old hybrid", "# the old report\n"


@pytest.fixture(scope="module")
def no_effect(tmp_path_factory):
    """The DC drive measured against its own model: nothing significant (short windows: fast)."""
    folder = tmp_path_factory.mktemp("no_effect")
    return measure(folder, "dc_drive", (0.0, 6.0), 0), measure(folder, "dc_drive", (20.5, 24.0), 1)


@pytest.fixture
def old_results(tmp_path):
    fmu, report = tmp_path / "h.fmu", tmp_path / "report"
    fmu.write_bytes(OLD_FMU)
    report.mkdir()
    (report / "report.md").write_text(OLD_REPORT)
    write_manifest(report)      # an earlier run's report: fmubuilder made it
    return fmu, report


def assert_untouched(fmu, report):
    assert fmu.read_bytes() == OLD_FMU
    assert sorted(p.name for p in report.iterdir()) == [MANIFEST_NAME, "report.md"]
    assert (report / "report.md").read_text() == OLD_REPORT
    leftovers = [p.name for p in report.parent.iterdir() if p.name.startswith(".")]
    assert leftovers == [], leftovers


def test_force_keeps_the_old_results_when_the_data_are_bad(no_effect, old_results, tmp_path):
    fmu, report = old_results
    bad = tmp_path / "bad.csv"
    bad.write_text("time,speed\n0,1\n0.1,not a number\n")
    proc = run_cli(example_fmu("dc_drive"), "--train", bad, "--test", no_effect[1], "-o", fmu, "--report", report,
                   "--force")
    assert_one_line_error(proc, "bad.csv")
    assert_untouched(fmu, report)


def test_force_keeps_the_old_results_when_the_run_fails_late(no_effect, old_results, monkeypatch):
    """The run fails while writing its report, after the diagnosis and the scoring."""
    fmu, report = old_results

    def failing(folder, **kwargs):
        (folder / "report.json").write_text("{half")
        raise FmuBuilderError("disk full")
    monkeypatch.setattr(report_module, "write_report", failing)
    with pytest.raises(FmuBuilderError, match="disk full"):
        hybridize(example_fmu("dc_drive"), no_effect[0], no_effect[1], fmu, report, force=True, progress=False)
    assert_untouched(fmu, report)


def test_force_replaces_the_report_when_the_run_succeeds(no_effect, old_results):
    fmu, report = old_results
    result = hybridize(example_fmu("dc_drive"), no_effect[0], no_effect[1], fmu, report, force=True, progress=False)
    assert result.report_dir == report and not result.report["diagnosis"]["significant"]
    assert "No significant effect" in (report / "report.md").read_text()
    assert (report / "report.json").is_file()
    assert [p.name for p in report.parent.iterdir() if p.name.startswith(".")] == []


def test_force_refuses_a_report_folder_fmubuilder_did_not_make(no_effect, old_results):
    fmu, report = old_results
    (report / "thesis.txt").write_text("years of work")
    with pytest.raises(FmuBuilderError, match="thesis.txt"):
        hybridize(example_fmu("dc_drive"), no_effect[0], no_effect[1], fmu, report, force=True, progress=False)
    assert (report / "thesis.txt").read_text() == "years of work" and fmu.read_bytes() == OLD_FMU
    assert [p.name for p in report.parent.iterdir() if p.name.startswith(".")] == []


def test_allow_insignificant_builds_candidates_that_force_does_not(no_effect, tmp_path):
    train, test = no_effect
    plain = hybridize(example_fmu("dc_drive"), train, test, tmp_path / "a.fmu", tmp_path / "a", force=True,
                      progress=False)
    assert not plain.report["diagnosis"]["significant"] and plain.report["models"] == []
    allowed = hybridize(example_fmu("dc_drive"), train, test, tmp_path / "b.fmu", tmp_path / "b", budget=1,
                        allow_insignificant=True, ann_on_term=False, progress=False)
    report = allowed.report
    assert not report["diagnosis"]["significant"]           # still said plainly
    assert report["models"] and "neural" in {m["name"] for m in report["models"]}
    assert report["diagnosis"]["channel"] is not None
    # published only when a candidate beats the plain FMU on the validation data
    assert (allowed.hybrid_fmu is not None) == (report["chosen"] is not None)


def test_the_cli_has_separate_flags():
    from fmubuilder.cli import parse
    args = parse(["hybridize", "m.fmu", "--train", "t.csv", "--test", "s.csv", "-o", "h.fmu", "--report", "r",
                  "--force"])
    assert args.force and not args.allow_insignificant
    args = parse(["hybridize", "m.fmu", "--train", "t.csv", "--test", "s.csv", "-o", "h.fmu", "--report", "r",
                  "--allow-insignificant"])
    assert args.allow_insignificant and not args.force
