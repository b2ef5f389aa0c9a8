"""The synthetic test bench (fmubuilder.synth) and the VLDM example folder.

References: closed-form first-order responses, fmpy simulations of the truth FMUs (the
generator's own noise-free values are never used as the reference), and the statistics of
Gaussian noise. Windows are short (150 s of a cycle) to keep the tests fast.
"""
import json
import subprocess
import sys
from functools import lru_cache

import numpy as np
import pytest
from fmpy import simulate_fmu

from fmubuilder.build import example_fmu
from fmubuilder.data import first_order_lag, linear_recurrence, sidecar_path, split_uncertainty_columns
from fmubuilder.errors import FmuBuilderError
from fmubuilder.synth import (
    DEFAULT_NOISE_STD,
    BenchSettings,
    measure,
    sample_times,
    unit_noise,
    write_measurement,
)
from fmubuilder.simulation.inputs import read_csv_signals

WINDOW = 150.0          # s of the CADC road cycle (cycle=1): standstill, urban driving, 64 km/h
CADC = {"cycle": 1}
SIGNALS = ("speed", "power", "energy")


@lru_cache(maxsize=None)
def fmu(name):
    return example_fmu(name)


@lru_cache(maxsize=None)
def reference(name, stop_time=WINDOW, names=SIGNALS + ("target_speed",)):
    """fmpy's trajectories on the 0.01 s grid plus the values before/after every event."""
    result = simulate_fmu(str(fmu(name)), stop_time=stop_time, start_values=dict(CADC), output=list(names),
                          output_interval=0.01, record_events=True, relative_tolerance=1e-10)
    return result["time"], {n: np.asarray(result[n], dtype=float) for n in names}


def reference_at(name, stamps, lag, names=SIGNALS):
    """Reference signals through the sensor filter (checked analytically below) at the stamps."""
    time, values = reference(name)
    return {n: np.interp(stamps, time, first_order_lag(time, values[n], lag)) for n in names}


@lru_cache(maxsize=None)
def measured(name, seed=0):
    return measure(fmu(name), stop_time=WINDOW, start_values=CADC, settings=BenchSettings(seed=seed))


def noise_of_mean(signal, runs=2):
    return DEFAULT_NOISE_STD[signal] / np.sqrt(runs)


# ---------------------------------------------------------------------------------------
# bench model pieces against closed-form answers


def test_lag_of_a_step_is_the_first_order_response():
    tau = 0.1
    before = np.linspace(0.0, 1.0, 101)
    after = np.concatenate([[1.0], np.sort(np.random.default_rng(1).uniform(1.0, 2.0, 300)), [2.0]])
    time = np.concatenate([before, after])            # t = 1 appears twice: the step
    step = np.concatenate([np.zeros_like(before), np.ones_like(after)])
    expected = np.where(time < 1.0, 0.0, 1.0 - np.exp(-(time - 1.0) / tau))
    np.testing.assert_allclose(first_order_lag(time, step, tau), expected, atol=1e-12)


def test_lag_of_a_ramp_is_delayed_by_tau():
    tau, slope = 0.25, 3.0
    time = np.cumsum(np.random.default_rng(2).uniform(0.001, 0.05, 400))
    time -= time[0]
    expected = slope * time - slope * tau * (1.0 - np.exp(-time / tau))
    np.testing.assert_allclose(first_order_lag(time, slope * time, tau), expected, atol=1e-12)
    late = time > 30 * tau
    np.testing.assert_allclose(first_order_lag(time, slope * time, tau)[late], slope * (time[late] - tau), atol=1e-9)


def test_the_lag_s_recurrence_matches_a_plain_loop_on_a_grid_of_cut_steps():
    """Steps of very different length (the products of decay ratios leave exp(+-200), so the
    filter restarts) and repeated points: the recurrence y_j = a_j y_(j-1) + x_j written out."""
    rng = np.random.default_rng(4)
    a = np.exp(-rng.choice([0.001, 0.1, 0.1, 0.1, 5.0], size=30000))
    x = rng.normal(size=a.size)
    expected, y = np.empty_like(x), 0.7
    for j in range(a.size):
        y = a[j] * y + x[j]
        expected[j] = y
    np.testing.assert_allclose(linear_recurrence(a, x, 0.7), expected, rtol=1e-11, atol=1e-11)


