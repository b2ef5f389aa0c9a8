"""State-event detection and location on indicator functions with known roots."""
import math

import numpy as np
import pytest

from fmubuilder.simulation.events import EVENT, STEP, EventSequence, crossed, locate


@pytest.mark.parametrize("z0, z1, fires", [
    (-1.0, 1.0, True), (1.0, -1.0, True),
    (-1.0, 0.0, True), (1.0, 0.0, True),        # reaching exactly zero fires
    (0.0, 1.0, False), (0.0, -1.0, False),      # leaving exactly zero does not
    (0.0, 0.0, False), (1.0, 2.0, False), (-2.0, -1.0, False),
    (1e-300, -1e-300, True),                    # the product underflows to -0.0
])
def test_crossing_convention(z0, z1, fires):
    assert crossed(np.array([z0]), np.array([z1]))[0] == fires


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


class _Clock:
    """A driver of EventSequence for x(t) = t with the indicator x - crossing and time events at
    `times`: it records what the sequence asks, in order."""

    def __init__(self, crossing, times, step):
        self.crossing, self.times, self.h = crossing, list(times), step
        self.log = []

    def step_limit(self, seq, limit):
        return min(limit, seq.t + self.h)

    def indicators_at_end(self, seq, t):
        return np.array([t - self.crossing])

    def cut_at_state_event(self, seq, t0, t1, z1, tolerance):
        t, z, _, _ = locate(lambda t: np.array([t - self.crossing]), t0, seq.z, t1, z1, tolerance)
        self.log.append(("cut", t))
        return t, z

    def completed_step(self, seq, state_event):
        self.log.append(("completed", seq.t))
        return False, False

    def stepped_on(self, seq):
        pass

    def step(self, seq, end):
        self.log.append((STEP, end))
        return end

    def event(self, seq, kind):
        self.log.append((EVENT, kind))
        if kind == "time":
            seq.next_event = self.times.pop(0) if self.times else math.inf
        seq.z = np.array([seq.t - self.crossing])

    def run(self, seq, limit):
        seq.drive(limit, self)
        return self.log


def test_the_sequence_cuts_a_step_at_a_crossing_and_steps_on_to_the_limit():
    clock = _Clock(crossing=0.35, times=[], step=0.2)
    counts = {"time_events": 0, "state_events": 0, "step_events": 0}
    seq = EventSequence(0.0, 0.5, np.array([-0.35]), counts, 1.0)
    log = clock.run(seq, 0.6)
    assert log[:3] == [(STEP, 0.2), ("completed", 0.2), (STEP, 0.4)]
    assert log[3][0] == "cut" and 0.35 <= log[3][1] <= 0.35 + 1e-12
    assert log[4] == ("completed", log[3][1]) and log[5] == (EVENT, "state")
    assert log[6:] == [(STEP, 0.5), ("completed", 0.5), (EVENT, "time"), (STEP, 0.6), ("completed", 0.6)]
    assert counts == {"time_events": 1, "state_events": 1, "step_events": 0} and seq.t == 0.6


def test_a_time_event_at_the_end_of_a_step_takes_a_crossing_there_with_it():
    clock = _Clock(crossing=0.5, times=[], step=1.0)
    counts = {"time_events": 0, "state_events": 0, "step_events": 0}
    seq = EventSequence(0.0, 0.5, np.array([-0.5]), counts, 1.0)
    log = clock.run(seq, 1.0)
    assert log == [(STEP, 0.5), ("cut", 0.5), ("completed", 0.5), (EVENT, "time"), (STEP, 1.0), ("completed", 1.0)]
    assert counts == {"time_events": 1, "state_events": 0, "step_events": 0}
