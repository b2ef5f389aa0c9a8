"""The warm start: the ANN fitted to the closed-loop collocation estimate of the missing term,
checked against the term compiled into the DC drive's truth variant (windage)."""
import dataclasses
import math

import numpy as np
import pytest
import torch

from fmubuilder.build import example_fmu
from fmubuilder.data import MeasuredData
from fmubuilder.neural.train import train_neural_fmu
from fmubuilder.simulation import simulate

# examples/dc_drive/model.c: windage torque 3e-6 * w|w| on an inertia of 0.01 kg m2.
WINDAGE_PER_INERTIA = 3e-6 / 0.01
# Standard deviations of the sensors' noise in the windage data.
NOISE = {"speed": 0.5, "current": 0.05}


def measured(truth_variant: str, stop_time: float, speed_noise: float, current_noise: float, seed: int):
    """The speed-controlled drive's truth variant simulated, speed and current measured with noise."""
    truth = simulate(example_fmu(f"dc_drive_truth_{truth_variant}"), stop_time=stop_time, solver="rk4",
                     step_size=0.0005, output_interval=0.01, variables=["speed", "current"])
    rng = np.random.default_rng(seed)
    signals = {"speed": truth["speed"] + speed_noise * rng.standard_normal(truth.time.size),
               "current": truth["current"] + current_noise * rng.standard_normal(truth.time.size)}
    return MeasuredData(truth.time, signals, source=f"dc_drive {truth_variant}")


@pytest.fixture(scope="module")
def windage_data():
    """10 s of the drive with undeclared windage."""
    return measured("windage", 10.0, *NOISE.values(), seed=0)


def first_loss(fmu, data, **settings):
    """The training loss of the start parameters (one element batch: the first epoch measures them)
    and the trained model."""
    result = train_neural_fmu(fmu, data, targets=["der(speed)"], inputs=["speed"], topology="residual", hidden=[8],
                              epochs=1, element_length=2.0, step_size=0.002, progress=False, ccpt_window=0.2,
                              **settings)
    return result.history[0]["loss"], result


@pytest.fixture(scope="module")
def zero_init_loss(dc_drive_fmu, windage_data):
    loss, result = first_loss(dc_drive_fmu, windage_data)
    result.model.close()
    return loss


def test_warm_start_lowers_the_initial_loss_and_finds_the_windage(dc_drive_fmu, windage_data, zero_init_loss):
    warm, result = first_loss(dc_drive_fmu, windage_data, warm_start=True)
    try:
        assert zero_init_loss == pytest.approx(1.0)         # the residual ANN starts at zero: the plain FMU
        assert warm < 0.7 * zero_init_loss
        speeds = torch.tensor([[100.0], [150.0]], dtype=torch.float64)
        with torch.no_grad():
            learned = result.model.topology.correction(speeds)[:, 0].numpy()
        expected = -WINDAGE_PER_INERTIA * speeds[:, 0].numpy() ** 2
        np.testing.assert_allclose(learned, expected, rtol=0.25)
    finally:
        result.model.close()


