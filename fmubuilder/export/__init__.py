"""Export: freeze a torch network to ONNX, generate C from it, wrap the original FMU into a
hybrid FMI 2.0 Model-Exchange FMU, and validate the round trip.

Names load on first use, so the command line does not pay for onnx or torch in commands
that never export.
"""
from __future__ import annotations

import importlib

_EXPORTS = {
    "FrozenNetwork": "freeze", "freeze": "freeze",
    "SUPPORTED_OPS": "kernel", "GeneratedKernel": "kernel", "generate_kernel": "kernel",
    "HybridSpec": "spec",
    "ValidationReport": "validate", "validate_hybrid": "validate",
    "export_hybrid": "wrapper",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        value = getattr(importlib.import_module(f".{_EXPORTS[name]}", __name__), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
