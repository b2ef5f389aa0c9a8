"""The choice among the candidates, on the validation data.

The rule (score, margin, publish) is the README's "The choice"; the score (fmubuilder/score.py) is
the one the trainings stop on too.

The margin is what the noise alone can do to the ratio of two scores: at the floor a signal's MSE
over its noise variance, estimated from n independent pieces, has a relative spread of sqrt(2 / n);
the pieces are blocks of inputs.BLOCK_SECONDS (longer than the sensors' noise correlation, as the ANN's
input choice takes them). Two candidates' log-scores then differ by noise with a spread of at most
sqrt(2 * 2 / n) per signal (their errors share the noise, so less), over S signals averaged
sqrt(4 / (n S)); the margin is MARGIN_SIGMAS of that. Conservative where the signals lie far above
the floor, where the noise hardly moves an MSE.
"""
from __future__ import annotations

import math

import numpy as np

from .inputs import time_blocks
from .term_started import NAME as TERM_STARTED

# The ANN candidates and their start: they must beat the one-number candidates by the margin.
ANN_CANDIDATES = ("neural", TERM_STARTED)
# Standard deviations of the noise's spread that the margin spans.
MARGIN_SIGMAS = 2.0


def noise_margin(validation_times: list[np.ndarray], signals: int) -> float:
    """Factor by which an ANN candidate's score must undercut a simpler one's (> 1)."""
    return math.exp(MARGIN_SIGMAS * math.sqrt(2.0) * score_spread(validation_times, signals))


def score_spread(validation_times: list[np.ndarray], signals: int) -> float:
    """Standard deviation of the log of one score at the floor by the noise alone: sqrt(2 / (n S))."""
    blocks = sum(int(time_blocks(np.asarray(t))[-1]) + 1 for t in validation_times if np.size(t))
    return math.sqrt(2.0 / (max(blocks, 1) * max(signals, 1)))


def at_floor(errors: dict, floors: dict, validation_times: list[np.ndarray]) -> bool:
    """Whether every signal's MSE (`errors` as score.validation_score takes them) lies within
    MARGIN_SIGMAS of the noise's spread of its floor, the noise variance: nothing above the noise is
    left for another candidate to learn. Signal by signal, since the geometric mean would hide one
    signal several times its noise among others at the floor."""
    factor = floor_factor(validation_times)
    return all(math.isfinite(errors[s]["mse"]) and errors[s]["mse"] <= floor * factor
               for s, floor in floors.items())


def floor_factor(times: list[np.ndarray]) -> float:
    """The largest MSE / noise variance of one signal that the noise alone gives on samples at `times`
    (MARGIN_SIGMAS of its spread): 1.11 on the VLDM's 881 s training part, 1.23 on its 220 s
    validation tail, 2.45 on the DC drive's 12 s."""
    return math.exp(MARGIN_SIGMAS * score_spread(times, 1))


def choose(scores: dict, plain_score: float, margin: float) -> str | None:
    """The chosen candidate's name (see the module docstring), or None when none beats the plain FMU."""
    simple = {name: s for name, s in scores.items() if name not in ANN_CANDIDATES}
    ann = {name: s for name, s in scores.items() if name in ANN_CANDIDATES}
    chosen = min(simple, key=simple.get) if simple else None
    if ann:
        best_ann = min(ann, key=ann.get)
        if chosen is None or ann[best_ann] * margin < simple[chosen]:
            chosen = best_ann
    return chosen if chosen is not None and scores[chosen] < plain_score else None


RULE = ("lowest validation score (geometric mean over the signals of MSE / noise variance); a candidate with an "
        "ANN must beat the best one-number candidate by the noise margin x{margin:.3g}, else the simpler one wins; "
        "published if below the plain FMU's {plain:.3g}")
