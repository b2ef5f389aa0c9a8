"""The effect zoo (benchmarks/zoo, benchmarks/bench_zoo.py) on three development seeds with a tiny
training budget: the truth FMU adds exactly the drawn effect to exactly its channel, the data carry
the noise the generator declares, the size of the effect is the drawn multiple of the noise, and
the bench writes a manifest and a table with one row per seed."""
import json
import tomllib

import numpy as np
import pytest

from benchmarks import bench_zoo
from benchmarks.zoo.bases import BASES
from benchmarks.zoo.generate import DataSettings, check_truth, simulate_at, write_data
from fmubuilder.fmi import read_model_info
from fmubuilder.simulation import read_csv_signals

# Development seeds (below 1000): a wrong parameter, a missing effect and no effect at all, each on
# a model with a short run.
SEEDS = {"parameter": 0, "effect": 32, "none": 43}


@pytest.fixture(scope="module")
def zoo(tmp_path_factory):
    out = tmp_path_factory.mktemp("zoo")
    bench_zoo.main(["--seeds", ",".join(str(s) for s in SEEDS.values()), "--budget", "1", "--jobs", "1",
                    "--out", str(out)])
    return out


def truth_of(zoo, kind):
    return json.loads((zoo / f"seed-{SEEDS[kind]}" / "truth.json").read_text())


def test_each_seed_draws_the_kind_it_is_used_for(zoo):
    assert {kind: truth_of(zoo, kind)["kind"] for kind in SEEDS} == {kind: kind for kind in SEEDS}


def test_the_truth_adds_exactly_the_effect_to_its_channel(zoo):
    """At states along the training run the truth FMU's derivatives are the declared ones plus the
    effect evaluated with numpy on the declared FMU's variables; a check with the wrong effect fails."""
    from benchmarks.zoo.effects import Effect, Part
    truth = truth_of(zoo, "effect")
    assert truth["truth_check_relative_error"] < 1e-9
    case = zoo / f"seed-{SEEDS['effect']}"
    effect = Effect(truth["effect"]["channel"], [Part(**p) for p in truth["effect"]["parts"]])
    info = read_model_info(case / "declared.fmu")
    time, _ = read_csv_signals(case / "train.csv")
    start = json.loads((case / "train.csv.json").read_text())["start_values"]
    states = [s.name for s in info.states]
    plain = simulate_at(case / "declared.fmu", time, states + effect.inputs, start)
    points = np.column_stack([plain[s] for s in states])[::10]
    assert np.ptp(effect.evaluate({v: plain[v] for v in effect.inputs})) > 0   # the effect is there
    args = (case / "declared.fmu", case / "truth.fmu")
    assert check_truth(*args, effect, time[::10], points, {}, start) < 1e-9
    effect.parts[0].amplitude *= 1.5
    assert check_truth(*args, effect, time[::10], points, {}, start) > 1e-3


def test_the_plain_models_test_error_is_the_drawn_multiple_of_the_noise(zoo):
    """On the noise-free test run, the most affected signal's plain MSE / noise variance is the target."""
    for kind in ("parameter", "effect"):
        truth = truth_of(zoo, kind)
        assert 10 <= truth["target_ratio"] <= 1e4
        assert max(truth["plain_test_ratio"].values()) == pytest.approx(truth["target_ratio"], rel=1e-9)


@pytest.mark.parametrize("model", ["white", "ar1", "lowpass"])
def test_the_data_carry_the_declared_noise(tmp_path, model):
    """A long run of a zero signal: the mean column's variance is one run's over the runs, the
    spread column's mean square one run's (sampling error of about 5 % at this length)."""
    rate, runs, sigma = 50.0, 3, 0.2
    settings = DataSettings(rate=rate, jitter=0.3, runs=runs, spread_columns=True, noise_model=model,
                            noise_rho=0.5, noise_filter_tau=2.0 / rate, noise_filter_order=1,
                            separate_validation=False)
    stamps = np.arange(20000) / rate
    write_data(tmp_path / "d.csv", np.random.default_rng(1), settings, stamps, {"y": np.zeros(stamps.size)},
               {"y": sigma}, {}, {})
    _, columns = read_csv_signals(tmp_path / "d.csv")
    assert np.var(columns["y"]) == pytest.approx(sigma ** 2 / runs, rel=0.15)
    assert np.mean(columns["y_std"] ** 2) == pytest.approx(sigma ** 2, rel=0.1)


def test_the_truth_scores_at_the_noise_floor(zoo):
    """The truth simulated on the test data: MSE / noise variance near 1 for every signal (the
    scoring's own check; short coloured runs, so a wide band)."""
    rows = {kind: json.loads((zoo / f"seed-{seed}" / "result.json").read_text()) for kind, seed in SEEDS.items()}
    for row in rows.values():
        for ratio in row["truth_ratios"].values():
            assert 0.2 < ratio < 3.0, rows


def test_the_bench_writes_a_manifest_and_a_table_row_per_seed(zoo):
    manifest = tomllib.loads((zoo / "manifest.toml").read_text())
    assert [c["name"] for c in manifest["case"]] == [f"seed-{s}" for s in SEEDS.values()]
    for case in manifest["case"]:
        truth = json.loads((zoo / case["name"] / "truth.json").read_text())
        for path in [case["model"], *case["train"], case["test"], case.get("validation")]:
            assert path is None or (zoo / path).is_file()
        assert ("validation" in case) == truth["data"]["separate_validation"]
    table = (zoo / "zoo.md").read_text().splitlines()
    rows = [line for line in table if line.startswith("| ") and line.split("|")[1].strip().isdigit()]
    assert [int(r.split("|")[1]) for r in rows] == list(SEEDS.values())
    assert any(line.startswith("success: ") and "/2 seeds" in line for line in table)
    assert any(line.startswith("false publish: ") and "/1 seeds" in line for line in table)
    assert {b.name for b in BASES} >= {json.loads((zoo / c["name"] / "truth.json").read_text())["base"]
                                       for c in manifest["case"]}
