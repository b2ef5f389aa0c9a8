"""Which inputs the ANN gets on each DC drive truth, against the variables its effect depends on.

For each truth variant of the DC drive (fmubuilder/examples_zoo.py) the training run is split as
`hybridize` splits it (the first 80 % to fit, the last 20 % for validation), the diagnosis traces
the effect to its derivative on the first part, and fmubuilder.hybridize.inputs chooses the ANN's
channels and inputs as the workflow does. Printed per variant: the channels with their inputs
(the share of the estimated missing term they predict under cross-validation, and each input's
t), the best variable not admitted, and the truth's own dependence (examples/dc_drive/model.c).
no_effect is not significant, so `hybridize` builds no candidate for it; the choice is shown on the
channel the diagnosis traces anyway.

    python benchmarks/bench_inputs.py [--variants windage,stribeck,...] [--noise-seed N] [--truth-channels]

--noise-seed N (N > 0) measures the truths anew with other noise (written to a temporary folder);
--truth-channels takes the effect's derivatives from the truth instead of the diagnosis (faster).
"""
from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

from fmubuilder.build import example_fmu
from fmubuilder.examples_zoo import cached_data, dc_drive_data_sets
from fmubuilder.fmi import read_model_info
from fmubuilder.hybridize.evaluate import Scoring
from fmubuilder.hybridize.inputs import choose_ann
from fmubuilder.hybridize.workflow import _assign_roles

# The truths' effects: derivative -> the variables it depends on (examples/dc_drive/model.c).
TRUTH = {
    "no_effect": {},
    "windage": {"der(speed)": "speed"},
    "extra_heating": {"der(temperature)": "current"},
    "stribeck": {"der(speed)": "speed"},
    "coulomb": {"der(speed)": "speed"},
    "speed_current_loss": {"der(energy)": "current, speed"},
    "two_effects": {"der(energy)": "current, speed", "der(speed)": "speed"},
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--variants", default=",".join(TRUTH), help="DC drive variants, comma-separated")
    parser.add_argument("--noise-seed", type=int, default=0, help="0: the bundled data sets; N: new noise")
    parser.add_argument("--truth-channels", action="store_true", help="the truth's derivatives, not the diagnosis'")
    args = parser.parse_args()
    fmu = example_fmu("dc_drive")
    info = read_model_info(fmu)
    rows = []
    for variant in args.variants.split(","):
        train_csv, test_csv = _data(variant, args.noise_seed)
        roles = _assign_roles(info, train_csv, None, None, None, test_csv, None)
        channel, further = _channels(fmu, roles, variant, args.truth_channels)
        scoring = Scoring.checked(fmu, roles.train[0].samples(), roles.train[0].start_values)
        choice = choose_ann(fmu, info, roles.train, roles.validation, channel, further, scoring.step, scoring.solver)
        rows.append(_row(variant, channel, choice))
        print(f"done: {variant}", flush=True)
    print(f"\nDC drive, noise seed {args.noise_seed}, channels from "
          f"{'the truth' if args.truth_channels else 'the diagnosis'}:\n")
    print("| variant | truth | channel: inputs (explained; t per input) "
          "| best not admitted (error / error of the inputs chosen, t) |")
    print("|---|---|---|---|")
    for row in rows:
        print("| " + " | ".join(row) + " |")


def _data(variant: str, noise_seed: int) -> tuple[Path, Path]:
    sets = [s for s in dc_drive_data_sets() if s.variant.key == variant]
    if noise_seed == 0:
        paths, _ = cached_data(sets)
    else:
        paths = [_measured_anew(s, noise_seed) for s in sets]
    by_role = {s.cycle.role: p for s, p in zip(sets, paths)}
    return by_role["train"], by_role["test"]


def _measured_anew(data_set, noise_seed: int) -> Path:
    from dataclasses import replace

    from fmubuilder.examples_zoo import bench_settings
    from fmubuilder.synth import measure, write_measurement
    settings = replace(bench_settings(data_set), seed=noise_seed * 1000 + data_set.seed % 1000)
    measurement = measure(example_fmu(data_set.variant.fmu), stop_time=data_set.stop_time,
                          start_values=data_set.start_values, settings=settings,
                          truth_parameters=data_set.variant.truth_parameters)
    path = Path(tempfile.mkdtemp(prefix="bench_inputs_")) / data_set.file_name
    write_measurement(measurement, path)
    return path


def _channels(fmu, roles, variant: str, from_truth: bool) -> tuple[str, list[str]]:
    if from_truth:
        channels = list(TRUTH[variant]) or ["der(current)"]
        return channels[0], channels[1:]
    from fmubuilder.diagnose import diagnose
    first = roles.train[0]
    diagnosis = diagnose(fmu, first.samples(), first.start_values, trace_always=True)
    for part in (*roles.train, *roles.validation):     # as the workflow: the diagnosis' start values
        if part.data is first.data:
            part.start_values = {**part.start_values, **diagnosis.start_values}
    return diagnosis.channel, list(diagnosis.ambiguous_channels)


def _row(variant: str, channel: str, choice) -> list[str]:
    truth = "; ".join(f"{c} <- {v}" for c, v in TRUTH[variant].items()) or "none"
    if choice is None:
        return [variant, truth, f"{channel}: none (the workflow falls back to the diagnosis' leading variable)", "-"]
    chosen = "; ".join(f"{c.channel}: {', '.join(c.inputs)} ({c.explained:.2f}; t {_t_values(c)})"
                       for c in choice.per_channel)
    if choice.through is not None:
        through = choice.through
        chosen = (f"{channel}: {', '.join(choice.inputs)} (through {through.channel}: {', '.join(through.inputs)}, "
                  f"{through.explained:.2f}; t {_t_values(through)})")
    first = choice.per_channel[0]
    rejected = first.rejected
    best = (f"{rejected['variable']} ({rejected['cv_error'] / first.validation_error:.2f}, {rejected['t']:.1f})"
            if rejected else "-")
    return [variant, truth, chosen, best]


def _t_values(choice) -> str:
    return ", ".join(f"{step['t']:.1f}" for step in choice.steps)


if __name__ == "__main__":
    main()
