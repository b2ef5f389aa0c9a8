"""The diagnosis as text: a table of errors, the verdict, the ranked candidates, the term."""
from __future__ import annotations

from .significance import SIGNIFICANCE_LEVEL

MAX_CANDIDATE_ROWS = 12


def format_report(d) -> str:
    lines = [f"Diagnosis of {d.model}", f"  against {d.data}: {d.window[0]:g} to {d.window[1]:g} s"]
    if d.start_values_from_data:
        taken = ", ".join(f"{k}={v:.6g}" for k, v in d.start_values_from_data.items())
        lines.append(f"  start values taken from the data: {taken}")
    lines += ["", _errors_table(d.errors), ""]
    if d.significant:
        lines.append(f"Significant effect: the residual exceeds the measurement noise (joint p = {d.p_value:.2g} "
                     f"< {SIGNIFICANCE_LEVEL:g}).")
    else:
        lines.append(f"No significant effect: the residual is at the level of the measurement noise "
                     f"(joint p = {d.p_value:.2g} >= {SIGNIFICANCE_LEVEL:g}).")
    if getattr(d, "cut_short", None):
        lines.append(f"Warning: {d.cut_short}.")
    if d.channel_scores:
        lines += ["", _channels_table(d), "", _candidates_table(d)]
    if d.channel:
        lines += ["", f"Traced to {d.channel}; inputs, most likely first: {', '.join(d.inputs[:6])}"]
    if d.ambiguous_channels:
        lines.append(f"  ambiguous: {', '.join(d.ambiguous_channels)} explains the data about as well")
    if d.fitted_term:
        term = d.fitted_term
        state = "offered as a fitted term" if term["offered"] else "not offered: it explains too little"
        lines.append(f"Fitted term: {term['expression']}")
        lines.append(f"  explains {term['explained_variance']:.3f} of the weighted residual (linear estimate "
                     f"{term['explained_variance_linear']:.3f}) and removes {term['explained_excess']:.1%} of the "
                     f"excess over noise (p with the term {term['corrected_p_value']:.2g}); {state}")
    lines += ["", _timing(d)]
    return "\n".join(lines)


def _errors_table(errors) -> str:
    header = (f"{'signal':<16}{'MSE':>12}{'RMS':>12}{'max |e|':>12}{'final e':>12}{'noise':>11}"
              f"{'chi2/dof':>10}{'p':>10}  effect")
    rows = [header, "-" * len(header)]
    for e in errors:
        rows.append(f"{e.signal:<16}{e.mse:>12.4g}{e.rms:>12.4g}{e.max_abs:>12.4g}{e.final:>12.4g}{e.noise:>11.3g}"
                    f"{e.chi2_per_dof:>10.3g}{e.p_value:>10.2g}  {'yes' if e.significant else 'no'}")
    if any(e.corrected_rms is not None for e in errors):
        rows.append("RMS with the fitted term: " + ", ".join(
            f"{e.signal} {e.corrected_rms:.4g}" for e in errors if e.corrected_rms is not None))
    return "\n".join(rows)


def _channels_table(d) -> str:
    window = f" over {d.trace_window[0]:g} to {d.trace_window[1]:g} s" if d.trace_window else ""
    rows = [f"Channels (variance explained by a constant and a ramp added to the derivative{window}):"]
    for name, score in sorted(d.channel_scores.items(), key=lambda kv: -kv[1]):
        rows.append(f"  {name:<32}{score:8.3f}")
    return "\n".join(rows)


def _candidates_table(d) -> str:
    header = (f"  {'rank':<5}{'channel':<26}{'term form':<34}{'score':>7}{'shape':>7}{'coefficient':>13}"
              "  same response as")
    rows = ["Candidates (explained variance of the residuals; score: every signal alike, decides the channel;",
            "shape: signals weighted by precision, ranks the forms in a channel):", header]
    for rank, c in enumerate(d.candidates[:MAX_CANDIDATE_ROWS], start=1):
        same = ", ".join(c.equivalent[:3]) + (" ..." if len(c.equivalent) > 3 else "")
        rows.append(f"  {rank:<5}{c.channel:<26}{c.form:<34}{c.score:>7.3f}{c.shape_score:>7.3f}"
                    f"{c.coefficient:>13.4g}  {same}")
    if len(d.candidates) > MAX_CANDIDATE_ROWS:
        rows.append(f"  ... {len(d.candidates) - MAX_CANDIDATE_ROWS} more in the JSON report")
    return "\n".join(rows)


def _timing(d) -> str:
    w = d.wall_time
    parts = [f"{d.simulations} simulations (mean {w.get('simulation_mean', 0.0):.3f} s)"]
    if "trace" in w:
        parts.append(f"tracing {w['trace']:.1f} s")
    parts.append(f"total {w.get('total', 0.0):.1f} s")
    return "Wall time: " + ", ".join(parts)
