"""What the default ANN can represent, fitted supervised (no solver) with the warm start's full-batch
fit: a smoothed sign of the speed as the DC drive's Coulomb friction has it (examples/dc_drive/model.c),
checked against the analytic function; the bounded fit across a gap in the samples and the weight
decay against noise at standstill."""
import numpy as np
import pytest
import torch

from fmubuilder.fmi import read_model_info
from fmubuilder.neural.topology import Topology, TopologyConfig
from fmubuilder.neural.train import TrainSettings
from fmubuilder.neural.warm_start import WEIGHT_DECAY, fit_full_batch, range_penalty

AMPLITUDE = 5.0     # rad/s2: 0.05 N.m of Coulomb friction on 0.01 kg.m2
SMOOTHING = 1.0     # rad/s


def friction(w):
    return -AMPLITUDE * np.tanh(w / SMOOTHING)


def default_topology(info, speeds: np.ndarray) -> Topology:
    """The ANN hybridize builds (default size and activation, residual), its input scaled as the
    trainer scales it, its output to the effect's size."""
    torch.manual_seed(0)
    topology = Topology(TopologyConfig(channels=["der(speed)"], inputs=["speed"], kind="residual"), info, [])
    topology.initialise_scaling(speeds[:, None], 47.0 * np.sin(speeds / 30.0)[:, None])
    with torch.no_grad():
        topology.post_scale.fill_(AMPLITUDE)
    return topology


def correction(topology, speeds: np.ndarray) -> np.ndarray:
    with torch.no_grad():
        return topology.correction(torch.from_numpy(speeds[:, None]))[:, 0].numpy()


def test_the_default_ann_fits_a_smoothed_sign_of_the_speed(dc_drive_fmu):
    speeds = np.linspace(-150.0, 200.0, 3501)       # 10 samples per rad/s, the DC drive's speed range
    topology = default_topology(read_model_info(dc_drive_fmu), speeds)
    target = torch.from_numpy(friction(speeds)[:, None])
    fit_full_batch(topology, torch.from_numpy(speeds[:, None]), target, TrainSettings().warm_start_iterations,
                   weight_decay=0.0)   # the representation itself: the warm start's decay is for noisy estimates
    dense = np.linspace(-150.0, 200.0, 35001)
    error = correction(topology, dense) - friction(dense)
    assert np.sqrt(np.mean(error ** 2)) < 0.01 * AMPLITUDE
    near_zero = np.abs(dense) < 3.0 * SMOOTHING
    assert np.max(np.abs(error[near_zero])) < 0.1 * AMPLITUDE


def test_the_bounded_fit_stays_within_the_range_of_the_samples_across_a_gap(dc_drive_fmu):
    """Samples at standstill and beyond 20 rad/s only (the collocation drops the windows in which the
    speed crosses 0): unbounded, the fit across the steep change swings far beyond the friction
    inside the gap; bounded, it stays within the samples' range."""
    rng = np.random.default_rng(0)
    speeds = np.concatenate([rng.uniform(-0.7, 0.7, 100), rng.uniform(-150.0, -20.0, 1200),
                             rng.uniform(20.0, 200.0, 1200)])
    target = torch.from_numpy((friction(speeds) + 0.3 * rng.standard_normal(speeds.size))[:, None])
    gap = np.concatenate([np.linspace(-20.0, -0.7, 500), np.linspace(0.7, 20.0, 500)])
    swing = {}
    for bounded in (False, True):
        topology = default_topology(read_model_info(dc_drive_fmu), speeds)
        fit_full_batch(topology, torch.from_numpy(speeds[:, None]), target, 300, bounded=bounded, weight_decay=0.0)
        swing[bounded] = np.max(np.abs(correction(topology, gap)))
    high = float(np.quantile(target.numpy(), 0.999))
    assert swing[False] > 2.0 * AMPLITUDE           # the case the bound is for
    assert swing[True] < high + 0.1 * AMPLITUDE


def test_the_range_penalty_is_the_mean_square_excess_over_the_range():
    """A correction constant at 0 against targets in [2, 3]: every grid point lies 2 below the range."""
    x = torch.linspace(-1.0, 1.0, 101, dtype=torch.float64)[:, None]
    target = torch.linspace(2.0, 3.0, 101, dtype=torch.float64)[:, None]
    scale = torch.tensor([0.5], dtype=torch.float64)

    class Zero:
        @staticmethod
        def correction(inputs):
            return torch.zeros(inputs.shape[0], 1, dtype=torch.float64)

    low = float(np.quantile(target.numpy(), 0.001))
    assert float(range_penalty(x, target, scale)(Zero)) == pytest.approx(low ** 2 / 0.5, rel=1e-12)


def test_the_weight_decay_keeps_the_friction_s_sign_between_noisy_standstill_and_the_far_samples(dc_drive_fmu):
    """At standstill the estimate is noise (the measured speed is mostly sensor noise there); the
    friction is known only beyond 20 rad/s. Without the warm start's weight decay the fit turns
    steeply on that noise and the correction between 2 and 20 rad/s takes the wrong sign over much of
    it; with it the correction keeps the friction's sign there."""
    rng = np.random.default_rng(0)
    speeds = np.concatenate([rng.uniform(-0.7, 0.7, 100), rng.uniform(-150.0, -20.0, 1200),
                             rng.uniform(20.0, 200.0, 1200)])
    noisy = friction(speeds) + 0.3 * rng.standard_normal(speeds.size)
    noisy[:100] = 3.0 * rng.standard_normal(100)
    gap = np.concatenate([np.linspace(-20.0, -2.0, 500), np.linspace(2.0, 20.0, 500)])
    errors, wrong_sign = {}, {}
    for decay in (0.0, WEIGHT_DECAY):
        topology = default_topology(read_model_info(dc_drive_fmu), speeds)
        fit_full_batch(topology, torch.from_numpy(speeds[:, None]), torch.from_numpy(noisy[:, None]), 300,
                       weight_decay=decay)
        fitted = correction(topology, gap)
        errors[decay] = np.sqrt(np.mean((fitted - friction(gap)) ** 2))
        wrong_sign[decay] = np.mean(np.sign(fitted) != np.sign(friction(gap)))
    assert wrong_sign[0.0] > 0.2 and errors[0.0] > 0.8 * AMPLITUDE     # the case the decay is for
    assert wrong_sign[WEIGHT_DECAY] == 0.0
    assert errors[WEIGHT_DECAY] < 0.6 * AMPLITUDE