def test_an_estimate_blind_to_the_effect_is_replaced_by_a_fit_through_the_simulation(dc_drive_fmu, windage_data,
                                                                                     monkeypatch):
    """Where a controller hides the effect from the measured derivative, the collocation estimate is
    noise (here: replaced by noise of the estimate's size); its fits hardly lower the loss, and the
    last layer fitted through the simulation from the unfitted ANN alone (warm_start.FITTED_NOISE_ABOVE)
    takes it to the loss of the truth's own windage term."""
    from fmubuilder.neural import warm_start as module
    estimate = module.collocation_targets

    def blind(trainer, force=True):
        x, target = estimate(trainer, force)
        noise = torch.randn(target.shape, generator=torch.Generator().manual_seed(0), dtype=target.dtype)
        return x, target.std() * noise
    monkeypatch.setattr(module, "collocation_targets", blind)
    warm, result = first_loss(dc_drive_fmu, windage_data, warm_start=True)
    result.model.close()
    report = result.metrics["warm_start"]
    assert min(trial["loss"] for trial in report["trials"]) > 0.9
    assert report["through_simulation"]["kept"] and warm == pytest.approx(report["loss_after"], rel=1e-9)
    exact = [{"variable": "speed", "basis": "w*|w|", "center": 0.0, "coefficient": -WINDAGE_PER_INERTIA}]
    truth_term, with_term = first_loss(dc_drive_fmu, windage_data, base_terms=exact)
    with_term.model.close()
    assert warm < 1.05 * truth_term < 0.6

    # The kept fit lowered the loss a little and explains next to nothing of its estimate: the last
    # layer is fitted from the unfitted ANN alone, then once more from a fresh Jacobian. Searched from
    # both starts instead (the rule off), the fit's start ends higher.
    through = report["through_simulation"]
    assert report["fit_error"] > module.FITTED_NOISE_ABOVE and report["loss_fits"] < report["loss_before"]
    assert through["start"] == "unfitted" and "loss_from_fit" not in through
    unknowns = 8 + 1
    again = through["again"]
    # the second search's loss where it lowered the first's, else the first's
    assert through["loss"] == (again["loss"] if again["kept"] else again["loss_before"])
    # per search: the capture or the loss after it, the start, the columns, its trials
    assert through["simulations"] <= (1 + 1 + unknowns + module.UNFITTED_TRIALS
                                      + module.LOSS_SIMULATIONS + 1 + unknowns + module.RESTART_TRIALS)
    monkeypatch.setattr(module, "FITTED_NOISE_ABOVE", 1.0)
    both_loss, both = first_loss(dc_drive_fmu, windage_data, warm_start=True)
    both.model.close()
    both_through = both.metrics["warm_start"]["through_simulation"]
    assert both_through["loss_from_fit"] > through["loss"] <= both_through["loss_from_unfitted"] * (1 + 1e-9)
    assert warm <= both_loss * (1 + 1e-9)


@pytest.mark.parametrize("handicap", [1.0, 100.0])
def test_a_fit_that_hardly_lowers_the_loss_is_also_tried_unfitted_through_the_simulation(dc_drive_fmu, windage_data,
                                                                                         monkeypatch, handicap):
    """An estimate a fifth of the effect's size: its fit leaves most of the loss, so the last layer is
    fitted through the simulation from the fit and from the unfitted ANN; the lower loss is kept, and
    the training's first epoch measures it at the parameters kept. On these data the fit's start
    wins; with its loss reported `handicap` times too high the unfitted start must be kept, and the
    first epoch must then measure the unfitted path's parameters."""
    from fmubuilder.neural import warm_start as module
    estimate, through_simulation = module.collocation_targets, module._through_simulation
    paths = []

    def faint(trainer, force=True):
        x, target = estimate(trainer, force)
        return x, 0.2 * target

    starts = []

    def handicapped(trainer, loss, trials=module.THROUGH_SIMULATION_TRIALS):
        starts.append((loss, module._loss_from_own_starts(trainer)))     # as given, as measured here
        done = through_simulation(trainer, loss, trials)
        paths.append(done)
        return {**done, "loss": done["loss"] * handicap} if len(paths) == 1 else done
    monkeypatch.setattr(module, "collocation_targets", faint)
    monkeypatch.setattr(module, "_through_simulation", handicapped)
    loss, result = first_loss(dc_drive_fmu, windage_data, warm_start=True)
    result.model.close()
    report = result.metrics["warm_start"]
    through = report["through_simulation"]
    assert module.UNFITTED_TOO_ABOVE * report["loss_before"] < report["loss_fits"] < report["loss_before"]
    # a faint estimate of the right shape, not noise: its fit explains it, and both starts are searched
    assert report["fit_error"] < module.FITTED_NOISE_ABOVE
    assert len(paths) == 2 and through["loss_from_unfitted"] == paths[1]["loss"]
    # the unfitted start's loss is the one before the fits, not measured again
    assert starts[1][0] == report["loss_before"] and starts[1][1] == pytest.approx(starts[1][0], rel=1e-12)
    assert report["loss_after"] == min(through["loss_from_fit"], through["loss_from_unfitted"]) < report["loss_fits"]
    assert through["start"] == ("fit" if handicap == 1.0 else "unfitted")
    assert loss == pytest.approx(report["loss_after"], rel=1e-9)
    assert (report["estimate"] is None) == (through["start"] == "unfitted")


