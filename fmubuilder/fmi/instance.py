"""An FMU loaded into the process, and its instances.

`Fmu` owns the extracted archive and the shared library; `FmuInstance` wraps one
fmi2Component and exposes the FMI 2.0 calls with numpy arrays. Hot-path calls
(states, derivatives, event indicators) reuse preallocated C buffers.
"""
from __future__ import annotations

import collections
import re
import itertools
from pathlib import Path
from typing import Iterable, NamedTuple, Sequence

import numpy as np

from ..errors import FmuBuilderError
from . import breadcrumb
from .archive import FmuArchive
from .binding import STATUS_NAMES, ffi, libc, load_library
from .breadcrumb import CALL, CODE, TIME
from .model import ModelInfo, Variable
from .sources import runnable_fmu

_instance_counter = itertools.count(1)
# Breadcrumbs (breadcrumb.py): CALL[0] = +code before a call into the binary, -code after it.
# The hot-path calls use their codes as module constants: a dict lookup per call would cost.
# Their negatives are constants too (negating at run time allocates an int per call).
_SETTIME, _SETTIME_DONE = CODE["fmi2SetTime"], -CODE["fmi2SetTime"]
_GETCONTINUOUSSTATES, _GETCONTINUOUSSTATES_DONE = CODE["fmi2GetContinuousStates"], -CODE["fmi2GetContinuousStates"]
_SETCONTINUOUSSTATES, _SETCONTINUOUSSTATES_DONE = CODE["fmi2SetContinuousStates"], -CODE["fmi2SetContinuousStates"]
_GETDERIVATIVES, _GETDERIVATIVES_DONE = CODE["fmi2GetDerivatives"], -CODE["fmi2GetDerivatives"]
_GETEVENTINDICATORS, _GETEVENTINDICATORS_DONE = CODE["fmi2GetEventIndicators"], -CODE["fmi2GetEventIndicators"]
_COMPLETEDINTEGRATORSTEP = CODE["fmi2CompletedIntegratorStep"]
_COMPLETEDINTEGRATORSTEP_DONE = -CODE["fmi2CompletedIntegratorStep"]


class FmuCallError(FmuBuilderError):
    """An fmi2 function returned fmi2Discard, fmi2Error or fmi2Fatal."""

    def __init__(self, function: str, status: int, messages: Sequence[str] = ()):
        self.function = function
        self.status = status
        detail = f": {messages[-1]}" if messages else ""
        super().__init__(f"{function} returned {STATUS_NAMES[status]}{detail}")


class EventInfo(NamedTuple):     # a tuple: made at every event, cheaper than a frozen dataclass
    new_discrete_states_needed: bool
    terminate_simulation: bool
    nominals_of_continuous_states_changed: bool
    values_of_continuous_states_changed: bool
    next_event_time_defined: bool
    next_event_time: float
    iterations: int = 1         # fmi2NewDiscreteStates calls (update_discrete_states merges several)

    @property
    def next_event_time_or_inf(self) -> float:
        return self.next_event_time if self.next_event_time_defined else float("inf")


class Fmu:
    """An FMI 2.0 Model-Exchange FMU, extracted and loaded. Use as a context manager
    or call close(); instances must be freed before."""

    def __init__(self, path: str | Path):
        self.archive = FmuArchive(path, runnable_fmu(path))
        self.info: ModelInfo = self.archive.info
        try:
            self.lib = load_library(self.archive.library_path)
        except Exception:
            self.archive.close()
            raise
        self.live_instances = 0

    @property
    def path(self) -> Path:
        return self.archive.path

    def instantiate(self, name: str | None = None, *, logging: bool = False) -> "FmuInstance":
        if self.live_instances and self.info.capabilities.can_be_instantiated_only_once_per_process:
            # each Fmu is its own extracted copy of the library, so another load is another "process"
            raise FmuBuilderError(f"{self.info.model_name} declares canBeInstantiatedOnlyOncePerProcess and this "
                                  "loaded copy already has an instance; free it or load the FMU again")
        return FmuInstance(self, name or f"{self.info.model_identifier}_{next(_instance_counter)}", logging=logging)

    def close(self) -> None:
        # The library stays mapped as long as cffi objects reference it; removing the
        # extracted files is safe on Linux even while it is mapped.
        self.archive.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


