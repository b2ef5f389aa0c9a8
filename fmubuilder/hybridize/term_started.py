"""The third candidate: a NeuralFMU whose ANN adds to the fitted term and learns what it leaves
(the README's "The candidates"). It reads the term's variables and the ANN's inputs.
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
    """What the candidate trains, or None when the diagnosis offers no term an FMU can read."""
    inputs = fmu_term_inputs(fitted["terms"]) if fitted and fitted.get("offered") else []
    if not inputs:
        return None
    return TermStart(fitted["channel"], list(dict.fromkeys([*inputs, *ann_inputs])), fitted["terms"])


def fmu_term_inputs(terms: list[dict]) -> list[str]:
    """The variables a fitted term reads; none when it reads time itself, which an FMU cannot take
    as a variable input."""
    from ..neural.base_term import term_inputs
    inputs = term_inputs(terms)
    return [] if "time" in inputs else inputs