def test_where_the_forced_estimate_is_blind_the_plain_run_s_estimate_is_kept(dc_drive_fmu, monkeypatch):
    """A loss in der(energy) (the truth's 0.01 |speed * current|) does not move the speed or the
    current: the plain model's run follows the measured one, and the measured power minus the plain
    run's is the loss. With the forced run's estimate replaced by noise (as a controller set off by
    the forced noise makes it, on the VLDM), the plain run's fit is the one kept."""
    from fmubuilder.neural import warm_start as module
    estimate = module.collocation_targets

    def forced_blind(trainer, force=True):
        x, target = estimate(trainer, force)
        if not force:
            return x, target
        noise = torch.randn(target.shape, generator=torch.Generator().manual_seed(0), dtype=target.dtype)
        return x, target.std() * noise
    monkeypatch.setattr(module, "collocation_targets", forced_blind)
    truth = simulate(example_fmu("dc_drive_truth_speed_current_loss"), stop_time=10.0, solver="rk4",
                     step_size=0.0005, output_interval=0.01, variables=["speed", "current", "power", "energy"])
    rng = np.random.default_rng(2)
    noise = {"speed": 0.5, "current": 0.05, "power": 2.0, "energy": 2.0}
    data = MeasuredData(truth.time, {k: truth[k] + s * rng.standard_normal(truth.time.size) for k, s in noise.items()},
                        source="dc_drive speed_current_loss")
    result = train_neural_fmu(dc_drive_fmu, data, targets=["der(energy)"], inputs=["current", "speed"],
                              topology="residual", hidden=[8], epochs=1, element_length=2.0, step_size=0.002,
                              progress=False, ccpt_window=0.2, warm_start=True)
    try:
        report = result.metrics["warm_start"]
        forced = [t["loss"] for t in report["trials"] if t["estimates"] == ["forced"]]
        best_fit = min(report["trials"], key=lambda trial: trial["loss"])
        assert best_fit["estimates"] == ["plain"] and report["loss_fits"] == best_fit["loss"] < 0.85 * min(forced)
        # the through-simulation then ends from the fit or from the unfitted ANN, whichever is lower:
        # here they end within 1e-5 of each other, and the last layer is fitted alike from both
        assert report["loss_after"] < report["loss_fits"]
        at = torch.tensor([[2.5, 150.0], [6.5, 150.0], [5.6, 60.0]], dtype=torch.float64)    # held in the data
        with torch.no_grad():
            learned = result.model.topology.correction(at)[:, 0].numpy()
        np.testing.assert_allclose(learned, 0.01 * (at[:, 0] * at[:, 1]).abs().numpy(), rtol=0.25)
    finally:
        result.model.close()


@pytest.mark.parametrize("coefficient", [1.0, 0.5])
def test_an_ann_started_from_a_term_never_ends_worse_on_validation(dc_drive_fmu, windage_data, coefficient):
    """The ANN adds to a fitted windage term (exact, or half of it) and trains with a step size that
    overshoots; it ends with its best validation score, which is at most the term's own, in the score
    hybridize chooses by: the geometric mean over the signals of MSE / noise variance."""
    from fmubuilder.neural.train import Validation
    terms = [{"variable": "speed", "basis": "w*|w|", "center": 0.0, "coefficient": -coefficient * WINDAGE_PER_INERTIA}]
    split = 8.0
    noisy = dataclasses.replace(windage_data, runs=1, std={name: np.full(windage_data.time.size, sigma)
                                                           for name, sigma in NOISE.items()})
    result = train_neural_fmu(dc_drive_fmu, windage_data.window(0.0, split), targets=["der(speed)"], inputs=["speed"],
                              base_terms=terms, topology="residual", hidden=[8], epochs=4, element_length=2.0,
                              step_size=0.002, learning_rate=0.1, progress=False,
                              validation=Validation(noisy, (split + 1e-6, windage_data.stop)))
    try:
        history = [h["validation"] for h in result.history]
        summary = result.metrics["validation"]
        start = summary["start_score"]
        assert summary["best_score"] <= start and summary["best_score"] == min([start, *history])
        if summary["best_score"] == start:
            assert summary["best_stage"] == "start"
        else:
            assert summary["best_stage"] == "epoch" and history[summary["best_epoch"] - 1] == summary["best_score"]
        # The model returned is the best one: recomputed independently, and no worse than the term alone.
        trained = result.model
        best = trained.topology.state_dict()
        with torch.no_grad():
            trained.topology.ann[-1].weight.zero_()
            trained.topology.ann[-1].bias.zero_()
            trained.topology.post_shift.zero_()
        term_alone = _score_over_noise(trained, windage_data, split)
        trained.topology.load_state_dict(best)
        returned = _score_over_noise(trained, windage_data, split)
        assert returned == pytest.approx(summary["best_score"], rel=1e-6)
        assert returned <= term_alone * (1 + 1e-9)
    finally:
        result.model.close()


