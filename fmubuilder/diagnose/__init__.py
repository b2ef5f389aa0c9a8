"""Diagnosis: compare a declared model with measured data, decide whether the difference is
more than noise, and trace it to the state derivative and the variables a missing term
depends on (see diagnosis.py)."""
from .diagnosis import Candidate, Diagnosis, SignalErrors, added_terms, diagnose

__all__ = ["diagnose", "Diagnosis", "Candidate", "SignalErrors", "added_terms"]
