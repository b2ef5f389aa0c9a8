"""The integral (weak-form) warm start target: window means of the trapezoid rule against the
analytic integral; on a synthetic trajectory with a known Coulomb friction (the DC drive's,
examples/dc_drive/model.c) the target across the speed's sign change against the friction's mean
there; the target in the training path against the DC drive truth's windage."""
import numpy as np
import pytest
import torch

from fmubuilder.build import example_fmu
from fmubuilder.data import MeasuredData
from fmubuilder.neural.collocation import WindowMeans, local_fit, window_edges
from fmubuilder.neural.train import train_neural_fmu
from fmubuilder.simulation import simulate

AMPLITUDE = 5.0     # rad/s2: 0.05 N.m of Coulomb friction on 0.01 kg.m2
SMOOTHING = 1.0     # rad/s
WINDAGE_PER_INERTIA = 3e-6 / 0.01     # windage torque 3e-6 * w|w| on the same inertia
GRID = 0.01         # s, the forced run's step
SPAN = 0.5          # s, the windows (and the local lines of the pointwise target)


def coulomb(w):
    return -AMPLITUDE * np.tanh(w / SMOOTHING)


def test_window_means_are_the_integral_over_each_window():
    grid = np.arange(0.0, 10.0 + GRID / 2, GRID)
    starts = np.array([0.0, 1.234, 4.5678, 7.0])
    ends = starts + np.array([0.5, 2.0, 0.3333, 3.0])
    means = WindowMeans(grid, starts, ends)(torch.from_numpy(np.sin(grid)[:, None]))[:, 0].numpy()
    exact = (np.cos(starts) - np.cos(ends)) / (ends - starts)
    np.testing.assert_allclose(means, exact, atol=1e-4)


def test_window_edges_pair_each_edge_with_the_first_one_a_span_later():
    edges = np.array([0.0, 0.1, 0.25, 0.3, 0.6, 0.7, 1.2])
    lo, hi = window_edges(edges, 0.05, 1.0, 0.3)     # the edges within [0.05, 1.0]: 1 to 5
    assert lo.tolist() == [1, 2, 3]
    assert hi.tolist() == [4, 4, 4]
    lo, hi = window_edges(edges, 0.05, 1.0, 0.01)    # shorter than the spacing: the next edge
    assert lo.tolist() == [1, 2, 3, 4]
    assert hi.tolist() == [2, 3, 4, 5]


def test_the_integral_target_is_unbiased_across_the_sign_change():
    """A speed driven through 0 by a smooth torque (the FMU's own derivative, known), with the
    Coulomb friction the model lacks, measured at 10 Hz (jittered stamps, noise 0.05 rad/s). Over
    windows in which the speed changes sign the friction jumps by twice its size: the increment
    gives the friction's mean over the window up to the noise, the local line's slope assigned to
    the window's centre misses the friction there by a fifth of its size."""
    fine, duration = 1e-3, 48.0
    t = np.arange(0.0, duration + fine / 2, fine)
    drive = 30.0 * np.cos(2 * np.pi * t / 6.0) + 4.0
    w = np.zeros_like(t)
    for k in range(len(t) - 1):                            # explicit Euler at 1 ms: the kink resolved
        w[k + 1] = w[k] + fine * (drive[k] + coulomb(w[k]))
    rng = np.random.default_rng(0)
    stamps = np.arange(0.05, duration - 0.05, 0.1)
    time = np.sort(stamps + rng.uniform(-0.025, 0.025, stamps.size))
    measured = np.interp(time, t, w) + 0.05 * rng.standard_normal(time.size)
    grid = np.arange(0.0, duration + GRID / 2, GRID)

    lo, hi = window_edges(time, grid[0], grid[-1], SPAN)
    means = WindowMeans(grid, time[lo], time[hi])
    on_grid = torch.from_numpy(np.stack([np.interp(grid, t, drive), coulomb(np.interp(grid, t, w))], axis=1))
    fmu_mean, friction_mean = means(on_grid).numpy().T
    integral = (measured[hi] - measured[lo]) / (time[hi] - time[lo]) - fmu_mean

    centre = 0.5 * (time[lo] + time[hi])
    _, slope, _ = local_fit(time, measured, centre, SPAN)
    pointwise = slope - np.interp(centre, t, drive)

    crossing = np.sign(np.interp(time[lo], t, w)) != np.sign(np.interp(time[hi], t, w))
    assert crossing.sum() > 20
    integral_error = np.sqrt(np.mean((integral - friction_mean)[crossing] ** 2))
    pointwise_error = np.sqrt(np.mean((pointwise - coulomb(np.interp(centre, t, w)))[crossing] ** 2))
    assert integral_error < 0.06 * AMPLITUDE       # the noise: 0.05 * sqrt(2) / 0.5 s = 0.14 rad/s2
    assert pointwise_error > 0.15 * AMPLITUDE


def test_the_integral_target_in_the_training_finds_the_windage(dc_drive_fmu):
    """The training path with the integral target: the warm start fitted to the increments of 10 s
    of noisy speed, checked against the windage compiled into the DC drive's truth variant."""
    truth = simulate(example_fmu("dc_drive_truth_windage"), stop_time=10.0, solver="rk4", step_size=0.0005,
                     output_interval=0.01, variables=["speed", "current"])
    rng = np.random.default_rng(0)
    data = MeasuredData(truth.time, {"speed": truth["speed"] + 0.5 * rng.standard_normal(truth.time.size),
                                     "current": truth["current"] + 0.05 * rng.standard_normal(truth.time.size)},
                        source="dc_drive windage")
    result = train_neural_fmu(dc_drive_fmu, data, targets=["der(speed)"], inputs=["speed"], topology="residual",
                              hidden=[8], epochs=0, element_length=2.0, step_size=0.002, progress=False,
                              warm_start=True, warm_start_target="integral", integral_window=0.5)
    try:
        report = result.metrics["warm_start"]
        assert report["target"] == "integral" and report["kept"]
        assert report["samples"] > 900            # a window from every sample (100 Hz) but the last 0.5 s
        speeds = torch.tensor([[100.0], [150.0]], dtype=torch.float64)
        with torch.no_grad():
            learned = result.model.topology.correction(speeds)[:, 0].numpy()
        np.testing.assert_allclose(learned, -WINDAGE_PER_INERTIA * speeds[:, 0].numpy() ** 2, rtol=0.25)
    finally:
        result.model.close()


def test_an_unknown_warm_start_target_is_one_error_line(dc_drive_fmu):
    from fmubuilder.errors import FmuBuilderError
    with pytest.raises(FmuBuilderError, match="unknown warm start target 'weak'"):
        train_neural_fmu(dc_drive_fmu, "unused.csv", targets=["der(speed)"], inputs=["speed"],
                         warm_start_target="weak")
