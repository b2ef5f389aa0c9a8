"""The loss fits the element starts of a state nothing else depends on (the DC drive's energy, the
integral of its power): an element started a few noisy samples off carries that offset to its end,
which the loss must not charge to the model (Trainer._free_offsets, _without_start_offset).

Reference: the same elements simulated again with the energy started at the least-squares offset
(numpy's lstsq on the residuals the offset shifts), read without the fit."""
import time

import numpy as np
import torch

from fmubuilder.build import example_fmu
from fmubuilder.data import MeasuredData
from fmubuilder.neural import NeuralFMU, TopologyConfig
from fmubuilder.neural.solve import ElementStart
from fmubuilder.neural.train import Trainer, TrainSettings
from fmubuilder.simulation import simulate

LAG = 0.05
NOISE = {"speed": 0.5, "current": 0.05, "power": 2.0, "energy": 2.0}


def test_the_energys_element_starts_are_fitted_and_nothing_else():
    truth = simulate(example_fmu("dc_drive_truth_speed_current_loss"), stop_time=6.0, solver="rk4",
                     step_size=0.0005, output_interval=0.01, variables=list(NOISE))
    rng = np.random.default_rng(3)
    data = MeasuredData(truth.time, {k: truth[k] + s * rng.standard_normal(truth.time.size) for k, s in NOISE.items()},
                        source="dc_drive speed_current_loss", sensor_lag=LAG)
    config = TopologyConfig(channels=["der(energy)"], inputs=["speed"], hidden=[4], kind="residual")
    with NeuralFMU(example_fmu("dc_drive"), config) as model:
        settings = TrainSettings(solver="rk4", step_size=0.002, element_length=2.0, epochs=0, progress=False,
                                 sensor_lag=LAG)
        trainer = Trainer(model, data, settings, time.perf_counter())
        trainer.prepare()
        # the speed, the current and the temperature drive other derivatives; the energy drives none
        assert trainer.free_offsets == ["energy"]
        with torch.no_grad(), model.topology.ann_off():
            fitted = trainer._all_residuals()["energy"].numpy()
            trainer.free_offsets = []
            raw = trainer._all_residuals()["energy"].numpy()
            sizes = [len(e.targets["energy"][0]) for e in trainer.elements]
            shifted_starts, offsets = [], []
            for element, r in zip(trainer.elements, np.split(raw, np.cumsum(sizes)[:-1])):
                k0, frac, _, weight = element.targets["energy"]
                elapsed = (k0.numpy() + frac.numpy()) * trainer.step
                basis = np.sqrt(weight.numpy()) * (1.0 - np.exp(-elapsed / LAG))
                offset = -np.linalg.lstsq(basis[:, None], r, rcond=None)[0][0]
                offsets.append(offset)
                start = element.start
                states = dict(start.states, energy=start.states["energy"] + offset)
                shifted_starts.append(ElementStart(start.t0, start.fmu_state, start.next_event_time, states))
            for element, start in zip(trainer.elements, shifted_starts):
                element.start = start
            again = trainer._all_residuals()["energy"].numpy()
    assert max(abs(o) for o in offsets) > 0.3 * NOISE["energy"]        # starts a noticeable offset off
    np.testing.assert_allclose(fitted, again, rtol=0, atol=1e-9 * NOISE["energy"])
    assert np.mean(fitted ** 2) < np.mean(raw ** 2)


def test_a_state_that_acts_only_at_a_later_event_is_not_free():
    """Dropped from 10 m, the ball's height moves nothing else until its impact, at sqrt(2 h / g) =
    1.43 s: within the first second the velocity falls as -g t whatever the height. The impact
    then reverses the velocity, so the height's start is no offset the loss may take out."""
    h0, g = 10.0, 9.81
    impact = np.sqrt(2 * h0 / g)
    truth = simulate(example_fmu("bouncing_ball"), stop_time=3.0, solver="rk4", step_size=1e-3, output_interval=0.01,
                     start_values={"h": h0}, variables=["h", "v"])
    assert 1.0 < impact < 3.0 and truth["v"].max() > 0      # the impact lies past the first second, inside the data
    data = MeasuredData(truth.time, {"h": truth["h"], "v": truth["v"]}, source="bouncing ball from 10 m")
    config = TopologyConfig(channels=["der(v)"], inputs=["v"], hidden=[4], kind="residual")
    with NeuralFMU(example_fmu("bouncing_ball"), config, start_values={"h": h0}) as model:
        settings = TrainSettings(solver="rk4", step_size=0.002, element_length=3.0, epochs=0, progress=False)
        trainer = Trainer(model, data, settings, time.perf_counter())
        trainer.prepare()
        assert "h" in trainer._measured_states() and "h" in trainer.loss_signals     # a candidate
        assert trainer.free_offsets == []
