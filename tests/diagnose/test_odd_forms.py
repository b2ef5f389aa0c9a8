"""Which of two forms the diagnosis names when the data cannot tell them apart (trace.group_equivalent).

On data where a variable keeps its sign, w*|w| and w^2 (and w and |w|) give the same response. For
the channel's own state the odd form leads, whatever the noise made the scores: a friction or a
windage in der(speed) opposes the motion. For another variable the better score leads, as before.
"""
import numpy as np

from fmubuilder.build import example_fmu
from fmubuilder.diagnose.trace import Trial, group_equivalent
from fmubuilder.fmi import read_model_info


def twins(info, channel, variable, odd, even):
    """Two trials of one variable whose responses differ by a little noise; the even one scores higher."""
    rng = np.random.default_rng(0)
    response = np.sin(np.linspace(0.0, 6.0, 200))

    def trial(basis, score):
        noisy = response + 1e-4 * rng.standard_normal(response.size)
        return Trial(channel, variable, basis, 0.0, noisy, noisy, score=score, shape_score=score)
    return [trial(odd, 0.90), trial(even, 0.91)]


def test_the_odd_form_of_the_own_state_leads_its_even_twin():
    info = read_model_info(example_fmu("dc_drive"))
    speed = info.state_index("der(speed)")
    for odd, even in (("w*|w|", "w^2"), ("w", "|w|")):
        group, = group_equivalent(info, twins(info, speed, "speed", odd, even))
        assert [t.basis for t in group] == [odd, even]


def test_for_another_variable_the_better_score_leads():
    info = read_model_info(example_fmu("dc_drive"))
    speed = info.state_index("der(speed)")
    group, = group_equivalent(info, twins(info, speed, "current", "w*|w|", "w^2"))
    assert [t.basis for t in group] == ["w^2", "w*|w|"]
