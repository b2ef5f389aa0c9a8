"""`demo --force` keeps the previous demo folder until the new run has succeeded."""
import pytest

from fmubuilder import examples_zoo
from fmubuilder.demo import run_demo
from fmubuilder.errors import FmuBuilderError
from fmubuilder.hybridize import workflow


@pytest.fixture
def previous(tmp_path):
    folder = tmp_path / "demo"
    (folder / "report").mkdir(parents=True)
    (folder / "report" / "report.md").write_text("previous")
    return folder


@pytest.fixture
def quick_example(monkeypatch):
    """The example's files stand in for the real ones: this checks the folder handling only."""
    def write_example(name, output, force=False):
        output.mkdir(parents=True)
        (output / "vldm.fmu").write_bytes(b"new")
    monkeypatch.setattr(examples_zoo, "write_example", write_example)


def test_a_failed_run_puts_the_previous_demo_back(previous, quick_example, monkeypatch):
    def failing(*args, **kwargs):
        raise FmuBuilderError("the new run failed")
    monkeypatch.setattr(workflow, "hybridize", failing)
    with pytest.raises(FmuBuilderError, match="the new run failed"):
        run_demo(previous, force=True)
    assert (previous / "report" / "report.md").read_text() == "previous"
    assert not (previous / "example").exists()
    assert sorted(p.name for p in previous.parent.iterdir()) == ["demo"]


def test_a_successful_run_replaces_the_previous_demo(previous, quick_example, monkeypatch):
    seen = {}

    def succeeding(model, train, test, output, report, **kwargs):
        seen["previous during the run"] = any(previous.parent.glob("demo.previous-*/demo/report/report.md"))
        report.mkdir()
        (report / "report.md").write_text("new")
        return "result"
    monkeypatch.setattr(workflow, "hybridize", succeeding)
    result, example = run_demo(previous, force=True)
    assert result == "result" and example == previous / "example"
    assert seen["previous during the run"]          # set aside, not deleted, while the new run works
    assert (previous / "report" / "report.md").read_text() == "new"
    assert sorted(p.name for p in previous.parent.iterdir()) == ["demo"]


def test_without_force_an_existing_demo_is_an_error(previous):
    with pytest.raises(FmuBuilderError, match="--force"):
        run_demo(previous)
    assert (previous / "report" / "report.md").read_text() == "previous"


def test_demo_force_replaces_only_a_folder_an_earlier_demo_wrote(tmp_path, monkeypatch, capsys):
    """The command line marks the demo folder (its manifest) when the run succeeds; --force replaces
    such a folder and refuses one that holds anything else, before any work."""
    from fmubuilder import cli, demo
    from fmubuilder.cli import demo as demo_command
    runs = []

    def quick_demo(output, force=False, time_budget=None):
        runs.append(output)
        (output / "report").mkdir(parents=True, exist_ok=True)
        (output / "report" / "report.md").write_text(f"run {len(runs)}")
        return "result", output / "example"
    monkeypatch.setattr(demo, "run_demo", quick_demo)
    monkeypatch.setattr(demo_command, "summary", lambda result: "summary")
    folder = tmp_path / "demo"
    assert cli.run(["demo", "-o", str(folder)]) == 0
    assert cli.run(["demo", "-o", str(folder), "--force"]) == 0 and len(runs) == 2
    (folder / "thesis.txt").write_text("years of work")
    capsys.readouterr()
    assert cli.run(["demo", "-o", str(folder), "--force"]) == 1 and len(runs) == 2
    assert "thesis.txt" in capsys.readouterr().err
    assert (folder / "thesis.txt").read_text() == "years of work"


# The command line with quick stand-ins: argv[1] the demo folder, argv[2] "first" (a quick run) or
# "terminated" (a run with --force that waits until it is terminated).
STAND_IN = '''
import sys, time
from fmubuilder import cli, examples_zoo
from fmubuilder.cli import demo as demo_command
from fmubuilder.hybridize import workflow

def write_example(name, output, force=False):
    output.mkdir(parents=True)
    (output / "vldm.fmu").write_bytes(b"new")

def hybridize(model, train, test, output, report, **kwargs):
    report.mkdir()
    (report / "report.md").write_text(sys.argv[2])
    if sys.argv[2] == "terminated":
        print("working", flush=True)
        time.sleep(600)
    return "result"

examples_zoo.write_example, workflow.hybridize = write_example, hybridize
demo_command.summary = lambda result: "summary"
sys.exit(cli.main(["demo", "-o", sys.argv[1], *(["--force"] if sys.argv[2] == "terminated" else [])]))
'''


def test_a_terminated_demo_force_puts_the_previous_demo_back(tmp_path):
    import signal
    import subprocess
    import sys
    script, folder = tmp_path / "stand_in.py", tmp_path / "demo"
    script.write_text(STAND_IN)
    assert subprocess.run([sys.executable, str(script), str(folder), "first"], capture_output=True).returncode == 0
    run = subprocess.Popen([sys.executable, str(script), str(folder), "terminated"], stdout=subprocess.PIPE,
                           stderr=subprocess.PIPE, text=True)
    for line in run.stdout:
        if line.strip() == "working":
            break
    run.send_signal(signal.SIGTERM)
    _, stderr = run.communicate(timeout=60)
    assert run.returncode == 143 and len(stderr.strip().splitlines()) == 1, stderr
    assert (folder / "report" / "report.md").read_text() == "first"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["demo", "stand_in.py"]
