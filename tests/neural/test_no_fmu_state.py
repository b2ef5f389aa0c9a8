"""An FMU that cannot save its state (canGetAndSetFMUstate="false", as most OpenModelica exports):
element starts are replayed or continued in the instance that reached them (solve.Replay). The
reference is the same C model compiled with FMU-state support, where the starts are snapshots."""
import numpy as np
import pytest
import torch

from fmubuilder.build import example_fmu
from fmubuilder.errors import FmuBuilderError
from fmubuilder.fmi.binding import ffi
from fmubuilder.neural import ElementStart, NeuralFMU, TopologyConfig, simulate
from fmubuilder.neural.train import train_neural_fmu

from .conftest import plant_data

pytestmark = pytest.mark.filterwarnings("ignore:.* cannot get/set its FMU state")

CONFIG = TopologyConfig(channels=["der(w)"], inputs=["w"], hidden=[4], kind="residual")


@pytest.fixture(scope="module")
def plant_without_state():
    return example_fmu("sampled_plant_no_fmu_state")


@pytest.fixture(scope="module")
def plant_data_set(plant_fmu):
    data, _ = plant_data(plant_fmu, [0, 1, 1.001, 2.5, 2.501, 4], [1, 1, 2, 2, 0.5, 0.5], 4.0, seed=0)
    return data


def test_the_binary_refuses_fmu_state_calls(plant_without_state):
    with NeuralFMU(plant_without_state, CONFIG) as model:
        assert not model.info.capabilities.can_get_and_set_fmu_state
        inst = model.instances(1)[0]
        inst.setup_experiment(start_time=0.0)
        inst.enter_initialization_mode()
        inst.exit_initialization_mode()
        with pytest.raises(FmuBuilderError, match="does not support getting/setting its state"):
            inst.get_fmu_state()
        handle = ffi.new("fmi2FMUstate*", ffi.NULL)   # past the declared capability: the binary refuses
        with pytest.raises(FmuBuilderError):
            inst._call("fmi2GetFMUstate", inst.component, handle)


def _captured_and_continued(fmu):
    """Starts captured inside one run, then every element simulated from them twice (the second
    time the starts are replayed) and once more from the first pass' final states (carry-over)."""
    torch.manual_seed(0)
    with NeuralFMU(fmu, CONFIG) as model, torch.no_grad():
        for p in model.topology.parameters():
            p.add_(0.1 * torch.randn_like(p))
        run = simulate(model, 1.6, 0.004, starts=[ElementStart(0.0, states={"w": 0.2})], capture=[0, 100, 250],
                       record=["w", "i"])
        starts = [run.captured[k][0] for k in (0, 100, 250)]
        first = simulate(model, 0.8, 0.004, starts=starts, record=["w", "i", "u"], keep_final_state=True)
        again = simulate(model, 0.8, 0.004, starts=starts, record=["w", "i", "u"])
        carried = simulate(model, 0.4, 0.004, starts=first.final_starts, record=["w", "i", "u"])
        return run.values.numpy(), first.values.numpy(), again.values.numpy(), carried.values.numpy()


def test_replayed_and_carried_starts_equal_the_snapshots(plant_fmu, plant_without_state):
    with_snapshots = _captured_and_continued(plant_fmu)
    without = _captured_and_continued(plant_without_state)
    for reference, replayed in zip(with_snapshots, without):
        np.testing.assert_allclose(replayed, reference, rtol=1e-12, atol=1e-12)
    # the elements really start inside the run: the sampled PI integral is not at its start value
    assert np.abs(with_snapshots[1][0, 1, 2] - with_snapshots[1][0, 0, 2]) > 1e-3


@pytest.mark.parametrize("order", ["random", "sequential"])
def test_training_sees_the_same_losses_as_with_snapshots(plant_fmu, plant_without_state, plant_data_set, order):
    """With the parameters held (learning rate 0) every epoch's loss depends on the element starts
    only: captured, carried over, measured twice and replayed, they must agree exactly."""
    common = dict(targets=["der(w)"], inputs=["w"], hidden=[4], epochs=3, element_length=1.0, order=order,
                  step_size=0.004, learning_rate=0.0, progress=False)
    losses = []
    for fmu in (plant_fmu, plant_without_state):
        result = train_neural_fmu(fmu, plant_data_set, **common)
        losses.append([h["loss"] for h in result.history])
        result.model.close()
    np.testing.assert_allclose(losses[1], losses[0], rtol=1e-10)


def test_training_without_snapshots_reaches_the_same_quality(plant_fmu, plant_without_state, plant_data_set):
    """Learning: the starts are the same; the gradient lacks the path through the sampled PI's
    discrete state at events (that needs snapshots), which barely changes the result here."""
    common = dict(targets=["der(w)"], inputs=["w", "der(w)"], hidden=[8], epochs=8, element_length=1.0,
                  step_size=0.004, learning_rate=2e-2, progress=False)
    mse = []
    for fmu in (plant_fmu, plant_without_state):
        result = train_neural_fmu(fmu, plant_data_set, **common)
        errors = result.metrics["errors"]
        mse.append((errors["before"]["w"]["mse"], errors["after"]["w"]["mse"]))
        result.model.close()
    assert mse[0][0] == pytest.approx(mse[1][0], rel=1e-12)      # the plain FMU: identical
    assert mse[1][1] < 0.6 * mse[1][0]                           # the training helps ...
    assert mse[1][1] == pytest.approx(mse[0][1], rel=0.02)      # ... as much as with snapshots


