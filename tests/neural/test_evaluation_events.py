"""The training's evaluation of a hybrid (its validation score, the form choice's errors) reads a
sample that lies between two recorded steps as the choice's scoring does: the settled value after
an event between them, not a line across the jump. Reference: the bouncing ball's analytic flight."""
import numpy as np
import torch

from fmubuilder.data import MeasuredData
from fmubuilder.neural.model import NeuralFMU
from fmubuilder.neural.topology import TopologyConfig
from fmubuilder.neural.train import predicted_at_samples, simulate_over

G, E, H0, STEP = 9.81, 0.7, 1.0, 0.01


def analytic_flight(t: np.ndarray):
    """(h, v) of the ball dropped from H0 at rest: flights between impacts, rebound speed E times
    the impact speed (bouncing_ball/model.c; no latch at rest within the span used here)."""
    h, v = np.empty_like(t), np.empty_like(t)
    start, speed, height = 0.0, 0.0, H0          # flight start, its upward speed, its height
    while True:
        duration = (speed + np.sqrt(speed ** 2 + 2 * G * height)) / G
        inside = (t >= start) & (t < start + duration)
        tau = t[inside] - start
        h[inside], v[inside] = height + speed * tau - G * tau ** 2 / 2, speed - G * tau
        if start + duration > t[-1]:
            return h, v
        start, speed, height = start + duration, E * (G * duration - speed), 0.0


def test_a_sample_between_steps_after_an_impact_reads_the_rebound(ball_fmu):
    time = np.arange(0.0, 1.3, 0.013)       # samples off the 0.01 s grid: 0.455 s follows the impact at 0.4515 s
    h, v = analytic_flight(time)
    data = MeasuredData(time, {"h": h, "v": v}, source="analytic ball")
    with NeuralFMU(ball_fmu, TopologyConfig()) as model, torch.no_grad():
        run = simulate_over(model, data, STEP, "rk4")
        predicted = predicted_at_samples(data, run, "v")
    between = (time > np.sqrt(2 * H0 / G)) & (time < STEP * np.ceil(np.sqrt(2 * H0 / G) / STEP))
    assert between.any()                    # the case this test is about is in the data
    assert np.max(np.abs(predicted - v)) < 1e-6
    # h is a parabola read linearly between records: off by up to g step^2 / 8
    assert np.max(np.abs(predicted_at_samples(data, run, "h") - h)) < 1.01 * G * STEP ** 2 / 8
