"""A NeuralFMU: one FMU (kept loaded, with a pool of instances) plus a trainable topology."""
from __future__ import annotations

import weakref
from pathlib import Path

from torch import nn

from ..errors import FmuBuilderError
from ..fmi import Fmu, FmuInstance, convert_value
from .layer import EventSensitivity
from .topology import Topology, TopologyConfig


class NeuralFMU(nn.Module):
    """An FMI 2.0 ME FMU wrapped with a `Topology`.

    `start_values` (name -> value) are applied to every instance before initialization (parameters,
    start values of states). Instances are created on demand, one per batch element, and reused.
    Call close() (or use as a context manager) to free them.
    """

    def __init__(self, fmu_path: str | Path, config: TopologyConfig | dict,
                 start_values: dict[str, object] | None = None):
        super().__init__()
        self.fmu_path = Path(fmu_path)
        self.fmu = Fmu(self.fmu_path)
        self.info = self.fmu.info
        if self.info.n_states == 0:
            raise FmuBuilderError(f"{self.info.model_name} has no continuous states; a NeuralFMU needs state derivatives")
        config = config if isinstance(config, TopologyConfig) else TopologyConfig.from_dict(config)
        self.start_values = {name: convert_value(self.info.variable(name), value)
                             for name, value in (start_values or {}).items()}
        parameter_values = [float(self.start_values.get(p, self.info.variable(p).start or 0.0)) for p in config.parameters]
        self.topology = Topology(config, self.info, parameter_values)
        self._instances: list[FmuInstance] = []
        self._extra_loads: list[Fmu] = []   # one per further instance where the FMU allows one per process
        self._holders: dict[int, weakref.ref] = {}   # id(instance) -> the element start it stands at
        self.replays = {"runs": 0, "simulated_seconds": 0.0}   # element starts replayed (solve.Replay)
        n_knowns = self.info.n_states + len(config.parameters)
        caps = self.info.capabilities
        self.event_sensitivity = EventSensitivity(n_knowns, state_events=self.info.n_event_indicators > 0 or
                                                  not caps.completed_integrator_step_not_needed)

    @property
    def config(self) -> TopologyConfig:
        return self.topology.config

    @property
    def guid(self) -> str:
        return self.info.guid

    def instances(self, count: int, taken: frozenset = frozenset()) -> list[FmuInstance]:
        """`count` instances that no element start holds (see hold), none of those in `taken` (ids)."""
        idle = [inst for inst in self._instances if id(inst) not in taken and not self._held(inst)]
        while len(idle) < count:
            idle.append(self.loaded_copy().instantiate())
            self._instances.append(idle[-1])
        return idle[:count]

    def loaded_copy(self) -> Fmu:
        """The loaded FMU a new instance comes from: the one load, or for an FMU that allows one
        instance per process (global state in its binary) a load without a live instance."""
        if not self.info.capabilities.can_be_instantiated_only_once_per_process:
            return self.fmu
        free = next((fmu for fmu in [self.fmu, *self._extra_loads] if not fmu.live_instances), None)
        if free is None:
            free = Fmu(self.fmu_path)
            self._extra_loads.append(free)
        return free

    def instances_for(self, starts) -> list[FmuInstance]:
        """One instance per element start: the instance a start holds (taken from it: the run moves
        it on), else an idle one."""
        chosen = []
        for start in starts:
            inst = start.instance if self.holds(start) else None
            if inst is not None:
                start.instance = None
                del self._holders[id(inst)]
            chosen.append(inst)
        taken = frozenset(id(inst) for inst in chosen if inst is not None)
        spare = iter(self.instances(sum(inst is None for inst in chosen), taken))
        return [inst if inst is not None else next(spare) for inst in chosen]

    def hold(self, instance: FmuInstance, start) -> None:
        """`instance` stands at the element start `start` and is kept for it while `start` lives
        and still names it (an FMU without saved states continues there, see solve.Replay)."""
        start.instance = instance
        self._holders[id(instance)] = weakref.ref(start)

    def holds(self, start) -> bool:
        return start.instance is not None and self._held(start.instance) and \
            self._holders[id(start.instance)]() is start

    def _held(self, instance: FmuInstance) -> bool:
        ref = self._holders.get(id(instance))
        holder = ref() if ref is not None else None
        return holder is not None and holder.instance is instance

    def start_values_with_parameters(self) -> dict[str, object]:
        """Start values plus the current values of the trained FMU parameters."""
        trained = dict(zip(self.config.parameters, self.topology.fmu_parameters.detach().tolist()))
        return {**self.start_values, **trained}

    def state_names(self) -> list[str]:
        return [v.name for v in self.info.states]

    def close(self) -> None:
        for inst in self._instances:
            inst.free()
        self._instances.clear()
        self._holders.clear()
        for fmu in self._extra_loads + [self.fmu]:
            fmu.close()
        self._extra_loads.clear()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