def test_time_stamps_are_strictly_increasing_and_jittered():
    stamps = sample_times(0.0, 100.0, rate=10.0, jitter=0.25, resolution=1e-3, rng=np.random.default_rng(3))
    steps = np.diff(stamps)
    assert stamps[0] == 0.0 and stamps[-1] <= 100.0 and len(stamps) in (1000, 1001)
    assert np.all(steps > 0)
    assert len(np.unique(np.round(steps, 6))) > 50                # non-equidistant
    assert abs(steps.mean() - 0.1) < 1e-3
    nominal = 0.1 * np.arange(len(stamps))
    assert np.max(np.abs(stamps - nominal)) <= 0.025 + 0.0005 + 1e-12  # jitter + rounding
    np.testing.assert_allclose(stamps, np.round(stamps, 3), atol=1e-12)  # 1 ms clock


def test_bouncing_ball_velocity_through_the_bench_matches_the_analytic_response(bouncing_ball_fmu):
    """v(t) = -g t with a jump to e * g * t1 at the impact t1 = sqrt(2 h0 / g): a ramp plus a
    step, whose first-order responses are known in closed form."""
    tau, g, e, h0 = 0.05, 9.81, 0.7, 1.0
    settings = BenchSettings(signals=("v",), noise_std={"v": 0.0}, sample_rate=100.0, time_resolution=1e-4,
                             lag=tau, fine_step=0.001, runs=1, seed=4)
    data = measure(bouncing_ball_fmu, stop_time=1.0, settings=settings)
    t = data.time
    t1 = np.sqrt(2 * h0 / g)
    jump = (1 + e) * g * t1
    expected = -g * t + g * tau * (1 - np.exp(-t / tau)) + np.where(t > t1, jump * (1 - np.exp(-(t - t1) / tau)), 0.0)
    np.testing.assert_allclose(data.runs["v"][0], expected, atol=2e-3)
    # unfiltered, the measured value right after the impact would be ~jump higher
    assert np.max(np.abs(data.runs["v"][0] - np.where(t > t1, jump, 0.0) + g * t)) > 0.5 * jump


# ---------------------------------------------------------------------------------------
# the VLDM measured data against fmpy


def test_same_seed_same_file_other_seed_other_noise(tmp_path):
    first = write_measurement(measured("vldm", seed=11), tmp_path / "a.csv")
    again = write_measurement(measure(fmu("vldm"), stop_time=WINDOW, start_values=CADC,
                                      settings=BenchSettings(seed=11)), tmp_path / "b.csv")
    other = write_measurement(measured("vldm", seed=12), tmp_path / "c.csv")
    assert first.read_bytes() == again.read_bytes()
    assert first.read_bytes() != other.read_bytes()
    a, b = measured("vldm", seed=11), measured("vldm", seed=12)
    assert not np.array_equal(a.time, b.time)
    residual_a = a.runs["speed"][0] - reference_at("vldm", a.time, 0.1)["speed"]
    residual_b = b.runs["speed"][0] - reference_at("vldm", b.time, 0.1)["speed"]
    n = min(len(residual_a), len(residual_b))
    assert abs(np.corrcoef(residual_a[:n], residual_b[:n])[0, 1]) < 0.1   # independent noise


def test_csv_layout_and_sidecar(tmp_path):
    data = measured("vldm")
    path = write_measurement(data, tmp_path / "data.csv")
    header = path.read_text().splitlines()[0].split(",")
    assert header == ["time", *SIGNALS, *(s + "_std" for s in SIGNALS)]
    assert split_uncertainty_columns(header) == (list(SIGNALS), {s: s + "_std" for s in SIGNALS})
    time, columns = read_csv_signals(path)                     # the engine's CSV reader accepts it
    assert np.all(np.diff(time) > 0) and time[0] == 0.0
    assert len(np.unique(np.round(np.diff(time), 6))) > 10             # non-equidistant
    meta = json.loads(sidecar_path(path).read_text())
    assert meta["start_values"] == {"cycle": 1} and meta["start_options"] == "--start cycle=1"
    assert meta["seed"] == 0 and meta["truth_model"]["file"] == "vldm.fmu"
    assert meta["bench"]["noise_std"] == {s: DEFAULT_NOISE_STD[s] for s in SIGNALS}
    assert meta["bench"]["runs"] == 2 and meta["bench"]["lag"] == 0.1


