"""`fmubuilder batch`: the cases of a manifest, each run as `hybridize` runs it, in a process of its
own, locally or as Ray tasks; a summary; a crash that stays the crashing case's; resumable.

Three small cases (tiny budgets, short windows of the DC drive's profile, as tests/hybridize uses):
- "no-effect": the DC drive measured against its own model; nothing to find;
- "windage": its windage truth, whose term enters der(speed) (examples/dc_drive);
- "crash": the bouncing ball with a binary that segfaults in fmi2GetDerivatives at t = 0.5
  (tests/fmi/crashing).
The references are independent of the batch: the truths' C sources, a direct `hybridize()` call on
a case's files, and each case's report.json read against the summary's columns.
"""
import csv
import json
import math
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from fmubuilder.batch import read_manifest
from fmubuilder.build import example_fmu
from fmubuilder.errors import FmuBuilderError
from fmubuilder.hybridize import hybridize
from tests.fmi.crash_fmus import crash_fmus
from tests.hybridize.test_hybridize import measure

CASES = ("no-effect", "windage", "crash")
OPTIONS = dict(budget=0, ann_on_term=False)     # no NeuralFMU training: seconds per case

MANIFEST = """\
[defaults]
budget = 0
ann_on_term = false

[[case]]
name = "no-effect"
model = "data/dc_drive.fmu"
train = "data/plain_train.csv"
test = "data/plain_test.csv"
seed = 3

[[case]]
name = "windage"
model = "data/dc_drive.fmu"
train = ["data/windage_train.csv"]
test = "data/windage_test.csv"

[[case]]
name = "crash"
model = "data/segfault.fmu"
train = ["data/ball.csv"]
train_start = { h = 1.0 }
test = "data/ball_test.csv"
"""
# the no-effect case, then one whose FMU never returns from fmi2GetDerivatives at t = 0.5
INTERRUPTED = MANIFEST.split('[[case]]\nname = "windage"')[0] + """
[[case]]
name = "hang"
model = "data/hang.fmu"
train = ["data/ball.csv"]
test = "data/ball_test.csv"
"""

# a case that fails in seconds beside one that never ends (no call timeout)
STUCK = """\
[[case]]
name = "crash"
model = "data/segfault.fmu"
train = ["data/ball.csv"]
test = "data/ball_test.csv"

[[case]]
name = "hang"
model = "data/hang.fmu"
train = ["data/ball.csv"]
test = "data/ball_test.csv"
"""


@pytest.fixture(scope="module")
def cases(tmp_path_factory):
    """The manifest and its data, in a folder of their own."""
    folder = tmp_path_factory.mktemp("cases")
    data = folder / "data"
    data.mkdir()
    shutil.copy(example_fmu("dc_drive"), data / "dc_drive.fmu")
    shutil.copy(crash_fmus()["segfault"], data / "segfault.fmu")
    shutil.copy(crash_fmus()["hang"], data / "hang.fmu")
    for truth, name in (("dc_drive", "plain"), ("dc_drive_truth_windage", "windage")):
        for role, window, seed in (("train", (0.0, 6.0), 0), ("test", (20.5, 24.0), 1)):
            os.replace(measure(data, truth, window, seed), data / f"{name}_{role}.csv")
            os.replace(data / f"{truth}_{window[0]:g}-{window[1]:g}_{seed}.csv.json", data / f"{name}_{role}.csv.json")
    from fmubuilder.simulation import simulate
    for name in ("ball", "ball_test"):
        simulate(example_fmu("bouncing_ball"), stop_time=1.0, variables=["h", "v"], solver="euler", step_size=1e-3,
                 output_interval=0.01).to_csv(data / f"{name}.csv")
    (folder / "cases.toml").write_text(MANIFEST)
    (folder / "interrupted.toml").write_text(INTERRUPTED)
    return folder


def run_batch_cli(*args, timeout=600):
    return subprocess.run([sys.executable, "-m", "fmubuilder.cli", "batch", *map(str, args)], capture_output=True,
                          text=True, timeout=timeout)


def error_lines(proc) -> list[str]:
    assert "Traceback" not in proc.stderr, proc.stderr
    return [line for line in proc.stderr.splitlines() if line.strip()]


def summary_rows(out: Path) -> list[dict]:
    with open(out / "summary.csv", newline="") as handle:
        return list(csv.DictReader(handle))


def without_time(rows: list[dict]) -> list[dict]:
    return [{k: v for k, v in r.items() if k != "seconds"} for r in rows]


