"""fmpy as the independent reference importer: its CVode results and the events it handled.

fmpy does not report event counts, so they are read from its FMI call log: every
fmi2EnterEventMode is one event, classified as a step event when the preceding
fmi2CompletedIntegratorStep asked for it, a time event when the time equals the
nextEventTime the FMU announced, and a state event otherwise.
"""
import math
import re

import fmpy
import numpy as np

_SET_TIME = re.compile(r"fmi2SetTime\(c=\w+, time=([-+0-9.eE]+)\)")
_NEXT_EVENT = re.compile(r"nextEventTimeDefined=(\d), nextEventTime=([-+0-9.eEinf]+)\)")
_STEP = re.compile(r"fmi2CompletedIntegratorStep\(.*enterEventMode=(\d)")


def fmpy_simulation(path, *, output, rtol=1e-10, solver="CVode", **options):
    """(fmpy's result, [(time, 'time'|'state'|'step'), ...]) for one simulation."""
    log = []
    result = fmpy.simulate_fmu(str(path), solver=solver, relative_tolerance=rtol, output=list(output),
                               fmi_call_logger=log.append, **options)
    return result, classify_events(log)


def classify_events(log):
    events = []
    t, next_event, step_requested = 0.0, math.inf, False
    for line in log:
        if line.startswith("fmi2SetTime"):
            t = float(_SET_TIME.match(line).group(1))
        elif line.startswith("fmi2NewDiscreteStates"):
            defined, value = _NEXT_EVENT.search(line).groups()
            next_event = float(value) if defined == "1" else math.inf
        elif line.startswith("fmi2CompletedIntegratorStep"):
            step_requested = _STEP.match(line).group(1) == "1"
        elif line.startswith("fmi2EnterEventMode"):
            if step_requested:
                kind = "step"
            elif math.isclose(t, next_event, rel_tol=1e-9, abs_tol=1e-12):
                kind = "time"
            else:
                kind = "state"
            events.append((t, kind))
            step_requested = False
    return events


def count(events, kind):
    return sum(1 for _, k in events if k == kind)


def rows_at(reference, times, period):
    """Index of fmpy's row for each output time: the last row at that time, i.e. the value
    after any event there (fmpy records before and after events)."""
    index = np.searchsorted(reference["time"], np.asarray(times) + 1e-9 * period, side="right") - 1
    np.testing.assert_allclose(reference["time"][index], times, rtol=1e-9, atol=1e-9 * period)
    return index


def away_from(times, event_times, distance):
    """Mask of the output times farther than `distance` from every event time: at an event
    instant itself, which side an importer reports is a convention, not a result."""
    mask = np.ones(len(times), dtype=bool)
    for t_event in event_times:
        mask &= np.abs(np.asarray(times) - t_event) > distance
    return mask