def test_std_columns_are_the_spread_of_the_two_runs(tmp_path):
    data = measured("vldm")
    time, columns = read_csv_signals(write_measurement(data, tmp_path / "data.csv"))
    for s in SIGNALS:
        first, second = data.runs[s]
        scale = np.max(np.abs(data.runs[s])) * 1e-9 + 1e-12        # 10 significant digits in the file
        np.testing.assert_allclose(columns[s], (first + second) / 2, atol=scale)
        np.testing.assert_allclose(columns[s + "_std"], np.abs(first - second) / np.sqrt(2), atol=scale)
        # E[std^2] = sigma^2 for ddof=1; (a-b)^2/2 is sigma^2 chi2(1): relative spread sqrt(2/n)
        ratio = np.mean(columns[s + "_std"] ** 2) / DEFAULT_NOISE_STD[s] ** 2
        assert abs(ratio - 1) < 5 * np.sqrt(2 / len(time)), (s, ratio)


def test_noise_of_the_mean_and_of_each_run_has_the_configured_size():
    data = measured("vldm")
    expected = reference_at("vldm", data.time, 0.1)
    n = len(data.time)
    for s in SIGNALS:
        residual = data.mean(s) - expected[s]
        sigma = noise_of_mean(s)
        # sample std of n Gaussian values: relative standard error 1/sqrt(2n)
        assert abs(residual.std() / sigma - 1) < 5 / np.sqrt(2 * n), (s, residual.std(), sigma)
        assert abs(residual.mean()) < 5 * sigma / np.sqrt(n), (s, residual.mean())
        for run in data.runs[s]:
            assert abs((run - expected[s]).std() / DEFAULT_NOISE_STD[s] - 1) < 5 / np.sqrt(2 * n)


def test_no_effect_data_reproduce_the_declared_model_within_noise():
    data = measured("vldm", seed=5)
    expected = reference_at("vldm", data.time, 0.1)
    for s in SIGNALS:
        normalized = (data.mean(s) - expected[s]) / noise_of_mean(s)
        chi2 = np.mean(normalized ** 2)                            # ~ 1 +- sqrt(2/n)
        assert abs(chi2 - 1) < 5 * np.sqrt(2 / len(normalized)), (s, chi2)
        assert np.max(np.abs(normalized)) < 6                      # no outliers beyond Gaussian noise


def test_measured_speed_lags_the_true_speed_by_tau():
    tau = 0.1
    settings = BenchSettings(noise_std={s: 0.0 for s in SIGNALS}, lag=tau, seed=6)
    data = measure(fmu("vldm"), stop_time=WINDOW, start_values=CADC, settings=settings)
    time, values = reference("vldm")
    delays = np.arange(0.0, 0.3, 0.002)
    errors = [np.mean((data.runs["speed"][0] - np.interp(data.time - d, time, values["speed"])) ** 2) for d in delays]
    best = delays[int(np.argmin(errors))]
    assert abs(best - tau) < 0.01, best
    assert min(errors) < 0.05 * errors[0]                          # the delay explains the difference


def test_run_variation_scales_the_parameter_per_run():
    settings = BenchSettings(run_variation={"rolling_coefficient": 0.05}, seed=7)
    data = measure(fmu("vldm"), stop_time=60.0, start_values=CADC, settings=settings)
    runs = data.metadata["run_start_values"]
    coefficients = [run["rolling_coefficient"] for run in runs]
    assert coefficients[0] != coefficients[1] and all(abs(c / 0.0185 - 1) < 0.3 for c in coefficients)
    for run, values in zip(data.runs["energy"], runs):
        truth = simulate_fmu(str(fmu("vldm")), stop_time=60.0, start_values=values, output=["energy"],
                             output_interval=0.01, record_events=True, relative_tolerance=1e-10)
        lagged = np.interp(data.time, truth["time"], first_order_lag(truth["time"], truth["energy"], 0.1))
        assert np.std(run - lagged) < 1.2 * DEFAULT_NOISE_STD["energy"]


# ---------------------------------------------------------------------------------------
# coloured sensor noise


