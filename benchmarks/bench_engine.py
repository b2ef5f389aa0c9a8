"""Wall time of fmubuilder's simulate() versus fmpy.simulate_fmu() on the example FMUs,
and the per-call cost of fmi2GetDerivatives through cffi (ours) versus ctypes (fmpy).

Both simulators run the same FMU, interval and horizon in this process, alternately, and
the best of several repeats is kept (the machine may be shared). Pairs compared:
  adaptive   our DOPRI5 (rtol = atol = tol) vs fmpy CVode (relative_tolerance = tol; its
             absolute tolerance is tol times the state nominals, 1 here)
  euler      our Euler vs fmpy Euler, step = output interval = the DefaultExperiment stepSize
             (ours also locates state events inside a step; fmpy's Euler does not)
Times include opening the FMU, as a user of either function sees it. With --clock cpu they are
the process's CPU time (both simulators run in this process), steadier than wall time on a
shared machine.

    python benchmarks/bench_engine.py [--repeats R] [--models a,b] [--vldm-stop T] [--clock cpu]
"""
from __future__ import annotations

import argparse
import ctypes
import time
import timeit

import fmpy
import numpy as np

from fmubuilder.build import example_fmu, list_examples
from fmubuilder.fmi import Fmu, read_model_info
from fmubuilder.fmi.binding import ffi
from fmubuilder.simulation import simulate


CLOCKS = {"wall": time.perf_counter, "cpu": time.process_time}


def best_of(repeats, function, clock=time.perf_counter):
    best, value = float("inf"), None
    for _ in range(repeats):
        started = clock()
        value = function()
        best = min(best, clock() - started)
    return best, value


def compare(path, label, ours, theirs, repeats, clock):
    t_ours, result = best_of(repeats, ours, clock)
    t_theirs, _ = best_of(repeats, theirs, clock)
    stats = result.stats
    print(f"  {label:18s} ours {t_ours * 1e3:9.1f} ms  fmpy {t_theirs * 1e3:9.1f} ms  "
          f"ratio {t_ours / t_theirs:5.2f}   ({stats.steps} steps, {stats.rhs_evaluations} rhs, "
          f"{stats.time_events}/{stats.state_events}/{stats.step_events} time/state/step events)")
    return t_ours / t_theirs


def bench_simulation(name, repeats, vldm_stop, clock):
    path = example_fmu(name)
    info = read_model_info(path)
    experiment = info.default_experiment
    stop = experiment.stop_time if experiment.stop_time is not None else 1.0
    if name.startswith("vldm") and vldm_stop:
        stop = min(stop, vldm_stop)
    interval = experiment.step_size or stop / 500
    print(f"{name}  (0..{stop:g} s, output every {interval:g} s)")
    ratios = {}
    for tol in (1e-6, 1e-10):
        ratios[f"dopri5/cvode {tol:g}"] = compare(
            path, f"rtol {tol:g}",
            lambda: simulate(path, stop_time=stop, rtol=tol, atol=tol, output_interval=interval),
            lambda: fmpy.simulate_fmu(str(path), stop_time=stop, relative_tolerance=tol,
                                      output_interval=interval),
            repeats, clock)
    ratios["euler"] = compare(
        path, f"euler h={interval:g}",
        lambda: simulate(path, stop_time=stop, solver="euler", step_size=interval, output_interval=interval),
        lambda: fmpy.simulate_fmu(str(path), stop_time=stop, solver="Euler", step_size=interval,
                                  output_interval=interval),
        repeats, clock)
    return ratios


def bench_call_overhead(name, calls):
    """ns per fmi2GetDerivatives call: our FmuInstance (cffi) and fmpy's FMU2Model (ctypes)."""
    from fmpy.fmi2 import FMU2Model
    path = example_fmu(name)
    with Fmu(path) as fmu:
        inst = fmu.instantiate()
        inst.setup_experiment(0.0)
        inst.enter_initialization_mode()
        inst.exit_initialization_mode()
        inst.update_discrete_states()
        inst.enter_continuous_time_mode()
        ours = min(timeit.repeat(inst.get_derivatives, number=calls, repeat=5)) / calls
        n = fmu.info.n_states
        buffer = ffi.new("double[]", n)
        raw_cffi = fmu.lib.fmi2GetDerivatives
        ours_raw = min(timeit.repeat(lambda: raw_cffi(inst.component, buffer, n), number=calls, repeat=5)) / calls

        md = fmpy.read_model_description(str(path))
        unzipdir = fmpy.extract(str(path))
        model = FMU2Model(guid=md.guid, unzipDirectory=unzipdir,
                          modelIdentifier=md.modelExchange.modelIdentifier, instanceName="bench")
        model.instantiate()
        model.setupExperiment(startTime=0.0)
        model.enterInitializationMode()
        model.exitInitializationMode()
        model.newDiscreteStates()
        model.enterContinuousTimeMode()
        dx = np.zeros(n)
        pointer = dx.ctypes.data_as(ctypes.POINTER(ctypes.c_double))
        theirs = min(timeit.repeat(lambda: model.getDerivatives(pointer, n), number=calls, repeat=5)) / calls
        raw_ctypes = model._functions["fmi2GetDerivatives"]      # the bare ctypes function
        theirs_raw = min(timeit.repeat(lambda: raw_ctypes(model.component, pointer, n),
                                       number=calls, repeat=5)) / calls
        model.terminate()
        model.freeInstance()
        inst.free()
    print(f"fmi2GetDerivatives on {name}, ns per call (cffi / ctypes):")
    print(f"  bare C function         {ours_raw * 1e9:6.0f} / {theirs_raw * 1e9:6.0f}"
          f"   ratio {ours_raw / theirs_raw:.2f}")
    print(f"  wrapper with status check {ours * 1e9:4.0f} / {theirs * 1e9:6.0f}   ratio {ours / theirs:.2f}"
          "   (FmuInstance.get_derivatives returns a new array; FMU2Model.getDerivatives fills one)")


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--models", help="comma-separated example names (default: all)")
    parser.add_argument("--vldm-stop", type=float, default=200.0,
                        help="cap the long vldm driving cycles at this time (0: full cycle)")
    parser.add_argument("--calls", type=int, default=200_000)
    parser.add_argument("--clock", choices=sorted(CLOCKS), default="wall",
                        help="the simulations' time: wall (perf_counter) or the process's CPU time")
    args = parser.parse_args()
    names = args.models.split(",") if args.models else list_examples()
    summary = {}
    for name in names:
        for key, ratio in bench_simulation(name, args.repeats, args.vldm_stop, CLOCKS[args.clock]).items():
            summary.setdefault(key, []).append(ratio)
    print("geometric mean of ours/fmpy: " + ", ".join(
        f"{key} {np.exp(np.mean(np.log(values))):.2f}" for key, values in summary.items()))
    bench_call_overhead("bouncing_ball", args.calls)


if __name__ == "__main__":
    main()