def _losses_across_a_rewind(fmu, data):
    """Element losses with carry-over under changing parameters, then again from the starts of an
    earlier pass (what a rewind does): those starts were consumed and must be replayed."""
    from fmubuilder.neural.train import Trainer, TrainSettings
    settings = TrainSettings(element_length=0.5, step_size=0.004, progress=False, sensor_lag=0.0)
    torch.manual_seed(5)
    with NeuralFMU(fmu, CONFIG) as model, torch.no_grad():
        trainer = Trainer(model, data, settings, 0.0)
        trainer.prepare()
        losses = []
        saved = None
        for shift in (0.3, -0.2, 0.1):
            for p in model.topology.ann.parameters():
                p.add_(shift * torch.randn_like(p))
            if len(losses) == 1:   # the second pass: starts carried over from the first, then consumed
                saved = ([e.start for e in trainer.elements], {k: v.clone() for k, v in model.topology.state_dict().items()})
            losses.append(float(trainer.batch_loss(trainer.elements)))
        starts, state = saved      # back to the second pass' parameters and starts
        model.topology.load_state_dict(state)
        for element, start in zip(trainer.elements, starts):
            element.start = start
        losses.append(float(trainer.batch_loss(trainer.elements)))
        losses.append(float(trainer.batch_loss(trainer.elements[3:5])))
        return losses, dict(model.replays)


def test_rewound_starts_are_replayed_exactly(plant_fmu, plant_without_state, plant_data_set):
    with_snapshots, _ = _losses_across_a_rewind(plant_fmu, plant_data_set)
    without, replays = _losses_across_a_rewind(plant_without_state, plant_data_set)
    assert len(set(np.round(with_snapshots[:3], 6))) == 3          # the three passes differ
    assert with_snapshots[3] == pytest.approx(with_snapshots[1], rel=1e-12)   # the rewind repeats the second
    np.testing.assert_allclose(without, with_snapshots, rtol=1e-10)
    assert replays["runs"] > 0


def test_the_hybrid_of_an_fmu_without_state_exports_and_validates(plant_without_state, plant_data_set, tmp_path):
    from fmubuilder.export import export_hybrid, validate_hybrid
    from fmubuilder.fmi import read_model_info
    from fmubuilder.hybridize.terms import spec_from_neural
    result = train_neural_fmu(plant_without_state, plant_data_set, targets=["der(w)"], inputs=["w"], hidden=[4],
                              epochs=2, element_length=1.0, step_size=0.004, learning_rate=2e-2, progress=False)
    try:
        hybrid = export_hybrid(spec_from_neural(result.model, tmp_path), tmp_path / "hybrid.fmu")
    finally:
        result.model.close()
    assert not read_model_info(hybrid).capabilities.can_get_and_set_fmu_state
    report = validate_hybrid(hybrid, stop_time=1.0, step_size=0.004)
    assert report.passed, report.format_table()


def test_a_third_party_fmu_declared_without_state(tmp_path):
    """The Reference FMUs' BouncingBall (state events with a reset) declared
    canGetAndSetFMUstate="false": with the parameters held, the epoch losses equal those with
    snapshots; with learning, the loss falls, more slowly (the reset's gradient needs snapshots)."""
    from tests.fmi.broken_fmus import rewrite_fmu
    from tests.reference_fmus import reference_fmu
    original = reference_fmu("BouncingBall")
    declared = rewrite_fmu(original, tmp_path / "BouncingBall.fmu", xml=lambda text: text.replace(
        'canGetAndSetFMUstate="true"', 'canGetAndSetFMUstate="false"'))
    with NeuralFMU(original, TopologyConfig(channels=["der(v)"], inputs=["v"], hidden=[4])) as plain:
        from fmubuilder.neural.system import simulate_hybrid
        run = simulate_hybrid(plain, start_time=0.0, stop_time=2.0, variables=["h"], solver="rk4",
                              step_size=0.001, output_interval=0.01)
    from fmubuilder.data import MeasuredData
    data = MeasuredData(run.time, {"h": 0.9 * run["h"]}, source="ball")   # a ball that bounces lower
    common = dict(targets=["der(v)"], inputs=["v"], hidden=[4], epochs=3, element_length=0.5, step_size=0.005,
                  progress=False)
    for learning_rate in (0.0, 1e-2):
        losses = []
        for fmu in (original, declared):
            result = train_neural_fmu(fmu, data, learning_rate=learning_rate, **common)
            losses.append([h["loss"] for h in result.history])
            result.model.close()
        if learning_rate == 0.0:
            np.testing.assert_allclose(losses[1], losses[0], rtol=1e-10)
        else:   # the same starts, but no gradient through the reset (v+ = -e v-): it learns more slowly
            assert losses[1][0] == pytest.approx(losses[0][0], rel=1e-10)
            assert losses[1][-1] < 0.8 * losses[1][0] and losses[0][-1] < 0.8 * losses[0][0]