def _lag_correlation(noise, lag=1):
    return float(np.corrcoef(noise[lag:], noise[:-lag])[0, 1])


STAMPS = 0.1 * np.arange(40000)     # 10 Hz, equidistant: the correlations below are analytic


def test_ar1_noise_has_unit_variance_and_the_given_correlation():
    noise = unit_noise(STAMPS, BenchSettings(noise_model="ar1", noise_rho=0.7), np.random.default_rng(1))
    assert noise.std() == pytest.approx(1.0, rel=0.03)
    assert _lag_correlation(noise) == pytest.approx(0.7, abs=0.02)
    assert _lag_correlation(noise, 3) == pytest.approx(0.7 ** 3, abs=0.03)


def test_lowpass_noise_correlates_like_the_filtered_white_noise():
    """One first-order stage (time constant tau): rho(h) = exp(-h / tau); two stages:
    rho(h) = (1 + h / tau) exp(-h / tau)."""
    rng = np.random.default_rng(2)
    one = unit_noise(STAMPS, BenchSettings(noise_model="lowpass", noise_filter_tau=0.1), rng)
    assert one.std() == pytest.approx(1.0, rel=0.05)     # interpolation to the stamps smooths a little
    assert _lag_correlation(one) == pytest.approx(np.exp(-1.0), abs=0.03)
    two = unit_noise(STAMPS, BenchSettings(noise_model="lowpass", noise_filter_tau=0.3, noise_filter_order=2), rng)
    assert two.std() == pytest.approx(1.0, rel=0.05)
    assert _lag_correlation(two, 2) == pytest.approx((1 + 0.2 / 0.3) * np.exp(-0.2 / 0.3), abs=0.03)


def test_white_noise_is_independent_between_samples():
    noise = unit_noise(STAMPS, BenchSettings(), np.random.default_rng(3))
    assert abs(_lag_correlation(noise)) < 0.02 and noise.std() == pytest.approx(1.0, rel=0.03)


def test_coloured_noise_is_logged_with_the_configured_size():
    settings = BenchSettings(noise_model="ar1", noise_rho=0.6, seed=4)
    data = measure(fmu("vldm"), stop_time=WINDOW, start_values=CADC, settings=settings)
    expected = reference_at("vldm", data.time, 0.1)
    for s in SIGNALS:
        error = data.runs[s] - expected[s]
        assert error.std() == pytest.approx(DEFAULT_NOISE_STD[s], rel=0.2), s
        assert _lag_correlation(error[0]) == pytest.approx(0.6, abs=0.1), s
    assert json.loads(json.dumps(data.metadata))["bench"]["noise_model"] == "ar1"


@pytest.mark.parametrize("settings, fragment", [
    (BenchSettings(noise_model="pink"), "choose one of white, ar1, lowpass"),
    (BenchSettings(noise_model="ar1", noise_rho=1.0), "strictly between -1 and 1"),
    (BenchSettings(noise_model="lowpass"), "time constant > 0"),
    (BenchSettings(noise_model="lowpass", noise_filter_tau=0.1, noise_filter_order=7), "choose 1 to 4"),
])
def test_bad_noise_settings_are_refused(settings, fragment):
    with pytest.raises(FmuBuilderError, match=fragment):
        measure(fmu("vldm"), stop_time=5.0, start_values=CADC, settings=settings)


def test_truth_parameters_change_the_truth_and_are_recorded_apart_from_the_start_values(tmp_path):
    """A heavier car than declared: more energy; the sidecar names the mass only under
    'truth', never among the start values a user passes back to the model."""
    settings = BenchSettings(seed=5)
    heavy = measure(fmu("vldm"), stop_time=60.0, start_values=CADC, settings=settings,
                    truth_parameters={"mass": 1087.35})
    truth = simulate_fmu(str(fmu("vldm")), stop_time=60.0, start_values={**CADC, "mass": 1087.35}, output=["energy"],
                         output_interval=0.01, record_events=True, relative_tolerance=1e-10)
    lagged = np.interp(heavy.time, truth["time"], first_order_lag(truth["time"], truth["energy"], 0.1))
    assert np.std(heavy.mean("energy") - lagged) < 1.2 * noise_of_mean("energy")
    write_measurement(heavy, tmp_path / "heavy.csv")
    meta = json.loads(sidecar_path(tmp_path / "heavy.csv").read_text())
    assert meta["start_values"] == CADC and "mass" not in meta["start_options"]
    assert meta["truth"] == {"parameters": {"mass": 1087.35}}


