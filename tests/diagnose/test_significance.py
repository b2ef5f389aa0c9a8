"""The noise estimate and the block test, against the distributions they assume: Gaussian white
noise of a known standard deviation, the chi-square distribution, and a known offset."""
import math

import numpy as np
import pytest
from scipy import stats

from fmubuilder.diagnose import significance

N = 300


def test_white_noise_level_ignores_a_slow_model_error():
    rng = np.random.default_rng(1)
    t = np.linspace(0.0, 30.0, 3000)
    noise = rng.normal(0.0, 0.3, t.size)
    slow = 5.0 * np.sin(t / 3.0)
    sigma, dof = significance.white_noise_level(noise + slow)
    assert sigma == pytest.approx(0.3, rel=0.05)
    assert dof == pytest.approx(0.51 * t.size, rel=0.05)


def test_block_test_of_pure_noise_is_chi_square_distributed():
    """Over many noise draws the p-values are uniform: about 5 % fall below 0.05."""
    rng = np.random.default_rng(2)
    model = np.linspace(0.0, 10.0, N)
    p_values = [significance.block_test(rng.normal(0.0, 1.0, N), model, None, 2).p_value for _ in range(400)]
    below = np.mean(np.array(p_values) < 0.05)
    # Binomial(400, 0.05): standard deviation 1.1 %.
    assert 0.02 <= below <= 0.085
    assert min(p_values) > significance.SIGNIFICANCE_LEVEL


def test_an_offset_of_half_the_noise_is_significant():
    rng = np.random.default_rng(3)
    sigma = 1.0
    residual = rng.normal(0.0, sigma, N) + 0.5 * sigma
    result = significance.block_test(residual, np.linspace(0.0, 10.0, N), None, 2)
    blocks = result.dof
    expected_chi2 = blocks * (1.0 + (N / blocks) * 0.25)   # each block mean carries the offset
    assert result.chi2 == pytest.approx(expected_chi2, rel=0.35)
    assert result.significant


def test_spread_between_runs_excuses_a_residual_of_its_size():
    """Runs that differ systematically (spread three times the white noise) make a residual
    offset of one noise level insignificant; white-noise spread alone does not."""
    rng = np.random.default_rng(4)
    sigma = 1.0
    residual = rng.normal(0.0, sigma, N) + 1.0 * sigma
    model = np.linspace(0.0, 10.0, N)
    runs = 2
    systematic = np.full(N, 3.0 * sigma * math.sqrt(runs))          # per-run spread
    assert not significance.block_test(residual, model, systematic, runs).significant
    white = np.abs(rng.normal(0.0, sigma * math.sqrt(runs), N))       # spread of two noisy runs
    assert significance.block_test(residual, model, white, runs).significant


def test_joint_p_value_combines_the_signals_with_fishers_method():
    tests = [significance.SignalTest(noise=1.0, floor=0.0, chi2=0.0, dof=20, p_value=0.01),
             significance.SignalTest(noise=1.0, floor=0.0, chi2=0.0, dof=30, p_value=0.2)]
    fisher = stats.combine_pvalues([0.01, 0.2], method="fisher").pvalue
    assert significance.joint_p_value(tests) == pytest.approx(fisher)