@pytest.fixture(scope="module")
def local(cases):
    """The three cases on two local processes."""
    out = cases / "out-local"
    proc = run_batch_cli(cases / "cases.toml", "-o", out, "--jobs", "2")
    return proc, out


# -- the local executor ---------------------------------------------------------------------------

def test_each_case_completes_and_the_crash_is_that_cases_failure(local):
    proc, out = local
    [line] = error_lines(proc)
    assert proc.returncode == 1
    assert line.startswith("error: 1 of 3 case(s) failed, the first 'crash'") and "SIGSEGV" in line, line
    rows = {r["name"]: r for r in summary_rows(out)}
    assert [r["name"] for r in summary_rows(out)] == list(CASES)       # the manifest's order
    assert rows["no-effect"]["status"] == rows["windage"]["status"] == "ok"
    crash = rows["crash"]
    assert crash["status"] == "failed" and "crashed (SIGSEGV) in fmi2GetDerivatives" in crash["reason"], crash
    assert crash["report"] == "" and not (out / "crash" / "report").exists()
    assert "crashed (SIGSEGV)" in (out / "crash" / "log.txt").read_text()
    assert [p.name for p in out.iterdir() if p.name.endswith(".partial")] == []


def test_the_summary_says_what_each_report_holds(local):
    """The truths: windage enters der(speed), the plain data hold nothing; the gain is the report's
    per-signal test MSE factors' geometric mean (every signal has its noise, so the scores' floors
    cancel)."""
    _, out = local
    rows = {r["name"]: r for r in summary_rows(out)}
    assert rows["no-effect"]["found"] == "none" and rows["no-effect"]["shipped"] == "nothing"
    assert rows["no-effect"]["test_gain"] == ""
    windage = rows["windage"]
    assert windage["found"] == "der(speed)"
    report = json.loads((out / "windage" / "report" / "report.json").read_text())
    assert windage["shipped"] == report["chosen"] != "nothing"
    assert report["hybrid_fmu"] == "hybrid.fmu" and (out / "windage" / "hybrid.fmu").is_file()
    factors = report["mse_factor"]["test"].values()
    geometric_mean = math.exp(sum(math.log(f) for f in factors) / len(factors))
    assert float(windage["test_gain"]) == pytest.approx(geometric_mean, rel=1e-5)
    assert float(windage["test_gain"]) > 1
    for name in ("no-effect", "windage"):
        assert float(rows[name]["seconds"]) > 0
        assert (out / rows[name]["report"]).is_file()
    markdown, page = (out / "summary.md").read_text(), (out / "summary.html").read_text()
    assert "[windage](windage/report/report.md)" in markdown and "3 case(s): 2 ok, 1 failed" in markdown
    assert 'href="windage/report/report.html"' in page and (out / "windage" / "report" / "report.html").is_file()


def test_a_case_gives_what_hybridize_gives_on_its_files(local, cases, tmp_path):
    _, out = local
    data = cases / "data"
    reference = hybridize(data / "dc_drive.fmu", data / "plain_train.csv", data / "plain_test.csv",
                          tmp_path / "h.fmu", tmp_path / "report", seed=3, jobs=1, progress=False, **OPTIONS).report
    batch = json.loads((out / "no-effect" / "report" / "report.json").read_text())
    assert batch["diagnosis"]["p_value"] == reference["diagnosis"]["p_value"]
    assert batch["errors"] == reference["errors"] and batch["summary"] == reference["summary"]


# -- Ray --------------------------------------------------------------------------------------------

def test_ray_on_a_local_cluster_gives_the_same_summary(local, cases):
    pytest.importorskip("ray", reason="Ray is not installed (pip install 'fmubuilder[ray]')")
    _, local_out = local
    out = cases / "out-ray"
    proc = run_batch_cli(cases / "cases.toml", "-o", out, "--jobs", "2", "--executor", "ray")
    [line] = error_lines(proc)
    assert proc.returncode == 1 and "'crash'" in line, proc.stderr
    assert without_time(summary_rows(out)) == without_time(summary_rows(local_out))
    assert (out / "windage" / "hybrid.fmu").is_file()


# -- resumed -----------------------------------------------------------------------------------------

def running_commands_reading(path: Path) -> list[str]:
    """The command lines of the processes that name `path`."""
    found = []
    for cmdline in Path("/proc").glob("[0-9]*/cmdline"):
        try:
            text = cmdline.read_bytes().replace(b"\0", b" ").decode(errors="replace")
        except OSError:
            continue
        if str(path) in text:
            found.append(text)
    return found