# ---------------------------------------------------------------------------------------
# the truth effects


def test_extra_resistance_costs_energy_while_the_speed_follows_the_cycle():
    declared, truth = measured("vldm"), measured("vldm_truth_extra_resistance")
    gain = truth.mean("energy")[-1] / declared.mean("energy")[-1] - 1
    assert gain > 0.01                                             # a few % on this window
    assert gain * declared.mean("energy")[-1] > 100 * noise_of_mean("energy")
    target = reference_at("vldm", truth.time, 0.1, names=("target_speed",))["target_speed"]
    assert np.sqrt(np.mean((truth.mean("speed") - target) ** 2)) < 0.1   # m/s, at speeds up to 18 m/s


def test_extra_loss_costs_energy_and_leaves_the_speed_unchanged():
    declared, truth = measured("vldm"), measured("vldm_truth_extra_loss")
    assert np.array_equal(declared.time, truth.time)               # same seed, same stamps
    gain = truth.mean("energy")[-1] / declared.mean("energy")[-1] - 1
    assert gain > 0.01                                             # several % on this window
    assert gain * declared.mean("energy")[-1] > 100 * noise_of_mean("energy")
    driving = truth.mean("speed") > 1.0
    extra_power = truth.mean("power")[driving] - declared.mean("power")[driving]
    assert np.mean(extra_power) > 0.01 * np.mean(declared.mean("power")[driving])
    # Same seed: identical noise, so the speeds differ by the effect alone. With other seeds the
    # difference is pure noise of std sqrt(2) * sigma_mean.
    assert np.max(np.abs(truth.mean("speed") - declared.mean("speed"))) < 1e-3
    other = measured("vldm_truth_extra_loss", seed=8)
    difference = other.mean("speed") - np.interp(other.time, declared.time, declared.mean("speed"))
    sigma = np.sqrt(2) * noise_of_mean("speed")
    # interpolating the declared data between its stamps adds a little: allow 15 %
    assert abs(difference.std() / sigma - 1) < 0.15
    assert abs(difference.mean()) < 5 * sigma / np.sqrt(len(difference))


# ---------------------------------------------------------------------------------------
# command line


def run_cli(*args):
    return subprocess.run([sys.executable, "-m", "fmubuilder.cli", *map(str, args)],
                          capture_output=True, text=True, timeout=300)


def assert_one_line_error(proc, *fragments):
    assert proc.returncode != 0
    assert "Traceback" not in proc.stderr
    lines = [line for line in proc.stderr.strip().splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), proc.stderr
    for fragment in fragments:
        assert fragment in lines[0], lines[0]


@pytest.mark.parametrize("options, fragments", [
    (["--signals", "speed,sped"], ["unknown signal 'sped'", "did you mean 'speed'"]),
    (["--stop-time", "0"], ["not after the start time"]),
    (["--stop-time", "5", "--start-time", "10"], ["not after the start time"]),
    (["--start", "cycle=one"], ["cycle"]),
    (["--noise", "speed=abc"], ["must be a number"]),
    (["--signals", "speed", "--noise", "power=1"], ["names no logged signal"]),
    (["--signals", "speed,target_speed"], ["no default sensor noise", "--noise target_speed=STD"]),
])
def test_bad_input_gives_a_one_line_error(tmp_path, options, fragments):
    args = ["synth", fmu("vldm"), "--stop-time", "5", "-o", tmp_path / "data.csv", *options]
    proc = run_cli(*args)
    assert_one_line_error(proc, *fragments)
    assert not (tmp_path / "data.csv").exists()


def test_cli_does_not_clobber_without_force(tmp_path):
    output = tmp_path / "data.csv"
    first = run_cli("synth", fmu("vldm"), "--stop-time", "3", "--start", "cycle=2", "-o", output)
    assert first.returncode == 0, first.stderr
    assert "--start cycle=2" in first.stdout
    content = output.read_bytes()
    refused = run_cli("synth", fmu("vldm"), "--stop-time", "3", "--seed", "1", "-o", output)
    assert_one_line_error(refused, "exists", "--force")
    assert output.read_bytes() == content
    forced = run_cli("synth", fmu("vldm"), "--stop-time", "3", "--seed", "1", "-o", output, "--force")
    assert forced.returncode == 0, forced.stderr
    assert output.read_bytes() != content
    assert json.loads(sidecar_path(output).read_text())["seed"] == 1


