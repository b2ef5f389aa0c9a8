"""`hybridize` on an FMU without FMU-state support, against the same model with snapshots.

sampled_plant (a DC motor under a sampled PI controller) and its variant compiled with
canGetAndSetFMUstate="false", on the same measured data (the friction four times the declared
one, shaft speed with noise; a set-point input), with the same budget (loss evaluations, seed). Without
snapshots the NeuralFMU's element starts are carried over or replayed, which is exact, so the
two rows should agree. Printed: each candidate's mean MSE relative to the plain FMU per role.

    python benchmarks/bench_hybridize_no_fmu_state.py [--budget N] [--keep DIR]
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from fmubuilder.build import example_fmu  # noqa: E402
from fmubuilder.hybridize import hybridize  # noqa: E402
from fmubuilder.simulation import simulate  # noqa: E402

TRUE_FRICTION = 0.2      # declared: 0.05
NOISE = 0.002            # rad/s
TRAIN_PROFILE = ([0, 1, 1.001, 2.5, 2.501, 4, 4.001, 6, 6.001, 8], [1, 1, 2, 2, 0.5, 0.5, 1.5, 1.5, 3, 3], 8.0)
TEST_PROFILE = ([0, 1.5, 1.501, 3, 3.001, 6], [2, 2, 0.8, 0.8, 2.5, 2.5], 6.0)


def write_data(fmu: Path, profile, seed: int, path: Path) -> Path:
    """The plant with the true friction, speed sampled every 10 ms with noise, and the set point."""
    times, setpoints, stop = profile
    result = simulate(fmu, start_time=0.0, stop_time=stop, start_values={"b": TRUE_FRICTION},
                      inputs={"time": np.asarray(times, float), "setpoint": np.asarray(setpoints, float)},
                      solver="rk4", step_size=0.001, output_interval=0.01, variables=["w"])
    w = result["w"] + NOISE * np.random.default_rng(seed).standard_normal(result.time.size)
    setpoint = np.interp(result.time, times, setpoints)
    keep = np.concatenate([[True], np.diff(result.time) > 0])   # one sample per time stamp
    rows = np.column_stack([result.time[keep], w[keep], setpoint[keep]])
    np.savetxt(path, rows, delimiter=",", header="time,w,setpoint", comments="", fmt="%.10g")
    return path


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--budget", type=int, default=10, help="the NeuralFMU's loss evaluations")
    parser.add_argument("--keep", type=Path, help="folder for the data, hybrids and reports (default: temporary)")
    args = parser.parse_args()
    warnings.simplefilter("ignore")
    folder = args.keep or Path(tempfile.mkdtemp(prefix="bench-no-fmu-state-"))
    folder.mkdir(parents=True, exist_ok=True)
    with_state = example_fmu("sampled_plant")
    train = write_data(with_state, TRAIN_PROFILE, 0, folder / "train.csv")
    test = write_data(with_state, TEST_PROFILE, 1, folder / "test.csv")
    print("| FMU | candidate | train | validation (chooses) | test | chosen |")
    print("|---|---|---|---|---|---|")
    for label, name in (("snapshots", "sampled_plant"), ("no FMU state", "sampled_plant_no_fmu_state")):
        out = folder / name
        result = hybridize(example_fmu(name), train, test, out / "hybrid.fmu", out / "report", budget=args.budget,
                           seed=0, progress=False, force=True)
        for model in result.report["models"]:
            print(f"| {label} | {model['name']}: {model['description']} | {model['train_relative_mse']:.4g} | "
                  f"{model['validation_relative_mse']:.4g} | {model['test_relative_mse']:.4g} | "
                  f"{'yes' if model['chosen'] else 'no'} |")


if __name__ == "__main__":
    main()
