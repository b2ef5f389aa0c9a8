"""The last call into an FMU's binary, in memory a supervising process can read.

A binary that crashes, calls exit() or never returns takes the process with it, so the
process cannot say what happened. Before each fmi2 call the instance writes the call's
code into `CALL` (+code: in the call), after it -code (returned); fmi2SetTime writes the
model time. The CLI forks its worker after this module is imported, so parent and worker
share the page (MAP_SHARED anonymous memory) and the parent reports the crumb when the
worker dies. The writes are two stores into a memoryview per call (see
benchmarks/bench_breadcrumb.py for their cost on the hot path).

A second page serves one helper process the worker forks to run beside it (side_process.py):
the helper maps that page over its own view of the first (`become_helper`), so the crumbs it
leaves through the same memoryviews land where the supervisor reads them apart from the worker's.
"""
from __future__ import annotations

import ctypes
import math
import mmap
import os

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
PID_SLOT = 3       # helper page: the helper's pid while it runs, 0 otherwise
REPORTED = 1 << 16
# float64 slot (byte offset 64): model time of the last fmi2SetTime / fmi2SetupExperiment
# bytes 128..255: model identifier of the FMU making the call
_MODEL_OFFSET, _MODEL_SIZE = 128, 128

_MAP_FIXED = 0x10   # Linux; the mmap module does not export it

TIME_OFFSET = 64

_page = mmap.mmap(-1, mmap.PAGESIZE, flags=mmap.MAP_SHARED | mmap.MAP_ANONYMOUS)
CALL = memoryview(_page).cast("q")
TIME = memoryview(_page)[TIME_OFFSET:TIME_OFFSET + 8].cast("d")


def _helper_page():
    """The helper's page, backed by a memory file so that a forked helper can map it over its first."""
    try:
        fd = os.memfd_create("fmubuilder-breadcrumb-helper")
        os.ftruncate(fd, mmap.PAGESIZE)
        return fd, mmap.mmap(fd, mmap.PAGESIZE)
    except (AttributeError, OSError):
        return None, None       # no helper: side_process.py runs its work in the caller


_helper_fd, _helper = _helper_page()
HELPER = memoryview(_helper).cast("q") if _helper is not None else None


def page_address() -> int:
    """The address of the page the crumbs go to, for compiled code that leaves them itself (the
    helper's page is mapped at the same address, see become_helper)."""
    return ctypes.addressof(ctypes.c_char.from_buffer(_page))


def reset() -> None:
    """Forget earlier calls (before a worker starts)."""
    for page in (_page, _helper):
        if page is not None:
            _clear(page)


def reset_helper() -> None:
    """Forget the helper's calls (once its process has ended)."""
    _clear(_helper)


def _clear(page) -> None:
    page[:] = bytes(len(page))
    memoryview(page)[64:72].cast("d")[0] = math.nan


def has_helper_page() -> bool:
    return _helper is not None


def become_helper() -> None:
    """In a freshly forked helper: leave every later crumb on the helper page. Maps the helper
    page at the address of this process's first page, which the memoryviews held by the callers
    (instance.py's hot path) point into; the worker's own page is untouched."""
    libc = ctypes.CDLL(None, use_errno=True)
    libc.mmap.restype = ctypes.c_void_p
    libc.mmap.argtypes = (ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int, ctypes.c_int, ctypes.c_int, ctypes.c_long)
    address = ctypes.addressof(ctypes.c_char.from_buffer(_page))
    mapped = libc.mmap(address, mmap.PAGESIZE, mmap.PROT_READ | mmap.PROT_WRITE, mmap.MAP_SHARED | _MAP_FIXED,
                       _helper_fd, 0)
    if mapped != address:
        raise OSError(ctypes.get_errno(), "cannot map the helper's breadcrumb page")


def set_model(identifier: str) -> None:
    data = identifier.encode(errors="replace")[: _MODEL_SIZE - 1]
    _page[_MODEL_OFFSET:_MODEL_OFFSET + _MODEL_SIZE] = data.ljust(_MODEL_SIZE, b"\0")


def model(helper: bool = False) -> str:
    page = _helper if helper else _page
    return bytes(page[_MODEL_OFFSET:_MODEL_OFFSET + _MODEL_SIZE]).split(b"\0", 1)[0].decode(errors="replace")


def last_call(helper: bool = False) -> tuple[str, bool, float]:
    """(function name or "", whether it is still in progress, model time or NaN), of the worker or
    of its helper."""
    page = _helper if helper else _page
    code = memoryview(page).cast("q")[CALL_SLOT]
    name = FUNCTIONS[abs(code)] if abs(code) < len(FUNCTIONS) else f"call #{abs(code)}"
    return name, code > 0, memoryview(page)[64:72].cast("d")[0]


def crash_message(what: str, helper: bool = False) -> tuple[str, str]:
    """(message, hint) for a process that ended abnormally: in which FMI call, if in one."""
    function, in_call, t = last_call(helper)
    if in_call:
        return f"{who(helper)} {what} in {function}{at(t)}", "the FMU is faulty: report it to its vendor"
    last = f" (last FMI call: {function}{at(t)})" if function else ""
    return f"the command {what} outside a call into an FMU{last}", "rerun with --debug and please report it"


def who(helper: bool = False) -> str:
    name = model(helper)
    return f"the FMU's binary ({name})" if name else "the FMU's binary"


def at(t: float) -> str:
    return "" if math.isnan(t) else f" at t = {t:.6g} s"


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
