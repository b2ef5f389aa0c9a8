"""Collocation near steps: the windows whose local line bends are left out of the estimate of the
missing term, checked against np.polyfit and against the friction compiled into the DC drive's
Coulomb truth (examples/dc_drive/model.c)."""
import numpy as np
import pytest

from fmubuilder import synth
from fmubuilder.build import example_fmu
from fmubuilder.data import load_data
from fmubuilder.neural import collocation
from fmubuilder.neural.collocation import collocation_samples, local_roughness, smooth_windows
from fmubuilder.neural.model import NeuralFMU
from fmubuilder.neural.topology import TopologyConfig

# examples/dc_drive/model.c: Coulomb torque 0.05 * tanh(w / 1 rad/s) on an inertia of 0.01 kg m2.
COULOMB_PER_INERTIA = 0.05 / 0.01


def test_local_roughness_is_the_residual_of_a_least_squares_line():
    rng = np.random.default_rng(1)
    time = np.sort(rng.uniform(0.0, 10.0, 400))
    values = np.sin(time) + 0.1 * rng.standard_normal(time.size)
    at, window = np.array([1.0, 4.3, 7.7]), 1.5
    for t, got in zip(at, local_roughness(time, values, at, window)):
        inside = np.abs(time - t) <= 0.5 * window
        line = np.polyfit(time[inside], values[inside], 1)
        residual = values[inside] - np.polyval(line, time[inside])
        assert got == pytest.approx(np.sqrt(np.sum(residual ** 2) / (inside.sum() - 2)), rel=1e-9)


def test_windows_across_a_step_are_not_smooth(tmp_path):
    """A ramp with a step at 5 s, noise 0.01: windows holding the step are flagged, the others kept."""
    rng = np.random.default_rng(2)
    time = np.arange(0.0, 10.0, 0.1)
    clean = 0.3 * time + np.where(time >= 5.0, 1.0, 0.0)

    class Data:
        signals = {"x": clean + 0.01 * rng.standard_normal(time.size)}
    Data.time = time
    smooth = smooth_windows(Data, ["x"], time, 0.5)
    across = np.abs(time - 4.95) < 0.25
    assert not smooth[across].any()
    assert smooth[~across].mean() > 0.85


@pytest.fixture(scope="module")
def coulomb_data(tmp_path_factory):
    """30 s of the DC drive's profile (ramps, load steps, a reversal) logged from the Coulomb truth
    at 10 Hz with the bench's sensor lag and noise."""
    settings = synth.BenchSettings(signals=("speed", "current", "temperature", "energy"),
                                   noise_std={"speed": 0.1, "current": 0.02, "temperature": 0.02, "energy": 1.0},
                                   seed=0)
    path = tmp_path_factory.mktemp("coulomb") / "coulomb.csv"
    synth.write_measurement(synth.measure(example_fmu("dc_drive_truth_coulomb"), stop_time=30.0, settings=settings),
                            path)
    return path


def _estimate_error(fmu, path, monkeypatch, limit):
    """rms of (collocation estimate - true friction) over the kept samples, and the true friction's rms."""
    monkeypatch.setattr(collocation, "ROUGHNESS_LIMIT", limit)
    model = NeuralFMU(fmu, TopologyConfig(channels=["der(speed)"], inputs=["speed"], hidden=[4], kind="residual"))
    try:
        data = load_data(path, model.info)
        inputs, fmu_channels, measured, mask = collocation_samples(
            model, data, 0.01, "rk4", 0.5, data.input_signals(model.info), data.sensor_lag or 0.0)
    finally:
        model.close()
    kept = mask[:, 0]
    truth = -COULOMB_PER_INERTIA * np.tanh(inputs[kept, 0])
    estimate = measured[kept, 0] - fmu_channels[kept, 0]
    return np.sqrt(np.mean((estimate - truth) ** 2)), np.sqrt(np.mean(truth ** 2)), kept.mean()


def test_collocation_finds_the_coulomb_friction_away_from_the_steps(dc_drive_fmu, coulomb_data, monkeypatch):
    error, size, kept = _estimate_error(dc_drive_fmu, coulomb_data, monkeypatch, collocation.ROUGHNESS_LIMIT)
    assert kept > 0.3
    assert error < 0.15 * size
    # every window kept: the steps' windows dominate the estimate (the independent check that the
    # rule above is what makes the difference)
    error_all, size_all, _ = _estimate_error(dc_drive_fmu, coulomb_data, monkeypatch, np.inf)
    assert error_all > 0.5 * size_all


def test_the_output_is_scaled_to_the_estimated_effect_and_the_hybrid_stays_the_fmu(dc_drive_fmu):
    import torch
    from fmubuilder.neural.warm_start import scale_output_to_effect
    model = NeuralFMU(dc_drive_fmu, TopologyConfig(channels=["der(speed)"], inputs=["speed"], hidden=[4],
                                                   kind="residual"))
    try:
        topology = model.topology
        with torch.no_grad():
            topology.post_scale.fill_(47.0)        # the derivative's spread, as initialise_scaling sets it
        effect = torch.tensor([[3.0], [-4.0], [0.0], [5.0]], dtype=torch.float64)
        scale_output_to_effect(topology, effect)
        assert float(topology.post_scale[0].detach()) == pytest.approx(np.sqrt(np.mean([9.0, 16.0, 0.0, 25.0])))
        x = torch.tensor([[10.0], [-50.0]], dtype=torch.float64)
        assert torch.equal(topology.correction(x), torch.zeros(2, 1, dtype=torch.float64))
    finally:
        model.close()


def test_a_run_forced_along_the_model_s_own_run_keeps_its_events():
    """The VLDM forced to its own engine run, every state after every step: its derivatives are
    the run's at every grid point. Its driver's relay switches inside a step, and the switch brings
    the speed error back under the threshold by the step's end, so the forced end alone shows no
    crossing (before the step's natural course was checked, 462 of these 6001 points kept the
    brake on where the run had the throttle)."""
    from fmubuilder.data import MeasuredData
    from fmubuilder.simulation import simulate
    fmu = example_fmu("vldm")
    model = NeuralFMU(fmu, TopologyConfig())
    states = model.state_names()
    derivatives = [f"der({s})" for s in states]
    run = simulate(fmu, start_time=0.0, stop_time=60.0, variables=[*states, *derivatives], solver="rk4",
                   step_size=0.01, output_interval=0.01)
    grid = np.asarray(run.time, dtype=float)

    def along_run(t):
        t = np.atleast_1d(np.asarray(t, dtype=float))
        return np.stack([np.interp(t, grid, np.asarray(run[s], dtype=float)) for s in states], axis=1)
    window = MeasuredData(time=np.array([0.0, 60.0]), signals={"speed": np.zeros(2)})
    try:
        forced = collocation.forced_run(model, window, 0.01, "rk4", states, along_run, derivatives, None)
    finally:
        model.close()
    assert forced.stats["state_events"] > 0 and np.array_equal(forced.times, grid)
    for name in derivatives:
        np.testing.assert_allclose(forced.numpy(name)[:, 0], np.asarray(run[name], dtype=float),
                                   rtol=1e-9, atol=1e-9, err_msg=name)
