"""Is a residual more than measurement noise? One joint test that coloured noise does not fool.

Why the frequency domain: the README's "Is it an effect or coloured noise?". Everything is
estimated from the residual itself and the model's own run (no sensor settings are read):

1. **Bands.** A model error shows where the model itself moves: its residual is, to first order,
   the response of the model's trajectory to a change in its equations, so it shares the
   trajectory's frequencies (an oscillator whose damping or period is off shows at its own
   frequency). The effect band is therefore the lowest ``m`` Fourier frequencies (``m = n //
   SAMPLES_PER_FREQUENCY`` within [1, MAX_EFFECT_FREQUENCIES]: drifts and slow effects) plus the
   frequencies that carry MODEL_ENERGY of the model's own signals (a straight line removed, Hann
   tapered) with LEAKAGE neighbours on each side, at most 1 / EFFECT_SHARE_LIMIT of all frequencies. The noise band
   is the rest above ``GUARD * m``, LEAKAGE neighbours away from the effect band. The model's run
   is noise-free, so the bands do not depend on the noise. Without the model's values the effect
   band is the lowest ``m`` frequencies alone. The noise spectrum must bridge the holes the
   model's frequencies leave and extrapolate below them, so the fits on the whole band above
   ``GUARD * m`` (which an effect there can only inflate) join its envelope (step 2): the test is
   never less cautious than one that ignores the model, and finds an effect at the model's
   frequencies where the model leaves noise-only frequencies around them (an oscillation).
2. **Noise spectrum per signal.** The residual, a straight line removed and a Hann taper
   applied (so that a drift does not leak into the noise band), gives a periodogram on the
   noise band. The family ``S(w) = a + b g(w)^k`` with ``g = (1 - rho)^2 / |1 - rho e^{-iw}|^2``
   (white noise plus noise through k = 1 or 2 first-order low-passes: white, AR(1), a sensor
   lag, a filtered sensor and their sums) is fitted to it by the Whittle likelihood over a
   grid of poles rho (corners 1 - rho down to SLOWEST_CORNER times the noise band's lowest
   frequency: noise that decorrelates more slowly than that cannot be told from an effect in
   a record of this length), a and b >= 0 by iteratively reweighted least squares. The
   spectrum used in the effect band is, at each frequency, the largest of all fits whose BIC
   lies within 2 CONFIDENCE of the best: how far the noise band can be extrapolated to the
   lowest frequencies is uncertain, most of all for short data and slowly decorrelating noise.
3. **Dependence between signals.** The coherence of the signals' noise (their DFTs divided
   by their spectra's square roots) over the noise band gives one correlation matrix, so
   signals whose noise is shared (a power and the energy integrated from it) count once.
4. **Run-to-run spread** (``<signal>_std`` columns, when present): its mean square over the
   runs is the noise variance of the mean. The noise is capped a chance margin above it (an
   effect with fast parts reaching into the noise band would otherwise pass for noise: the
   spread does not contain the effect); spread beyond the noise and its chance fluctuation
   (runs that differ systematically, e.g. by a parameter) excuses a residual of that size.
   Without spread columns the test relies on the residual alone.
5. **Joint statistic.** With ``z_j`` the DFT vector of all signals at frequency j, each
   divided by the square root of its spectrum, and ``C_j`` its covariance under "no effect"
   (the noise coherence, plus the numerical floor ``NUMERICAL_FLOOR * range`` of each signal
   and the excused spread), ``Q = z_0^T C_0^-1 z_0 + sum_{j in effect band} 2 z_j^H C_j^-1 z_j`` is
   chi-square with ``S (2K + 1)`` degrees of freedom for S signals and K effect frequencies. With the noise estimated,
   ``Q / dof`` is taken F-distributed with (dof, noise-band degrees of freedom). The residual
   is a significant effect when the p-value is below SIGNIFICANCE_LEVEL (1e-6, strict because
   real noise has heavier tails than a Gaussian). The same statistic for one signal alone
   gives the per-signal p-values of the report. Q is taken twice, over the lowest ``m`` frequencies
   alone and over the whole effect band, and the smaller p-value doubled (each look is calibrated;
   the union bound keeps the pair so): a slow effect keeps the power of the narrow look.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy import optimize, stats

SIGNIFICANCE_LEVEL = 1e-6
NUMERICAL_FLOOR = 1e-5
SAMPLES_PER_FREQUENCY = 125    # effect band: one Fourier frequency per this many samples ...
MAX_EFFECT_FREQUENCIES = 25    # ... at most this many (a few dozen degrees of freedom per signal)
GUARD = 2                      # the noise band starts at GUARD times the lowest band's edge ...
MODEL_ENERGY = 0.99            # the effect band holds this share of the model signals' variance ...
LEAKAGE = 2                    # ... with the Hann window's main lobe (2 bins) on each side; the noise
                               # band keeps LEAKAGE more bins away, so no effect leaks into it
EFFECT_SHARE_LIMIT = 4         # ... and at most a quarter of all frequencies: every added frequency
                               # dilutes the test (2 dof each), and the noise fit needs the rest
MIN_NOISE_FREQUENCIES = 8
CONFIDENCE = 2.5               # BIC units (x2) within which a noise fit counts as plausible
POLE_COUNT = 30               # poles on the grid, from white (rho = 0) ...
SLOWEST_CORNER = 0.5         # ... to a corner 1 - rho at this share of the noise band's lowest frequency
LOWPASS_ORDERS = (1, 2)
MAX_BINS = 160                 # the noise band's periodogram is averaged into at most this many bins
SPREAD_CHANCE = 3.0            # standard errors of the spread's mean square counted as chance
_HANN_VARIANCE_INFLATION = 35.0 / 18.0   # periodogram ordinates one Hann-tapered ordinate is worth
_REWEIGHTING_STEPS = 8


@dataclass
class Spectrum:
    """S(w) = a + b g(w)^k, g = (1 - rho)^2 / |1 - rho e^{-iw}|^2 (per sample, S(0) = a + b)."""
    white: float
    coloured: float
    pole: float
    order: int

    def at(self, omega: np.ndarray) -> np.ndarray:
        return self.white + self.coloured * _lowpass(omega, self.pole) ** self.order


def _lowpass(omega: np.ndarray, pole: float) -> np.ndarray:
    return (1.0 - pole) ** 2 / (1.0 - 2.0 * pole * np.cos(omega) + pole ** 2)


@dataclass
class NoiseFit:
    """Noise of one signal's residual as the test sees it."""
    spectra: list[Spectrum]   # the best fit first, then the others within CONFIDENCE
    marginal: float           # standard deviation of the noise per sample (best fit)
    excused: float            # systematic run-to-run spread excusing a residual of this size
    floor: float              # numerical agreement tolerance
    dof: float                # degrees of freedom of the noise estimate
    variance_cap: float = math.inf   # no plausible noise has a larger variance per sample (spread)
    away: list = field(default_factory=list)   # plausible fits away from the model's frequencies

    def spectrum(self, omega: np.ndarray, wide: bool = False) -> np.ndarray:
        """The noise spectrum the test assumes: the largest of the plausible fits (with `wide`, those
        away from the model's frequencies too), each scaled down to the variance cap."""
        omega = np.asarray(omega, dtype=float)
        fits = self.spectra + self.away if wide else self.spectra
        if not fits:
            return np.zeros(omega.size)
        capped = [s.at(omega) * min(1.0, self.variance_cap / max(_marginal_variance(s), 1e-300))
                  for s in fits]
        return np.max(capped, axis=0)

    @property
    def long_run(self) -> float:
        """Standard deviation of a long mean times sqrt(n): sqrt of the spectrum at zero."""
        return math.sqrt(float(self.spectrum(np.zeros(1))[0]))


