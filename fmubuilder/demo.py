"""`fmubuilder demo`: the main job on the bundled example, end to end."""
from __future__ import annotations

import shutil
from pathlib import Path

from .errors import FmuBuilderError


def prepare_output_dir(path: Path, force: bool) -> Path:
    if path.exists():
        if not force:
            raise FmuBuilderError(f"{path} exists; choose another folder with -o or pass --force to replace it")
        shutil.rmtree(path)
    path.mkdir(parents=True)
    return path


def run_demo(output: Path, force: bool = False) -> None:
    from .build import example_fmu
    from .simulation import simulate

    out = prepare_output_dir(output, force)
    fmu = example_fmu("bouncing_ball")
    shutil.copy(fmu, out / fmu.name)
    result = simulate(out / fmu.name, stop_time=3.0, output_interval=0.01)
    result.to_csv(out / "bouncing_ball.csv")
    plot_result(result, out / "bouncing_ball.png", title="bouncing_ball.fmu simulated by fmubuilder")
    print(f"simulated {fmu.name}: {result.stats_line()}")
    print(f"results and plot in {out}/")


def plot_result(result, path: Path, title: str) -> None:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(result.names)
    fig, axes = plt.subplots(len(names), 1, figsize=(8, 2.2 * len(names)), sharex=True, squeeze=False)
    for ax, name in zip(axes[:, 0], names):
        ax.plot(result.time, result[name])
        ax.set_ylabel(name)
        ax.grid(alpha=0.3)
    axes[-1, 0].set_xlabel("time [s]")
    axes[0, 0].set_title(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
