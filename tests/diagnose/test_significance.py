"""The noise fit and the joint test against what they assume and what they must not be fooled
by: the analytic spectra of white and AR(1) noise, coloured noise without an effect, known
offsets and slow effects, shared noise between signals and the runs' spread."""
import math

import numpy as np
import pytest
from scipy import stats

from fmubuilder import synth
from fmubuilder.diagnose import significance

N = 600
NOISE_MODELS = {
    "white": synth.BenchSettings(),
    "ar1 0.3": synth.BenchSettings(noise_model="ar1", noise_rho=0.3),
    "ar1 0.6": synth.BenchSettings(noise_model="ar1", noise_rho=0.6),
    "ar1 0.9": synth.BenchSettings(noise_model="ar1", noise_rho=0.9),
    "low-pass 0.3 s, 2nd order": synth.BenchSettings(noise_model="lowpass", noise_filter_tau=0.3, noise_filter_order=2),
    "sensor lag 0.1 s": synth.BenchSettings(noise_model="lowpass", noise_filter_tau=0.1),
}


def coloured(n, model, rng):
    return synth.unit_noise(0.1 * np.arange(n), NOISE_MODELS[model], rng)


def ar1(n, rho, rng):
    return synth.unit_noise(0.1 * np.arange(n), synth.BenchSettings(noise_model="ar1", noise_rho=rho), rng)


def test_noise_level_ignores_a_slow_model_error():
    rng = np.random.default_rng(1)
    t = np.linspace(0.0, 30.0, 3000)
    fit = significance.fit_noise(rng.normal(0.0, 0.3, t.size) + 5.0 * np.sin(t / 3.0))
    assert fit.marginal == pytest.approx(0.3, rel=0.1)


def test_the_long_run_noise_of_ar1_noise_matches_its_spectrum_at_zero():
    """AR(1) noise of unit variance: S(0) = (1 + rho) / (1 - rho) per sample."""
    rng = np.random.default_rng(2)
    for rho in (0.3, 0.6):
        fit = significance.fit_noise(ar1(5000, rho, rng))
        assert fit.long_run == pytest.approx(math.sqrt((1 + rho) / (1 - rho)), rel=0.25), rho
        assert fit.marginal == pytest.approx(1.0, rel=0.1)


@pytest.mark.parametrize("model", list(NOISE_MODELS))
def test_noise_without_an_effect_is_not_called_an_effect(model):
    """Three signals of coloured noise, 30 draws: never significant, and p-values not
    concentrated at small values (at most a few below 0.05)."""
    rng = np.random.default_rng(3)
    p_values = [significance.joint_test([coloured(N, model, rng) for _ in range(3)]).p_value for _ in range(30)]
    assert min(p_values) > significance.SIGNIFICANCE_LEVEL
    assert np.mean(np.array(p_values) < 0.05) <= 0.15


def test_an_offset_of_half_the_noise_is_significant():
    rng = np.random.default_rng(4)
    residual = rng.normal(0.0, 1.0, N) + 0.5
    single = significance.signal_test(residual, np.linspace(0.0, 10.0, N), None, 2)
    # The offset alone puts n * 0.5^2 = 150 into the zero-frequency term.
    assert single.chi2 > 0.5 * N * 0.25
    assert single.significant


def test_a_slow_effect_is_found_in_strongly_correlated_noise():
    """AR(1) rho 0.9 noise (unit variance, 19 times that at zero frequency) plus a drift to
    three noise standard deviations."""
    rng = np.random.default_rng(5)
    drift = np.linspace(0.0, 3.0, 3000)
    hits = [significance.joint_test([ar1(3000, 0.9, rng) + drift]).significant for _ in range(5)]
    assert all(hits)


def test_shared_noise_counts_once():
    """Two signals carrying the same noise (a power and an energy integrated from it share
    their noise) give the evidence of one signal, where independent ones add up."""
    rng = np.random.default_rng(6)
    base = rng.normal(0.0, 1.0, N) + 0.15
    single = significance.joint_test([base])
    shared = significance.joint_test([base, base + rng.normal(0.0, 0.01, N)])
    # The second signal adds only its own tiny noise: a chi-square of its degrees of freedom.
    assert shared.chi2 - single.chi2 < 3 * single.dof
    assert shared.p_value > single.p_value
    fisher = stats.combine_pvalues([single.p_value, single.p_value], method="fisher").pvalue
    assert shared.p_value > 10 * fisher     # what treating them as independent would claim
    other = rng.normal(0.0, 1.0, N) + 0.15
    independent = significance.joint_test([base, other])
    assert independent.chi2 == pytest.approx(single.chi2 + significance.joint_test([other]).chi2, rel=0.1)


def test_spread_between_runs_excuses_a_residual_of_its_size():
    """Runs that differ systematically (spread three times the noise) make a residual offset
    of one noise level insignificant; spread of noisy runs alone does not."""
    rng = np.random.default_rng(7)
    runs = 2
    residual = rng.normal(0.0, 1.0, N) + 1.0
    model = np.linspace(0.0, 10.0, N)
    systematic = np.full(N, 3.0 * math.sqrt(runs))                  # per-run spread
    assert not significance.signal_test(residual, model, systematic, runs).significant
    white = np.abs(rng.normal(0.0, math.sqrt(runs), N))               # spread of two noisy runs
    assert significance.signal_test(residual, model, white, runs).significant


def test_spread_caps_the_noise_when_an_effect_reaches_into_the_noise_band():
    """A large effect that switches every 2 s fills the noise band; from the residual alone it
    could be noise, but the runs' spread shows that the noise is 30 times smaller."""
    rng = np.random.default_rng(8)
    runs, sigma = 2, 0.02
    n = 150
    effect = 0.5 * np.sign(np.sin(2.0 * math.pi * np.arange(n) / 40.0)) + 0.3
    residual = effect + rng.normal(0.0, sigma, n)
    spread = np.abs(rng.normal(0.0, sigma * math.sqrt(runs), n))
    with_spread = significance.signal_test(residual, None, spread, runs)
    assert with_spread.significant
    assert sigma <= with_spread.noise < 2.0 * sigma     # capped a chance margin above the spread


def test_noise_free_data_off_by_more_than_the_floor_are_significant():
    model = np.linspace(0.0, 10.0, N)
    assert significance.signal_test(np.full(N, 1e-3), model, None, 2).significant
    assert not significance.signal_test(np.full(N, 1e-5), model, None, 2).significant
    assert not significance.signal_test(np.zeros(N), model, None, 2).significant