@dataclass
class SignalTest:
    noise: float          # standard deviation of the measured value's noise (per sample)
    noise_dof: float      # degrees of freedom of its variance estimate (relative std sqrt(2 / dof))
    floor: float          # numerical agreement tolerance
    chi2: float           # Q of this signal alone
    dof: int
    p_value: float

    @property
    def significant(self) -> bool:
        return self.p_value < SIGNIFICANCE_LEVEL


@dataclass
class JointTest:
    chi2: float
    dof: int
    p_value: float
    signals: int

    @property
    def significant(self) -> bool:
        return self.p_value < SIGNIFICANCE_LEVEL


# ---------------------------------------------------------------------------------------
# Bands and the noise fit


def effect_band(n: int) -> int:
    """m: how many of the lowest non-zero Fourier frequencies always belong to the effect band of n samples."""
    noise_room = (n - 1) // 2 - MIN_NOISE_FREQUENCIES
    return int(max(1, min(n // SAMPLES_PER_FREQUENCY, MAX_EFFECT_FREQUENCIES, noise_room // GUARD)))


@dataclass(frozen=True)
class Bands:
    """The non-zero Fourier frequencies (indices j of n samples) of the effect and of the noise."""
    effect: np.ndarray
    noise: np.ndarray


def bands(n: int, model_values=()) -> Bands:
    """The effect and noise bands of n samples (module docstring, step 1); model_values: the model's
    runs of the signals tested together (entries may be None)."""
    highest = (n - 1) // 2
    lowest = effect_band(n)
    effect = set(range(1, lowest + 1))
    for values in model_values:
        effect |= _carrying(values, n)
    room = max(highest // EFFECT_SHARE_LIMIT, lowest)
    if len(effect) > room:     # keep room for the noise and power for the test: the lowest ones
        effect = set(range(1, lowest + 1)) | set(sorted(effect - set(range(1, lowest + 1)))[:room - lowest])
    effect_indices = np.array(sorted(j for j in effect if j <= highest), dtype=int)
    near = set()
    for j in effect_indices.tolist():
        near.update(range(j - LEAKAGE, j + LEAKAGE + 1))
    start = min(GUARD * lowest + 1, max(highest, 1))
    noise = np.array([j for j in range(start, highest + 1) if j not in near], dtype=int)
    if noise.size < MIN_NOISE_FREQUENCIES:          # too short to spare: the old split
        effect_indices = np.arange(1, lowest + 1)
        noise = np.arange(start, highest + 1)
    return Bands(effect_indices, noise)


def _carrying(values, n: int) -> set[int]:
    """Frequencies carrying MODEL_ENERGY of a model signal's variance, with their LEAKAGE neighbours."""
    if values is None or np.size(values) != n or not np.all(np.isfinite(values)):
        return set()
    values = np.asarray(values, dtype=float)
    dft, norm = _tapered_dft(values)
    power = np.abs(dft[1:(n - 1) // 2 + 1]) ** 2
    total = float(np.sum(power))
    if not total > n * norm * (NUMERICAL_FLOOR * float(np.ptp(values))) ** 2:
        return set()        # a straight line (or round-off about one) carries nothing
    order = np.argsort(power)[::-1]
    count = int(np.searchsorted(np.cumsum(power[order]), MODEL_ENERGY * total)) + 1
    carrying = set()
    for j in (order[:count] + 1).tolist():
        carrying.update(range(max(1, j - LEAKAGE), j + LEAKAGE + 1))
    return carrying


def _tapered_dft(residual: np.ndarray) -> tuple[np.ndarray, float]:
    """DFT of the residual with a straight line removed and a Hann taper, and the taper's sum
    of squares (the periodogram's normalisation)."""
    n = residual.size
    k = np.arange(n)
    line = np.polynomial.polynomial.polyfit(k, residual, 1)
    detrended = residual - np.polynomial.polynomial.polyval(k, line)
    taper = np.hanning(n + 2)[1:-1]
    return np.fft.rfft(detrended * taper), float(np.sum(taper ** 2))


def fit_noise(residual: np.ndarray, model_values: np.ndarray | None = None,
              spread: np.ndarray | None = None, runs: int = 2, band: np.ndarray | None = None) -> NoiseFit:
    """The noise of a residual (see the module docstring, steps 2 and 4) on the noise band `band`
    (default: the one of this signal's model values)."""
    residual = np.asarray(residual, dtype=float)
    n = residual.size
    span = float(np.ptp(model_values)) if model_values is not None and np.size(model_values) else 0.0
    if band is None:
        band = bands(n, [model_values]).noise
    dft, norm = _tapered_dft(residual)
    # The narrow look (the lowest frequencies) keeps the fits on the whole band above them. The wide
    # look (the model's frequencies) needs the noise away from the model's frequencies too: fitted
    # there, and joined by the whole band's fits, since over the holes the model's frequencies leave
    # (and below them) the spectrum is bridged or extrapolated: it is never less cautious than without.
    whole = np.arange(min(GUARD * effect_band(n) + 1, max((n - 1) // 2, 1)), (n - 1) // 2 + 1)
    spectra = _fitted_spectra(dft, norm, n, whole)
    away = _fitted_spectra(dft, norm, n, band) if not np.array_equal(band, whole) else []
    fit = NoiseFit(spectra=spectra, marginal=0.0, excused=0.0, floor=NUMERICAL_FLOOR * span,
                   dof=2.0 * max(whole.size / _HANN_VARIANCE_INFLATION, 1.0), away=away)
    # The noise level: from the band without the model's frequencies, which holds less of an effect.
    best = (away or spectra)[:1]
    fit.marginal = math.sqrt(_marginal_variance(best[0])) if best else 0.0
    if spread is not None and np.size(spread) and runs > 1:
        _apply_spread(fit, np.asarray(spread, dtype=float), runs)
    return fit


def _fitted_spectra(dft: np.ndarray, norm: float, n: int, frequencies: np.ndarray) -> list[Spectrum]:
    """The plausible noise spectra fitted to the periodogram at `frequencies` (step 2)."""
    omega, periodogram, weight = _binned(2.0 * math.pi * frequencies / n, np.abs(dft[frequencies]) ** 2 / norm)
    poles = 1.0 - np.geomspace(1.0, SLOWEST_CORNER * float(omega[0]), POLE_COUNT) if omega.size else np.zeros(1)
    return _plausible_spectra(omega, periodogram, weight / _HANN_VARIANCE_INFLATION, poles)


def _binned(omega: np.ndarray, periodogram: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The periodogram averaged over consecutive frequencies into at most MAX_BINS bins, and
    how many ordinates each bin holds (the Whittle fit weighs a bin by that count)."""
    if omega.size <= MAX_BINS:
        return omega, periodogram, np.ones(omega.size)
    edges = np.linspace(0, omega.size, MAX_BINS + 1).round().astype(int)
    counts = np.diff(edges).astype(float)
    return (np.add.reduceat(omega, edges[:-1]) / counts, np.add.reduceat(periodogram, edges[:-1]) / counts, counts)


def _plausible_spectra(omega: np.ndarray, periodogram: np.ndarray, weight: np.ndarray,
                       poles: np.ndarray) -> list[Spectrum]:
    """Whittle fits over the grid of poles and orders, ranked by BIC (white noise has one
    parameter, a coloured part two more): the best first, then every other fit whose BIC
    is within 2 CONFIDENCE of it."""
    if not np.any(periodogram > 0):
        return []
    penalty = math.log(max(float(np.sum(weight)), 2.0))
    fits = [(_white_bic(periodogram, weight, penalty), Spectrum(float(np.average(periodogram, weights=weight)),
                                                                0.0, 0.0, 1))]
    for order in LOWPASS_ORDERS:
        for pole in poles:
            shape = _lowpass(omega, pole) ** order
            white, coloured = _whittle_weights(shape, periodogram, weight)
            spectrum = white + coloured * shape
            log_likelihood = -float(np.sum(weight * (np.log(spectrum) + periodogram / spectrum)))
            fits.append((-2.0 * log_likelihood + 3.0 * penalty, Spectrum(white, coloured, float(pole), order)))
    fits.sort(key=lambda f: f[0])
    best = fits[0][0]
    return [spectrum for bic, spectrum in fits if bic <= best + 2.0 * CONFIDENCE]


def _white_bic(periodogram: np.ndarray, weight: np.ndarray, penalty: float) -> float:
    level = float(np.average(periodogram, weights=weight))
    return 2.0 * float(np.sum(weight * (math.log(level) + periodogram / level))) + penalty


def _whittle_weights(shape: np.ndarray, periodogram: np.ndarray, weight: np.ndarray) -> tuple[float, float]:
    """a, b >= 0 maximising the Whittle likelihood of S = a + b shape: least squares of the
    periodogram on (1, shape) weighted by 1 / S^2, S updated from the fit."""
    design = np.column_stack([np.ones(shape.size), shape])
    spectrum = np.full(shape.size, float(np.average(periodogram, weights=weight)))
    coefficients = np.array([spectrum[0], 0.0])
    for _ in range(_REWEIGHTING_STEPS):
        root = np.sqrt(weight) / spectrum
        coefficients, _ = optimize.nnls(design * root[:, None], periodogram * root)
        updated = design @ coefficients
        if not np.all(updated > 0):
            break
        spectrum = updated
    return float(coefficients[0]), float(coefficients[1])


def _marginal_variance(spectrum: Spectrum, points: int = 513) -> float:
    """Variance per sample: the mean of the spectrum over all frequencies."""
    omega = np.linspace(0.0, math.pi, points)
    return float(np.trapezoid(spectrum.at(omega), omega) / math.pi)


def _apply_spread(fit: NoiseFit, spread: np.ndarray, runs: int) -> None:
    """Cap the noise a chance margin above the spread's level and excuse spread beyond the
    noise (step 4). The cap matters when an effect with fast parts reaches into the noise
    band: the runs' spread does not contain the effect. Spread beyond the residual's noise
    cannot be noise of the mean (the residual would show it): the runs differ systematically."""
    spread_variance = float(np.mean(spread ** 2)) / runs
    # The spread's mean square fluctuates more when the noise is correlated.
    pole = max([sp.pole for sp in fit.spectra if sp.coloured > 0], default=0.0)
    independent = spread.size * (runs - 1) * (1.0 - pole ** 2) / (1.0 + pole ** 2)
    chance = 1.0 + SPREAD_CHANCE * math.sqrt(2.0 / max(independent, 1.0))
    fit.variance_cap = spread_variance * chance
    fit.marginal = min(fit.marginal, math.sqrt(fit.variance_cap))
    fit.excused = math.sqrt(max(0.0, spread_variance - chance * fit.marginal ** 2))


# ---------------------------------------------------------------------------------------
# The statistic


def joint_test(residuals, model_values=None, spreads=None, runs: int = 2,
               fits: list[NoiseFit] | None = None) -> JointTest:
    """One test of all signals' residuals together (the module docstring, steps 3 and 5).
    residuals: equally long arrays, one per signal; model_values / spreads: matching lists
    (entries may be None)."""
    residuals = [np.asarray(r, dtype=float) for r in residuals]
    if not residuals:
        return JointTest(chi2=0.0, dof=0, p_value=1.0, signals=0)
    count = len(residuals)
    model_values = model_values or [None] * count
    spreads = spreads or [None] * count
    n = residuals[0].size
    band = bands(n, model_values)
    if fits is None:
        fits = [fit_noise(r, v, s, runs, band.noise) for r, v, s in zip(residuals, model_values, spreads)]
    coherence = _noise_coherence(residuals, fits, band.noise)
    noise_dof = min(f.dof for f in fits) - count
    # Two looks, each calibrated, the smaller p doubled (a union bound): the lowest frequencies alone
    # keep the full power against slow effects, the model's frequencies find the others.
    lowest = np.arange(1, effect_band(n) + 1)
    looks = [(_statistic(residuals, fits, coherence, frequencies, wide), count * (2 * frequencies.size + 1))
             for frequencies, wide in ((lowest, False), (band.effect, True))]
    (chi2, dof), p_value = min(((look, _p_value(look[0], look[1], noise_dof)) for look in looks),
                               key=lambda pair: pair[1])
    p_value = p_value if np.array_equal(lowest, band.effect) else min(1.0, 2.0 * p_value)
    return JointTest(chi2=float(chi2), dof=dof, p_value=p_value, signals=count)


def _statistic(residuals: list[np.ndarray], fits: list[NoiseFit], coherence: np.ndarray,
               effect: np.ndarray, wide: bool) -> float:
    """Q over the zero frequency and the `effect` frequencies (module docstring, step 5)."""
    n = residuals[0].size
    frequencies = np.concatenate([[0], effect]).astype(int)
    omega = 2.0 * math.pi * frequencies / n
    spectra = np.array([f.spectrum(omega, wide) for f in fits])               # (S, 1 + K)
    with np.errstate(divide="ignore", invalid="ignore"):
        root = np.where(spectra > 0, 1.0 / np.sqrt(spectra), 0.0)
        z = np.array([np.fft.rfft(r)[frequencies] for r in residuals]) * root
        systematic = np.array([f.floor ** 2 + f.excused ** 2 for f in fits])[:, None] * root ** 2
    silent = spectra <= 0          # no noise at all: any residual beyond the floor is an effect
    chi2 = 0.0
    for j, frequency in enumerate(frequencies.tolist()):
        if np.any(silent[:, j]):
            raw = np.fft.rfft(np.array(residuals)[silent[:, j]], axis=1)[:, frequency]
            floors = np.array([f.floor for f in fits])[silent[:, j]]
            if np.any(np.abs(raw) > n * floors * (1.0 + 1e-9)):
                return math.inf
        keep = ~silent[:, j]
        covariance = n * coherence[np.ix_(keep, keep)] + n ** 2 * np.diag(systematic[keep, j])
        weight = 1.0 if frequency == 0 else 2.0
        chi2 += weight * _quadratic_form(z[keep, j], covariance)
    return chi2


def signal_test(residual: np.ndarray, model_values: np.ndarray, spread: np.ndarray | None,
                runs: int) -> SignalTest:
    """The test of one signal's residual alone (for the per-signal columns of the report)."""
    fit = fit_noise(residual, model_values, spread, runs)
    joint = joint_test([residual], [model_values], [spread], runs, fits=[fit])   # fit's band: the same
    return SignalTest(noise=fit.marginal, noise_dof=fit.dof, floor=fit.floor, chi2=joint.chi2, dof=joint.dof, p_value=joint.p_value)


def _noise_coherence(residuals: list[np.ndarray], fits: list[NoiseFit], band: np.ndarray) -> np.ndarray:
    """Correlation of the signals' noise: their tapered DFTs on the noise band, each divided
    by the square root of its best-fit spectrum."""
    count = len(residuals)
    if count == 1:
        return np.ones((1, 1))
    n = residuals[0].size
    omega = 2.0 * math.pi * band / n
    normalised = []
    for r, f in zip(residuals, fits):
        dft, norm = _tapered_dft(r)
        level = f.spectra[0].at(omega) if f.spectra else np.zeros(omega.size)
        with np.errstate(divide="ignore", invalid="ignore"):
            normalised.append(np.where(level > 0, dft[band] / np.sqrt(norm * level), 0.0))
    normalised = np.array(normalised)
    covariance = np.real(normalised @ normalised.conj().T)
    own = np.sqrt(np.diag(covariance))
    with np.errstate(divide="ignore", invalid="ignore"):
        correlation = np.where(np.outer(own, own) > 0, covariance / np.outer(own, own), 0.0)
    np.fill_diagonal(correlation, 1.0)
    return correlation


def _quadratic_form(z: np.ndarray, covariance: np.ndarray) -> float:
    """z^H C^-1 z, infinite when z has a part where C has no variance."""
    scale = np.sqrt(np.clip(np.diag(covariance), 0.0, None))
    silent = scale == 0
    if np.any(np.abs(z[silent]) > 0):
        return math.inf
    keep = ~silent
    if not np.any(keep):
        return 0.0
    scaled = z[keep] / scale[keep]
    correlation = covariance[np.ix_(keep, keep)] / np.outer(scale[keep], scale[keep])
    correlation += 1e-12 * np.eye(correlation.shape[0])
    return float(np.real(np.conj(scaled) @ np.linalg.solve(correlation, scaled)))


def _p_value(chi2: float, dof: int, noise_dof: float) -> float:
    if not math.isfinite(chi2):
        return 0.0
    if dof <= 0:
        return 1.0
    return float(stats.f.sf(chi2 / dof, dof, max(noise_dof, 1.0)))
