"""The choice among the candidates on the validation data (fmubuilder/hybridize/choice.py).

The margin is checked against its purpose with simulated noise: two models whose errors differ by
the noise alone must not tell apart by more than the margin, save rarely.
"""
import math

import numpy as np
import pytest

from fmubuilder.hybridize.choice import at_floor, choose, noise_margin
from fmubuilder.score import floors_of, validation_score
from fmubuilder.hybridize.workflow import Scores, _select

SIGNALS = ("speed", "current", "power", "energy", "temperature")
FLOORS = {s: 1.0 for s in SIGNALS}


def errors(**mse):
    return {s: {"mse": mse.get(s, 1.0), "max_abs": 0.0, "final": 0.0} for s in SIGNALS}


def test_the_ann_on_the_term_is_never_chosen_when_worse_than_the_term_on_validation():
    term = validation_score(errors(energy=170.0, temperature=358.0), FLOORS)
    for worse in (1.0, 1.01, 2.0):       # equal (it kept its start) or worse
        ann = validation_score(errors(energy=170.0 * worse, temperature=358.0 * worse), FLOORS)
        scores = {"fitted term": term, "neural on the fitted term": ann}
        assert choose(scores, plain_score=1e4, margin=1.0) == "fitted term"
        assert choose(scores, plain_score=1e4, margin=1.5) == "fitted term"


def test_an_ann_must_beat_the_simpler_candidate_by_the_margin():
    scores = {"fitted term": 10.0, "calibrated x": 12.0, "neural": 8.0, "neural on the fitted term": 9.0}
    assert choose(scores, plain_score=100.0, margin=1.2) == "neural"          # 8 * 1.2 < 10
    assert choose(scores, plain_score=100.0, margin=1.3) == "fitted term"     # 8 * 1.3 > 10
    assert choose({"neural": 8.0}, plain_score=100.0, margin=2.0) == "neural"   # nothing simpler
    assert choose(scores, plain_score=5.0, margin=1.0) is None                # none beats the plain FMU


def test_every_signal_counts_by_its_factor_not_by_its_share_of_the_plain_error():
    """The Coulomb friction's case: the ANN 3 % better where the plain FMU is near the floor, 6.5
    times worse in the energy, which the plain FMU misses by 7e5. The mean of MSE / MSE plain, the
    rule before, prefers the ANN; the geometric mean over the floor prefers the term."""
    plain = errors(speed=2.7, current=1190.0, power=478.0, energy=6.9e5, temperature=8.4e5)
    term = errors(speed=2.0, current=116.0, power=24.8, energy=170.0, temperature=358.0)
    ann = errors(speed=1.94, current=102.0, power=16.6, energy=1110.0, temperature=2790.0)
    mean_relative = lambda e: np.mean([e[s]["mse"] / plain[s]["mse"] for s in SIGNALS])  # noqa: E731
    assert mean_relative(ann) < mean_relative(term)
    floors = floors_of(plain, FLOORS)
    assert validation_score(term, floors) < validation_score(ann, floors)


def test_the_floor_is_the_plain_error_where_the_data_carry_no_spread():
    plain = errors(speed=4.0, current=9.0)
    floors = floors_of(plain, {"speed": 2.0, "current": None})
    assert floors["speed"] == 2.0 and floors["current"] == 9.0
    assert validation_score(errors(speed=4.0, current=9.0), floors) == pytest.approx(
        math.exp(np.mean([math.log(2.0)] + [0.0] * 4)))
    assert validation_score(errors(speed=float("nan")), floors) == math.inf     # a run-off


@pytest.mark.parametrize("seconds", [12.0, 60.0])
def test_noise_alone_rarely_moves_a_score_by_the_margin(seconds):
    """Two models, both at the noise floor, each seeing its own low-passed noise (correlated over
    0.2 s, as the examples' sensors) at 10 Hz: the ratio of their scores exceeds the margin in
    under 5 % of 400 draws."""
    rng = np.random.default_rng(0)
    time = np.arange(0.0, seconds, 0.1)
    margin = noise_margin([time], len(SIGNALS))
    assert margin > 1.0

    def low_passed_noise():
        white = rng.standard_normal((len(SIGNALS), time.size + 20))
        kernel = np.exp(-np.arange(20) * 0.1 / 0.2)
        coloured = np.array([np.convolve(w, kernel, mode="valid")[: time.size] for w in white])
        return coloured / np.sqrt(np.sum(kernel ** 2))

    exceeded = 0
    for _ in range(400):
        a, b = (validation_score({s: {"mse": float(np.mean(n[i] ** 2))} for i, s in enumerate(SIGNALS)}, FLOORS)
                for n in (low_passed_noise(), low_passed_noise()))
        exceeded += max(a / b, b / a) > margin
    assert exceeded < 0.05 * 400


@pytest.mark.parametrize("seconds", [12.0, 60.0])
def test_a_model_at_the_noise_floor_is_judged_at_it_and_one_above_is_not(seconds):
    """at_floor against simulated noise (low-passed over 0.2 s, 10 Hz, as above): a model whose
    errors are the noise alone is at the floor in at least 97.5 % of 400 draws, one that adds a bias
    of twice the noise's deviation to one signal of five (its MSE 5 times the noise variance, the
    geometric mean 1.38 times) is not in any."""
    rng = np.random.default_rng(1)
    time = np.arange(0.0, seconds, 0.1)

    def errors_of_draw(bias=0.0):
        white = rng.standard_normal((len(SIGNALS), time.size + 20))
        kernel = np.exp(-np.arange(20) * 0.1 / 0.2)
        noise = np.array([np.convolve(w, kernel, mode="valid")[: time.size] for w in white])
        noise /= np.sqrt(np.sum(kernel ** 2))
        noise[0] += bias
        return {s: {"mse": float(np.mean(n ** 2))} for s, n in zip(SIGNALS, noise)}

    assert sum(at_floor(errors_of_draw(), FLOORS, [time]) for _ in range(400)) >= 0.975 * 400
    assert not any(at_floor(errors_of_draw(bias=2.0), FLOORS, [time]) for _ in range(400))
    assert not at_floor(errors(energy=float("nan")), FLOORS, [time])       # a run-off


def test_the_margin_shrinks_as_the_validation_data_grow():
    short, long = (noise_margin([np.arange(0.0, s, 0.1)], 3) for s in (12.0, 220.0))
    assert long < short
    assert noise_margin([np.arange(0.0, 12.0, 0.1)] * 2, 3) < short        # two validation runs


def test_the_workflow_choice_reports_its_scores_and_rule():
    plain = Scores(fmu=None, errors={"validation": errors(energy=100.0)})
    term = type("C", (), {"name": "fitted term", "scores": Scores(fmu=None, errors={"validation": errors(energy=2.0)})})
    ann = type("C", (), {"name": "neural on the fitted term",
                         "scores": Scores(fmu=None, errors={"validation": errors(energy=2.0)})})
    selection = _select([term, ann], plain)
    assert selection["chosen"] == "fitted term"          # a tie goes to the simpler candidate
    assert selection["scores"]["fitted term"] == pytest.approx(2.0 ** (1 / 5) / 100.0 ** (1 / 5))
    assert "geometric mean" in selection["rule"]
