"""A NeuralFMU whose ANN adds to a fitted term: the torch topology, the engine's numpy kernel and the
term's expression agree; at the start the hybrid is the term."""
import numpy as np
import pytest
import torch

from fmubuilder.errors import FmuBuilderError
from fmubuilder.neural import NeuralFMU, TopologyConfig
from fmubuilder.neural.system import NumpyTopology

TERMS = [{"variable": "v", "basis": "w*|w|", "center": 0.0, "coefficient": -0.02},
         {"variable": "h", "basis": "|w|", "center": 0.5, "coefficient": 0.3},
         {"variable": "time", "basis": "1", "center": 0.0, "coefficient": 0.1}]


def term(h, v):
    return -0.02 * v * np.abs(v) + 0.3 * np.abs(h - 0.5) + 0.1


@pytest.fixture
def model(ball_fmu):
    config = TopologyConfig(channels=["der(v)"], inputs=["h", "v"], hidden=[6], kind="residual", base_terms=TERMS)
    with NeuralFMU(ball_fmu, config) as neural:
        yield neural


def points(count=40):
    rng = np.random.default_rng(1)
    x = rng.uniform(-3, 3, size=(count, 2))          # states h, v of the bouncing ball
    der = np.column_stack([x[:, 1], np.full(count, -9.81)])
    return x, der


def test_the_untrained_hybrid_is_the_term(model):
    x, der = points()
    expected = der[:, 1] + term(x[:, 0], x[:, 1])
    with torch.no_grad():
        torch_result = model.topology(torch.from_numpy(x), torch.from_numpy(der)).numpy()
    np.testing.assert_allclose(torch_result[:, 1], expected, rtol=1e-13, atol=1e-13)
    kernel = NumpyTopology(model.topology)
    numpy_result = kernel.rows(x, der.copy(), np.zeros((len(x), 0)))
    np.testing.assert_allclose(numpy_result[:, 1], expected, rtol=1e-13, atol=1e-13)
    one_point = [kernel(x[row], der[row].copy(), np.zeros(0))[1] for row in range(len(x))]  # the engine's path
    np.testing.assert_allclose(one_point, expected, rtol=1e-13, atol=1e-13)
    assert not model.topology.is_neutral()


def test_torch_and_numpy_agree_with_a_trained_ann_on_top(model):
    torch.manual_seed(0)
    with torch.no_grad():
        for parameter in model.topology.ann.parameters():
            parameter.normal_(0.0, 0.5)
    x, der = points()
    with torch.no_grad():
        torch_result = model.topology(torch.from_numpy(x), torch.from_numpy(der)).numpy()
        ann_alone = model.topology.correction(torch.from_numpy(x))[:, 0].numpy() - term(x[:, 0], x[:, 1])
    assert np.max(np.abs(ann_alone)) > 1e-2                   # the ANN adds something
    kernel = NumpyTopology(model.topology)
    np.testing.assert_allclose(kernel.rows(x, der.copy(), np.zeros((len(x), 0))), torch_result, rtol=1e-12, atol=1e-12)
    for row in range(len(x)):                                 # the one-point path of the engine
        one = kernel(x[row], der[row].copy(), np.zeros(0))
        np.testing.assert_allclose(one, torch_result[row], rtol=1e-12, atol=1e-12)


def test_a_base_term_must_read_ann_inputs(ball_fmu):
    config = TopologyConfig(channels=["der(v)"], inputs=["v"], hidden=[4], kind="residual", base_terms=TERMS)
    with pytest.raises(FmuBuilderError, match="add it to the ANN inputs"):
        NeuralFMU(ball_fmu, config)
