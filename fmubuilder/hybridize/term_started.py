"""The third candidate: a NeuralFMU whose ANN adds to the fitted term and learns what it leaves.

Its correction is `fitted term + ANN`, the ANN's last layer at zero, so it starts as the fitted term
exactly; the training ends with the parameters of its best validation score, the start included,
so on the validation data it is never worse than the term it started from. It reads the term's
variables and the ANN's inputs.
"""
from __future__ import annotations

NAME = "neural on the fitted term"


def term_started_candidate(ctx, fitted: dict | None, inputs: list[str], settings: dict):
    """The candidate, or None when the diagnosis offers no term an FMU can read (none, or one of
    time itself)."""
    from ..neural.base_term import term_inputs
    from .workflow import _aliases_of, _neural_candidate
    if not fitted or not fitted.get("offered"):
        return None
    terms = fitted["terms"]
    if any(t["variable"] == "time" for t in terms if t["basis"] != "1") or not term_inputs(terms):
        return None
    channel = fitted["channel"]
    reads = list(dict.fromkeys([*term_inputs(terms), *inputs]))
    ctx.say(f"      training an ANN on top of the fitted term: {channel} with inputs {', '.join(reads)} "
            f"({ctx.epochs} epochs) ...")
    return _neural_candidate(ctx, channel, reads, _aliases_of(ctx, channel), settings, name=NAME,
                             base_terms=terms)
