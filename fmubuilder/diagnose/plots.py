"""PNG plots of a diagnosis: measured vs model, residuals over time, residuals vs the traced
variables. matplotlib with the Agg backend (no display needed)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import FmuBuilderError

MAX_INPUT_COLUMNS = 3


def write_plots(folder: Path, diagnosis, data, nominal, fitted_run=None) -> list[Path]:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise FmuBuilderError(f"cannot create the plot folder {folder}: {exc.strerror or exc}") from None
    noise = {e.signal: e.noise for e in diagnosis.errors}
    paths = [_signals(plt, folder, data, nominal, fitted_run), _residuals(plt, folder, data, nominal, noise)]
    inputs = [n for n in diagnosis.inputs if n in nominal.trajectories][:MAX_INPUT_COLUMNS]
    if inputs:
        paths.append(_residual_vs_inputs(plt, folder, data, nominal, inputs))
    return paths


def _figure(plt, rows: int, columns: int = 1):
    fig, axes = plt.subplots(rows, columns, figsize=(4.5 * columns + 3, 2.4 * rows), squeeze=False)
    return fig, axes


def _save(plt, fig, path: Path) -> Path:
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _signals(plt, folder, data, nominal, fitted_run) -> Path:
    fig, axes = _figure(plt, len(data.names))
    for ax, name in zip(axes[:, 0], data.names):
        ax.plot(data.time, data.signals[name], ".", ms=2, color="0.4", label="measured")
        ax.plot(data.time, nominal.predicted[name], "-", lw=1.2, label="declared model")
        if fitted_run is not None:
            ax.plot(data.time, fitted_run.predicted[name], "--", lw=1.2, label="with fitted term")
        ax.set_ylabel(name)
    axes[0, 0].legend(loc="best", fontsize=8)
    axes[-1, 0].set_xlabel("time [s]")
    return _save(plt, fig, folder / "signals.png")


def _residuals(plt, folder, data, nominal, noise) -> Path:
    fig, axes = _figure(plt, len(data.names))
    for ax, name in zip(axes[:, 0], data.names):
        residual = data.signals[name] - nominal.predicted[name]
        ax.fill_between(data.time, -2 * noise[name], 2 * noise[name], color="0.85", label="±2 noise")
        ax.plot(data.time, residual, "-", lw=0.8)
        ax.axhline(0.0, color="0.3", lw=0.5)
        ax.set_ylabel(f"{name}\nmeasured - model", fontsize=8)
    axes[0, 0].legend(loc="best", fontsize=8)
    axes[-1, 0].set_xlabel("time [s]")
    return _save(plt, fig, folder / "residuals.png")


def _residual_vs_inputs(plt, folder, data, nominal, inputs) -> Path:
    fig, axes = _figure(plt, len(data.names), len(inputs))
    for i, name in enumerate(data.names):
        residual = data.signals[name] - nominal.predicted[name]
        for j, variable in enumerate(inputs):
            ax = axes[i, j]
            ax.scatter(nominal.trajectories[variable], residual, s=3, c=data.time, cmap="viridis")
            ax.axhline(0.0, color="0.3", lw=0.5)
            if i == len(data.names) - 1:
                ax.set_xlabel(f"{variable} (model)")
            if j == 0:
                ax.set_ylabel(f"{name} residual", fontsize=8)
    return _save(plt, fig, folder / "residual_vs_inputs.png")
