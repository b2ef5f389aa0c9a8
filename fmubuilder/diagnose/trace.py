"""Trace a residual to the state derivative and the variables a missing term lives in.

Idea: if the real system has an extra term g(w) in der(x_c), then adding a small
``alpha * phi(w)`` to der(x_c) of the declared model moves *all* measured signals roughly
the way the real effect moved them away from the model, including what a controller in the
loop does about it (it may hold a speed on target and draw more power instead). So the
closed-loop response to a trial term, from a finite difference of two simulations, is
compared with the residuals of all signals at once.

Signals are stacked into one vector, each divided by a weight, in two ways:

* by signal: each divided by its residual's RMS (at least its noise level), so every signal
  has the same say: a signal the effect left alone (a speed a controller holds on target)
  counts as much as one it moved, and a trial that moves it is penalised. This decides the
  channel: which derivative explains how the signals moved.
* by precision: each divided by its noise level, but at least by its residual's RMS / MAX_SNR
  (so that model-form errors in a very precise signal cannot hide the others). This ranks the
  variables and forms within a channel and fits the coefficient: a precise signal shows the
  residual's shape best, while signals at noise level add only chance to the comparison.

For a trial response S (per unit coefficient) and a stacked residual r, the least-squares
coefficient is (S.r)/(S.S) and the score is the explained variance (S.r)^2 / ((S.S)(r.r)),
between 0 and 1 (by signal: the mean over the signals of the share of each signal's residual
the trial explains, so a signal holding only noise caps it below 1).

Steps (each trial is one simulation):

1. channels: per state derivative a constant and a ramp in time (two generic shapes); the
   score is the variance both explain together. The best channel goes on, and the second when
   it scores at least SECOND_CHANNEL_RATIO of the best. The constant trial also gives the
   size of a term whose response matches the residual's size; later trials use that size,
   where the linearisation is valid.
2. inputs: in each kept channel, candidate variables w (states, outputs, inputs, locals; not
   parameters, not constant ones, not the channel's own derivative) in forms of the deviation
   u = w - w(t_start): first w and w^2 for every variable, then |w| and w*|w| for the
   REFINED_VARIABLES leading ones. Forms identical up to a factor on the nominal run are one
   trial. Trials whose responses cannot be told apart (squared cosine > EQUIVALENT) form one
   candidate, and scores within SCORE_TIE of the unexplained variance are a tie; both times
   a state is preferred to an output, an input, a local, a derivative. Within a candidate an
   odd form of the channel's own state (w, w*|w|) leads its even twin (|w|, w^2).
3. term: one form or a pair of forms of a leading variable, checked by simulation (fit_term).

A trial that makes the model fail or run far slower than the plain model (a term can
destabilise the loop) is repeated ten times smaller, at most twice, and then skipped.
"""
from __future__ import annotations

import math
import time as wallclock
from dataclasses import dataclass, field

import numpy as np

from ..errors import FmuBuilderError
from ..progress import counted
from ..simulation.results import equal_along
from .runs import TIME, AddedTerm, ModelRun, ModelRunner, TrialTooSlow, basis_values, rms

MAX_SNR = 10.0                 # precision weights give a signal at most this signal-to-noise ratio
MAX_CHANNELS = 2
INPUT_FORMS = ("w", "|w|", "w*|w|", "w^2")
FIRST_FORMS = ("w", "w^2")     # one odd and one even form for every variable
REFINED_VARIABLES = 4          # variables that also get the other forms
SECOND_CHANNEL_RATIO = 0.5     # a further channel is traced when it scores this share of the best
EQUIVALENT = 0.999             # squared cosine of two responses that cannot be told apart
SCORE_TIE = 0.01               # scores this close (share of the unexplained variance) are a tie
PAIR_GAIN = 0.01               # explained variance a second form of the variable must add
TOP_VARIABLES_FOR_TERM = 3
VERIFIED = 2                   # fitted options checked by simulation
RETRIES, RETRY_SHRINK = 2, 10.0
SLOW_TRIAL_FACTOR = 10.0       # a trial needing this many times the plain run's work is abandoned
MIN_TRIAL_CALLS = 1000         # derivative evaluations a trial may always use (times the factor)
SCREEN_SIZE = 1e-3             # trial constant, relative to the derivative's RMS
_ALIAS = 1.0 - 1e-9            # squared cosine of two forms that are the same trial
# Preference among variables alike: states, then outputs, inputs, locals, derivatives last.
KIND_ORDER = {"state": 0, "output": 1, "input": 2, "local": 3, "derivative": 4}


