"""The whole workflow in one call: diagnose, add the effect, train, export, validate, report."""
from __future__ import annotations


def hybridize(*args, **kwargs):
    from .workflow import hybridize as run
    return run(*args, **kwargs)


__all__ = ["hybridize"]
