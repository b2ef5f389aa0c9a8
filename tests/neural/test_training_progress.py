"""The training's bar counts epochs x batches and closes with a note when the training stops early."""
import pytest

from fmubuilder import progress
from fmubuilder.neural import train_neural_fmu

from .conftest import plant_data


@pytest.fixture
def shown():
    progress.set_enabled(True)
    yield
    progress.set_enabled(None)


def test_training_bar_stops_with_a_note_on_an_early_stop(plant_fmu, shown, capsys):
    data, _ = plant_data(plant_fmu, [0, 1], [1, 1], 1.0, seed=0)
    stop_after = 2
    result = train_neural_fmu(plant_fmu, data, targets=["der(w)"], inputs=["w"], topology="residual", hidden=[4],
                              epochs=5, element_length=1.0, step_size=0.002, ccpt_iterations=0,
                              on_epoch=lambda epoch, trainer: epoch >= stop_after)
    result.model.close()
    assert result.metrics["epochs"] == stop_after
    lines = capsys.readouterr().err.replace("\r", "\n").strip().splitlines()
    training = [line for line in lines if line.startswith("training")]
    assert training, lines
    # one element per epoch: total 5 batches, closed at 2 with the reason
    assert training[-1].startswith("training (stopped: ended by the caller after epoch 2):  40%")
    assert "| 2/5 [" in training[-1] and "<" not in training[-1]      # no time left to wait for
