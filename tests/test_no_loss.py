"""Nothing the user had is lost (issue 60): every scenario of benchmarks/sweep_bad_inputs.py, one test
each. A scenario runs the command line in a folder holding the user's files (inputs, an unrelated
thesis.txt, earlier outputs, a FIFO, a symbolic link, a device node); every one of them must be
byte-identical afterwards, a refusal must come as one error line naming the problem before any
work, and nothing may be left behind."""
import importlib.util
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


def _sweep_module():
    spec = importlib.util.spec_from_file_location("sweep_bad_inputs", ROOT / "benchmarks" / "sweep_bad_inputs.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules.setdefault("sweep_bad_inputs", module)
    spec.loader.exec_module(module)
    return module


sweep = _sweep_module()
SCENARIOS = {scenario.name: scenario for scenario in sweep.scenarios()}


@pytest.fixture(scope="module")
def shared(tmp_path_factory):
    return sweep.Shared(tmp_path_factory.mktemp("shared"))


@pytest.mark.parametrize("name", [pytest.param(name, marks=[pytest.mark.slow] if scenario.slow else [])
                                  for name, scenario in SCENARIOS.items()])
def test_every_file_the_user_had_is_unchanged(name, shared, tmp_path):
    outcome = sweep.run_scenario(SCENARIOS[name], shared, tmp_path)
    if outcome.skipped:
        pytest.skip(outcome.skipped)
    assert outcome.lost == [], f"changed or lost: {outcome.lost} ({outcome.first_line})"
    assert not outcome.defective, (outcome.first_line, outcome.problems)
    assert outcome.left == [], f"left behind: {outcome.left}"
    assert outcome.problems == [], (outcome.first_line, outcome.problems)
    assert outcome.clean


def test_the_sweep_covers_every_case_of_the_issue():
    """The issue's cases by the words they are known by; a renamed scenario must keep its case."""
    names = " | ".join(SCENARIOS)
    for words in ("working folder", "did not write", "another program writes", "FIFO", "symbolic link",
                  "device node", "run A wrote the same outputs", "own FMU", "the FMU it wraps", "--json its own data", "existing checkpoint",
                  "existing plots", "--resume without a checkpoint", ".partial", "sidecar's start values",
                  "/proc", "same path", "read-only mount", "--report an existing file", "modelIdentifier",
                  "NaN (rk4)", "--lag nan", "1_000", "e=0_5", 'start="nine"', "duplicate variable names",
                  "duplicate value references", "banana", "--step-size 0", "--batch-size -1", "--decay nan",
                  "--validation-start without --validation", "training file as test data", "no guid",
                  "unknown XML encoding", "2**70", "--lr nan", "sidecar bench.runs a string"):
        assert words in names, words


def test_the_bad_input_sweep_in_short(tmp_path):
    """The sweep's first part (bad FMUs, CSVs, arguments, misbehaving binaries), a few of its cases."""
    outcomes = sweep.sweep(tmp_path, "--start", messages=False)
    assert len(outcomes) >= 3
    assert not any(o.defective for o in outcomes)
    assert all(o.clean for o in outcomes), [(o.case, o.first_line) for o in outcomes if not o.clean]