@dataclass
class Weighting:
    """One way of stacking the signals (see the module docstring)."""
    signals: list[str]
    weights: dict[str, float]

    def stack(self, values: dict[str, np.ndarray]) -> np.ndarray:
        return np.concatenate([values[s] / self.weights[s] for s in self.signals])


@dataclass
class Trial:
    channel: int
    variable: str | None        # None: a generic shape (constant or time ramp)
    basis: str
    center: float
    by_signal: np.ndarray       # stacked response per unit coefficient, weighted by signal
    by_precision: np.ndarray    # ... weighted by precision
    score: float = 0.0          # explained variance by signal: decides the channel
    shape_score: float = 0.0    # explained variance by precision: ranks variables and forms
    coefficient: float = 0.0    # least-squares coefficient (by precision)
    equivalent: list[str] = field(default_factory=list)


@dataclass
class ChannelScore:
    channel: int
    score: float
    observable: bool
    size: float                 # constant whose response has the residual's size


@dataclass
class TracedTerm:
    """The term the tracing fitted: the added terms of one channel and the variance they explain."""
    channel: int
    terms: list[AddedTerm]
    explained_variance: float             # predicted by the linear responses
    verified_explained_variance: float    # from a simulation with the term


class Tracer:
    """The trials of one data window: `runner` simulates it, `nominal` is its plain run,
    `measured` the data in it, `noise` each signal's noise level."""

    def __init__(self, runner: ModelRunner, nominal: ModelRun, measured: dict[str, np.ndarray],
                 noise: dict[str, float]):
        self.runner = runner
        self.info = runner.info
        self.nominal = nominal
        self.signals = list(measured)
        residual = {s: measured[s] - nominal.predicted[s] for s in self.signals}
        effect = {s: math.sqrt(max(0.0, rms(residual[s]) ** 2 - noise[s] ** 2)) for s in self.signals}
        self.by_signal = Weighting(self.signals, {s: max(rms(residual[s]), noise[s], 1e-300) for s in self.signals})
        self.by_precision = Weighting(self.signals, {s: max(noise[s], effect[s] / MAX_SNR, 1e-300)
                                                     for s in self.signals})
        self.r = self.by_signal.stack(residual)
        self.rr = float(self.r @ self.r)
        self.r_precise = self.by_precision.stack(residual)
        self.rr_precise = float(self.r_precise @ self.r_precise)
        self.start = runner.start
        # A trial may do this much more work than the plain run before it is abandoned.
        self.max_calls = SLOW_TRIAL_FACTOR * max(nominal.derivative_calls, MIN_TRIAL_CALLS)
        self.deadline = math.inf      # perf_counter() time: the caller's wall-time cap, if any
        self.failed: list[str] = []

    # -- responses ------------------------------------------------------------------------
    def response(self, terms: list[AddedTerm]) -> dict[str, np.ndarray]:
        """Change of the measured signals when the terms are added."""
        time_left = self.deadline - wallclock.perf_counter()
        if time_left <= 0:
            raise TrialTooSlow("the time budget is spent")
        run = self.runner.simulate(terms, trajectories=False, time_limit=time_left, max_calls=self.max_calls)
        return {s: run.predicted[s] - self.nominal.predicted[s] for s in self.signals}

    def trial(self, channel: int, variable: str | None, basis: str, center: float, size: float) -> Trial | None:
        """Score of one trial form; a size that makes the model fail (a term can destabilise
        the loop) is retried smaller, the response per unit size stays the same."""
        for _ in range(RETRIES + 1):
            term = AddedTerm(channel, variable or TIME, basis, center, size)
            try:
                delta = self.response([term])
            except FmuBuilderError:
                size /= RETRY_SHRINK
                continue
            by_signal, by_precision = self.by_signal.stack(delta) / size, self.by_precision.stack(delta) / size
            if np.all(np.isfinite(by_signal)):
                return self._scored(Trial(channel, variable, basis, center, by_signal, by_precision))
            size /= RETRY_SHRINK
        self.failed.append(f"{self.info.derivatives[channel].name} += {term.expression()}")
        return None

    def _scored(self, trial: Trial) -> Trial:
        trial.score = _cos2(trial.by_signal, self.r)
        trial.shape_score = _cos2(trial.by_precision, self.r_precise)
        # (S.r)/(S.S) through the norm, as in _cos2: S.S of a response that ran off overflows.
        norm = _norm(trial.by_precision)
        trial.coefficient = float((trial.by_precision / norm) @ self.r_precise) / norm if 0 < norm < math.inf else 0.0
        return trial

    # -- step 1: channels -------------------------------------------------------------------
    def screen_channels(self) -> list[ChannelScore]:
        scores = []
        span = self.runner.stop - self.start
        ramp_scale = span / math.sqrt(3.0)     # RMS of (t - start) over the window
        for c in counted(range(self.info.n_states), "diagnosis: screening the derivatives", "derivative"):
            trial_size = SCREEN_SIZE * self._derivative_scale(c)
            constant = self.trial(c, None, "1", 0.0, trial_size)
            gain = _norm(constant.by_signal) if constant is not None else 0.0
            if not gain > 1e-12 * math.sqrt(self.rr):
                scores.append(ChannelScore(c, 0.0, False, 0.0))
                continue
            size = math.sqrt(self.rr) / gain
            ramp = self.trial(c, None, "w", 0.0, size / ramp_scale)
            shapes = [constant.by_signal] + ([ramp.by_signal] if ramp is not None else [])
            scores.append(ChannelScore(c, least_squares(shapes, self.r)[0], True, size))
        return scores

    def _derivative_scale(self, c: int) -> float:
        der = self.info.derivatives[c].name
        x = self.info.states[c].name
        values = self.nominal.trajectories
        if der in values and rms(values[der]) > 0:
            return rms(values[der])
        if x in values and rms(values[x]) > 0:
            return rms(values[x]) / (self.runner.stop - self.start)
        return 1.0

    # -- step 2: inputs ---------------------------------------------------------------------
    def candidate_forms(self, variables: list[str]) -> list[tuple[str, str, float, float, list[str]]]:
        """(variable, basis, center, RMS of the form, aliases) for the distinct trial forms."""
        forms: list[tuple[str, str, float, float, list[str]]] = []
        shapes: list[np.ndarray] = []
        for name in sorted(variables, key=lambda n: KIND_ORDER[variable_kind(self.info, n)]):
            w = self.nominal.trajectories[name]
            center = float(w[0])
            for basis in INPUT_FORMS:
                phi = basis_values(basis, w - center)
                norm = float(np.linalg.norm(phi))
                if not norm > 0 or np.std(phi) <= 1e-9 * np.max(np.abs(phi)):
                    continue  # zero or constant: no trial beyond the channel's constant
                unit = phi / norm
                for k, shape in enumerate(shapes):
                    if float(unit @ shape) ** 2 > _ALIAS:
                        forms[k][4].append(_form_label(name, basis))
                        break
                else:
                    shapes.append(unit)
                    forms.append((name, basis, center, rms(phi), []))
        return forms

    def rank_inputs(self, channel: ChannelScore, forms) -> list[Trial]:
        """Trials of the first forms for every variable, then of the other forms for the
        variables that lead after the first round. The channel's own derivative (and any
        variable equal to it) is no input: a term proportional to it rescales the whole
        derivative, a parameter error rather than a missing effect."""
        own = self._equal_to_derivative(channel.channel)
        forms = [f for f in forms if f[0] not in own]
        trials = self._trials(channel, [f for f in forms if f[1] in FIRST_FORMS])
        first = prefer_simple(self.info, [group[0] for group in group_equivalent(self.info, trials)])
        leaders = _distinct(t.variable for t in first)[:REFINED_VARIABLES]
        trials += self._trials(channel, [f for f in forms if f[1] not in FIRST_FORMS and f[0] in leaders])
        return prefer_simple(self.info, [_leader(group) for group in group_equivalent(self.info, trials)])

    def _equal_to_derivative(self, c: int) -> set[str]:
        values = self.nominal.trajectories
        der = self.info.derivatives[c].name
        return set(equal_along(values, values[der])) if der in values else {der}

    def _trials(self, channel: ChannelScore, forms) -> list[Trial]:
        trials = []
        label = f"diagnosis: trials on {self.info.derivatives[channel.channel].name}"
        for name, basis, center, size_of_form, aliases in counted(forms, label, "trial"):
            trial = self.trial(channel.channel, name, basis, center, channel.size / size_of_form)
            if trial is not None:
                trial.equivalent = list(aliases)
                trials.append(trial)
        return trials

    # -- step 3: term -----------------------------------------------------------------------
    def fit_term(self, trials: list[Trial]) -> TracedTerm | None:
        """A term in the leading variable: one of its forms, or a pair of its forms when the
        pair explains PAIR_GAIN more of the residual. Another of the leading variables is
        taken only when it fits better by more than a tie (SCORE_TIE). The VERIFIED best
        options are simulated with their fitted coefficients; the one that really explains
        most wins (the linear estimates of close forms differ less than their errors)."""
        options = []
        for name in _distinct(t.variable for t in trials)[:TOP_VARIABLES_FOR_TERM]:
            own = [t for t in trials if t.variable == name]
            singles = [least_squares([t.by_precision], self.r_precise) + ([t],) for t in own]
            pairs = [least_squares([a.by_precision, b.by_precision], self.r_precise) + ([a, b],)
                     for i, a in enumerate(own) for b in own[i + 1:]]
            best_single = max(f[0] for f in singles)
            options.append([f for f in singles + pairs
                            if f[0] > 0 and (len(f[2]) == 1 or f[0] > best_single + PAIR_GAIN)])
        top = max((f[0] for own in options for f in own), default=0.0)
        chosen = next((own for own in options if own and top - max(f[0] for f in own) <= SCORE_TIE * (1.0 - top)), None)
        if not chosen:
            return None
        best = None
        for ev, coefficients, option in counted(sorted(chosen, key=lambda f: -f[0])[:VERIFIED],
                                                "diagnosis: simulating the best terms", "term"):
            terms = [AddedTerm(t.channel, t.variable, t.basis, t.center, float(k))
                     for t, k in zip(option, coefficients)]
            verified, terms = self._verify(terms)
            if best is None or verified > best.verified_explained_variance:
                best = TracedTerm(option[0].channel, terms, ev, verified)
        return best

    def _verify(self, terms: list[AddedTerm]) -> tuple[float, list[AddedTerm]]:
        """Explained variance (by precision) of a simulation with the terms; one secant
        correction of their common scale when the response is not linear in their size."""
        verified, scale = self._explained(terms)
        if scale is not None and abs(scale - 1.0) > 0.02:
            scaled = [AddedTerm(t.channel, t.variable, t.basis, t.center, t.coefficient * scale) for t in terms]
            verified2, _ = self._explained(scaled)
            if verified2 > verified:
                return verified2, scaled
        return verified, terms

    def _explained(self, terms: list[AddedTerm]) -> tuple[float, float | None]:
        """(explained variance, scale that would fit best) of a run with the terms."""
        try:
            delta = self.by_precision.stack(self.response(terms))
        except FmuBuilderError:
            return -math.inf, None
        left = self.r_precise - delta
        dd = float(delta @ delta)
        return 1.0 - float(left @ left) / self.rr_precise, (float(delta @ self.r_precise) / dd if dd > 0 else None)


