"""The third candidate: a NeuralFMU whose ANN adds to the fitted term and learns what it leaves.

Its correction is `fitted term + ANN`, the ANN's last layer at zero, so it starts as the fitted term
exactly; the training ends with the parameters of its best validation score, the start included,
so on the validation data it is never worse than the term it started from. It reads the term's
variables and the ANN's inputs.
"""
from __future__ import annotations

from dataclasses import dataclass

NAME = "neural on the fitted term"


@dataclass
class TermStart:
    channel: str
    inputs: list[str]       # the term's variables, then the ANN's other inputs
    terms: list[dict]       # the diagnosis' fitted terms (base_term.py)


def term_start(fitted: dict | None, ann_inputs: list[str]) -> TermStart | None:
    """What the candidate trains, or None when the diagnosis offers no term an FMU can read (none,
    or one of time itself)."""
    from ..neural.base_term import term_inputs
    if not fitted or not fitted.get("offered"):
        return None
    terms = fitted["terms"]
    if any(t["variable"] == "time" for t in terms if t["basis"] != "1") or not term_inputs(terms):
        return None
    return TermStart(fitted["channel"], list(dict.fromkeys([*term_inputs(terms), *ann_inputs])), terms)
