"""Export: freeze a torch network to ONNX, generate C from it, wrap the original FMU into a
hybrid FMI 2.0 Model-Exchange FMU, and validate the round trip. Names load on first use (_lazy.py).
"""
from __future__ import annotations

from .._lazy import lazy_exports

_EXPORTS = {
    "FrozenNetwork": "onnx_freeze", "freeze": "onnx_freeze",
    "SUPPORTED_OPS": "kernel", "GeneratedKernel": "kernel", "generate_kernel": "kernel",
    "HybridSpec": "spec",
    "ValidationReport": "validate", "validate_hybrid": "validate",
    "export_hybrid": "wrapper",
}

__all__ = sorted(_EXPORTS)
__getattr__ = lazy_exports(__name__, _EXPORTS)
