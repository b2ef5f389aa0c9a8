"""Per-channel inputs: with two corrected derivatives each correction reads only the inputs chosen
for it (neural/topology.py, block_diagonal), in torch, in the numpy fold, after saving and in the
exported network; the input choice hands each channel its own inputs (hybridize/inputs.py).

The reference is a synthetic truth: the speed channel's target is a function of the speed plus a
disturbance that depends on the current alone, with zero mean, as the collocation estimate's error
on the DC drive's two effects does (there the friction read the current and biased the heating)."""
import numpy as np
import onnxruntime
import pytest
import torch

from fmubuilder.hybridize.inputs import AnnChoice, InputChoice
from fmubuilder.neural import NeuralFMU, TopologyConfig, load_neural_fmu, save_neural_fmu
from fmubuilder.neural.warm_start import fit_full_batch

CHANNELS = ["der(energy)", "der(speed)"]
INPUTS = ["current", "speed"]


def friction(speed):
    return -8.0 * np.tanh(speed / 20.0)


def samples(n=600, seed=0):
    """(inputs [n, 2], targets [n, 2], the speed channel's truth [n]): current and speed drawn
    independently, so that the disturbance's mean at any speed is 0."""
    rng = np.random.default_rng(seed)
    current, speed = rng.uniform(-4.0, 8.0, n), rng.uniform(-150.0, 200.0, n)
    disturbance = 3.0 * np.sin(current)          # mean 0 over the current's range at every speed
    disturbance -= disturbance.mean()
    loss = 0.01 * np.abs(speed * current)
    x = np.stack([current, speed], axis=1)
    return torch.from_numpy(x), torch.from_numpy(np.stack([loss, friction(speed) + disturbance], axis=1)), \
        friction(speed)


def fitted_model(dc_drive_fmu, channel_inputs):
    torch.manual_seed(0)
    model = NeuralFMU(dc_drive_fmu, TopologyConfig(channels=CHANNELS, inputs=INPUTS, hidden=[8, 8], kind="residual",
                                                   channel_inputs=channel_inputs))
    x, target, _ = samples()
    model.topology.initialise_scaling(x.numpy(), target.numpy())
    fit_full_batch(model.topology, x, target, 150)
    return model


def speed_channel_on_grid(correct):
    """The speed channel's correction on a grid of (current, speed): [currents, speeds]."""
    currents, speeds = np.linspace(-4.0, 8.0, 7), np.linspace(-150.0, 200.0, 15)
    grid = np.stack(np.meshgrid(currents, speeds, indexing="ij"), axis=-1).reshape(-1, 2)
    return np.asarray(correct(grid))[:, 1].reshape(len(currents), len(speeds)), speeds


def torch_correction(model):
    def correct(grid):
        with torch.no_grad():
            return model.topology.correction(torch.from_numpy(grid)).numpy()
    return correct


def test_the_speed_channel_reads_the_speed_alone(dc_drive_fmu, tmp_path):
    model = fitted_model(dc_drive_fmu, [["current", "speed"], ["speed"]])
    try:
        values, speeds = speed_channel_on_grid(torch_correction(model))
        # no trace of the current: the same value at every current (to rounding)
        assert np.ptp(values, axis=0).max() < 1e-12 * np.abs(values).max()
        # and the speed's function, the disturbance averaged out (its size is 3 / sqrt(2) rms)
        assert np.sqrt(np.mean((values[0] - friction(speeds)) ** 2)) < 0.6
        # the energy channel still reads both
        x, target, _ = samples()
        with torch.no_grad():
            energy = model.topology.correction(x)[:, 0]
        assert torch.sqrt(torch.mean((energy - target[:, 0]) ** 2)) < 0.2 * torch.sqrt(torch.mean(target[:, 0] ** 2))
        # the fold that the engine's numpy path and the export use
        layers = model.topology.folded()

        def folded(grid):
            z = grid
            for layer in layers:
                z = z @ layer[0].detach().numpy().T + layer[1].detach().numpy() if isinstance(layer, tuple) \
                    else np.tanh(z)
            return z
        np.testing.assert_allclose(speed_channel_on_grid(folded)[0], values, rtol=1e-12, atol=1e-12)
        # saved and loaded: the same network, still blind to the current
        save_neural_fmu(model, tmp_path / "two.neuralfmu")
        loaded = load_neural_fmu(tmp_path / "two.neuralfmu")
        try:
            assert loaded.config.channel_inputs == [["current", "speed"], ["speed"]]
            np.testing.assert_array_equal(speed_channel_on_grid(torch_correction(loaded))[0], values)
        finally:
            loaded.close()
        # the exported network
        from fmubuilder.hybridize.terms import spec_from_neural
        (tmp_path / "spec").mkdir()
        spec = spec_from_neural(model, tmp_path / "spec")
        session = onnxruntime.InferenceSession(str(spec.onnx))
        name = session.get_inputs()[0].name
        exported, _ = speed_channel_on_grid(
            lambda grid: np.concatenate([session.run(None, {name: row[None, :]})[0] for row in grid]))
        np.testing.assert_allclose(exported, values, rtol=1e-12, atol=1e-12)
    finally:
        model.close()


def test_with_shared_inputs_the_speed_channel_learns_the_current(dc_drive_fmu):
    """The case the per-channel inputs prevent: one network over both inputs fits the disturbance."""
    model = fitted_model(dc_drive_fmu, [])
    try:
        values, speeds = speed_channel_on_grid(torch_correction(model))
        assert np.ptp(values, axis=0).mean() > 2.0
    finally:
        model.close()


def test_per_channel_inputs_must_be_among_the_inputs(dc_drive_fmu):
    from fmubuilder.errors import FmuBuilderError
    for channel_inputs in ([["speed"]], [["speed"], ["temperature"]], [["speed"], []]):
        with pytest.raises(FmuBuilderError):
            NeuralFMU(dc_drive_fmu, TopologyConfig(channels=CHANNELS, inputs=INPUTS, kind="residual",
                                                   channel_inputs=channel_inputs))


def test_the_input_choice_gives_each_channel_its_own_inputs():
    energy = InputChoice("der(energy)", ["current", "speed"], 10.0, 30.0)
    speed = InputChoice("der(speed)", ["speed"], 1.0, 2.7)
    choice = AnnChoice(CHANNELS, INPUTS, [energy, speed])
    assert choice.channel_inputs == [["current", "speed"], ["speed"]]
    through = AnnChoice(["der(speed)"], ["current"], [speed], through=energy)
    assert through.channel_inputs == [["current"]]