# ---------------------------------------------------------------------------------------
# Least squares, grouping and names


def least_squares(responses: list[np.ndarray], r: np.ndarray) -> tuple[float, np.ndarray]:
    """Coefficients of r ~ sum_k c_k S_k and the fraction of r's variance they explain."""
    matrix = np.column_stack(responses)
    if not np.all(np.isfinite(matrix)):
        return 0.0, np.zeros(len(responses))
    coefficients, *_ = np.linalg.lstsq(matrix, r, rcond=1e-10)
    rr = float(r @ r)
    left = r - matrix @ coefficients
    return (1.0 - float(left @ left) / rr if rr > 0 else 0.0), coefficients


def group_equivalent(info, trials: list[Trial]) -> list[list[Trial]]:
    """Groups of trials, best first; a trial whose response cannot be told from a better
    one's joins its group, and within a group the preferred kind of variable leads."""
    ordered = sorted(trials, key=lambda t: -t.shape_score)
    groups: list[list[Trial]] = []
    for trial in ordered:
        for group in groups:
            if _cos2(group[0].by_precision, trial.by_precision) > EQUIVALENT:
                group.append(trial)
                break
        else:
            groups.append([trial])
    for group in groups:
        group.sort(key=lambda t: (KIND_ORDER[variable_kind(info, t.variable)], _even_in_own_state(info, t),
                                  -t.shape_score))
    return groups


