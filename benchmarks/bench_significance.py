"""False-positive and detection rates of the diagnosis' significance test.

For each example model the declared FMU and each truth (no effect, the effect variants, a
parameter mismatch) are simulated once, noise-free, through the bench of fmubuilder.synth
(sensor lag, jittered 10 Hz stamps). Then, for each noise model and seed, the bench's noise
is drawn for each of the two runs, and the joint test runs on the residual the diagnosis
would see (mean over the runs minus the declared model's prediction, with the runs' spread
columns). Printed: the share of seeds called significant at the tool's threshold
(SIGNIFICANCE_LEVEL), and for the no-effect truth also at 0.01 and 0.05 (a calibrated test
stays at or below those levels).

    python benchmarks/bench_significance.py [--seeds 100] [--cases dc_drive,vldm] [--no-spread]
"""
from __future__ import annotations

import argparse
import time
from dataclasses import dataclass, field

import numpy as np

from fmubuilder import synth
from fmubuilder.build import example_fmu
from fmubuilder.diagnose import diagnosis, significance
from fmubuilder.data import MeasuredData

NOISE_MODELS = {
    "white": dict(noise_model="white"),
    "AR(1) 0.3": dict(noise_model="ar1", noise_rho=0.3),
    "AR(1) 0.6": dict(noise_model="ar1", noise_rho=0.6),
    "AR(1) 0.9": dict(noise_model="ar1", noise_rho=0.9),
    "low-pass 0.3 s x2": dict(noise_model="lowpass", noise_filter_tau=0.3, noise_filter_order=2),
    "sensor lag 0.1 s": dict(noise_model="lowpass", noise_filter_tau=0.1),
}


@dataclass
class Case:
    model: str
    stop_time: float
    signals: tuple
    noise_std: dict
    start_values: dict | None
    truths: dict                      # label -> (truth FMU, truth parameters)
    settings: dict = field(default_factory=dict)


CASES = {
    "dc_drive": Case("dc_drive", 30.0, ("speed", "current", "power", "temperature"),
                     {"speed": 0.1, "current": 0.02, "power": 1.0, "temperature": 0.02}, None, {
                         "no effect": ("dc_drive", None),
                         "windage": ("dc_drive_truth_windage", None),
                         "extra heating": ("dc_drive_truth_extra_heating", None),
                         "resistance +10 %": ("dc_drive", {"nominal_resistance": 1.32}),
                     }),
    "vldm": Case("vldm", 300.0, ("speed", "power", "energy"), {}, {"cycle": 1}, {
        "no effect": ("vldm", None),
        "extra resistance": ("vldm_truth_extra_resistance", None),
        "extra loss": ("vldm_truth_extra_loss", None),
        "mass +10 %": ("vldm", {"mass": 1087.35}),
    }),
}


def noise_free(case: Case, truth: str, parameters) -> tuple[np.ndarray, dict]:
    """Stamps and the bench's noise-free (lagged) truth signals."""
    settings = synth.BenchSettings(signals=case.signals, noise_std={s: 0.0 for s in case.signals}, runs=1, seed=0)
    m = synth.measure(example_fmu(truth), stop_time=case.stop_time, start_values=case.start_values,
                      settings=settings, truth_parameters=parameters)
    return m.time, {s: m.true[s][0] for s in case.signals}


def declared_prediction(case: Case, stamps: np.ndarray, lag: float) -> dict:
    """The declared model as the diagnosis simulates it for these stamps."""
    fmu = example_fmu(case.model)
    data = MeasuredData(time=stamps, signals={s: stamps for s in case.signals},
                        sensor_lag=lag, fine_step=0.01, start_values=dict(case.start_values or {}))
    from fmubuilder.fmi.archive import read_model_info
    runner = diagnosis._runner(fmu, data.start_values, data, float(stamps[0]), float(stamps[-1]),
                               diagnosis.candidate_variables(read_model_info(fmu)))
    try:
        return runner.simulate(trajectories=False).predicted
    finally:
        runner.close()


def p_values(case: Case, stamps, truth: dict, model: dict, noise: dict, seeds: int, use_spread: bool) -> np.ndarray:
    base = synth.BenchSettings(signals=case.signals, noise_std=case.noise_std, **noise)
    result = []
    for seed in range(seeds):
        rng = np.random.default_rng(seed)
        residuals, spreads = [], []
        for s in case.signals:
            sigma = base.noise_of(s)
            runs = np.array([truth[s] + sigma * synth.unit_noise(stamps, base, rng) for _ in range(2)])
            residuals.append(runs.mean(axis=0) - model[s])
            spreads.append(runs.std(axis=0, ddof=1) if use_spread else None)
        result.append(significance.joint_test(residuals, [model[s] for s in case.signals], spreads, 2).p_value)
    return np.array(result)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=100)
    parser.add_argument("--cases", default="dc_drive,vldm")
    parser.add_argument("--no-spread", action="store_true", help="test without the runs' spread columns")
    args = parser.parse_args()
    level = significance.SIGNIFICANCE_LEVEL
    print(f"{args.seeds} seeds per cell; share called significant at p < {level:g} "
          f"(no effect: also at 0.01 / 0.05); spread columns {'not ' if args.no_spread else ''}used")
    for name in args.cases.split(","):
        case = CASES[name]
        started = time.perf_counter()
        lag = synth.BenchSettings().lag
        simulated = {label: noise_free(case, fmu, parameters) for label, (fmu, parameters) in case.truths.items()}
        stamps = simulated["no effect"][0]
        model = declared_prediction(case, stamps, lag)
        n = stamps.size
        print(f"\n{name}: {case.stop_time:g} s, {n} samples, effect band {significance.effect_band(n)} frequencies")
        header = f"{'noise':<20}" + "".join(f"{label:>22}" for label in case.truths)
        print(header + "\n" + "-" * len(header))
        for noise_label, noise in NOISE_MODELS.items():
            cells = []
            for label in case.truths:
                p = p_values(case, stamps, simulated[label][1], model, noise, args.seeds, not args.no_spread)
                if label == "no effect":
                    cells.append(f"{np.mean(p < level):.2f} /{np.mean(p < 0.01):.2f} /{np.mean(p < 0.05):.2f}")
                else:
                    cells.append(f"{np.mean(p < level):.2f}")
            print(f"{noise_label:<20}" + "".join(f"{c:>22}" for c in cells))
        print(f"({time.perf_counter() - started:.0f} s)")


if __name__ == "__main__":
    main()
