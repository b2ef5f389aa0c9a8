"""An FMU that declares canBeInstantiatedOnlyOncePerProcess (global state in its binary) gets one
loaded copy of its library per instance: a NeuralFMU's batch still runs several instances at once,
and trains exactly as the same FMU without the declaration."""
import re

import pytest

from fmubuilder.errors import FmuBuilderError
from fmubuilder.fmi import Fmu
from fmubuilder.data import MeasuredData
from fmubuilder.neural.train import train_neural_fmu
from fmubuilder.simulation import simulate as engine_simulate

from ..fmi.broken_fmus import rewrite_fmu


def once_per_process(text: str) -> str:
    text = re.sub(r'\s+canBeInstantiatedOnlyOncePerProcess="\w+"', "", text)
    return re.sub(r"<ModelExchange\b", '<ModelExchange canBeInstantiatedOnlyOncePerProcess="true"', text, count=1)


@pytest.fixture(scope="module")
def once_fmu(ball_fmu, tmp_path_factory):
    return rewrite_fmu(ball_fmu, tmp_path_factory.mktemp("once") / "ball_once.fmu", xml=once_per_process)


def test_one_loaded_copy_refuses_a_second_instance(once_fmu):
    with Fmu(once_fmu) as fmu:
        assert fmu.info.capabilities.can_be_instantiated_only_once_per_process
        first = fmu.instantiate()
        with pytest.raises(FmuBuilderError, match="canBeInstantiatedOnlyOncePerProcess"):
            fmu.instantiate()
        first.free()
        fmu.instantiate().free()      # freed, the copy takes a new one


def test_a_batch_trains_as_without_the_declaration(ball_fmu, once_fmu):
    run = engine_simulate(ball_fmu, stop_time=1.4, start_values={"g": 8.0}, solver="rk4", step_size=0.001,
                          output_interval=0.01, variables=["h"])
    data = MeasuredData(run.time, {"h": run["h"]}, source="ball")
    losses = []
    for path in (ball_fmu, once_fmu):
        result = train_neural_fmu(path, data, targets=["der(v)"], inputs=["v"], topology="residual", hidden=[4],
                                  epochs=2, step_size=0.005, solver="rk4", learning_rate=1e-2,
                                  element_length=0.35, batch_size=4, progress=False, seed=0)
        losses.append(result.metrics["errors"]["after"]["h"]["mse"])
        assert len(result.model._instances) >= 2      # several instances lived at once
        result.model.close()
    assert losses[1] == losses[0]
