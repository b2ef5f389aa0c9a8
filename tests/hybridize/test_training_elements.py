"""How `hybridize` cuts the training data into the NeuralFMU's elements."""
from types import SimpleNamespace

import numpy as np

from fmubuilder.hybridize import recipe, workflow
from fmubuilder.neural.train import plan_elements


def _settings_for(span: float):
    data = SimpleNamespace(time=np.arange(0.0, span + 1e-9, 0.1))
    diagnosis = SimpleNamespace(errors=[SimpleNamespace(signal="temperature", significant=True)])
    return workflow._training_settings(data, diagnosis, budget=5)


def test_a_short_run_is_one_element_so_the_loss_sees_a_slow_signal_drift():
    # The DC drive's training part (48 s): elements restarted from the measured states every 6 s
    # hid the temperature's drift (25 s time constant) from the loss (docs/MEASUREMENTS.md).
    settings = _settings_for(47.9)
    assert plan_elements(0.0, 47.9, settings.element_length, 0.01) == [0.0]


def test_a_long_run_keeps_elements_of_at_most_the_maximum_length():
    # The VLDM demo's training part (881 s): 8 elements of 100 s, as before.
    settings = _settings_for(881.0)
    assert settings.element_length == recipe.MAX_ELEMENT_LENGTH
    starts = plan_elements(0.0, 881.0, settings.element_length, 0.01)
    assert len(starts) == 8 and np.allclose(np.diff(starts), 100.0)


def test_one_element_or_several_the_loss_divides_each_signal_by_its_noise():
    # Each signal's MSE over its noise variance (the held-out score's unit), on one element (the DC
    # drive) and on the VLDM's elements of 100 s alike.
    assert _settings_for(47.9).loss_scale == _settings_for(881.0).loss_scale == recipe.LOSS_SCALE == "noise"


def test_a_one_element_run_refines_the_last_layer_on_simulations_counted_with_the_budget():
    # A loss evaluation costs about 18 engine simulations on the DC drive: the refinement's work grows
    # with the budget. Runs of several elements (the VLDM's): measured on the demo, not kept (recipe.py).
    assert _settings_for(47.9).last_layer_simulations == 5 * recipe.LAST_LAYER_SIMULATIONS_PER_EVALUATION
    assert _settings_for(881.0).last_layer_simulations == 0
