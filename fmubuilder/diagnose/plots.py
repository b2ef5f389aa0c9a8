"""PNG plots of a diagnosis: measured vs model, residuals over time, residuals vs the traced
variables. matplotlib with the Agg backend (no display needed).

The look is shared with the hybridize report's plots (which import it from here): one colour per
model in every plot, residuals always "model − measured", y-limits from percentiles so that one
spike does not set the scale (a note in the axes says when points lie outside).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import FmuBuilderError

MAX_INPUT_COLUMNS = 3

# One colour per model, the same in every plot fmubuilder draws.
COLOURS = {"measured": "0.45", "fmu": "tab:red", "hybrid": "tab:blue", "truth": "tab:green"}
RESIDUAL = "model − measured"
# The central range: between these percentiles; values more than OUTLIER_SPANS times its width
# beyond it are left outside the y-limits.
CLIP_PERCENTILE = 0.5
OUTLIER_SPANS = 1.0
# Measured samples as small dots over the lines; the FMU wide and pale below the hybrid's dashes, so
# neither hides the other where they agree.
MEASURED_STYLE = dict(ls="none", marker=".", ms=2.5, color=COLOURS["measured"], alpha=0.6, zorder=4)
FMU_STYLE = dict(color=COLOURS["fmu"], lw=2.0, alpha=0.85, zorder=2)
HYBRID_STYLE = dict(color=COLOURS["hybrid"], lw=1.1, ls="--", zorder=3)


def pyplot():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def label(name: str, unit: str | None) -> str:
    """`speed [rad/s]`, or the bare name when the model declares no unit."""
    return f"{name} [{unit}]" if unit else name


def robust_ylim(ax, *series, percentile: float = CLIP_PERCENTILE) -> int:
    """Y-limits from the central percentiles of the drawn values (plus a margin); returns how many
    points lie outside and notes it in the axes, so a clipped spike is never silently hidden."""
    values = np.concatenate([np.asarray(s, dtype=float).ravel() for s in series if s is not None])
    values = values[np.isfinite(values)]
    if values.size == 0:
        return 0
    low, high = np.percentile(values, [percentile, 100.0 - percentile])
    span = high - low if high > low else max(abs(high), 1.0) * 0.1
    # The extremes stay in view unless they lie more than a span beyond the central range: a
    # genuine peak is kept, an isolated spike is cut off.
    full_low, full_high = float(values.min()), float(values.max())
    low = full_low if full_low >= low - OUTLIER_SPANS * span else low
    high = full_high if full_high <= high + OUTLIER_SPANS * span else high
    margin = 0.06 * (high - low if high > low else span)
    low, high = low - margin, high + margin
    outside = int(np.sum((values < low) | (values > high)))
    ax.set_ylim(low, high)
    if outside:
        note = f"{outside} point{'s' if outside > 1 else ''} outside the y-range"
        ax.text(0.99, 0.02, note, transform=ax.transAxes, ha="right", va="bottom", fontsize=7, color="0.3",
                bbox=dict(fc="white", ec="0.7", lw=0.5, alpha=0.8))
    return outside


def cumulative_signals(names, trajectories: dict, states) -> set[str]:
    """Measured signals that accumulate: model states that never change direction over the run
    (an energy, a distance). Their residual is a sum over the past, not a function of the present
    inputs, so they are left out of the residual-vs-variable plots."""
    found = set()
    for name in names:
        values = np.asarray(trajectories.get(name, ()), dtype=float)
        if name not in states or values.size < 3:
            continue
        steps = np.diff(values)
        if np.all(steps >= 0) or np.all(steps <= 0):
            found.add(name)
    return found


def write_plots(folder: Path, diagnosis, data, nominal, fitted_run=None, info=None) -> list[Path]:
    """`info` (ModelInfo, optional): the units and states of the model's variables."""
    plt = pyplot()
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise FmuBuilderError(f"cannot create the plot folder {folder}: {exc.strerror or exc}") from None
    units = units_of(info)
    noise = {e.signal: e.noise for e in diagnosis.errors}
    paths = [_signals(plt, folder, data, nominal, fitted_run, units),
             _residuals(plt, folder, data, nominal, fitted_run, noise, units)]
    inputs = [n for n in diagnosis.inputs if n in nominal.trajectories][:MAX_INPUT_COLUMNS]
    states = {s.name for s in info.states} if info is not None else set()
    cumulative = cumulative_signals(data.names, {n: nominal.predicted[n] for n in data.names}, states)
    shown = [n for n in data.names if n not in cumulative]
    if inputs and shown:
        paths.append(_residual_vs_inputs(plt, folder, data, nominal, inputs, shown, sorted(cumulative), units))
    return paths