def test_an_interrupted_batch_resumes_without_redoing_the_finished_cases(local, cases):
    """One case at a time and no call timeout: the first case finishes, then the batch is interrupted
    while the second is stuck in its FMU (a binary that never returns). A re-run skips the first (its
    folder untouched) and runs the second, which now meets a call timeout."""
    out = cases / "out-interrupted"
    batch = subprocess.Popen([sys.executable, "-m", "fmubuilder.cli", "batch", cases / "interrupted.toml", "-o", out,
                              "--jobs", "1", "--call-timeout", "0"], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                             text=True)
    first = out / "no-effect" / "case.json"
    while not first.exists() and batch.poll() is None:
        time.sleep(0.2)
    batch.send_signal(signal.SIGINT)
    _, stderr = batch.communicate(timeout=120)
    assert batch.returncode == 130 and stderr.strip() == "error: interrupted", stderr
    assert running_commands_reading(cases / "data" / "hang.fmu") == []     # the stuck case's processes ended
    assert sorted(p.name for p in out.iterdir() if not p.name.startswith(".")) == [
        "no-effect", "summary.csv", "summary.html", "summary.md"]
    assert [p.name for p in out.iterdir() if p.name.endswith(".partial")] == []   # the cut case's staging
    assert [r["status"] for r in summary_rows(out)] == ["ok", "pending"]
    finished = {p: p.stat().st_mtime_ns for p in (out / "no-effect").rglob("*")}

    proc = run_batch_cli(cases / "interrupted.toml", "-o", out, "--jobs", "1", "--call-timeout", "1")
    assert proc.returncode == 1, proc.stderr
    assert {p: p.stat().st_mtime_ns for p in (out / "no-effect").rglob("*")} == finished
    no_effect, hang = summary_rows(out)
    assert no_effect["status"] == "skipped" and hang["status"] == "failed"
    assert "did not return from fmi2GetDerivatives" in hang["reason"] and "within 1 s" in hang["reason"], hang
    [uninterrupted] = [r for r in without_time(summary_rows(local[1])) if r["name"] == "no-effect"]
    assert without_time([no_effect])[0] == {**uninterrupted, "status": "skipped"}


def test_a_batch_that_stops_early_stops_its_running_cases_and_leaves_no_staged_folder(cases, tmp_path, monkeypatch):
    """From Python: publishing the first case to finish (the crash) fails; the other, stuck in its
    FMU, is stopped, and neither leaves a staged folder."""
    from fmubuilder.batch import run as batch_run
    manifest = cases / "stuck.toml"
    manifest.write_text(STUCK)

    def failing(staging, target):
        raise FmuBuilderError("disk full")
    monkeypatch.setattr(batch_run, "replace_folder", failing)
    out = tmp_path / "out"
    with pytest.raises(FmuBuilderError, match="disk full"):
        batch_run.run_batch(manifest, out, jobs=2, call_timeout=0, progress=False)
    assert running_commands_reading(cases / "data" / "hang.fmu") == []
    assert [p.name for p in out.iterdir() if p.name.endswith(".partial")] == []


def test_a_changed_case_is_redone_only_with_force(local, cases, tmp_path):
    out = tmp_path / "out"
    shutil.copytree(local[1], out)
    manifest = cases / "changed.toml"
    manifest.write_text(MANIFEST.replace("seed = 3", "seed = 4").split("[[case]]\nname = \"windage\"")[0])
    kept = (out / "no-effect" / "case.json").read_text()
    proc = run_batch_cli(manifest, "-o", out)
    [line] = error_lines(proc)
    assert "case 'no-effect'" in line and "changed" in line and "--force" in line, line
    assert (out / "no-effect" / "case.json").read_text() == kept

    proc = run_batch_cli(manifest, "-o", out, "--force")
    assert proc.returncode == 0, proc.stderr
    assert json.loads((out / "no-effect" / "case.json").read_text())["key"] != json.loads(kept)["key"]
    assert [r["status"] for r in summary_rows(out)] == ["ok"]
    assert (out / "windage" / "hybrid.fmu").is_file()       # not in this manifest: left alone


# -- bad input: one line, before any work --------------------------------------------------------------

