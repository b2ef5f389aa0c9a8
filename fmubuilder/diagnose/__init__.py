"""Diagnosis: compare a declared model with measured data, decide whether the difference is
more than noise, and trace it to the state derivative and the variables a missing term
depends on (see diagnosis.py). Names load on first use (scipy is slow to import)."""
from .._lazy import lazy_exports

_EXPORTS = {"diagnose": "diagnosis", "Diagnosis": "diagnosis", "Candidate": "diagnosis",
            "SignalErrors": "diagnosis"}

__all__ = sorted(_EXPORTS)
__getattr__ = lazy_exports(__name__, _EXPORTS)
