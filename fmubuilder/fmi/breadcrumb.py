"""The last call into an FMU's binary, in memory a supervising process can read.

A binary that crashes, calls exit() or never returns takes the process with it, so the
process cannot say what happened. Before each fmi2 call the instance writes the call's
code into `CALL` (+code: in the call), after it -code (returned); fmi2SetTime writes the
model time. The CLI forks its worker after this module is imported, so parent and worker
share the page (MAP_SHARED anonymous memory) and the parent reports the crumb when the
worker dies. The writes are two stores into a memoryview per call (see
benchmarks/bench_breadcrumb.py for their cost on the hot path).
"""
from __future__ import annotations

import math
import mmap

FUNCTIONS = (
    "", "fmi2Instantiate", "fmi2FreeInstance", "fmi2SetupExperiment", "fmi2EnterInitializationMode",
    "fmi2ExitInitializationMode", "fmi2Terminate", "fmi2Reset", "fmi2GetReal", "fmi2GetInteger",
    "fmi2GetBoolean", "fmi2GetString", "fmi2SetReal", "fmi2SetInteger", "fmi2SetBoolean", "fmi2SetString",
    "fmi2GetFMUstate", "fmi2SetFMUstate", "fmi2FreeFMUstate", "fmi2SerializedFMUstateSize",
    "fmi2SerializeFMUstate", "fmi2DeSerializeFMUstate", "fmi2GetDirectionalDerivative", "fmi2EnterEventMode",
    "fmi2NewDiscreteStates", "fmi2EnterContinuousTimeMode", "fmi2CompletedIntegratorStep", "fmi2SetTime",
    "fmi2SetContinuousStates", "fmi2GetDerivatives", "fmi2GetEventIndicators", "fmi2GetContinuousStates",
    "fmi2GetNominalsOfContinuousStates", "dlopen",
)
CODE = {name: code for code, name in enumerate(FUNCTIONS)}

# int64 slots
CALL_SLOT = 0      # +code while in the call, -code after it returned, 0 before any call
REPORT_SLOT = 1    # the worker's exit code + REPORTED once it finished on its own
PING_SLOT = 2      # set by the watchdog, cleared by the worker's signal handler
REPORTED = 1 << 16
# float64 slot (byte offset 64): model time of the last fmi2SetTime / fmi2SetupExperiment
# bytes 128..255: model identifier of the FMU making the call
_MODEL_OFFSET, _MODEL_SIZE = 128, 128

_page = mmap.mmap(-1, mmap.PAGESIZE, flags=mmap.MAP_SHARED | mmap.MAP_ANONYMOUS)
CALL = memoryview(_page).cast("q")
TIME = memoryview(_page)[64:72].cast("d")


def reset() -> None:
    """Forget earlier calls (before a worker starts)."""
    _page[:] = bytes(len(_page))
    TIME[0] = math.nan


def set_model(identifier: str) -> None:
    data = identifier.encode(errors="replace")[: _MODEL_SIZE - 1]
    _page[_MODEL_OFFSET:_MODEL_OFFSET + _MODEL_SIZE] = data.ljust(_MODEL_SIZE, b"\0")


def model() -> str:
    return bytes(_page[_MODEL_OFFSET:_MODEL_OFFSET + _MODEL_SIZE]).split(b"\0", 1)[0].decode(errors="replace")


def last_call() -> tuple[str, bool, float]:
    """(function name or "", whether it is still in progress, model time or NaN)."""
    code = CALL[CALL_SLOT]
    name = FUNCTIONS[abs(code)] if abs(code) < len(FUNCTIONS) else f"call #{abs(code)}"
    return name, code > 0, TIME[0]


def watch_fmpy() -> None:
    """Leave breadcrumbs in the FMI calls fmpy makes too (validation runs FMUs through fmpy):
    all of them pass through fmpy's `_FMU._call`."""
    from fmpy.fmi1 import _FMU
    original = _FMU._call
    if getattr(original, "leaves_breadcrumbs", False):
        return

    def call(self, name, *args):
        code = CODE.get(name, 0)
        if name == "fmi2SetTime" and len(args) > 1:
            TIME[0] = float(args[1])
        elif name == "fmi2Instantiate":
            set_model(getattr(self, "modelIdentifier", ""))
        CALL[CALL_SLOT] = code
        result = original(self, name, *args)
        CALL[CALL_SLOT] = -code
        return result
    call.leaves_breadcrumbs = True
    _FMU._call = call


reset()
