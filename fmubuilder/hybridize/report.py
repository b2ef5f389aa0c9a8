"""The hybridize report: report.json for tools, report.md with tables and plots for people."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..files import write_atomically
from .evaluate import relative_mse


def write_report(folder: Path, *, model_fmu, diagnosis, before, candidates, chosen, roundtrip, hybrid_fmu,
                 train_data, test_data, seconds: float, timings: dict | None = None) -> dict:
    before_train, before_test = before
    after_train = chosen.train if chosen else before_train
    after_test = chosen.test if chosen else before_test
    report = {
        "diagnosis": {
            "significant": bool(diagnosis.significant),
            "p_value": float(diagnosis.p_value),
            "channel": diagnosis.channel,
            "inputs": list(diagnosis.inputs),
            "candidates": [{"channel": c.channel, "inputs": list(c.inputs), "score": float(c.score),
                            "form": c.form} for c in diagnosis.candidates],
            "fitted_term": diagnosis.fitted_term,
        },
        "errors": {
            "train": {"before": before_train.errors, "after": after_train.errors},
            "test": {"before": before_test.errors, "after": after_test.errors},
        },
        "mse_factor": {
            "train": _factors(before_train.errors, after_train.errors),
            "test": _factors(before_test.errors, after_test.errors),
        },
        "models": [{"name": c.name, "description": c.description,
                    "test_relative_mse": relative_mse(before_test.errors, c.test.errors),
                    "train_relative_mse": relative_mse(before_train.errors, c.train.errors),
                    "test_mse_factor": _factors(before_test.errors, c.test.errors),
                    "train_mse_factor": _factors(before_train.errors, c.train.errors), **c.details}
                   for c in candidates],
        "chosen": chosen.name if chosen else None,
        "roundtrip": {"max_rel_error": roundtrip["max_rel_error"] if roundtrip else None,
                      "passed": roundtrip["passed"] if roundtrip else None,
                      "span": roundtrip["span"] if roundtrip else None},
        "hybrid_fmu": str(hybrid_fmu) if hybrid_fmu else None,
        "model_fmu": str(model_fmu),
        "data": {"train": str(train_data.path), "test": str(test_data.path)},
        "seconds": seconds,
        "timings": dict(timings or {}),     # wall seconds per stage
    }
    plots = [_plot_signals(folder / f"{name}.png", data, ev_before, ev_after, chosen, name)
             for name, data, ev_before, ev_after in (("train", train_data, before_train, after_train),
                                                     ("test", test_data, before_test, after_test))]
    report["plots"] = [str(p.relative_to(folder)) for p in plots] + \
        [str(Path("diagnosis") / Path(p).name) for p in diagnosis.plots]
    write_atomically(folder / "report.json", json.dumps(report, indent=2, default=_json_default) + "\n")
    write_atomically(folder / "report.md", markdown(report, roundtrip))
    return report


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
    d = report["diagnosis"]
    lines = ["# fmubuilder hybridize report", "",
             f"Model: `{Path(report['model_fmu']).name}`; training data: `{Path(report['data']['train']).name}`; "
             f"held-out data: `{Path(report['data']['test']).name}`; wall time {report['seconds']:.0f} s.", "",
             "## Diagnosis", ""]
    if d["significant"]:
        lines.append(f"The residual exceeds the measurement noise (joint p = {d['p_value']:.2g}). It is traced to "
                     f"**{d['channel']}**, depending most likely on {', '.join(f'`{v}`' for v in d['inputs'][:3])}.")
        if d["fitted_term"]:
            lines.append(f"Fitted term: `{d['fitted_term']['expression']}`.")
    else:
        lines.append(f"No significant effect: the residual is at the level of the measurement noise "
                     f"(joint p = {d['p_value']:.2g}). No hybrid FMU was written.")
    if report["models"]:
        lines += ["", "## Candidates", "", "| model | description | train MSE after/before | test MSE after/before |",
                  "|---|---|---|---|"]
        for m in report["models"]:
            lines.append(f"| {m['name']} | {m['description']} | {m['train_relative_mse']:.3g} | {m['test_relative_mse']:.3g} |")
        lines.append(f"\nChosen on the held-out data: **{report['chosen'] or 'none (no candidate improved it)'}**.")
    lines += ["", "## Errors before and after", "",
              "| data | signal | MSE before | MSE after | factor | max abs before | max abs after | final before | final after |",
              "|---|---|---|---|---|---|---|---|---|"]
    for part in ("train", "test"):
        errors = report["errors"][part]
        for signal, b in errors["before"].items():
            a = errors["after"][signal]
            lines.append(f"| {part} | {signal} | {b['mse']:.4g} | {a['mse']:.4g} | {report['mse_factor'][part][signal]:.3g} | "
                         f"{b['max_abs']:.4g} | {a['max_abs']:.4g} | {b['final']:.4g} | {a['final']:.4g} |")
    if roundtrip:
        lines += ["", "## Round trip", "",
                  f"The exported FMU `{Path(report['hybrid_fmu']).name}` against the Python reference over "
                  f"{roundtrip['span'][0]:g} to {roundtrip['span'][1]:g} s: max relative difference "
                  f"{roundtrip['max_rel_error']:.2g} ({'passed' if roundtrip['passed'] else 'FAILED'}).", "",
                  "```", roundtrip["table"], "```"]
    lines += ["", "## Plots", ""] + [f"![{Path(p).stem}]({p})" for p in report["plots"]]
    return "\n".join(lines) + "\n"


def _plot_signals(path: Path, data, before, after, chosen, part: str) -> Path:
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
    axes[0, 0].legend(loc="best", fontsize=8)
    axes[0, 1].legend(loc="best", fontsize=8)
    axes[-1, 0].set_xlabel("time [s]")
    axes[-1, 1].set_xlabel("time [s]")
    fig.suptitle(f"{part} data: measured, plain FMU and hybrid")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path
