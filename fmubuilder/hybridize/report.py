"""The hybridize report: report.json for tools, report.md with tables and plots for people."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..files import write_atomically
from .evaluate import relative_mse


ROLES = ("train", "validation", "test")


def write_report(folder: Path, *, model_fmu, diagnosis, plain, candidates, chosen, selection, roundtrip, hybrid_fmu,
                 roles, scoring, training, seconds: float, timings: dict | None = None) -> dict:
    after = chosen.scores if chosen else plain
    report = {
        "diagnosis": {
            "significant": bool(diagnosis.significant),
            "p_value": float(diagnosis.p_value),
            "channel": diagnosis.channel,
            "inputs": list(diagnosis.inputs),
            "candidates": [{"channel": c.channel, "inputs": list(c.inputs), "score": float(c.score),
                            "form": c.form} for c in diagnosis.candidates],
            "fitted_term": diagnosis.fitted_term,
            "data": roles.train[0].label,
            "trace_window": list(diagnosis.trace_window) if diagnosis.trace_window else None,
        },
        "data": roles.describe(),
        "scoring": scoring.describe(),
        "training": training,
        "selection": selection,
        "chosen": chosen.name if chosen else None,
        "errors": {role: {"before": plain.errors[role], "after": after.errors[role]} for role in ROLES},
        "mse_factor": {role: _factors(plain.errors[role], after.errors[role]) for role in ROLES},
        "models": [{"name": c.name, "description": c.description,
                    **{f"{role}_relative_mse": relative_mse(plain.errors[role], c.scores.errors[role])
                       for role in ROLES},
                    **{f"{role}_mse_factor": _factors(plain.errors[role], c.scores.errors[role]) for role in ROLES},
                    "chosen": c is chosen, **c.details}
                   for c in candidates],
        "test_note": TEST_NOTE,
        "roundtrip": {"max_rel_error": roundtrip["max_rel_error"] if roundtrip else None,
                      "passed": roundtrip["passed"] if roundtrip else None,
                      "not_compared": roundtrip["not_compared"] if roundtrip else None,
                      "span": roundtrip["span"] if roundtrip else None},
        "hybrid_fmu": str(hybrid_fmu) if hybrid_fmu else None,
        "model_fmu": str(model_fmu),
        "seconds": seconds,
        "timings": dict(timings or {}),     # wall seconds per stage
    }
    first = roles.train[0]
    plots = [_plot_signals(folder / "train.png", first.data, plain.runs[id(first.data)],
                           chosen.scores.runs[id(first.data)] if chosen else None, chosen, "training",
                           roles.validation[0].window if roles.held_out_of_training else None),
             _plot_signals(folder / "test.png", roles.test.data, plain.runs[id(roles.test.data)],
                           chosen.scores.runs[id(roles.test.data)] if chosen else None, chosen, "test", None)]
    report["plots"] = [str(p.relative_to(folder)) for p in plots] + \
        [str(Path("diagnosis") / Path(p).name) for p in diagnosis.plots]
    write_atomically(folder / "report.json", json.dumps(report, indent=2, default=_json_default) + "\n")
    write_atomically(folder / "report.md", markdown(report, roundtrip))
    return report


TEST_NOTE = ("The test numbers were computed once, after the candidate and the decision to publish were fixed "
             "on the validation data; they chose nothing.")


def _factors(before: dict, after: dict) -> dict:
    return {s: (before[s]["mse"] / after[s]["mse"] if after[s]["mse"] > 0 else float("inf")) for s in before}


def _json_default(value):
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, tuple):
        return list(value)
    return str(value)


def markdown(report: dict, roundtrip: dict | None) -> str:
    d, data = report["diagnosis"], report["data"]
    lines = ["# fmubuilder hybridize report", "",
             f"Model: `{Path(report['model_fmu']).name}`; wall time {report['seconds']:.0f} s.", "",
             "## Data and their roles", "",
             f"- training (the diagnosis and the fit): {', '.join(f'`{x}`' for x in data['train'])}",
             f"- validation (the choice and the decision to publish; {data['validation_from']}): "
             f"{', '.join(f'`{x}`' for x in data['validation'])}",
             f"- test (touched once, after everything was decided): {', '.join(f'`{x}`' for x in data['test'])}",
             f"- every model simulated the same way: {report['scoring']}", "",
             "## Diagnosis", ""]
    if d["significant"]:
        lines.append(f"The residual exceeds the measurement noise (joint p = {d['p_value']:.2g}). It is traced to "
                     f"**{d['channel']}**, depending most likely on {', '.join(f'`{v}`' for v in d['inputs'][:3])}.")
        if d["fitted_term"]:
            lines.append(f"Fitted term: `{d['fitted_term']['expression']}`.")
    else:
        lines.append(f"No significant effect: the residual is at the level of the measurement noise "
                     f"(joint p = {d['p_value']:.2g}). No hybrid FMU was written.")
    training = report.get("training")
    if training:
        cut = (" The wall-clock cap of {:g} s cut it short.".format(training["time_budget"])
               if training["cut_short_by_time_budget"] else "")
        lines.append(f"\nThe NeuralFMU trained {training['epochs_done']} of {training['epochs']} epochs "
                     f"(seed {training['seed']}) on `{training['trained_on']}`.{cut}")
    if report["models"]:
        selection = report["selection"]
        lines += ["", "## Candidates", "",
                  "MSE after/before, mean over the signals (below 1: better than the plain FMU).", "",
                  "| model | description | train | validation (chooses) | test (touched once) | chosen |",
                  "|---|---|---|---|---|---|"]
        for m in report["models"]:
            lines.append(f"| {m['name']} | {m['description']} | {m['train_relative_mse']:.3g} | "
                         f"{m['validation_relative_mse']:.3g} | {m['test_relative_mse']:.3g} | "
                         f"{'yes' if m['chosen'] else 'no'} |")
        lines.append(f"\nChosen on the validation data: **{selection['chosen'] or 'none (no candidate improved it)'}** "
                     f"({selection['rule']}). {report['test_note']}")
    lines += ["", "## Errors before and after", "",
              "Before: the plain FMU; after: the published hybrid. Train: the samples the fit saw.", "",
              "| data | signal | MSE before | MSE after | factor | max abs before | max abs after | final before | final after |",
              "|---|---|---|---|---|---|---|---|---|"]
    for part in ROLES:
        errors = report["errors"][part]
        for signal, b in errors["before"].items():
            a = errors["after"][signal]
            lines.append(f"| {part} | {signal} | {b['mse']:.4g} | {a['mse']:.4g} | {report['mse_factor'][part][signal]:.3g} | "
                         f"{b['max_abs']:.4g} | {a['max_abs']:.4g} | {b['final']:.4g} | {a['final']:.4g} |")
    if roundtrip:
        verdict = "passed" if roundtrip["passed"] else "FAILED"
        lines += ["", "## Round trip", "",
                  f"The exported FMU `{Path(report['hybrid_fmu']).name}` against the Python reference over "
                  f"{roundtrip['span'][0]:g} to {roundtrip['span'][1]:g} s: max relative difference "
                  f"{roundtrip['max_rel_error']:.2g} over the rows compared ({verdict})."]
        if roundtrip["not_compared"]:
            lines.append(f"Not compared (no samples left): {'; '.join(roundtrip['not_compared'])}.")
        lines += ["", "```", roundtrip["table"], "```"]
    lines += ["", "## Plots", ""] + [f"![{Path(p).stem}]({p})" for p in report["plots"]]
    return "\n".join(lines) + "\n"


def _plot_signals(path: Path, data, before, after, chosen, part: str, held_out: tuple | None) -> Path:
    """Measured, plain and hybrid over a whole run; `held_out`: the validation window, shaded."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = data.names
    fig, axes = plt.subplots(len(names), 2, figsize=(12, 2.6 * len(names)), sharex=True, squeeze=False)
    label = f"hybrid ({chosen.name})" if chosen else "hybrid"
    measured_time = data.time
    for row, name in enumerate(names):
        measured = np.interp(before.time, measured_time, data.signals[name])
        ax = axes[row, 0]
        ax.plot(measured_time, data.signals[name], color="black", lw=0.8, label="measured")
        ax.plot(before.time, before.predicted[name], color="tab:red", lw=0.8, label="FMU")
        if chosen:
            ax.plot(after.time, after.predicted[name], color="tab:blue", lw=0.8, ls="--", label=label)
        ax.set_ylabel(name)
        ax.grid(alpha=0.3)
        ax = axes[row, 1]
        ax.plot(before.time, before.predicted[name] - measured, color="tab:red", lw=0.8, label="FMU - measured")
        if chosen:
            ax.plot(after.time, after.predicted[name] - measured, color="tab:blue", lw=0.8,
                    label=f"{label} - measured")
        ax.set_ylabel(f"error of {name}")
        ax.grid(alpha=0.3)
        if held_out is not None:
            for ax in axes[row]:
                ax.axvspan(*held_out, color="0.85", zorder=0, label="validation (held out of the fit)")
    axes[0, 0].legend(loc="best", fontsize=8)
    axes[0, 1].legend(loc="best", fontsize=8)
    axes[-1, 0].set_xlabel("time [s]")
    axes[-1, 1].set_xlabel("time [s]")
    fig.suptitle(f"{part} data: measured, plain FMU and hybrid")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path