def _even_in_own_state(info, trial: Trial) -> bool:
    """An even form (|w|, w^2) of the channel's own state. Where the state keeps its sign, the even
    and the odd form (w, w*|w|) give the same response; the odd one leads, since a term of a state
    in its own derivative (a friction, a windage) opposes the motion and changes sign with it."""
    return trial.basis in ("|w|", "w^2") and trial.variable == info.states[trial.channel].name


def prefer_simple(info, trials: list[Trial], score=lambda t: t.shape_score) -> list[Trial]:
    """The trials best first by `score`; scores within SCORE_TIE of the unexplained variance
    are a tie, and a state moves ahead of an output, an input, a local, a derivative (a term
    in a state is the simpler model)."""
    ranked = sorted(trials, key=lambda t: -score(t))
    for i in range(len(ranked)):
        best = ranked[i]
        tolerance = SCORE_TIE * (1.0 - score(best))
        for j in range(i + 1, len(ranked)):
            if score(best) - score(ranked[j]) > tolerance:
                break
            if KIND_ORDER[variable_kind(info, ranked[j].variable)] < KIND_ORDER[variable_kind(info, best.variable)]:
                ranked.insert(i, ranked.pop(j))
                best = ranked[i]
    return ranked


def _leader(group: list[Trial]) -> Trial:
    """The group's first trial, carrying the forms the others stand for."""
    leader = group[0]
    leader.equivalent = leader.equivalent + [f for t in group[1:] for f in [_form_label(t.variable, t.basis),
                                                                             *t.equivalent]]
    return leader


def _norm(a: np.ndarray) -> float:
    """|a|; inf, without a warning, for a response that ran off (1e160) so far that its squares overflow."""
    with np.errstate(over="ignore"):
        return float(np.linalg.norm(a))


def _cos2(a: np.ndarray, b: np.ndarray) -> float:
    # Through the norms: a response that ran off must not overflow the squared products.
    na, nb = _norm(a), _norm(b)
    if not (0 < na < math.inf and 0 < nb < math.inf):
        return 0.0
    return float((a / na) @ (b / nb)) ** 2


def variable_kind(info, name: str) -> str:
    var = info.variable(name)
    if var.derivative_of is not None:
        return "derivative"
    if any(s.name == name for s in info.states):
        return "state"
    return var.causality if var.causality in ("output", "input") else "local"


def candidate_variables(info) -> list[str]:
    """Real variables a missing term could depend on: states, outputs, inputs and locals."""
    return [v.name for v in info.variables.values()
            if v.type == "Real" and v.causality in ("output", "local", "input")
            and v.variability in ("continuous", "discrete")]


def _form_label(variable: str, basis: str) -> str:
    return basis.replace("w", variable)


def _distinct(names) -> list[str]:
    return list(dict.fromkeys(n for n in names if n is not None))
