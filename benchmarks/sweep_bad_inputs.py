"""Sweep of bad inputs through the command line: every one must end cleanly.

Generates damaged and hostile FMUs (corrupt, truncated, path traversal, zip and entity bombs,
FMI 1.0/3.0, Co-Simulation only, missing or broken binaries), malformed CSVs, bad arguments
and FMU binaries that segfault, abort, exit or hang (tests/fmi/crashing), runs each through
`python -m fmubuilder.cli` with TMPDIR pointed at a fresh folder and prints one row per run:

    case | command | exit code | stderr lines | traceback | files left behind

A run is clean when it exits non-zero with exactly one `error:` line, no traceback, no
temporary folder and no output left behind; for the few runs that should succeed (`inspect`
reads the archive but never loads the binary) when it exits 0 with nothing on stderr.

    python benchmarks/sweep_bad_inputs.py [--only SUBSTRING] [--keep DIR]
"""
from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

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
        "no linux64 binary": bad.rewrite_fmu(ball, folder / "no_bin.fmu", drop=("binaries/linux64",)),
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
    args = parser.parse_args()

    work = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="fmubuilder-sweep-"))
    work.mkdir(parents=True, exist_ok=True)
    try:
        outcomes = sweep(work, args.only, args.messages)
    finally:
        if not args.keep:
            shutil.rmtree(work, ignore_errors=True)
    clean = sum(o.clean for o in outcomes)
    print(f"\n{len(outcomes)} cases, {clean} clean, {len(outcomes) - clean} not clean")
    sys.exit(0 if clean == len(outcomes) else 1)


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
