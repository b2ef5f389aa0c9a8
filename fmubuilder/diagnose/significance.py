"""Is a residual more than measurement noise? Noise levels from the data, and a block test.

Noise of a signal (standard deviation per sample of the measured value), the larger of:

* the white noise left in the residual, from its second differences
  ``d[k] = r[k+1] - 2 r[k] + r[k-1]``: for white noise E[d^2] = 6 sigma^2, while a slow model
  error hardly contributes. Differences beyond CLIP median absolute deviations (the spikes a
  shifted event leaves) are dropped. The estimate of sigma^2 carries about 0.51 n degrees of
  freedom (the d[k] are correlated: var(mean d^2) = 140 sigma^4 / n);
* the spread columns: the per-run spread ``<signal>_std`` over sqrt(runs) is the uncertainty
  of the mean over the runs; its square carries n (runs - 1) degrees of freedom.

Block test. The residual of each signal is cut into B consecutive blocks (about ten samples
each, 4 <= B <= 50). If the model is right, a block mean m_j is noise with variance

    v_j = sigma^2 / n_j  +  e_j^2  +  f^2

where n_j is the block's sample count, e_j^2 the part of the spread in that block beyond the
white noise and its chance fluctuation (runs that differ systematically, e.g. by a parameter,
excuse a residual of that size) and f = NUMERICAL_FLOOR * (range of the signal) the agreement
expected from two different numerical solvers. Q = sum_j m_j^2 / v_j would be chi-square with
B degrees of freedom for a known sigma; with sigma estimated, Q / B follows the F distribution
with (B, nu) degrees of freedom, nu those of the noise estimate. The signals' p-values are
combined with Fisher's method (-2 sum ln p is chi-square with 2 S degrees of freedom). The
residual is a significant effect when the joint p-value is below SIGNIFICANCE_LEVEL (1e-6,
strict because real noise has heavier tails than a Gaussian). Averaging over blocks makes the
test sensitive to slow deviations: an offset of half a noise standard deviation over a few
hundred samples is significant.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import stats

SIGNIFICANCE_LEVEL = 1e-6
NUMERICAL_FLOOR = 1e-5
SAMPLES_PER_BLOCK = 10
MIN_BLOCKS, MAX_BLOCKS = 4, 50
CLIP = 5.0
_MAD_TO_SIGMA = 1.4826
_SECOND_DIFFERENCE_DOF = 36.0 / 70.0   # degrees of freedom of the estimate per difference


@dataclass
class SignalTest:
    noise: float          # standard deviation of the measured value's noise (per sample)
    floor: float          # numerical agreement tolerance
    chi2: float           # Q
    dof: int              # B
    p_value: float

    @property
    def significant(self) -> bool:
        return self.p_value < SIGNIFICANCE_LEVEL


def white_noise_level(residual: np.ndarray) -> tuple[float, float]:
    """(standard deviation, degrees of freedom) of the white noise in a residual."""
    if residual.size < 5:
        return 0.0, 1.0
    second = residual[2:] - 2.0 * residual[1:-1] + residual[:-2]
    center = float(np.median(second))
    mad = _MAD_TO_SIGMA * float(np.median(np.abs(second - center)))
    kept = second[np.abs(second - center) <= CLIP * mad] if mad > 0 else second
    sigma = math.sqrt(float(np.mean(kept ** 2)) / 6.0)
    return sigma, max(1.0, _SECOND_DIFFERENCE_DOF * kept.size)


def noise_level(residual: np.ndarray, spread: np.ndarray | None, runs: int) -> tuple[float, float]:
    """(standard deviation, degrees of freedom): the larger of the two estimates above."""
    sigma, dof = white_noise_level(residual)
    if spread is not None and spread.size and runs > 1:
        from_spread = math.sqrt(float(np.mean(spread ** 2)) / runs)
        if from_spread > sigma:
            sigma, dof = from_spread, float(spread.size * (runs - 1))
    return sigma, dof


def systematic_spread(spread: np.ndarray, sigma: float, runs: int) -> float:
    """The part of a block's run-to-run spread (as uncertainty of the mean) beyond the white
    noise sigma, counted only beyond three standard errors of a block of white noise: the
    spread of two noisy runs alone fluctuates that much."""
    n = spread.size
    mean_square = float(np.mean(spread ** 2)) / runs
    chance = sigma ** 2 * (1.0 + 3.0 * math.sqrt(2.0 / max(n * (runs - 1), 1)))
    return math.sqrt(max(0.0, mean_square - chance))


def block_edges(n: int) -> np.ndarray:
    """Indices splitting n samples into B nearly equal consecutive blocks."""
    blocks = int(np.clip(n // SAMPLES_PER_BLOCK, MIN_BLOCKS, MAX_BLOCKS))
    blocks = min(blocks, n)
    return np.linspace(0, n, blocks + 1).round().astype(int)


def block_test(residual: np.ndarray, model_values: np.ndarray, spread: np.ndarray | None,
               runs: int) -> SignalTest:
    """The block test of one signal's residual (see the module docstring)."""
    sigma, noise_dof = noise_level(residual, spread, runs)
    span = float(np.ptp(model_values)) if model_values.size else 0.0
    floor = NUMERICAL_FLOOR * span
    edges = block_edges(residual.size)
    chi2 = 0.0
    for a, b in zip(edges[:-1], edges[1:]):
        mean = float(np.mean(residual[a:b]))
        variance = sigma ** 2 / (b - a) + floor ** 2
        if spread is not None and runs > 1:
            variance += systematic_spread(spread[a:b], sigma, runs) ** 2
        chi2 += mean ** 2 / variance if variance > 0 else (0.0 if mean == 0 else math.inf)
    dof = len(edges) - 1
    p_value = float(stats.f.sf(chi2 / dof, dof, noise_dof)) if math.isfinite(chi2) else 0.0
    return SignalTest(noise=sigma, floor=floor, chi2=float(chi2), dof=dof, p_value=p_value)


def joint_p_value(tests: list[SignalTest]) -> float:
    """p-value of all signals together (Fisher's method)."""
    if not tests:
        return 1.0
    p_values = np.array([t.p_value for t in tests])
    if np.any(p_values <= 0.0):
        return 0.0
    return float(stats.chi2.sf(-2.0 * float(np.sum(np.log(p_values))), 2 * len(tests)))
