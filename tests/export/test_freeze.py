"""freeze(): torch network -> float64 ONNX file, checked against torch with onnxruntime."""

from __future__ import annotations

import numpy as np
import onnx
import onnxruntime
import pytest
import torch

from fmubuilder.errors import FmuBuilderError
from fmubuilder.export import freeze


def small_network(seed: int = 0) -> torch.nn.Module:
    torch.manual_seed(seed)
    return torch.nn.Sequential(torch.nn.Linear(3, 12), torch.nn.Tanh(), torch.nn.Linear(12, 2))


class SignSwitch(torch.nn.Module):
    """Data-dependent branch: tracing records only the branch taken for the dummy input."""

    def forward(self, x):
        if x.sum() > 0:
            return 2.0 * x
        return 3.0 * x


def test_onnx_file_reproduces_torch_network(tmp_path):
    network = small_network()
    frozen = freeze(network, 3, tmp_path / "net.onnx")

    assert (frozen.n_inputs, frozen.n_outputs) == (3, 2)
    assert 0.0 <= frozen.max_abs_diff < 1e-12
    model = onnx.load(frozen.path)
    assert model.graph.input[0].type.tensor_type.elem_type == onnx.TensorProto.DOUBLE

    # Fresh inputs, independent of the samples freeze() checked itself.
    inputs = np.random.default_rng(42).uniform(-5, 5, size=(50, 1, 3))
    session = onnxruntime.InferenceSession(str(frozen.path), providers=["CPUExecutionProvider"])
    with torch.no_grad():
        expected = [network.double()(torch.from_numpy(x)).numpy() for x in inputs]
    actual = [session.run(None, {"input": x})[0] for x in inputs]
    np.testing.assert_allclose(np.array(actual), np.array(expected), rtol=1e-13, atol=1e-13)


def test_an_output_near_zero_among_large_ones_is_round_off_not_a_mismatch(tmp_path):
    """Outputs up to about 1e5 (a network whose scales carry a power or an energy): one that comes
    out near zero is a difference of terms as large as the others, so onnxruntime's and torch's
    orders of summation differ there by the round-off of 1e5, not of 1. The check is relative to
    the outputs' range; onnxruntime is compared here independently of it."""
    torch.manual_seed(0)
    network = torch.nn.Sequential(torch.nn.Linear(1, 16), torch.nn.Tanh(), torch.nn.Linear(16, 1)).double()
    checked = np.random.default_rng(0).standard_normal((256, 1))      # the samples freeze() checks
    with torch.no_grad():
        network[2].weight.mul_(1e5)
        nearest_zero = torch.from_numpy(checked[np.argmin(np.abs(checked)), None])
        network[2].bias.sub_(network(nearest_zero).item())              # that sample's output: ~0

    frozen = freeze(network, 1, tmp_path / "net.onnx")

    session = onnxruntime.InferenceSession(str(frozen.path), providers=["CPUExecutionProvider"])
    with torch.no_grad():
        expected = network(torch.from_numpy(checked)).numpy()
    actual = np.array([session.run(None, {"input": x[None]})[0][0] for x in checked])
    largest = np.max(np.abs(expected))
    assert largest > 1e4
    np.testing.assert_allclose(actual, expected, rtol=0, atol=1e-13 * largest)
    assert frozen.max_abs_diff <= 1e-13 * largest


def test_module_is_left_untouched(tmp_path):
    network = small_network()
    before = {name: value.clone() for name, value in network.state_dict().items()}
    network.train()
    freeze(network, 3, tmp_path / "net.onnx")
    assert network.training
    for name, value in network.state_dict().items():
        assert value.dtype == torch.float32
        assert torch.equal(value, before[name])


