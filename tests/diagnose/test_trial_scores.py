"""Scores of one trial: the formulas of trace.py's docstring, and a response that ran off (a
term that destabilises the model) scored as no explanation, without an overflow."""
import warnings

import numpy as np

from fmubuilder.diagnose.trace import Tracer, Trial


def _scored(residual: np.ndarray, response: np.ndarray) -> Trial:
    tracer = Tracer.__new__(Tracer)     # scoring reads only the stacked residuals
    tracer.r = tracer.r_precise = residual
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        return tracer._scored(Trial(0, "x", "w", 0.0, response, response))


def test_a_large_response_gets_the_least_squares_coefficient_and_explained_variance():
    trial = _scored(np.array([1.0, 2.0, -1.0]), 1e100 * np.array([1.0, 1.0, 0.0]))
    # (S.r)/(S.S) = 3e100 / 2e200 and (S.r)^2 / ((S.S)(r.r)) = 9 / (2 * 6), by hand
    assert np.isclose(trial.coefficient, 1.5e-100, rtol=1e-12, atol=0.0)
    assert np.isclose(trial.shape_score, 0.75, rtol=1e-12)
    assert np.isclose(trial.score, 0.75, rtol=1e-12)


def test_a_response_whose_squares_overflow_explains_nothing_and_warns_nothing():
    trial = _scored(np.array([1.0, 2.0, -1.0]), 1e200 * np.array([1.0, 1.0, 0.0]))
    assert (trial.coefficient, trial.shape_score, trial.score) == (0.0, 0.0, 0.0)
