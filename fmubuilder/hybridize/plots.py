"""The hybridize report's plots: the signals of one data set (measured, declared FMU, hybrid) with
their errors, and the effect the hybrid learned against its inputs. Colours, the residual's sign
and the robust y-limits are those of the diagnosis plots (fmubuilder.diagnose.plots)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from ..diagnose.plots import (COLOURS, FMU_STYLE, HYBRID_STYLE, MEASURED_STYLE, RESIDUAL, label, pyplot,
                              robust_ylim, save_figure)


def plot_signals(path: Path, data, before, after, hybrid_label: str | None, units: dict, title: str,
                 held_out: tuple | None = None) -> Path:
    """Each measured signal with the declared FMU and the hybrid (left) and their errors (right);
    `held_out`: the validation window, shaded; `after`/`hybrid_label` None: no hybrid."""
    plt = pyplot()
    names = data.names
    fig, axes = plt.subplots(len(names), 2, figsize=(12, 2.5 * len(names) + 0.7), sharex=True, squeeze=False)
    for row, name in enumerate(names):
        measured = np.interp(before.time, data.time, data.signals[name])
        ax = axes[row, 0]
        ax.plot(data.time, data.signals[name], label="measured", **MEASURED_STYLE)
        ax.plot(before.time, before.predicted[name], label="declared FMU", **FMU_STYLE)
        shown = [data.signals[name], before.predicted[name]]
        if after is not None:
            ax.plot(after.time, after.predicted[name], label=hybrid_label, **HYBRID_STYLE)
            shown.append(after.predicted[name])
        robust_ylim(ax, *shown)
        ax.set_ylabel(label(name, units.get(name)), fontsize=9)
        ax.grid(alpha=0.3)
        ax = axes[row, 1]
        errors = [before.predicted[name] - measured]
        ax.plot(before.time, errors[0], color=COLOURS["fmu"], lw=1.0, alpha=0.85, label="declared FMU", zorder=2)
        if after is not None:
            errors.append(after.predicted[name] - measured)
            ax.plot(after.time, errors[1], color=COLOURS["hybrid"], lw=1.0, alpha=0.85, label=hybrid_label, zorder=3)
        ax.axhline(0.0, color="0.3", lw=0.5)
        robust_ylim(ax, *errors)
        ax.set_ylabel(f"{label(name, units.get(name))}\n{RESIDUAL}", fontsize=9)
        ax.grid(alpha=0.3)
        if held_out is not None:
            for ax in axes[row]:
                ax.axvspan(*held_out, color="0.9", zorder=0, label="validation (held out of the fit)")
    axes[0, 0].legend(loc="best", fontsize=8)
    axes[0, 1].legend(loc="best", fontsize=8)
    axes[0, 0].set_title("signals", fontsize=10)
    axes[0, 1].set_title(f"errors ({RESIDUAL})", fontsize=10)
    for ax in axes[-1]:
        ax.set_xlabel("time [s]")
    return save_figure(plt, fig, path, title)


def plot_effects(path: Path, effects: list, units: dict, title: str) -> Path:
    """Each channel's learned correction (a row per channel) against each input it reads, and the
    truth's where known."""
    plt = pyplot()
    columns = max(len(effect.inputs) for effect in effects)
    fig, axes = plt.subplots(len(effects), columns, figsize=(6.5 * columns, 4.2 * len(effects)), squeeze=False)
    for row, effect in zip(axes, effects):
        for ax, name in zip(row, effect.inputs):
            _draw_effect(ax, effect, name, units)
        for ax in row[len(effect.inputs):]:
            ax.set_visible(False)
    return save_figure(plt, fig, path, title)


def _draw_effect(ax, effect, name: str, units: dict) -> None:
    x = effect.inputs[name]
    shown = [effect.learned]
    if effect.truth is not None:
        ax.scatter(x, effect.truth, s=28, color=COLOURS["truth"], alpha=0.35, lw=0, zorder=2,
                   label=f"true effect ({effect.truth_source})")
        shown.append(effect.truth)
    learned_label = f"learned {effect.kind}"
    if len(effect.inputs) == 1:
        order = np.argsort(x, kind="stable")
        ax.plot(x[order], effect.learned[order], color=COLOURS["hybrid"], lw=1.4, ls="--", zorder=3,
                label=learned_label)
    else:   # the term depends on the others too: its values along the run, not a curve
        ax.scatter(x, effect.learned, s=6, color=COLOURS["hybrid"], zorder=3, label=learned_label)
    ax.axhline(0.0, color="0.3", lw=0.5)
    robust_ylim(ax, *shown)
    ax.set_xlabel(f"{label(name, units.get(name))} (declared FMU over the training run)", fontsize=9)
    ax.set_ylabel(f"added to {label(effect.channel, units.get(effect.channel))}", fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    if effect.truth is None:
        ax.text(0.01, 0.02, f"no true effect drawn: {effect.truth_source}", transform=ax.transAxes,
                fontsize=7, color="0.35")