@pytest.mark.parametrize("change, fragments", [
    (lambda m: m.replace("budget = 0", "bugdet = 0"), ("[defaults]", "unknown key 'bugdet'", "'budget'")),
    (lambda m: m.replace("seed = 3", "seed = -1"), ("case 'no-effect'", "seed = -1", "whole number")),
    (lambda m: m.replace("plain_test.csv", "missing.csv"), ("case 'no-effect'", "data/missing.csv not found")),
    (lambda m: m.replace('name = "windage"', 'name = "no-effect"'), ("two cases are named 'no-effect'",)),
    (lambda m: m.replace('name = "crash"', 'name = "../crash"'), ("cannot be a folder name",)),
    (lambda m: m.replace("train_start = { h = 1.0 }", "train_start = [{ h = 1.0 }, { h = 2.0 }]"),
     ("2 tables for 1 training files",)),
    (lambda m: m + "[[case]\n", ("cannot read the manifest", "TOML")),
    (lambda m: m.replace("[[case]]", "[[cases]]"), ("unknown key 'cases'", "'case'")),
])
def test_a_bad_manifest_is_refused_in_one_line_before_any_work(cases, tmp_path, change, fragments):
    manifest = cases / f"bad-{tmp_path.name}.toml"
    manifest.write_text(change(MANIFEST))
    proc = run_batch_cli(manifest, "-o", tmp_path / "out", timeout=60)
    [line] = error_lines(proc)
    assert proc.returncode == 1 and line.startswith("error: "), proc.stderr
    for fragment in fragments:
        assert fragment in line, line
    assert not (tmp_path / "out").exists()


def test_an_output_folder_the_batch_did_not_write_is_refused(cases, tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "thesis.txt").write_text("years of work")
    proc = run_batch_cli(cases / "cases.toml", "-o", out, timeout=60)
    [line] = error_lines(proc)
    assert "not written by fmubuilder batch" in line
    assert sorted(p.name for p in out.iterdir()) == ["thesis.txt"]


def test_an_input_inside_a_case_folder_is_refused(cases, tmp_path):
    out = tmp_path / "out"
    (out / "no-effect").mkdir(parents=True)
    (out / ".fmubuilder-batch.json").write_text("{}")      # an earlier batch's folder
    for name in ("plain_train.csv", "plain_train.csv.json"):
        shutil.copy(cases / "data" / name, out / "no-effect" / name)
    manifest = tmp_path / "cases.toml"
    manifest.write_text(MANIFEST.replace('"data/', f'"{cases / "data"}/').replace(
        f'{cases / "data"}/plain_train.csv', "out/no-effect/plain_train.csv"))
    proc = run_batch_cli(manifest, "-o", out, timeout=60)
    [line] = error_lines(proc)
    assert "case 'no-effect' reads" in line and "keep the inputs outside the output folder" in line, line


def test_the_ray_executor_without_ray_or_an_address_without_ray(cases, tmp_path, monkeypatch):
    from fmubuilder.batch import run_batch
    with pytest.raises(FmuBuilderError, match="--address names a Ray cluster"):
        run_batch(cases / "cases.toml", tmp_path / "out", address="auto")
    monkeypatch.setitem(sys.modules, "ray", None)       # as if not installed
    with pytest.raises(FmuBuilderError, match=r"needs Ray, which is not installed: pip install 'fmubuilder\[ray\]'"):
        run_batch(cases / "cases.toml", tmp_path / "out", executor="ray")
    assert not (tmp_path / "out").exists()


def test_the_manifest_gives_each_case_its_files_starts_and_options(cases):
    no_effect, windage, crash = read_manifest(cases / "cases.toml")
    assert no_effect.options == {"budget": 0, "ann_on_term": False, "seed": 3}
    assert windage.options == {"budget": 0, "ann_on_term": False}
    assert no_effect.train == [cases / "data" / "plain_train.csv"]
    assert crash.train_start == [{"h": "1.0"}] and crash.test_start == {}
    assert cases / "data" / "plain_train.csv.json" in no_effect.input_files()


def test_the_guide_manifest_reads_as_written(tmp_path):
    """docs/batch.md's manifest, its files stood in by empty ones."""
    import re
    page = Path(__file__).resolve().parents[1] / "docs" / "batch.md"
    [text] = re.findall(r"```toml\n(.*?)```", page.read_text(), flags=re.S)
    (tmp_path / "seed-1000").mkdir()
    for name in ("declared.fmu", "train.csv", "validation.csv", "test.csv"):
        (tmp_path / "seed-1000" / name).write_bytes(b"")
    (tmp_path / "cases.toml").write_text(text)
    [case] = read_manifest(tmp_path / "cases.toml")
    assert case.name == "seed-1000" and case.options == {"budget": 5, "seed": 0}
    assert case.train_start == [{"x0": "1.0"}] and case.validation == tmp_path / "seed-1000" / "validation.csv"