class FmuInstance:
    """One fmi2Component in Model-Exchange mode."""

    def __init__(self, fmu: Fmu, name: str, *, logging: bool = False):
        self.fmu = fmu
        self.info = fmu.info
        self.name = name
        self._lib = fmu.lib
        self.messages: collections.deque[str] = collections.deque(maxlen=20)
        self._print_log = logging
        self._logger = ffi.callback("fmi2CallbackLogger", self._on_log)
        self._callbacks = ffi.new("fmi2CallbackFunctions*")
        self._callbacks.logger = self._logger
        self._callbacks.allocateMemory = ffi.addressof(libc, "calloc")
        self._callbacks.freeMemory = ffi.addressof(libc, "free")
        self._keep = [ffi.new("char[]", s.encode()) for s in (name, self.info.guid, fmu.archive.resources_uri)]
        breadcrumb.set_model(self.info.model_identifier)
        CALL[0] = CODE["fmi2Instantiate"]
        self.component = self._lib.fmi2Instantiate(
            self._keep[0], self._lib.fmi2ModelExchange, self._keep[1], self._keep[2],
            self._callbacks, 0, 1 if logging else 0)
        CALL[0] = -CODE["fmi2Instantiate"]
        if self.component == ffi.NULL:
            detail = f": {self.messages[-1]}" if self.messages else ""
            raise FmuBuilderError(f"fmi2Instantiate failed for {self.info.model_name}{detail}")
        fmu.live_instances += 1
        n, nz = self.info.n_states, self.info.n_event_indicators
        self._n_states, self._n_indicators = n, nz   # read in every hot-path call
        self._x = ffi.new("double[]", max(n, 1))
        self._dx = ffi.new("double[]", max(n, 1))
        self._z = ffi.new("double[]", max(nz, 1))
        self._x_view = np.frombuffer(ffi.buffer(self._x), dtype=np.float64)[:n]
        self._dx_view = np.frombuffer(ffi.buffer(self._dx), dtype=np.float64)[:n]
        self._z_view = np.frombuffer(ffi.buffer(self._z), dtype=np.float64)[:nz]
        self._event_info = ffi.new("fmi2EventInfo*")
        self._flags = ffi.new("fmi2Boolean[2]")
        self._freed = False

    # -- logging and status ------------------------------------------------------------
    def _on_log(self, env, instance_name, status, category, message, first_argument):
        text = format_log_message(message, first_argument)
        self.messages.append(text)
        if self._print_log:
            cat = ffi.string(category).decode(errors="replace") if category != ffi.NULL else ""
            print(f"[{STATUS_NAMES[status] if 0 <= status < 6 else status}] [{cat}] {text}")

    def _call(self, function: str, *args) -> int:
        """Call an fmi2 function, leaving a breadcrumb, and check its status."""
        code = CODE[function]
        CALL[0] = code
        status = getattr(self._lib, function)(*args)
        CALL[0] = -code
        if status > 1:      # fmi2Discard or worse; tested inline, as in the hot-path calls below
            self._fail(status, function)
        return status

    def _fail(self, status: int, function: str):
        """Raise for a status of fmi2Discard or worse, with the FMU's last log message."""
        raise FmuCallError(function, status, tuple(self.messages))

    # -- life cycle ----------------------------------------------------------------------
    def setup_experiment(self, start_time: float = 0.0, stop_time: float | None = None,
                         tolerance: float | None = None) -> None:
        TIME[0] = start_time
        self._call("fmi2SetupExperiment", self.component, tolerance is not None, tolerance or 0.0, start_time,
                   stop_time is not None, stop_time if stop_time is not None else 0.0)

    def enter_initialization_mode(self) -> None:
        self._call("fmi2EnterInitializationMode", self.component)

    def exit_initialization_mode(self) -> None:
        self._call("fmi2ExitInitializationMode", self.component)

    def terminate(self) -> None:
        self._call("fmi2Terminate", self.component)

    def reset(self) -> None:
        self._call("fmi2Reset", self.component)

    def free(self) -> None:
        if not self._freed:
            self._freed = True
            CALL[0] = CODE["fmi2FreeInstance"]
            self._lib.fmi2FreeInstance(self.component)
            CALL[0] = -CODE["fmi2FreeInstance"]
            self.component = ffi.NULL
            self.fmu.live_instances -= 1

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.free()

    # -- variables -----------------------------------------------------------------------
    def _get_values(self, function: str, c_type: str, vrs: Sequence[int]):
        """The C array that fmi2Get<Type> `function` fills for the value references `vrs`."""
        out = ffi.new(f"{c_type}[]", len(vrs))
        self._call(function, self.component, ffi.new("fmi2ValueReference[]", list(vrs)), len(vrs), out)
        return out

    def _set_values(self, function: str, c_type: str, vrs: Sequence[int], values: list) -> None:
        self._call(function, self.component, ffi.new("fmi2ValueReference[]", list(vrs)), len(values),
                   ffi.new(f"{c_type}[]", values))

    def get_real(self, vrs: Sequence[int]) -> np.ndarray:
        return np.frombuffer(ffi.buffer(self._get_values("fmi2GetReal", "double", vrs)), dtype=np.float64).copy()

    def set_real(self, vrs: Sequence[int], values: Iterable[float]) -> None:
        self._set_values("fmi2SetReal", "double", vrs, [float(v) for v in values])

    def get_integer(self, vrs: Sequence[int]) -> list[int]:
        return list(self._get_values("fmi2GetInteger", "int", vrs))

    def set_integer(self, vrs: Sequence[int], values: Iterable[int]) -> None:
        self._set_values("fmi2SetInteger", "int", vrs, [int(v) for v in values])

    def get_boolean(self, vrs: Sequence[int]) -> list[bool]:
        return [bool(v) for v in self._get_values("fmi2GetBoolean", "int", vrs)]

    def set_boolean(self, vrs: Sequence[int], values: Iterable[bool]) -> None:
        self._set_values("fmi2SetBoolean", "int", vrs, [1 if v else 0 for v in values])

    def get_string(self, vrs: Sequence[int]) -> list[str]:
        strings = self._get_values("fmi2GetString", "fmi2String", vrs)
        return [ffi.string(s).decode() if s != ffi.NULL else "" for s in strings]

    def set_string(self, vrs: Sequence[int], values: Iterable[str]) -> None:
        keep = [ffi.new("char[]", str(v).encode()) for v in values]     # alive until the call returns
        self._set_values("fmi2SetString", "fmi2String", vrs, keep)

    def get(self, names: Sequence[str]) -> list:
        """Values of variables by name, each in its own Python type."""
        variables = [self.info.variable(n) for n in names]
        return [getattr(self, f"get_{v.api_type.lower()}")([v.value_reference])[0] for v in variables]

    def set(self, values: dict[str, object]) -> None:
        """Set variables by name; strings from the command line are converted by type."""
        for name, value in values.items():
            var = self.info.variable(name)
            setter = getattr(self, f"set_{var.api_type.lower()}")
            setter([var.value_reference], [convert_value(var, value)])

    def real_getter(self, vrs: Sequence[int]):
        """A fast reader of a fixed set of Real variables: returns a function giving a new array."""
        fill = self.real_reader(vrs)
        return lambda: fill(None).copy()

    def real_reader(self, vrs: Sequence[int]):
        """A fast reader of a fixed set of Real variables into a given array: returns a function
        fill(out) that writes the values into `out` (a float64 array of len(vrs)), or with out None
        returns a view of its own buffer, valid until the next call."""
        n = len(vrs)
        c_vrs = ffi.new("fmi2ValueReference[]", list(vrs) or [0])
        out = ffi.new("double[]", max(n, 1))
        view = np.frombuffer(ffi.buffer(out), dtype=np.float64)[:n]
        get_real, component, fail = self._lib.fmi2GetReal, self.component, self._fail
        code, done = CODE["fmi2GetReal"], -CODE["fmi2GetReal"]

        def fill(into: np.ndarray | None) -> np.ndarray:
            if n:
                CALL[0] = code
                status = get_real(component, c_vrs, n, out)
                CALL[0] = done
                if status > 1:
                    fail(status, "fmi2GetReal")
            if into is None:
                return view
            into[:] = view
            return into
        return fill

    def real_setter(self, vrs: Sequence[int]):
        """A fast writer of a fixed set of Real variables: returns a function taking the values."""
        n = len(vrs)
        c_vrs = ffi.new("fmi2ValueReference[]", list(vrs) or [0])
        buffer = ffi.new("double[]", max(n, 1))
        view = np.frombuffer(ffi.buffer(buffer), dtype=np.float64)[:n]
        set_real, component, fail = self._lib.fmi2SetReal, self.component, self._fail
        code, done = CODE["fmi2SetReal"], -CODE["fmi2SetReal"]

        def write(values) -> None:
            if n:
                view[:] = values
                CALL[0] = code
                status = set_real(component, c_vrs, n, buffer)
                CALL[0] = done
                if status > 1:
                    fail(status, "fmi2SetReal")
        return write

    # -- continuous-time interface ---------------------------------------------------------
    def set_time(self, t: float) -> None:
        TIME[0] = t
        CALL[0] = _SETTIME
        status = self._lib.fmi2SetTime(self.component, t)
        CALL[0] = _SETTIME_DONE
        if status > 1:
            self._fail(status, "fmi2SetTime")

    # With no states (or no indicators) the array calls below are not made: fmpy and fmusim skip
    # them, and some tools' FMUs answer nx = 0 with an error.
    def get_continuous_states(self) -> np.ndarray:
        if not self._n_states:
            return self._x_view.copy()
        CALL[0] = _GETCONTINUOUSSTATES
        status = self._lib.fmi2GetContinuousStates(self.component, self._x, self._n_states)
        CALL[0] = _GETCONTINUOUSSTATES_DONE
        if status > 1:
            self._fail(status, "fmi2GetContinuousStates")
        return self._x_view.copy()

    def set_continuous_states(self, x) -> None:
        if not self._n_states:
            return
        self._x_view[:] = x
        CALL[0] = _SETCONTINUOUSSTATES
        status = self._lib.fmi2SetContinuousStates(self.component, self._x, self._n_states)
        CALL[0] = _SETCONTINUOUSSTATES_DONE
        if status > 1:
            self._fail(status, "fmi2SetContinuousStates")

    def get_derivatives(self) -> np.ndarray:
        return self._derivatives_view().copy()

    def derivatives_into(self, out: np.ndarray) -> None:
        """get_derivatives() written into `out` (a float64 array of n_states), without a new array."""
        out[:] = self._derivatives_view()

    def _derivatives_view(self) -> np.ndarray:
        """The derivatives at the current point in the instance's own buffer (valid until the next call)."""
        if self._n_states:
            CALL[0] = _GETDERIVATIVES
            status = self._lib.fmi2GetDerivatives(self.component, self._dx, self._n_states)
            CALL[0] = _GETDERIVATIVES_DONE
            if status > 1:
                self._fail(status, "fmi2GetDerivatives")
        return self._dx_view

    def get_event_indicators(self) -> np.ndarray:
        if not self._n_indicators:
            return self._z_view.copy()
        CALL[0] = _GETEVENTINDICATORS
        status = self._lib.fmi2GetEventIndicators(self.component, self._z, self._n_indicators)
        CALL[0] = _GETEVENTINDICATORS_DONE
        if status > 1:
            self._fail(status, "fmi2GetEventIndicators")
        return self._z_view.copy()

    def get_nominals_of_continuous_states(self) -> np.ndarray:
        if not self._n_states:
            return np.zeros(0)
        out = ffi.new("double[]", self._n_states)
        self._call("fmi2GetNominalsOfContinuousStates", self.component, out, self._n_states)
        return np.frombuffer(ffi.buffer(out), dtype=np.float64).copy()

    def completed_integrator_step(self, no_set_fmu_state_prior: bool = True) -> tuple[bool, bool]:
        """Returns (enter_event_mode, terminate_simulation)."""
        flags = self._flags
        CALL[0] = _COMPLETEDINTEGRATORSTEP
        status = self._lib.fmi2CompletedIntegratorStep(self.component, no_set_fmu_state_prior, flags, flags + 1)
        CALL[0] = _COMPLETEDINTEGRATORSTEP_DONE
        if status > 1:
            self._fail(status, "fmi2CompletedIntegratorStep")
        return bool(flags[0]), bool(flags[1])

    # -- event mode ------------------------------------------------------------------------
    def enter_event_mode(self) -> None:
        self._call("fmi2EnterEventMode", self.component)

    def enter_continuous_time_mode(self) -> None:
        self._call("fmi2EnterContinuousTimeMode", self.component)

    def new_discrete_states(self) -> EventInfo:
        info = self._event_info
        info.newDiscreteStatesNeeded = 1  # the importer's initial value, as the standard's pseudo-code
        self._call("fmi2NewDiscreteStates", self.component, info)
        return EventInfo(bool(info.newDiscreteStatesNeeded), bool(info.terminateSimulation),
                         bool(info.nominalsOfContinuousStatesChanged), bool(info.valuesOfContinuousStatesChanged),
                         bool(info.nextEventTimeDefined), float(info.nextEventTime))

    def update_discrete_states(self) -> EventInfo:
        """The event iteration: call fmi2NewDiscreteStates until no new discrete states are
        needed, merging what each pass reports (a state change or a terminate request in any
        pass counts)."""
        values_changed = nominals_changed = False
        iterations = 0
        while True:
            info = self.new_discrete_states()
            iterations += 1
            if iterations == 1 and (info.terminate_simulation or not info.new_discrete_states_needed):
                return info     # one pass, the usual case: nothing to merge
            values_changed |= info.values_of_continuous_states_changed
            nominals_changed |= info.nominals_of_continuous_states_changed
            if info.terminate_simulation or not info.new_discrete_states_needed:
                return EventInfo(False, info.terminate_simulation, nominals_changed, values_changed,
                                 info.next_event_time_defined, info.next_event_time, iterations)

    # -- FMU state -------------------------------------------------------------------------
    def _require(self, capability: str, what: str) -> None:
        if not getattr(self.info.capabilities, capability):
            raise FmuBuilderError(f"{self.info.model_name} does not support {what} (modelDescription: {capability} is false)")

    def get_fmu_state(self, state=None):
        """Snapshot the instance; pass a previous snapshot to overwrite it in place."""
        self._require("can_get_and_set_fmu_state", "getting/setting its state")
        handle = ffi.new("fmi2FMUstate*", state if state is not None else ffi.NULL)
        self._call("fmi2GetFMUstate", self.component, handle)
        return handle[0]

    def set_fmu_state(self, state) -> None:
        self._call("fmi2SetFMUstate", self.component, state)

    def free_fmu_state(self, state) -> None:
        handle = ffi.new("fmi2FMUstate*", state)
        self._call("fmi2FreeFMUstate", self.component, handle)

    def serialize_fmu_state(self, state) -> bytes:
        self._require("can_serialize_fmu_state", "serializing its state")
        size = ffi.new("size_t*")
        self._call("fmi2SerializedFMUstateSize", self.component, state, size)
        data = ffi.new("fmi2Byte[]", size[0])
        self._call("fmi2SerializeFMUstate", self.component, state, data, size[0])
        return ffi.buffer(data)[:]

    def deserialize_fmu_state(self, data: bytes):
        self._require("can_serialize_fmu_state", "serializing its state")
        handle = ffi.new("fmi2FMUstate*", ffi.NULL)
        buf = ffi.new("fmi2Byte[]", data)
        self._call("fmi2DeSerializeFMUstate", self.component, buf, len(data), handle)
        return handle[0]

    # -- directional derivatives -----------------------------------------------------------
    def get_directional_derivative(self, unknowns: Sequence[int], knowns: Sequence[int], seed) -> np.ndarray:
        """J[unknowns, knowns] @ seed, from the FMU's own derivative code."""
        self._require("provides_directional_derivative", "directional derivatives")
        out = ffi.new("double[]", len(unknowns))
        self._call(
            "fmi2GetDirectionalDerivative", self.component, ffi.new("fmi2ValueReference[]", list(unknowns)), len(unknowns),
            ffi.new("fmi2ValueReference[]", list(knowns)), len(knowns),
            ffi.new("double[]", [float(s) for s in seed]), out)
        return np.frombuffer(ffi.buffer(out), dtype=np.float64).copy()


