"""The outcome of a simulation: sampled variables, event log and solver statistics."""
from __future__ import annotations

import os
from dataclasses import asdict, dataclass, field
from typing import IO

import numpy as np

from ..errors import FmuBuilderError
from ..files import write_atomically


@dataclass
class SimulationStats:
    solver: str = ""
    steps: int = 0                  # accepted solver steps
    rejected_steps: int = 0         # steps repeated with a smaller size (adaptive solver)
    rhs_evaluations: int = 0        # derivative evaluations by the solver
    indicator_evaluations: int = 0  # event-indicator evaluations (step ends and root finding)
    time_events: int = 0
    state_events: int = 0
    step_events: int = 0
    event_iterations: int = 0       # fmi2NewDiscreteStates passes, initialisation included
    wall_time: float = 0.0          # seconds, initialisation to termination

    def as_dict(self) -> dict:
        return asdict(self)


@dataclass
class SimulationResult:
    """Sampled values of the recorded variables: `result['h']` is an array over `result.time`.

    Rows are non-decreasing in time; a time appears twice only when events are recorded
    (values just before and just after the event). Integer and Boolean variables keep
    their type.
    """
    time: np.ndarray
    values: dict[str, np.ndarray]
    stats: SimulationStats = field(default_factory=SimulationStats)
    terminated_early: bool = False      # the model asked to stop before the stop time
    stop_time: float = 0.0              # the time the simulation reached
    events: list[tuple[float, str]] = field(default_factory=list)   # (time, 'time'|'state'|'step')

    @property
    def names(self) -> list[str]:
        return list(self.values)

    def __getitem__(self, name: str) -> np.ndarray:
        if name == "time":
            return self.time
        try:
            return self.values[name]
        except KeyError:
            raise FmuBuilderError(
                f"'{name}' was not recorded; recorded: {', '.join(self.values) or 'nothing'}") from None

    def __contains__(self, name: str) -> bool:
        return name == "time" or name in self.values

    def stats_line(self) -> str:
        s = self.stats
        end = f"terminated by the model at t={self.stop_time:g}" if self.terminated_early else f"t={self.stop_time:g}"
        return (f"{s.solver}: {end}, {s.steps} steps ({s.rejected_steps} rejected), "
                f"{s.rhs_evaluations} derivative evaluations, events: {s.time_events} time, "
                f"{s.state_events} state, {s.step_events} step; {s.wall_time * 1e3:.1f} ms")

    def to_csv(self, target: str | os.PathLike | IO[str]) -> None:
        """Write `time,<names...>` rows; a path is replaced atomically (temp file + rename)."""
        if hasattr(target, "write"):
            target.write(self._csv_text())
            return
        write_atomically(target, self._csv_text())

    def _csv_text(self) -> str:
        formatted = [_format_column(c) for c in (self.time, *self.values.values())]
        lines = [",".join(["time", *self.values])] + [",".join(row) for row in zip(*formatted)]
        return "\n".join(lines) + "\n"


def _format_column(values: np.ndarray) -> list[str]:
    if values.dtype == bool:
        return ["1" if v else "0" for v in values.tolist()]
    if np.issubdtype(values.dtype, np.integer):
        return [str(v) for v in values.tolist()]
    return [repr(v) for v in values.tolist()]   # shortest text that reads back exactly


def equal_along(trajectories: dict[str, np.ndarray], reference: np.ndarray) -> list[str]:
    """The names whose trajectory equals `reference` along the run (to 1e-9 of its largest value):
    a variable the model sets to a derivative, such as a power to der(energy)."""
    tolerance = 1e-9 * max(float(np.max(np.abs(reference))), 1e-300)
    return [name for name, values in trajectories.items() if float(np.max(np.abs(values - reference))) <= tolerance]


def sample_settled(time: np.ndarray, values: np.ndarray, at: np.ndarray) -> np.ndarray:
    """Recorded `values` at the times `at`, linear between records; where two records share a time
    (before and after an event) a stamp there takes the value after it, as a logger sees the
    settled value."""
    if len(time) == len(at) and np.array_equal(time, at):
        return values.copy()
    index = np.clip(np.searchsorted(time, at, side="right") - 1, 0, len(time) - 2)
    t0, t1 = time[index], time[index + 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        fraction = np.where(t1 > t0, (at - t0) / (t1 - t0), 1.0)
    return values[index] + np.clip(fraction, 0.0, 1.0) * (values[index + 1] - values[index])
