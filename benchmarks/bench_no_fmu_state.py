"""Training an FMU that cannot save its state, against the same model with snapshots.

sampled_plant (a DC motor under a sampled PI controller: a discrete integrator) and its variant
compiled without FMU-state support (canGetAndSetFMUstate="false", the binary refuses the calls),
trained on the same data (three times the declared friction) with each element order. Without
snapshots the element starts are continued in the FMU instance that reached them or replayed
(fmubuilder/neural/solve.py, Replay). Printed per run: the epoch losses, the error before and
after, the replays (runs, simulated seconds, against the seconds simulated with gradient in
the epochs) and the wall time relative to the snapshot run measured in the same process.

    python benchmarks/bench_no_fmu_state.py [--epochs N]
"""
from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from fmubuilder.build import example_fmu  # noqa: E402
from fmubuilder.neural.train import train_neural_fmu  # noqa: E402
from tests.neural.conftest import plant_data  # noqa: E402

ORDERS = (("random, one batch", dict(order="random")), ("random, batches of 2", dict(order="random", batch_size=2)),
          ("sequential", dict(order="sequential")))


def run(fmu, data, epochs: int, order: dict) -> dict:
    started = time.perf_counter()
    result = train_neural_fmu(fmu, data, targets=["der(w)"], inputs=["w", "der(w)"], hidden=[8], epochs=epochs,
                              element_length=0.5, step_size=0.004, learning_rate=2e-2, progress=False, **order)
    seconds = time.perf_counter() - started
    errors = result.metrics["errors"]
    result.model.close()
    return {"losses": [h["loss"] for h in result.history], "before": errors["before"]["w"]["mse"],
            "after": errors["after"]["w"]["mse"], "replays": result.metrics["element_start_replays"],
            "seconds": seconds}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--epochs", type=int, default=8)
    args = parser.parse_args()
    warnings.simplefilter("ignore")
    torch.set_num_threads(1)
    with_state, without_state = example_fmu("sampled_plant"), example_fmu("sampled_plant_no_fmu_state")
    data, _ = plant_data(with_state, [0, 1, 1.001, 2.5, 2.501, 4], [1, 1, 2, 2, 0.5, 0.5], 4.0, seed=0)
    simulated = args.epochs * (data.stop - data.start)
    print("| order | FMU | epoch losses | MSE w before | MSE w after | replays: runs, simulated s "
          f"(epochs: {simulated:g} s) | time / snapshot run |")
    print("|---|---|---|---|---|---|---|")
    for label, order in ORDERS:
        baseline = None
        for name, fmu in (("snapshots", with_state), ("no FMU state", without_state)):
            r = run(fmu, data, args.epochs, order)
            baseline = baseline or r["seconds"]
            losses = ", ".join(f"{loss:.4f}" for loss in r["losses"])
            print(f"| {label} | {name} | {losses} | {r['before']:.4g} | {r['after']:.4g} | "
                  f"{r['replays']['runs']}, {r['replays']['simulated_seconds']:.1f} | {r['seconds'] / baseline:.2f} |")


if __name__ == "__main__":
    main()
