"""Lazy package exports: names resolve on first use, so importing a package stays cheap
(the command line must not pay for torch or onnx in commands that never use them)."""
from __future__ import annotations

import importlib
import sys


def lazy_exports(package: str, exports: dict[str, str]):
    """A module-level __getattr__ that imports `name` from `package.<exports[name]>` once."""
    def __getattr__(name: str):
        if name not in exports:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        value = getattr(importlib.import_module(f"{package}.{exports[name]}"), name)
        setattr(sys.modules[package], name, value)
        return value
    return __getattr__
