"""Cost of the crash breadcrumb (fmubuilder/fmi/breadcrumb.py) on the hot path.

Every call into an FMU's binary writes its code into shared memory before and after the
call, so that the CLI can name the call a crashing binary died in. This measures, in the
same process and alternately:
  calls     fmi2GetDerivatives calls per second through FmuInstance.get_derivatives, with
            the breadcrumb (as shipped) and without (the same method minus the two writes)
  engine    a whole simulation (Euler, fixed step) with the hot-path methods as shipped and
            with breadcrumb-free copies of them patched in
and prints the time ratios (with / without; 1.00 = no cost): the ratio of the best times and
the median of the ratios of adjacent pairs (robust when the machine is shared).

    python benchmarks/bench_breadcrumb.py [--repeats R] [--model vldm] [--stop T]
"""
from __future__ import annotations

import argparse
import contextlib
import statistics
import time
import timeit

from fmubuilder.build import example_fmu
from fmubuilder.fmi import Fmu
from fmubuilder.fmi.instance import FmuInstance
from fmubuilder.simulation import simulate


# -- the hot-path methods without the breadcrumb: otherwise identical to fmi/instance.py ----

def _plain_get_derivatives(self):
    status = self._lib.fmi2GetDerivatives(self.component, self._dx, self._n_states)
    if status > 1:
        self._check(status, "fmi2GetDerivatives")
    return self._dx_view.copy()


def _plain_get_event_indicators(self):
    status = self._lib.fmi2GetEventIndicators(self.component, self._z, self._n_indicators)
    if status > 1:
        self._check(status, "fmi2GetEventIndicators")
    return self._z_view.copy()


def _plain_set_time(self, t):
    status = self._lib.fmi2SetTime(self.component, t)
    if status > 1:
        self._check(status, "fmi2SetTime")


def _plain_set_continuous_states(self, x):
    self._x_view[:] = x
    status = self._lib.fmi2SetContinuousStates(self.component, self._x, self._n_states)
    if status > 1:
        self._check(status, "fmi2SetContinuousStates")


def _plain_get_continuous_states(self):
    status = self._lib.fmi2GetContinuousStates(self.component, self._x, self._n_states)
    if status > 1:
        self._check(status, "fmi2GetContinuousStates")
    return self._x_view.copy()


def _plain_completed_integrator_step(self, no_set_fmu_state_prior=True):
    flags = self._flags
    status = self._lib.fmi2CompletedIntegratorStep(self.component, no_set_fmu_state_prior, flags, flags + 1)
    if status > 1:
        self._check(status, "fmi2CompletedIntegratorStep")
    return bool(flags[0]), bool(flags[1])


PLAIN = {"get_derivatives": _plain_get_derivatives, "get_event_indicators": _plain_get_event_indicators,
         "set_time": _plain_set_time, "set_continuous_states": _plain_set_continuous_states,
         "get_continuous_states": _plain_get_continuous_states,
         "completed_integrator_step": _plain_completed_integrator_step}


@contextlib.contextmanager
def without_breadcrumb():
    shipped = {name: getattr(FmuInstance, name) for name in PLAIN}
    for name, method in PLAIN.items():
        setattr(FmuInstance, name, method)
    try:
        yield
    finally:
        for name, method in shipped.items():
            setattr(FmuInstance, name, method)


def calls_seconds(instance, repeats: int, number: int) -> tuple[list[float], list[float]]:
    """Seconds per fmi2GetDerivatives call (with, without), `repeats` adjacent pairs."""
    plain = _plain_get_derivatives.__get__(instance)
    with_crumb, without = [], []
    for _ in range(repeats):
        with_crumb.append(timeit.timeit(instance.get_derivatives, number=number) / number)
        without.append(timeit.timeit(plain, number=number) / number)
    return with_crumb, without


def engine_seconds(path, stop: float, step: float, repeats: int) -> tuple[list[float], list[float], int]:
    def run():
        started = time.perf_counter()
        result = simulate(path, stop_time=stop, solver="euler", step_size=step, output_interval=max(step, stop / 1000))
        return time.perf_counter() - started, result.stats.rhs_evaluations
    with_crumb, without = [], []
    evaluations = 0
    for _ in range(repeats):
        seconds, evaluations = run()
        with_crumb.append(seconds)
        with without_breadcrumb():
            without.append(run()[0])
    return with_crumb, without, evaluations


def ratios(with_crumb: list[float], without: list[float]) -> str:
    paired = statistics.median(a / b for a, b in zip(with_crumb, without))
    return f"time ratio with/without: best {min(with_crumb) / min(without):.3f}, median of pairs {paired:.3f}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--number", type=int, default=200_000, help="calls per timing of fmi2GetDerivatives")
    parser.add_argument("--model", default="vldm", help="example FMU for the engine run (default vldm)")
    parser.add_argument("--stop", type=float, default=60.0, help="simulated seconds of the engine run (default 60)")
    args = parser.parse_args()

    with Fmu(example_fmu("bouncing_ball")) as fmu:
        instance = fmu.instantiate()
        instance.setup_experiment(0.0)
        instance.enter_initialization_mode()
        instance.exit_initialization_mode()
        instance.update_discrete_states()
        instance.enter_continuous_time_mode()
        with_crumb, without = calls_seconds(instance, args.repeats, args.number)
        instance.free()
    print(f"fmi2GetDerivatives via FmuInstance.get_derivatives (bouncing_ball), best of {args.repeats}:")
    print(f"  with breadcrumb    {1e-6 / min(with_crumb):6.3f} M calls/s  ({1e9 * min(with_crumb):5.0f} ns per call)")
    print(f"  without            {1e-6 / min(without):6.3f} M calls/s  ({1e9 * min(without):5.0f} ns per call)")
    print(f"  {ratios(with_crumb, without)}")

    path = example_fmu(args.model)
    from fmubuilder.fmi import read_model_info
    step = read_model_info(path).default_experiment.step_size or 1e-3
    seconds_with, seconds_without, evaluations = engine_seconds(path, args.stop, step, args.repeats)
    print(f"engine, {args.model} 0..{args.stop:g} s, Euler h = {step:g} s ({evaluations} derivative evaluations), "
          f"best of {args.repeats}:")
    print(f"  with breadcrumb {min(seconds_with):.3f} s, without {min(seconds_without):.3f} s")
    print(f"  {ratios(seconds_with, seconds_without)}")


if __name__ == "__main__":
    main()
