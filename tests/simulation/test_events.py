"""State-event detection and location on indicator functions with known roots."""
import math

import numpy as np
import pytest

from fmubuilder.simulation.events import any_crossed, crossed, cut_at_state_event, locate


@pytest.mark.parametrize("z0, z1, fires", [
    (-1.0, 1.0, True), (1.0, -1.0, True),
    (-1.0, 0.0, True), (1.0, 0.0, True),        # reaching exactly zero fires
    (0.0, 1.0, False), (0.0, -1.0, False),      # leaving exactly zero does not
    (0.0, 0.0, False), (1.0, 2.0, False), (-2.0, -1.0, False),
    (1e-300, -1e-300, True),                    # the product underflows to -0.0
])
def test_crossing_convention(z0, z1, fires):
    assert crossed(np.array([z0]), np.array([z1]))[0] == fires
    assert any_crossed(np.array([z0]), np.array([z1])) == fires


def evaluate(functions):
    def indicators(t):
        return np.array([g(t) for g in functions])
    return indicators


def test_locates_a_single_root_to_the_tolerance_from_the_right():
    g = evaluate([lambda t: math.sin(t) - 0.5])
    root = math.pi / 6
    t, z, fired, evaluations = locate(g, 0.0, g(0.0), 1.0, g(1.0), tolerance=1e-12)
    assert root <= t <= root + 1e-12
    assert z[0] >= 0.0 and fired.tolist() == [True]
    assert evaluations < 20


def test_the_earliest_of_several_crossings_wins():
    g = evaluate([lambda t: 0.7 - t, lambda t: t - 0.3, lambda t: 5.0])
    t, _, fired, _ = locate(g, 0.0, g(0.0), 1.0, g(1.0), tolerance=1e-12)
    assert t == pytest.approx(0.3, abs=1e-12) and t >= 0.3
    assert fired.tolist() == [False, True, False]


def test_simultaneous_crossings_in_opposite_directions_are_one_event():
    # two indicators for one relation, as in examples/event_corner_cases: p - 1 and 2 (1 - p)
    g = evaluate([lambda t: 2.0 * t - 1.0, lambda t: 2.0 * (1.0 - 2.0 * t)])
    t, _, fired, _ = locate(g, 0.0, g(0.0), 1.0, g(1.0), tolerance=1e-12)
    assert t == pytest.approx(0.5, abs=1e-12)
    assert fired.tolist() == [True, True]


def test_a_root_exactly_at_the_step_end_is_returned_there():
    g = evaluate([lambda t: t - 1.0])
    t, z, fired, _ = locate(g, 0.0, g(0.0), 1.0, g(1.0), tolerance=1e-12)
    assert 1.0 - 1e-12 <= t <= 1.0 and fired[0]


def test_flat_indicators_still_converge_by_bisection():
    # t^9 - 1e-9 is nearly flat at its root (t = 0.1): plain regula falsi would crawl
    g = evaluate([lambda t: t ** 9 - 1e-9])
    t, _, fired, evaluations = locate(g, 0.0, g(0.0), 1.0, g(1.0), tolerance=1e-13)
    assert 0.1 <= t <= 0.1 + 1e-12 and fired[0]
    assert evaluations < 120


def test_a_step_without_a_crossing_ends_where_it_ended_without_evaluations():
    calls = []
    g = evaluate([lambda t: calls.append(t) or t + 1.0])
    t, z, fired, evaluations = cut_at_state_event(g, 0.0, np.array([1.0]), 0.5, np.array([1.5]), 1e-12)
    assert (t, z.tolist(), fired, evaluations, calls) == (0.5, [1.5], None, 0, [])


def test_a_step_with_a_crossing_is_cut_just_after_the_root():
    g = evaluate([lambda t: math.cos(t) - 0.5, lambda t: 2.0])
    t, z, fired, evaluations = cut_at_state_event(g, 0.0, g(0.0), 2.0, g(2.0), 1e-12)
    assert math.pi / 3 <= t <= math.pi / 3 + 1e-12
    assert z[0] <= 0.0 and fired.tolist() == [True, False] and evaluations > 0
