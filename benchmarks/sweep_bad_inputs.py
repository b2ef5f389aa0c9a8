"""Sweep of bad inputs through the command line: every one must end cleanly.

Generates damaged and hostile FMUs (corrupt, truncated, path traversal, zip and entity bombs,
FMI 1.0/3.0, Co-Simulation only, missing or broken binaries), malformed CSVs, bad arguments
and FMU binaries that segfault, abort, exit or hang (tests/fmi/crashing), runs each through
`python -m fmubuilder.cli` with TMPDIR pointed at a fresh folder and prints one row per run:

    case | command | exit code | stderr lines | traceback | files left behind

A run is clean when it exits non-zero with exactly one `error:` line, no traceback, no
temporary folder and no output left behind; for the few runs that should succeed (`inspect`
reads the archive but never loads the binary) when it exits 0 with nothing on stderr.

The second part (`scenarios`) is about what the user had: each case runs in a folder holding the
user's files (inputs, an unrelated thesis.txt, outputs of earlier runs, a FIFO, a symbolic link, a
device node), and every file there must be byte-identical afterwards (the same kind of file, too).
A case is defective when it loses or changes such a file, replaces a non-regular file, exits 0
where it must fail (NaN results, nonsense options) or prints an internal error; it is clean when
it also ends in one `error:` line naming the problem, leaves nothing behind and refuses within
REFUSAL_SECONDS (before any work). `tests/test_no_loss.py` runs every scenario.

    python benchmarks/sweep_bad_inputs.py [--only SUBSTRING] [--keep DIR] [--scenarios]
"""
from __future__ import annotations

import argparse
import hashlib
import json
import os
import shutil
import stat
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))  # for tests.fmi (the bad-FMU makers)

from fmubuilder.build import example_fmu  # noqa: E402
from tests.fmi import broken_fmus as bad  # noqa: E402
from tests.fmi.crash_fmus import MODES, crash_fmus  # noqa: E402

CALL_TIMEOUT = "1"
# (case, command) runs that are right to succeed: inspect does not load the binary
EXPECTED_TO_SUCCEED = {("garbage binary", "inspect"), ("binary without fmi2 functions", "inspect")}


@dataclass
class Outcome:
    case: str
    command: str
    code: int
    stderr_lines: int
    traceback: bool
    left: list[str]
    first_line: str

    @property
    def clean(self) -> bool:
        if (self.case, self.command) in EXPECTED_TO_SUCCEED:
            return self.code == 0 and self.stderr_lines == 0 and not self.left
        return (self.code != 0 and self.stderr_lines == 1 and self.first_line.startswith("error: ")
                and not self.traceback and not self.left)

    @property
    def defective(self) -> bool:
        return self.traceback or "internal error" in self.first_line


# -- inputs --------------------------------------------------------------------------------