def units_of(info) -> dict[str, str]:
    """{variable: unit} from the modelDescription (variable unit, else its declared type's)."""
    if info is None:
        return {}
    return {name: v.unit for name, v in info.variables.items() if getattr(v, "unit", None)}


def _figure(plt, rows: int, columns: int = 1, **options):
    return plt.subplots(rows, columns, figsize=(4.5 * columns + 3, 2.4 * rows + 0.6), squeeze=False, **options)


def save_figure(plt, fig, path: Path, title: str) -> Path:
    fig.suptitle(title, fontsize=11)
    if fig.get_layout_engine() is None:     # a constrained layout (room for a colourbar) stays
        fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _signals(plt, folder, data, nominal, fitted_run, units) -> Path:
    fig, axes = _figure(plt, len(data.names))
    for ax, name in zip(axes[:, 0], data.names):
        ax.plot(data.time, data.signals[name], label="measured", **MEASURED_STYLE)
        ax.plot(data.time, nominal.predicted[name], label="declared FMU", **FMU_STYLE)
        shown = [data.signals[name], nominal.predicted[name]]
        if fitted_run is not None:
            ax.plot(data.time, fitted_run.predicted[name], label="with the fitted term", **HYBRID_STYLE)
            shown.append(fitted_run.predicted[name])
        robust_ylim(ax, *shown)
        ax.set_ylabel(label(name, units.get(name)), fontsize=8)
        ax.grid(alpha=0.3)
    axes[0, 0].legend(loc="best", fontsize=8)
    axes[-1, 0].set_xlabel("time [s]")
    return save_figure(plt, fig, folder / "signals.png", "Diagnosis: measured signals and the declared FMU")


def _residuals(plt, folder, data, nominal, fitted_run, noise, units) -> Path:
    fig, axes = _figure(plt, len(data.names))
    for ax, name in zip(axes[:, 0], data.names):
        residual = nominal.predicted[name] - data.signals[name]
        ax.fill_between(data.time, -2 * noise[name], 2 * noise[name], color="0.88", label="±2 σ noise", zorder=0)
        ax.plot(data.time, residual, lw=1.0, label="declared FMU", **{k: v for k, v in FMU_STYLE.items() if k != "lw"})
        shown = [residual, [-2 * noise[name], 2 * noise[name]]]
        if fitted_run is not None:
            corrected = fitted_run.predicted[name] - data.signals[name]
            ax.plot(data.time, corrected, label="with the fitted term",
                    **{**HYBRID_STYLE, "lw": 0.9, "ls": "-", "alpha": 0.8})
            shown.append(corrected)
        ax.axhline(0.0, color="0.3", lw=0.5)
        robust_ylim(ax, *shown)
        ax.set_ylabel(f"{label(name, units.get(name))}\n{RESIDUAL}", fontsize=8)
        ax.grid(alpha=0.3)
    axes[0, 0].legend(loc="best", fontsize=8)
    axes[-1, 0].set_xlabel("time [s]")
    return save_figure(plt, fig, folder / "residuals.png", f"Diagnosis: residuals ({RESIDUAL}) over time")


def _residual_vs_inputs(plt, folder, data, nominal, inputs, shown, left_out, units) -> Path:
    # constrained layout: it leaves room for the colourbar, tight_layout does not
    fig, axes = _figure(plt, len(shown), len(inputs), layout="constrained")
    points = None
    for i, name in enumerate(shown):
        residual = nominal.predicted[name] - data.signals[name]
        for j, variable in enumerate(inputs):
            ax = axes[i, j]
            points = ax.scatter(nominal.trajectories[variable], residual, s=3, c=data.time, cmap="viridis")
            ax.axhline(0.0, color="0.3", lw=0.5)
            robust_ylim(ax, residual)
            ax.grid(alpha=0.3)
            if i == len(shown) - 1:
                ax.set_xlabel(f"{label(variable, units.get(variable))} (declared FMU)", fontsize=8)
            if j == 0:
                ax.set_ylabel(f"{label(name, units.get(name))}\n{RESIDUAL}", fontsize=8)
    title = "Diagnosis: residuals against the traced variables"
    if left_out:
        title += f"\n(left out, they accumulate over time: {', '.join(left_out)})"
    fig.colorbar(points, ax=axes, fraction=0.03, pad=0.01).set_label("time [s]")
    return save_figure(plt, fig, folder / "residual_vs_inputs.png", title)