def test_write_measurement_refuses_an_existing_sidecar(tmp_path):
    data = measure(fmu("vldm"), stop_time=2.0, start_values=CADC)
    sidecar_path(tmp_path / "data.csv").write_text("{}")
    with pytest.raises(FmuBuilderError, match="--force"):
        write_measurement(data, tmp_path / "data.csv")
    assert not (tmp_path / "data.csv").exists()


# ---------------------------------------------------------------------------------------
# the example folder


@pytest.fixture
def short_examples(monkeypatch, tmp_path):
    """The VLDM example with 20 s cycles and a private data cache."""
    from fmubuilder import examples_zoo
    monkeypatch.setattr(examples_zoo, "cycle_duration", lambda cycle: 20.0)
    monkeypatch.setattr(examples_zoo, "data_cache_dir", lambda: tmp_path / "cache")
    return examples_zoo


def test_example_folder_holds_fmus_data_and_readme(short_examples, tmp_path):
    folder = short_examples.write_example("vldm", tmp_path / "example")
    names = {p.name for p in (tmp_path / "example").iterdir()}
    assert {"vldm.fmu", "vldm_truth_extra_resistance.fmu", "vldm_truth_extra_loss.fmu", "README.md"} <= names
    for variant in ("no_effect", "extra_resistance", "extra_loss", "mass_mismatch"):
        for role, cycle, number in (("train", "cadc", 1), ("test", "wltc2", 2)):
            csv = tmp_path / "example" / f"{variant}_{role}_{cycle}.csv"
            meta = json.loads(sidecar_path(csv).read_text())
            assert meta["start_values"] == {"cycle": number}       # the mismatch's mass is not a start value
            assert (tmp_path / "example" / meta["truth_model"]["file"]).is_file()
            assert meta["bench"]["noise_model"] == "lowpass"        # filtered sensors: coloured noise
            assert meta.get("truth") == ({"parameters": {"mass": 1087.35}} if variant == "mass_mismatch" else None)
    readme = (tmp_path / "example" / "README.md").read_text()
    assert "--start cycle=1" in readme and "--start cycle=2" in readme
    assert folder.generation_seconds > 0

    again = short_examples.write_example("vldm", tmp_path / "again")
    assert again.generation_seconds == 0.0                         # all from the cache
    for name in folder.data:
        assert (tmp_path / "example" / name).read_bytes() == (tmp_path / "again" / name).read_bytes()

    with pytest.raises(FmuBuilderError, match="--force"):
        short_examples.write_example("vldm", tmp_path / "example")
    short_examples.write_example("vldm", tmp_path / "example", force=True)


@pytest.mark.parametrize("cycle", ["cadc", "wltc2"])
def test_example_cycle_numbers_select_the_cycle_profiles(cycle):
    """`cycle=N` in the FMU drives the profile the example names (target speed vs the CSV)."""
    from fmubuilder.build import repo_root
    from fmubuilder.examples_zoo import VLDM_CYCLES, cycle_duration
    chosen = next(c for c in VLDM_CYCLES if c.key == cycle)
    profile = np.loadtxt(repo_root() / "examples" / "vldm" / "data" / "cycles" / chosen.profile,
                         delimiter=",", skiprows=1, usecols=(0, 1))
    assert cycle_duration(chosen) == profile[-1, 0]
    result = simulate_fmu(str(fmu("vldm")), stop_time=300.0, start_values={"cycle": chosen.number},
                          output=["target_speed"], output_interval=0.5, record_events=False)
    np.testing.assert_allclose(result["target_speed"], np.interp(result["time"], profile[:, 0], profile[:, 1]),
                               atol=1e-9)


def test_unknown_example_is_a_one_line_error(tmp_path):
    assert_one_line_error(run_cli("example", "nothing", "-o", tmp_path / "x"), "unknown example 'nothing'", "vldm")