def bad_fmus(folder: Path, ball: Path) -> dict[str, Path]:
    xml_bomb = lambda text: bad.billion_laughs(text)  # noqa: E731
    not_zip = folder / "not_a_zip.fmu"
    not_zip.write_text("this is not an FMU")
    empty = folder / "empty.fmu"
    empty.write_bytes(b"")
    directory = folder / "directory.fmu"
    directory.mkdir()
    foreign = _foreign_library()
    fmus = {
        "not a zip": not_zip,
        "empty file": empty,
        "missing file": folder / "missing.fmu",
        "directory": directory,
        "truncated": bad.truncate(ball, folder / "truncated.fmu"),
        "bad CRC (binary)": bad.flip_byte_in_entry(ball, folder / "crc.fmu", bad.binary_name(ball), compressed=False),
        "bad deflate (binary)": bad.flip_byte_in_entry(ball, folder / "deflate.fmu", bad.binary_name(ball), compressed=True),
        "bad deflate (XML)": bad.flip_byte_in_entry(ball, folder / "xml.fmu", "modelDescription.xml", compressed=True),
        "path traversal": bad.add_entries(ball, folder / "traversal.fmu", {"resources/../../evil.txt": b"x"}),
        "zip bomb 2 GB": bad.add_zip_bomb(ball, folder / "bomb.fmu", megabytes=2048),
        "entity bomb": bad.rewrite_fmu(ball, folder / "laughs.fmu", xml=xml_bomb),
        "XML cut in half": bad.rewrite_fmu(ball, folder / "half_xml.fmu", xml=lambda t: t[: len(t) // 2]),
        "FMI 1.0": bad.rewrite_fmu(ball, folder / "fmi1.fmu", xml=bad.set_fmi_version("1.0")),
        "FMI 3.0": bad.rewrite_fmu(ball, folder / "fmi3.fmu", xml=bad.set_fmi_version("3.0")),
        "Co-Simulation only": bad.rewrite_fmu(ball, folder / "cs.fmu", xml=bad.co_simulation_only),
        "no modelDescription": bad.rewrite_fmu(ball, folder / "no_md.fmu", drop=("modelDescription.xml",)),
        "no linux64 binary": bad.rewrite_fmu(ball, folder / "no_bin.fmu", drop=("binaries/linux64", "sources/")),
        "garbage binary": bad.replace_binary(ball, folder / "garbage.fmu", b"\x7fELF not a library"),
    }
    if foreign:
        fmus["binary without fmi2 functions"] = bad.replace_binary(ball, folder / "foreign.fmu", foreign.read_bytes())
    return fmus


def _foreign_library() -> Path | None:
    for candidate in ("/lib/x86_64-linux-gnu/libz.so.1", "/usr/lib/x86_64-linux-gnu/libz.so.1"):
        if Path(candidate).is_file():
            return Path(candidate)
    return None


def bad_csvs(folder: Path, ball: Path) -> dict[str, Path]:
    from fmubuilder.simulation import simulate
    result = simulate(ball, stop_time=1.0, variables=["h", "v"], solver="euler", step_size=1e-3, output_interval=0.01)
    rows = list(zip(result.time.tolist(), result["h"].tolist(), result["v"].tolist()))
    good = "time,h,v\n" + "".join(f"{t!r},{h!r},{v!r}\n" for t, h, v in rows)
    texts = {
        "empty CSV": "",
        "header only": "time,h,v\n",
        "one row": "time,h,v\n0,1,0\n",
        "not numbers": good.replace("0.5,", "half,", 1).replace("\n0.01,", "\nabc,", 1),
        "NaN values": good.replace(f"{rows[10][1]!r}", "nan", 1),
        "time not increasing": "time,h,v\n" + "".join(f"{t!r},{h!r},{v!r}\n" for t, h, v in rows[::-1]),
        "unknown column": good.replace("time,h,v", "time,h,velocity", 1),
        "no time column": good.replace("time,h,v", "t,h,v", 1),
        "values near 1e300": "time,h,v\n" + "".join(f"{t!r},{h * 1e300!r},{v * 1e300!r}\n" for t, h, v in rows),
        "ragged rows": good + "1.5,2\n",
    }
    paths = {}
    for name, text in texts.items():
        paths[name] = folder / (name.replace(" ", "_") + ".csv")
        paths[name].write_text(text)
    garbage = folder / "garbage.csv"
    garbage.write_bytes(bytes(range(256)) * 20)
    paths["binary garbage"] = garbage
    good_path = folder / "good.csv"
    good_path.write_text(good)
    return paths, good_path


# -- commands ------------------------------------------------------------------------------

def fmu_commands(fmu: Path, out: Path, data: Path) -> dict[str, list]:
    return {
        "inspect": ["inspect", fmu],
        "simulate": ["simulate", fmu, "--stop-time", "1", "-o", out / "result.csv"],
        "diagnose": ["diagnose", fmu, "--data", data, "--json", out / "diagnosis.json", "--time-budget", "10"],
        "train": ["train", fmu, "--data", data, "--target", "der(v)", "--inputs", "h,v", "--epochs", "1",
                  "--element-length", "1", "--step-size", "0.01", "--quiet", "-o", out / "trained.nfmu"],
        "hybridize": ["hybridize", fmu, "--train", data, "--test", data, "-o", out / "hybrid.fmu",
                      "--report", out / "report", "--time-budget", "10"],
    }


def argument_cases(ball: Path, out: Path, data: Path, folder: Path) -> list[tuple[str, str, list]]:
    exists = folder / "exists.csv"
    exists.write_text("precious\n")
    spec_garbage = folder / "spec.json"
    spec_garbage.write_text("{not json")
    return [
        ("no command arguments", "simulate", ["simulate"]),
        ("unknown command", "frobnicate", ["frobnicate"]),
        ("stop time not a number", "simulate", ["simulate", ball, "--stop-time", "abc"]),
        ("stop before start", "simulate", ["simulate", ball, "--start-time", "2", "--stop-time", "1"]),
        ("malformed --start", "simulate", ["simulate", ball, "--start", "h"]),
        ("unknown --start name", "simulate", ["simulate", ball, "--start", "gg=1"]),
        ("--start of the wrong type", "simulate", ["simulate", ball, "--start", "h=high"]),
        ("unknown --variables", "simulate", ["simulate", ball, "--variables", "h,heigth"]),
        ("negative --call-timeout", "simulate", ["simulate", ball, "--call-timeout", "-1"]),
        ("output folder missing", "simulate", ["simulate", ball, "-o", out / "no" / "such" / "x.csv"]),
        ("output exists, no --force", "simulate", ["simulate", ball, "-o", exists]),
        ("negative --time-budget", "diagnose", ["diagnose", ball, "--data", data, "--time-budget", "-5"]),
        ("--hidden not integers", "train", ["train", ball, "--data", data, "--target", "der(v)", "--inputs", "h",
                                            "--hidden", "a,b", "-o", out / "t.nfmu"]),
        ("unknown --target", "train", ["train", ball, "--data", data, "--target", "der(x)", "--inputs", "h",
                                       "-o", out / "t.nfmu"]),
        ("export of a missing file", "export", ["export", folder / "nothing.json", "-o", out / "h.fmu"]),
        ("export of broken JSON", "export", ["export", spec_garbage, "-o", out / "h.fmu"]),
        ("export of a non-model file", "export", ["export", exists, "-o", out / "h.fmu"]),
        ("validate of a non-FMU", "validate", ["validate", exists]),
        ("unknown example", "example", ["example", "nothing", "-o", out / "ex"]),
        ("synth with a bad --noise", "synth", ["synth", ball, "--stop-time", "1", "--signals", "h",
                                               "--noise", "h=abc", "-o", out / "d.csv"]),
    ]


# -- scenarios: nothing the user had is lost ---------------------------------------------------

REFUSAL_SECONDS = 20.0      # a refusal comes before any work: the command line's start-up and the checks
THESIS = b"years of work, not to be lost\n"


@dataclass
class Scenario:
    """One case of issue 60: `setup(here, shared)` puts the user's files into the folder `here` and
    returns the command's arguments (run in `here`); `expect` "error" (with `fragment` in the one
    error line) or "success"; `during(here)` runs beside the command (another program writing);
    `check(here)` returns a problem with the result, or None; `keep_new`: new files are right."""
    name: str
    setup: Callable
    expect: str = "error"
    fragment: str = ""
    during: Callable | None = None
    check: Callable | None = None
    refusal: bool = True          # refused before any work: within REFUSAL_SECONDS
    needs_root: bool = False
    slow: bool = False            # runs the workflow (about 20 s)


@dataclass
class ScenarioOutcome:
    name: str
    code: int
    seconds: float
    first_line: str
    stderr_lines: int
    traceback: bool
    lost: list[str] = field(default_factory=list)        # pre-existing files changed, removed or replaced
    left: list[str] = field(default_factory=list)        # new files left by a failed run
    problems: list[str] = field(default_factory=list)    # what else is wrong (message, time, check)
    skipped: str = ""

    @property
    def defective(self) -> bool:
        return bool(self.lost or self.traceback or "internal error" in self.first_line
                    or any(p.startswith("exit 0") for p in self.problems))

    @property
    def clean(self) -> bool:
        return not self.skipped and not self.defective and not self.left and not self.problems


class Shared:
    """Inputs built once per sweep: the bouncing ball FMU, its measured data, a hanging FMU."""

    def __init__(self, folder: Path):
        self.folder = folder
        folder.mkdir(parents=True, exist_ok=True)
        self.ball = example_fmu("bouncing_ball")
        self._data = None

    @property
    def data_text(self) -> str:
        if self._data is None:
            from fmubuilder.simulation import simulate
            result = simulate(self.ball, stop_time=1.0, variables=["h", "v"], solver="euler", step_size=1e-3,
                              output_interval=0.01)
            self._data = "time,h,v\n" + "".join(f"{t!r},{h!r},{v!r}\n" for t, h, v in
                                                 zip(result.time.tolist(), result["h"].tolist(), result["v"].tolist()))
        return self._data

    def hang(self) -> Path:
        return crash_fmus()["hang"]


def _user_folder(here: Path, shared: Shared, fmu: str = "m.fmu") -> tuple[str, str, str]:
    """The user's folder: the model, training and test data, an unrelated thesis.txt."""
    shutil.copyfile(shared.ball, here / fmu)
    (here / "d.csv").write_text(shared.data_text)
    (here / "t.csv").write_text(shared.data_text)     # the same numbers, another file: the test data
    (here / "thesis.txt").write_bytes(THESIS)
    return fmu, "d.csv", "t.csv"


def _hybridize(fmu="m.fmu", *more):
    return ["hybridize", fmu, "--train", "d.csv", "--test", "t.csv", "--time-budget", "10", *more]


def _train(*more):
    return ["train", "m.fmu", "--data", "d.csv", "--target", "der(v)", "--inputs", "h,v", "--epochs", "1",
            "--element-length", "1", "--step-size", "0.01", "--quiet", *more]


def _fmu_variant(edit: Callable[[str], str]):
    def setup(here: Path, shared: Shared):
        _user_folder(here, shared)
        bad.rewrite_fmu(shared.ball, here / "odd.fmu", xml=edit)
        return ["simulate", "odd.fmu", "--stop-time", "1", "-o", "r.csv"]
    return setup


def _sidecar(content, command="diagnose"):
    def setup(here: Path, shared: Shared):
        _user_folder(here, shared)
        (here / "d.csv.json").write_text(content if isinstance(content, str) else json.dumps(content))
        if command == "train":
            return _train("-o", "x.nfmu")
        return ["diagnose", "m.fmu", "--data", "d.csv", "--json", "diag.json"]
    return setup


def _simple(args: Callable[[Path, Shared], list] | list):
    def setup(here: Path, shared: Shared):
        _user_folder(here, shared)
        return args(here, shared) if callable(args) else list(args)
    return setup


def _with(files: dict, args: list):
    """The user's folder plus `files` ({name: bytes, or a callable(here) that makes it})."""
    def setup(here: Path, shared: Shared):
        _user_folder(here, shared)
        for name, content in files.items():
            path = here / name
            path.parent.mkdir(parents=True, exist_ok=True)
            content(path) if callable(content) else path.write_bytes(content)
        return list(args)
    return setup


def _fifo(path: Path):
    os.mkfifo(path)


def _symlink_to_thesis(path: Path):
    path.symlink_to("thesis.txt")


def _device(path: Path):
    os.mknod(path, 0o666 | stat.S_IFCHR, os.makedev(1, 3))    # a null device: harmless if written


def _own_report(path: Path):
    """A report folder an earlier run wrote (its manifest), for --force to replace."""
    from fmubuilder.files import write_manifest
    path.mkdir()
    (path / "report.md").write_text("# an earlier report\n")
    write_manifest(path)


OTHER_PROGRAM = b"written by another program\n"


def _write_during_hang(here: Path, wrote: dict):
    """Another program writes the output while the command hangs in the FMU (after its checks)."""
    time.sleep(1.0)
    if not (here / "r.csv").exists():
        (here / "r.csv").write_bytes(OTHER_PROGRAM)
        wrote["r.csv"] = ("file", hashlib.sha256(OTHER_PROGRAM).hexdigest())


def _train_used_sidecar(here: Path) -> str | None:
    """The MSE before training is the plain FMU's with the sidecar's start (e=0.5 leaves the data's
    first bounce as measured: the error is that of the sidecar's start, not of the default e=0.7)."""
    metrics = json.loads((here / "metrics.json").read_text())
    used = metrics["errors"]["before"]["h"]["mse"]
    return None if used < 1e-6 else f"the MSE before training is {used:.3g}: the sidecar's start values were ignored"


def _measured_with_e(here: Path, shared: Shared):
    """Data of the ball with e = 0.5 and its sidecar saying so; train must start from it."""
    from fmubuilder.simulation import simulate
    _user_folder(here, shared)
    result = simulate(shared.ball, stop_time=2.0, variables=["h", "v"], solver="euler", step_size=1e-3,
                      output_interval=0.01, start_values={"e": 0.5})
    (here / "e.csv").write_text("time,h,v\n" + "".join(f"{t!r},{h!r},{v!r}\n" for t, h, v in
                                zip(result.time.tolist(), result["h"].tolist(), result["v"].tolist())))
    (here / "e.csv.json").write_text(json.dumps({"start_values": {"e": 0.5}}))
    return ["train", "m.fmu", "--data", "e.csv", "--target", "der(v)", "--inputs", "h,v", "--epochs", "0",
            "--element-length", "2", "--step-size", "0.001", "--solver", "euler", "--quiet", "-o", "x.nfmu",
            "--json", "metrics.json"]


A_REPORT = b"# the report of run A\n"


def _run_a_finishes_meanwhile(here: Path, wrote: dict):
    """Run A publishes h.fmu and rep/ while run B (the command) is still working: B fails at its end
    ("h.fmu exists") and must leave A's outputs as they are."""
    time.sleep(4.0)
    if not (here / "h.fmu").exists():
        (here / "rep").mkdir()
        (here / "rep" / "report.md").write_bytes(A_REPORT)
        shutil.copyfile(here / "m.fmu", here / "h.fmu")
        wrote["rep/report.md"] = ("file", hashlib.sha256(A_REPORT).hexdigest())
        wrote["h.fmu"] = ("file", hashlib.sha256((here / "m.fmu").read_bytes()).hexdigest())
        wrote["rep"] = (stat.S_IFDIR, None)


def _trained_here(here: Path, shared: Shared):
    """A NeuralFMU trained (0 epochs) on the user's m.fmu; the export is asked to write over m.fmu."""
    _user_folder(here, shared)
    subprocess.run([sys.executable, "-m", "fmubuilder.cli", "train", "m.fmu", "--data", "d.csv", "--target", "der(v)",
                    "--inputs", "h,v", "--epochs", "0", "--element-length", "1", "--step-size", "0.01", "--quiet",
                    "-o", "x.nfmu"], cwd=here, check=True, capture_output=True, env=_environment(here.parent / "tmp"))
    return ["export", "x.nfmu", "-o", "m.fmu", "--force"]


def _underscore_csv(here: Path, shared: Shared):
    _user_folder(here, shared)
    lines = shared.data_text.splitlines()
    cells = lines[5].split(",")
    cells[1] = "1_000"
    lines[5] = ",".join(cells)
    (here / "u.csv").write_text("\n".join(lines) + "\n")
    return ["diagnose", "m.fmu", "--data", "u.csv"]


def _environment(tmp: Path) -> dict:
    """The command's environment: TMPDIR in the case's folder, this checkout's package first."""
    env = {**os.environ, "TMPDIR": str(tmp)}
    root = str(Path(__file__).resolve().parent.parent)
    env["PYTHONPATH"] = root + (os.pathsep + env["PYTHONPATH"] if env.get("PYTHONPATH") else "")
    return env


def _read_only_mount(here: Path, shared: Shared):
    _user_folder(here, shared)
    (here / "ro").mkdir()
    subprocess.run(["mount", "-t", "tmpfs", "-o", "ro,size=64k", "tmpfs", str(here / "ro")], check=True,
                   capture_output=True)
    return ["simulate", "m.fmu", "--stop-time", "1", "-o", "ro/r.csv"]


def _unmount(here: Path) -> None:
    if (here / "ro").is_mount():
        subprocess.run(["umount", str(here / "ro")], capture_output=True)


def scenarios() -> list[Scenario]:
    hy = _hybridize
    nan_step = ["simulate", "m.fmu", "--solver", "rk4", "--start", "g=1e308", "-o", "r.csv"]
    return [
        # 1. --force replaces only the named outputs and a report folder fmubuilder made
        Scenario("--report is the working folder, with --force",
                 lambda here, shared: (_user_folder(here, shared), hy("m.fmu", "-o", "h.fmu", "--report",
                                                                       str(here), "--force"))[1], fragment="holds the input"),
        Scenario("--report holds files fmubuilder did not write, with --force",
                 _with({"rep/notes.txt": b"mine"}, hy("m.fmu", "-o", "h.fmu", "--report", "rep", "--force")),
                 fragment="did not write"),
        Scenario("--report fmubuilder wrote, with a file changed since, with --force",
                 _with({"rep": lambda p: (_own_report(p), (p / "report.md").write_text("my edits"))},
                       hy("m.fmu", "-o", "h.fmu", "--report", "rep", "--force")),
                 fragment="changed since"),
        Scenario("--plots folder holding a user's .partial file, failed run",
                 _with({"plots/.notes.txt.abc.partial": b"mine", "bad.csv": b"time,h\n0,1\n0.1,x\n"},
                       ["diagnose", "m.fmu", "--data", "bad.csv", "--plots", "plots"]),
                 fragment="bad.csv", refusal=False),
        Scenario("a hanging run while another program writes its output",
                 lambda here, shared: (_user_folder(here, shared),
                                       ["simulate", str(shared.hang()), "--stop-time", "1", "-o", "r.csv",
                                        "--call-timeout", "1"])[1],
                 during=_write_during_hang, fragment="", refusal=False),
        Scenario("run B fails at its end after run A wrote the same outputs",
                 _simple(hy("m.fmu", "-o", "h.fmu", "--report", "rep", "--budget", "0", "--no-ann-on-term",
                            "--jobs", "1", "--quiet")),
                 during=_run_a_finishes_meanwhile, fragment="h.fmu exists", refusal=False, slow=True),
        # 2. outputs are regular files, never an input
        Scenario("-o a FIFO, with --force", _with({"pipe": _fifo}, ["simulate", "m.fmu", "-o", "pipe", "--force"]),
                 fragment="FIFO"),
        Scenario("-o a symbolic link, with --force",
                 _with({"link.csv": _symlink_to_thesis}, ["simulate", "m.fmu", "-o", "link.csv", "--force"]),
                 fragment="symbolic link"),
        Scenario("-o a device node, with --force", _with({"dev0": _device}, ["simulate", "m.fmu", "-o", "dev0",
                                                                          "--force"]),
                 fragment="device", needs_root=True),
        Scenario("-o a folder, with --force", _with({"out/x": b"x"}, ["simulate", "m.fmu", "-o", "out", "--force"]),
                 fragment="folder"),
        Scenario("simulate -o its own FMU", _simple(["simulate", "m.fmu", "-o", "m.fmu", "--force"]),
                 fragment="is an input"),
        Scenario("simulate -o its FMU through a symbolic link", _with({"alias.fmu": lambda p: p.symlink_to("m.fmu")},
                                                                     ["simulate", "alias.fmu", "-o", "m.fmu", "--force"]),
                 fragment="is an input"),
        Scenario("hybridize -o its own FMU", _simple(hy("m.fmu", "-o", "m.fmu", "--report", "rep", "--force")),
                 fragment="is an input"),
        Scenario("hybridize -o its training data", _simple(hy("m.fmu", "-o", "d.csv", "--report", "rep", "--force")),
                 fragment=".fmu"),
        Scenario("diagnose --json its own data", _simple(["diagnose", "m.fmu", "--data", "d.csv", "--json", "d.csv",
                                                          "--force"]), fragment="is an input"),
        Scenario("diagnose --json the data's sidecar",
                 _with({"d.csv.json": b'{"start_values": {}}'},
                       ["diagnose", "m.fmu", "--data", "d.csv", "--json", "d.csv.json", "--force"]),
                 fragment="is an input"),
        Scenario("export a NeuralFMU -o the FMU it wraps", _trained_here, fragment="wraps"),
        Scenario("train -o its data", _simple(_train("-o", "d.csv", "--force")), fragment="is an input"),
        # 3. every output check before any work
        Scenario("-o in /proc", _simple(hy("m.fmu", "-o", "/proc/h.fmu", "--report", "rep")), fragment="cannot write"),
        Scenario("-o and --report the same path", _simple(hy("m.fmu", "-o", "x.fmu", "--report", "x.fmu")),
                 fragment="same path"),
        Scenario("-o on a read-only mount", _read_only_mount, fragment="cannot write", needs_root=True),
        Scenario("--report an existing file", _with({"rep.txt": b"mine"}, hy("m.fmu", "-o", "h.fmu", "--report",
                                                                            "rep.txt", "--force")),
                 fragment="not a folder"),
        Scenario("a modelIdentifier the export refuses",
                 lambda here, shared: (_user_folder(here, shared), bad.rewrite_fmu(
                     shared.ball, here / "odd.fmu", xml=lambda t: t.replace('modelIdentifier="bouncing_ball"',
                                                                           'modelIdentifier="1ball"')),
                     hy("odd.fmu", "-o", "h.fmu", "--report", "rep"))[2], fragment="not a C identifier"),
        Scenario("hybridize -o without .fmu", _simple(hy("m.fmu", "-o", "h.zip", "--report", "rep")), fragment=".fmu"),
        # 4. no overwrite without --force
        Scenario("train beside an existing checkpoint",
                 _with({"x.nfmu.ckpt": b"another training's state"}, _train("-o", "x.nfmu")), fragment="x.nfmu.ckpt"),
        Scenario("diagnose --plots over existing plots",
                 _with({"plots/signals.png": b"my plot"}, ["diagnose", "m.fmu", "--data", "d.csv", "--plots", "plots"]),
                 fragment="signals.png"),
        Scenario("train --resume without a checkpoint",
                 _with({"x.nfmu": b"an earlier model"}, _train("-o", "x.nfmu", "--resume")), fragment="no checkpoint"),
        Scenario("train --json over an existing file",
                 _with({"m.json": b"mine"}, _train("-o", "x.nfmu", "--json", "m.json")), fragment="exists"),
        Scenario("synth over an existing sidecar",
                 _with({"s.csv.json": b"mine"}, ["synth", "m.fmu", "--stop-time", "1", "--signals", "h", "-o", "s.csv"]),
                 fragment="exists"),
        Scenario("example --force into a folder whose README.md is a symbolic link",
                 _with({"ex/README.md": lambda p: p.symlink_to("../thesis.txt")},
                       ["example", "vldm", "-o", "ex", "--force"]), fragment="symbolic link"),
        # 5. the sidecar's start values in train
        Scenario("train starts from the sidecar's start values", _measured_with_e, expect="success",
                 check=_train_used_sidecar, refusal=False),
        # 6. strict input checks
        Scenario("simulate diverging to NaN (rk4)", _simple(nan_step), fragment="diverged", refusal=False),
        Scenario("synth --lag nan", _simple(["synth", "m.fmu", "--stop-time", "1", "--lag", "nan", "-o", "s.csv"]),
                 fragment="finite"),
        Scenario("a CSV number written 1_000", _underscore_csv, fragment="without '_'"),
        Scenario("--start e=0_5", _simple(["simulate", "m.fmu", "--start", "e=0_5", "-o", "r.csv"]),
                 fragment="without '_'"),
        Scenario("sidecar start value e=0_5", _sidecar({"start_values": {"e": "0_5"}}), fragment="start_values.e"),
        Scenario('start="nine" in the modelDescription', _fmu_variant(lambda t: t.replace('start="9.81"', 'start="nine"')),
                 fragment="nine"),
        Scenario("duplicate variable names", _fmu_variant(lambda t: t.replace('name="e"', 'name="g"')),
                 fragment="twice"),
        Scenario("duplicate value references",
                 _fmu_variant(lambda t: t.replace('name="v" valueReference="2"', 'name="v" valueReference="0"')),
                 fragment="value reference"),
        Scenario('causality="banana"', _fmu_variant(lambda t: t.replace('causality="output"', 'causality="banana"', 1)),
                 fragment="banana"),
        Scenario("no guid", _fmu_variant(lambda t: t.replace('guid="', 'nothing="', 1)), fragment="guid"),
        Scenario("an unknown XML encoding", _fmu_variant(lambda t: t.replace('encoding="UTF-8"', 'encoding="klingon"')),
                 fragment="klingon"),
        Scenario("simulate --step-size 0", _simple(["simulate", "m.fmu", "--solver", "rk4", "--step-size", "0",
                                                    "-o", "r.csv"]), fragment="> 0"),
        Scenario("train --batch-size -1", _simple(_train("-o", "x.nfmu", "--batch-size", "-1")), fragment="--batch-size"),
        Scenario("train --decay nan", _simple(_train("-o", "x.nfmu", "--decay", "nan")), fragment="--decay"),
        Scenario("train --lr nan", _simple(_train("-o", "x.nfmu", "--lr", "nan")), fragment="--lr"),
        Scenario("train --seed 2**70", _simple(_train("-o", "x.nfmu", "--seed", str(2**70))), fragment="--seed"),
        Scenario("hybridize --seed 2**70", _simple(hy("m.fmu", "-o", "h.fmu", "--report", "rep", "--seed", str(2**70))),
                 fragment="--seed"),
        Scenario("--validation-start without --validation",
                 _simple(hy("m.fmu", "-o", "h.fmu", "--report", "rep", "--validation-start", "e=0.5")),
                 fragment="--validation"),
        Scenario("the training file as test data",
                 _simple(["hybridize", "m.fmu", "--train", "d.csv", "--test", "d.csv", "-o", "h.fmu", "--report", "rep"]),
                 fragment="one role"),
        Scenario("sidecar start_values a list", _sidecar({"start_values": [1, 2]}), fragment="start_values"),
        Scenario("sidecar bench a number", _sidecar({"bench": 3}), fragment="bench"),
        Scenario("sidecar bench.runs a string", _sidecar({"bench": {"runs": "two"}}), fragment="bench.runs"),
        Scenario("sidecar sensor_lag a string, in train", _sidecar({"sensor_lag": "fast"}, "train"),
                 fragment="sensor_lag"),
        Scenario("sidecar start value a list, in train", _sidecar({"start_values": {"e": [0.5]}}, "train"),
                 fragment="start_values.e"),
        Scenario("sidecar start value NaN", _sidecar('{"start_values": {"e": NaN}}'), fragment="start_values.e"),
    ]


def _snapshot(here: Path) -> dict[str, tuple]:
    """{relative path: (kind, sha256 of a file's bytes / a link's target)} of everything in `here`."""
    found = {}
    for root, dirs, names in os.walk(here):
        for name in dirs + names:
            path = Path(root) / name
            mode = os.lstat(path).st_mode
            if stat.S_ISREG(mode):
                found[str(path.relative_to(here))] = ("file", hashlib.sha256(path.read_bytes()).hexdigest())
            elif stat.S_ISLNK(mode):
                found[str(path.relative_to(here))] = ("link", os.readlink(path))
            else:
                found[str(path.relative_to(here))] = (stat.S_IFMT(mode), None)
    return found


def run_scenario(scenario: Scenario, shared: Shared, work: Path) -> ScenarioOutcome:
    """Run one scenario in a fresh folder under `work`."""
    here, tmp = work / "here", work / "tmp"
    for folder in (here, tmp):
        if folder.exists():
            _unmount(folder)
            shutil.rmtree(folder)
        folder.mkdir(parents=True)
    if scenario.needs_root and os.geteuid() != 0:
        return ScenarioOutcome(scenario.name, 0, 0.0, "", 0, False, skipped="needs root")
    try:
        args = scenario.setup(here, shared)
    except Exception as exc:    # e.g. no mount permission, or a checkout without a helper this case needs
        _unmount(here)
        return ScenarioOutcome(scenario.name, 0, 0.0, "", 0, False, skipped=f"cannot set up ({exc})")
    try:
        before = _snapshot(here)
        started = time.perf_counter()
        proc = subprocess.Popen([sys.executable, "-m", "fmubuilder.cli", *map(str, args)], cwd=here,
                                env=_environment(tmp),
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        helper, wrote = None, {}
        if scenario.during:
            helper = threading.Thread(target=scenario.during, args=(here, wrote))
            helper.start()
        _, stderr = proc.communicate(timeout=600)
        seconds = time.perf_counter() - started
        if helper:
            helper.join()
            before.update(wrote)    # what the other program wrote is the user's too
        after = _snapshot(here)
        lines = [line for line in stderr.splitlines() if line.strip()]
        outcome = ScenarioOutcome(scenario.name, proc.returncode, seconds, lines[0] if lines else "", len(lines),
                                  "Traceback" in stderr)
        outcome.lost = sorted(name for name, fingerprint in before.items() if after.get(name) != fingerprint)
        if scenario.expect == "error":
            outcome.left = sorted(set(after) - set(before)) + [f"tmp/{p.name}" for p in tmp.iterdir()]
            if proc.returncode == 0:
                outcome.problems.append("exit 0 where the command must fail")
            elif not (len(lines) == 1 and lines[0].startswith("error: ") and scenario.fragment in lines[0]):
                outcome.problems.append(f"not one error line naming '{scenario.fragment}'")
            if scenario.refusal and seconds > REFUSAL_SECONDS:
                outcome.problems.append(f"refused only after {seconds:.0f} s")
        else:
            if proc.returncode != 0:
                outcome.problems.append(f"exit {proc.returncode}: {outcome.first_line}")
            elif scenario.check:
                problem = scenario.check(here)
                if problem:
                    outcome.problems.append(problem)
        return outcome
    finally:
        _unmount(here)


def sweep_scenarios(work: Path, only: str | None = None, messages: bool = False) -> list[ScenarioOutcome]:
    shared = Shared(work / "shared")
    chosen = [s for s in scenarios() if not only or only.lower() in s.name.lower()]
    print("| case | exit code | seconds | lost | left behind | clean | defective |")
    print("|---|---|---|---|---|---|---|")
    outcomes = []
    for scenario in chosen:
        outcome = run_scenario(scenario, shared, work / "run")
        outcomes.append(outcome)
        if outcome.skipped:
            print(f"| {scenario.name} | skipped: {outcome.skipped} | | | | | |", flush=True)
            continue
        print(f"| {scenario.name} | {outcome.code} | {outcome.seconds:.1f} | {', '.join(outcome.lost) or '-'} | "
              f"{', '.join(outcome.left) or '-'} | {'yes' if outcome.clean else '**NO**'} | "
              f"{'**YES**' if outcome.defective else 'no'} |", flush=True)
        if messages or not outcome.clean:
            print(f"|   | {outcome.first_line[:300]} {'; '.join(outcome.problems)} | | | | | |", flush=True)
    return outcomes


# -- running -------------------------------------------------------------------------------

def run_case(case: str, command: str, args: list, out: Path, tmp: Path) -> Outcome:
    for folder in (out, tmp):
        shutil.rmtree(folder, ignore_errors=True)
        folder.mkdir(parents=True)
    env = {**os.environ, "TMPDIR": str(tmp)}
    proc = subprocess.run([sys.executable, "-m", "fmubuilder.cli", *map(str, args)], capture_output=True,
                          text=True, env=env, timeout=600)
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    left = [f"tmp/{p.name}" for p in tmp.iterdir()] + [f"out/{p.name}" for p in out.iterdir()]
    return Outcome(case, command, proc.returncode, len(lines), "Traceback" in proc.stderr, left,
                   lines[0] if lines else "")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", help="run the cases whose name contains this text")
    parser.add_argument("--keep", metavar="DIR", help="generate the inputs into DIR and keep them")
    parser.add_argument("--messages", action="store_true", help="print each run's error line too")
    part = parser.add_mutually_exclusive_group()
    part.add_argument("--scenarios", action="store_true", help="only the scenarios of the user's files (issue 60)")
    part.add_argument("--no-scenarios", action="store_true", help="only the bad inputs, not the scenarios")
    args = parser.parse_args()

    work = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="fmubuilder-sweep-"))
    work.mkdir(parents=True, exist_ok=True)
    outcomes: list = []
    try:
        if not args.scenarios:
            outcomes += sweep(work, args.only, args.messages)
            print()
        if not args.no_scenarios:
            outcomes += sweep_scenarios(work / "scenarios", args.only, args.messages)
    finally:
        if not args.keep:
            shutil.rmtree(work, ignore_errors=True)
    ran = [o for o in outcomes if not getattr(o, "skipped", "")]
    clean = sum(o.clean for o in ran)
    defective = sum(o.defective for o in ran)
    skipped = len(outcomes) - len(ran)
    print(f"\n{len(ran)} cases, {clean} clean, {defective} defective, {len(ran) - clean} not clean"
          + (f" ({skipped} skipped)" if skipped else ""))
    sys.exit(0 if clean == len(ran) else 1)


def sweep(work: Path, only: str | None, messages: bool) -> list[Outcome]:
    ball = example_fmu("bouncing_ball")
    inputs, out, tmp = work / "inputs", work / "out", work / "tmp"
    inputs.mkdir(exist_ok=True)
    started = time.perf_counter()
    fmus = bad_fmus(inputs, ball)
    csvs, good_csv = bad_csvs(inputs, ball)
    crashing = crash_fmus()
    print(f"generated the inputs in {time.perf_counter() - started:.1f} s\n")

    runs: list[tuple[str, str, list]] = []
    for case, fmu in fmus.items():
        for command in ("inspect", "simulate"):
            runs.append((case, command, fmu_commands(fmu, out, good_csv)[command]))
    for case, csv in csvs.items():
        for command in ("diagnose", "train", "hybridize"):
            runs.append((case, command, fmu_commands(ball, out, csv)[command]))
    runs += argument_cases(ball, out, good_csv, inputs)
    for mode in MODES:
        for command in ("simulate", "diagnose", "train", "hybridize"):
            runs.append((f"binary: {mode}", command,
                         [*fmu_commands(crashing[mode], out, good_csv)[command], "--call-timeout", CALL_TIMEOUT]))
    if only:
        runs = [r for r in runs if only.lower() in r[0].lower()]

    print("| case | command | exit code | stderr lines | traceback | files left behind | clean |")
    print("|---|---|---|---|---|---|---|")
    outcomes = []
    for case, command, command_args in runs:
        outcome = run_case(case, command, command_args, out, tmp)
        outcomes.append(outcome)
        print(f"| {case} | {command} | {outcome.code} | {outcome.stderr_lines} | "
              f"{'yes' if outcome.traceback else 'no'} | {', '.join(outcome.left) or '-'} | "
              f"{'yes' if outcome.clean else '**NO**'} |", flush=True)
        if messages or not outcome.clean:
            print(f"|   | {outcome.first_line[:300]} | | | | | |", flush=True)
    return outcomes


if __name__ == "__main__":
    main()