def _score_over_noise(model, data, split):
    """Geometric mean over the signals of the held-out MSE / the known noise variance."""
    from fmubuilder.neural.train import simulate_over
    result = simulate_over(model, data, 0.002)
    held_out = data.time > split
    logs = []
    for name, sigma in NOISE.items():
        predicted = np.interp(data.time[held_out], np.asarray(result.time), np.asarray(result[name]))
        logs.append(math.log(np.mean((predicted - data.signals[name][held_out]) ** 2) / sigma ** 2))
    return math.exp(np.mean(logs))


@pytest.fixture(scope="module")
def coulomb_data():
    """25 s of the drive with an undeclared Coulomb friction (a sign over 1 rad/s): start-up, load
    steps, a reversal through standstill, a stop."""
    return measured("coulomb", 25.0, 0.1, 0.02, seed=1)


def test_the_warm_start_keeps_the_weight_decay_whose_fit_simulates_best(dc_drive_fmu, coulomb_data, monkeypatch):
    """Each decay's fit is simulated; the kept one has the lowest training loss, whichever order they
    were fitted in, and the training's first epoch measures that loss at the parameters it keeps.
    The sign's step is steep against the speed's range: the weak decay fits it, the strong one
    rounds it off and simulates worse."""
    from fmubuilder.neural import warm_start as module
    kept = {}
    for order in (module.WEIGHT_DECAYS, module.WEIGHT_DECAYS[::-1]):
        monkeypatch.setattr(module, "WEIGHT_DECAYS", order)
        loss, result = first_loss(dc_drive_fmu, coulomb_data, warm_start=True)
        result.model.close()
        report = result.metrics["warm_start"]
        trials = report["trials"]
        assert len(trials) == len(order) * len(module.ESTIMATES)        # one channel: no splicing
        assert report["kept"] and report["loss_fits"] == min(trial["loss"] for trial in trials)
        assert loss == pytest.approx(report["loss_after"], rel=1e-9) and loss <= report["loss_fits"]
        kept[order] = report["estimate"], report["weight_decay"], loss
        forced = {trial["decays"][0]: trial["loss"] for trial in trials if trial["estimates"] == ["forced"]}
    assert len({(tuple(estimate), tuple(decays), loss) for estimate, decays, loss in kept.values()}) == 1
    # the forced estimate: the plain run's current misses the friction the controller compensates
    assert kept[module.WEIGHT_DECAYS][:2] == (["forced"], [min(forced)])
    assert forced[min(forced)] < 0.8 * forced[max(forced)]


def test_a_spliced_warm_start_takes_each_channel_s_block_from_its_own_fit(dc_drive_fmu):
    """With a sub-network per channel, the parameters and output scales spliced from two fits give
    each channel the correction of the fit it was taken from, exactly."""
    from fmubuilder.fmi import read_model_info
    from fmubuilder.neural.topology import Topology, TopologyConfig
    from fmubuilder.neural.warm_start import _Fit, _spliced
    config = TopologyConfig(channels=["der(speed)", "der(energy)"], inputs=["speed", "current"], hidden=[4, 3],
                            kind="gates", channel_inputs=[["speed"], ["current", "speed"]])
    topology = Topology(config, read_model_info(dc_drive_fmu), [])     # gates: no layer starts at zero
    blocks = [p != 0 for p in topology.ann.parameters()]
    x = torch.randn(50, 2, dtype=torch.float64)
    fits, corrections = {}, {}
    for decay in (1e-4, 1e-6):
        with torch.no_grad():
            for p, block in zip(topology.ann.parameters(), blocks):
                p.copy_(torch.randn_like(p) * block)      # keep the zeros between the channels' blocks
            topology.post_scale.copy_(torch.rand_like(topology.post_scale) + 0.5)
            corrections[decay] = topology.correction(x)
        fits[decay] = _Fit([p.detach().clone() for p in topology.ann.parameters()],
                           topology.post_scale.detach().clone())
    assert (corrections[1e-4] - corrections[1e-6]).abs().min() > 0      # the fits differ in both channels
    _spliced(fits, [1e-6, 1e-4], topology.row_channels()).apply(topology)
    with torch.no_grad():
        mixed = topology.correction(x)
    torch.testing.assert_close(mixed[:, 0], corrections[1e-6][:, 0], rtol=0, atol=0)
    torch.testing.assert_close(mixed[:, 1], corrections[1e-4][:, 1], rtol=0, atol=0)
