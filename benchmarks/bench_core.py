"""The simulation engine against the floor: a plain C loop over the same FMU binary.

One run of the bundled VLDM over the CADC cycle's first 881 s (RK4 at h = 0.01 s, an output every
step, 88,100 time events) three ways, alternately, best of several repeats:

  floor     benchmarks/plain_fmu_loop.c, built here with the C compiler: RK4, the indicators and
            fmi2CompletedIntegratorStep after every step, event mode at every time event, the
            same variables read at every output time; instantiation to fmi2FreeInstance
  engine    fmubuilder's engine (the compiled core) from an opened FMU: the instance, its
            initialisation, the loop, the result's arrays
  python    the same with FMUBUILDER_ENGINE=python: the loop in Python (one run)

It prints each time and the ratios engine/floor and python/floor, and checks that the engine's
final states agree with the floor's (to 1e-6 relative: the floor does not locate state events).

Then the same run of a NeuralFMU (the model's network on der(speed) and der(energy), reading the
speed, der(speed) and the power, 16 x 16 tanh units, random weights behind a gate of 0.1), by the
compiled core with the network in C and by the Python loop with it in numpy, against the same floor.

    python benchmarks/bench_core.py [--repeats R] [--stop 881] [--model vldm]
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from fmubuilder.build import c_compiler, example_fmu, fmi_headers_dir
from fmubuilder.fmi import Fmu
from fmubuilder.simulation import make_solver, output_grid, run
from fmubuilder.simulation.system import FmuSystem

HERE = Path(__file__).resolve().parent


def build_floor(folder: Path) -> Path:
    program = folder / "plain_fmu_loop"
    subprocess.run([c_compiler(), "-O2", "-std=c99", f"-I{fmi_headers_dir()}", str(HERE / "plain_fmu_loop.c"),
                    "-o", str(program), "-ldl", "-lm"], check=True)
    return program


def run_floor(program: Path, fmu: Fmu, names: list[str], stop: float, step: float) -> tuple[float, np.ndarray]:
    info = fmu.info
    vrs = [str(info.variable(name).value_reference) for name in names
           if info.variable(name).api_type == "Real" and name not in {v.name for v in info.states}]
    command = [str(program), str(fmu.archive.library_path), info.guid, fmu.archive.resources_uri, repr(stop),
               repr(step), "1", str(info.n_states), str(info.n_event_indicators), *vrs]
    out = subprocess.run(command, check=True, capture_output=True, text=True).stdout.split("\n")
    seconds = float(out[0].split()[1])
    return seconds, np.array([float(v) for v in out[1].split()[1:]])


def run_engine(fmu: Fmu, names: list[str], stop: float, step: float):
    system = FmuSystem(fmu, variables=names)
    try:
        return run(system, make_solver("rk4", step_size=step), start_time=0.0, stop_time=stop,
                   output_times=output_grid(0.0, stop, step))
    finally:
        system.close()


def run_neural(fmu_path, names: list[str], stop: float, step: float):
    import torch
    from fmubuilder.neural import NeuralFMU, TopologyConfig
    from fmubuilder.neural.system import simulate_hybrid
    torch.manual_seed(0)
    config = TopologyConfig(channels=["der(speed)", "der(energy)"], inputs=["speed", "der(speed)", "power"],
                            hidden=[16, 16])
    with NeuralFMU(fmu_path, config) as model:
        with torch.no_grad():
            model.topology.gate_ann.fill_(0.1)
        started = time.perf_counter()
        result = simulate_hybrid(model, start_time=0.0, stop_time=stop, variables=names, solver="rk4",
                                 step_size=step)
        return time.perf_counter() - started, result


def timed(function):
    started = time.perf_counter()
    value = function()
    return time.perf_counter() - started, value


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default="vldm")
    parser.add_argument("--stop", type=float, default=881.0)
    parser.add_argument("--step", type=float, default=0.01)
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as folder, Fmu(example_fmu(args.model)) as fmu:
        program = build_floor(Path(folder))
        info = fmu.info
        names = [v.name for v in info.outputs] + [v.name for v in info.states]
        floor, engine = [], []
        for _ in range(args.repeats):
            seconds, floor_states = run_floor(program, fmu, names, args.stop, args.step)
            floor.append(seconds)
            seconds, result = timed(lambda: run_engine(fmu, names, args.stop, args.step))
            engine.append(seconds)
        neural = [run_neural(fmu.path, names, args.stop, args.step)[0] for _ in range(args.repeats)]
        os.environ["FMUBUILDER_ENGINE"] = "python"
        python, _ = timed(lambda: run_engine(fmu, names, args.stop, args.step))
        neural_python, _ = run_neural(fmu.path, names, args.stop, args.step)
        del os.environ["FMUBUILDER_ENGINE"]
    states = np.array([result[v.name][-1] for v in info.states])
    agree = np.allclose(states, floor_states, rtol=1e-6, atol=1e-9)
    best_floor, best_engine = min(floor), min(engine)
    print(f"{args.model}, 0..{args.stop:g} s, RK4 h = {args.step:g} s, {result.stats.steps} steps, "
          f"{result.stats.time_events} time events, {len(result.time)} output rows of {len(names)} variables")
    print(f"  floor (plain C loop)   {best_floor * 1e3:8.1f} ms   (median {np.median(floor) * 1e3:.1f})")
    print(f"  engine (compiled core) {best_engine * 1e3:8.1f} ms   (median {np.median(engine) * 1e3:.1f})"
          f"   ratio {best_engine / best_floor:5.2f}")
    print(f"  engine (Python loop)   {python * 1e3:8.1f} ms   (one run)"
          f"              ratio {python / best_floor:5.2f}")
    print(f"  final states agree with the floor's (rtol 1e-6): {'yes' if agree else 'NO'}")
    print("with the NeuralFMU's network in the loop (16 x 16 tanh units on der(speed), der(energy)):")
    print(f"  compiled core, network in C   {min(neural) * 1e3:8.1f} ms   (median {np.median(neural) * 1e3:.1f})"
          f"   ratio {min(neural) / best_floor:5.2f}")
    print(f"  Python loop, network in numpy {neural_python * 1e3:8.1f} ms   (one run)"
          f"              ratio {neural_python / best_floor:5.2f}")
    if not agree:
        print("    engine", states, "\n    floor ", floor_states)
        sys.exit(1)


if __name__ == "__main__":
    main()