_CONVERSION = re.compile(rb"%[-+ #0]*[0-9*]*(?:\\.[0-9*]+)?(?:hh|h|ll|l|L|z|j|t)?([diouxXeEfFgGaAcspn%])")


def format_log_message(message, first_argument) -> str:
    """The logged text. Only a leading %s conversion is filled in (its argument is known to
    be a string); other conversions stay as written, since their arguments cannot be read
    safely through a fixed-signature callback."""
    if message == ffi.NULL:
        return ""
    raw = ffi.string(message)
    for match in _CONVERSION.finditer(raw):
        if match.group(1) == b"%":
            continue
        if match.group(1) == b"s" and match.group(0) == b"%s" and first_argument != ffi.NULL:
            head, tail = raw[:match.start()], raw[match.end():]
            return (head.replace(b"%%", b"%") + ffi.string(first_argument) + tail).decode(errors="replace")
        break
    return raw.replace(b"%%", b"%").decode(errors="replace")


def convert_value(var: Variable, value):
    """Convert a value (possibly a command-line string) to the variable's type."""
    try:
        if var.api_type == "Real":
            return float(value)
        if var.api_type == "Integer":
            if isinstance(value, str):
                as_float = float(value)
                if as_float != int(as_float):
                    raise ValueError
                return int(as_float)
            return int(value)
        if var.api_type == "Boolean":
            if isinstance(value, str):
                lowered = value.strip().lower()
                if lowered in ("true", "1"):
                    return True
                if lowered in ("false", "0"):
                    return False
                raise ValueError
            return bool(value)
        return str(value)
    except (TypeError, ValueError):
        raise FmuBuilderError(
            f"cannot set {var.name} ({var.type}) to {value!r}; give a value of type {var.type}") from None