class FarShiftedInput(torch.nn.Module):
    """The shape of a NeuralFMU's correction on the VLDM: an input shifted by 32,087 and scaled by
    3e-5 (its standardisation), an MLP, an output scale of 324; the outputs below 1."""

    def __init__(self):
        super().__init__()
        torch.manual_seed(0)
        self.mlp = torch.nn.Sequential(torch.nn.Linear(1, 16), torch.nn.Tanh(), torch.nn.Linear(16, 16),
                                       torch.nn.Tanh(), torch.nn.Linear(16, 1)).double()
        with torch.no_grad():
            for layer in self.mlp[::2]:
                layer.weight.mul_(5.0 / layer.weight.abs().max())
        self.register_buffer("shift", torch.tensor([32087.47], dtype=torch.float64))
        self.register_buffer("scale", torch.tensor([3.0e-5], dtype=torch.float64))
        self.register_buffer("post", torch.tensor([324.0], dtype=torch.float64))
        with torch.no_grad():
            self.mlp[4].bias.sub_((self(torch.zeros(1, 1)).item() - 0.2) / 324.0)

    def forward(self, x):
        return self.post * self.mlp((x - self.shift) * self.scale)

    def extended_precision(self, x: np.ndarray) -> np.ndarray:
        """The same function in numpy's long double, layer by layer: the reference for both."""
        weights = [(layer.weight.detach().numpy().astype(np.longdouble), layer.bias.detach().numpy().astype(np.longdouble))
                   for layer in self.mlp[::2]]
        h = (x.astype(np.longdouble) - np.longdouble(32087.47)) * np.longdouble(3.0e-5)
        for i, (w, b) in enumerate(weights):
            h = h @ w.T + b
            h = np.tanh(h) if i < len(weights) - 1 else h
        return h * np.longdouble(324.0)


def test_a_network_s_own_round_off_is_no_mismatch(tmp_path):
    """Outputs of 0.2 carry this network's float64 round-off, about 1e-12 (onnxruntime and torch
    differ by 1e-12 to 1e-11 on its check samples, beyond CHECK_TOLERANCE alone): freeze() accepts
    it, and both agree with the function in extended precision to that round-off."""
    network = FarShiftedInput()
    frozen = freeze(network, 1, tmp_path / "net.onnx")

    inputs = np.random.default_rng(7).standard_normal((100, 1))
    session = onnxruntime.InferenceSession(str(frozen.path), providers=["CPUExecutionProvider"])
    actual = np.array([session.run(None, {"input": x[None]})[0][0] for x in inputs])
    with torch.no_grad():
        torch_out = network(torch.from_numpy(inputs)).numpy()
    reference = network.extended_precision(inputs)
    assert 0.0 < np.max(np.abs(reference)) < 1.0
    assert np.max(np.abs(actual - reference)) < 1e-10
    assert np.max(np.abs(torch_out - reference)) < 1e-10


def test_written_atomically_without_leftovers(tmp_path):
    target = tmp_path / "net.onnx"
    target.write_bytes(b"old contents")
    freeze(small_network(), 3, target)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["net.onnx"]
    onnx.checker.check_model(onnx.load(target))


def test_traced_branch_mismatch_is_detected_and_nothing_written(tmp_path):
    target = tmp_path / "net.onnx"
    with pytest.raises(FmuBuilderError, match="disagrees with the torch network"):
        freeze(SignSwitch(), 2, target)
    assert list(tmp_path.iterdir()) == []


def test_wrong_input_count(tmp_path):
    with pytest.raises(FmuBuilderError, match=r"does not accept an input of shape \[1, 5\]"):
        freeze(small_network(), 5, tmp_path / "net.onnx")


@pytest.mark.parametrize("n_inputs", [0, -1, 2.0, True])
def test_invalid_input_count(tmp_path, n_inputs):
    with pytest.raises(FmuBuilderError, match="n_inputs must be a positive integer"):
        freeze(small_network(), n_inputs, tmp_path / "net.onnx")


def test_missing_directory(tmp_path):
    with pytest.raises(FmuBuilderError, match="does not exist"):
        freeze(small_network(), 3, tmp_path / "missing" / "net.onnx")


def test_not_a_module(tmp_path):
    with pytest.raises(FmuBuilderError, match="needs a torch.nn.Module"):
        freeze(lambda x: x, 3, tmp_path / "net.onnx")
