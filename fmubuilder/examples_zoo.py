"""`fmubuilder example NAME`: a ready-to-use folder with FMUs and measured data.

``vldm`` is the electric-car reference case: the declared vehicle
model, two "truth" variants with an effect the declared model lacks, a parameter-mismatch
variant (the declared model with a heavier car: a wrong parameter, no missing term), and for
each a training set (CADC road cycle) and a test set (WLTC class 2) produced by the test
bench of :mod:`fmubuilder.synth`. The declared model's own data are the control case: a
hybrid model trained on them has nothing to learn. The sensors are filtered, so their noise
is coloured (:data:`SENSOR_NOISE`: a first-order low-pass, correlation about 0.6 between
samples), as in most real data.

``dc_drive`` is the DC speed drive (examples/dc_drive) with truths whose effects no power law of
one variable describes, its runs and data: the README's "Effects no term library holds".

Data sets are cached under ``<cache>/example_data/<hash>/`` keyed by the truth FMU's bytes,
the cycle, the bench settings and the generator's source, so a second call only copies
files. Missing data sets are generated in parallel worker processes.
"""
from __future__ import annotations

import hashlib
import json
import os
import time
import zlib
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

from .data import sidecar_path
from .errors import FmuBuilderError
from .files import copy_atomically, file_sha256, write_atomically
from .progress import counted

# Bump when the layout of cached data changes.
_CACHE_FORMAT = "1"


@dataclass(frozen=True)
class DrivingCycle:
    key: str          # short name used in file names
    number: int       # value of the FMU parameter `parameter` that selects the run
    title: str
    profile: str      # target-speed CSV in examples/vldm/data/cycles (gives the duration), or ""
    role: str         # "train" or "test"
    parameter: str = "cycle"          # VLDM: the cycle (examples/vldm/make_tables.py order)
    duration: float | None = None     # [s] when there is no profile CSV


@dataclass(frozen=True)
class Variant:
    key: str          # short name used in file names
    fmu: str          # example FMU name (fmubuilder.build.example_fmu)
    summary: str
    parameters: tuple[tuple[str, float], ...] = ()   # truth parameters differing from the FMU's

    @property
    def truth_parameters(self) -> dict[str, float]:
        return dict(self.parameters)


VLDM_CYCLES = (
    DrivingCycle("cadc", 1, "CADC road (Artemis road, 100 Hz test-bench profile)", "CADC_Road_100Hz.csv", "train"),
    DrivingCycle("wltc2", 2, "WLTC class 2", "WLTP_class_2_1Hz.csv", "test"),
)

VLDM_VARIANTS = (
    Variant("no_effect", "vldm", "the declared model itself: the control case, the data hold nothing to learn"),
    Variant("extra_resistance", "vldm_truth_extra_resistance",
            "an undeclared speed-dependent driving resistance (the driver compensates it: more energy, same speed)"),
    Variant("extra_loss", "vldm_truth_extra_loss",
            "an undeclared electrical drivetrain loss (more energy, the motion is unchanged)"),
    Variant("mass_mismatch", "vldm",
            "the declared model, but the car is 10 % heavier than declared (mass 1087.35 kg instead of "
            "988.5 kg): a wrong parameter, no missing term", (("mass", 1087.35),)),
)

# Sensor noise of the bundled data: each sensor filters its noise with a first-order low-pass
# of 0.2 s, so that successive 10 Hz samples correlate by about exp(-0.5) = 0.6.
SENSOR_NOISE = dict(noise_model="lowpass", noise_filter_tau=0.2)

# The DC drive (examples/dc_drive): its profile of 30 s, driven `profile_repeats` times.
DC_DRIVE_RUNS = (
    DrivingCycle("twice", 2, "the drive profile twice (60 s)", "", "train", "profile_repeats", 60.0),
    DrivingCycle("thrice", 3, "the drive profile three times (90 s, the winding hotter)", "", "test",
                 "profile_repeats", 90.0),
)
DC_DRIVE_VARIANTS = (
    Variant("no_effect", "dc_drive", "the declared model itself: the control case, the data hold nothing to learn"),
    Variant("windage", "dc_drive_truth_windage", "an undeclared windage torque ~ speed*|speed| in der(speed)"),
    Variant("extra_heating", "dc_drive_truth_extra_heating",
            "an undeclared heat ~ current^2 in der(temperature) only"),
    Variant("stribeck", "dc_drive_truth_stribeck",
            "an undeclared Stribeck friction in der(speed): largest at low speed, fading out at high speed"),
    Variant("coulomb", "dc_drive_truth_coulomb",
            "an undeclared Coulomb friction in der(speed): a sign of the speed smoothed over 1 rad/s"),
    Variant("speed_current_loss", "dc_drive_truth_speed_current_loss",
            "an undeclared electrical loss ~ |speed*current| in der(energy) (and the power equal to it)"),
    Variant("two_effects", "dc_drive_truth_two_effects",
            "the Stribeck friction in der(speed) and the speed-current loss in der(energy) at once"),
)
# The drive's sensors, with noise levels of a lab drive's logger, filtered like the VLDM's.
DC_DRIVE_BENCH = dict(signals=("speed", "current", "power", "energy", "temperature"),
                      noise_std={"speed": 0.1, "current": 0.02, "power": 1.0, "energy": 1.0, "temperature": 0.02},
                      **SENSOR_NOISE)

EXAMPLES = ("dc_drive", "vldm")


@dataclass(frozen=True)
class DataSet:
    variant: Variant
    cycle: DrivingCycle
    stop_time: float
    bench: tuple[tuple[str, object], ...] = tuple(SENSOR_NOISE.items())   # BenchSettings options

    @property
    def file_name(self) -> str:
        return f"{self.variant.key}_{self.cycle.role}_{self.cycle.key}.csv"

    @property
    def start_values(self) -> dict[str, int]:
        return {self.cycle.parameter: self.cycle.number}

    @property
    def seed(self) -> int:
        """A fixed seed per data set, so that no two sets share a noise realisation."""
        return zlib.crc32(self.file_name.encode())


@dataclass
class ExampleFolder:
    path: Path
    fmus: dict[str, Path]            # example FMU name -> file in the folder
    data: dict[str, Path]            # data-set file name -> CSV in the folder
    generation_seconds: float        # time spent simulating (0 when all data came from the cache)


def vldm_data_sets() -> list[DataSet]:
    """Every VLDM data set: each variant on the full training and test cycles."""
    return [DataSet(variant, cycle, cycle_duration(cycle)) for variant in VLDM_VARIANTS for cycle in VLDM_CYCLES]


def dc_drive_data_sets() -> list[DataSet]:
    """Every DC drive data set: each variant on the training and the test run."""
    bench = tuple(DC_DRIVE_BENCH.items())
    return [DataSet(variant, run, run.duration, bench) for variant in DC_DRIVE_VARIANTS for run in DC_DRIVE_RUNS]


# The DC drive truths that are a term of the diagnosis' forms: the missing term's derivative,
# variable, form, and its coefficient as (C constant of examples/dc_drive/model.c, sign, parameter
# dividing it in the derivative).
_DC_DRIVE_TRUTH_TERMS = {
    "windage": ("der(speed)", "speed", "w*|w|", ("WINDAGE", -1.0, "inertia")),
    "extra_heating": ("der(temperature)", "current", "w^2", ("EXTRA_HEATING_RESISTANCE", 1.0, "heat_capacity")),
}


def dc_drive_truth_term(variant: str) -> dict | None:
    """The missing term of a DC drive truth variant as the diagnosis writes a fitted term
    ({"channel", "variable", "basis", "coefficient"}), read from its C definition and the declared
    parameters; None for a variant whose effect is no such term."""
    import re

    from .build import data_path, example_fmu
    from .fmi import read_model_info
    if variant not in _DC_DRIVE_TRUTH_TERMS:
        return None
    channel, variable, basis, (constant, sign, divisor) = _DC_DRIVE_TRUTH_TERMS[variant]
    source = data_path("examples", "dc_drive", "model.c").read_text()
    found = re.search(rf"static const double {constant} = ([-+0-9.eE]+);", source)
    if found is None:
        raise FmuBuilderError(f"examples/dc_drive/model.c defines no {constant}")
    parameter = float(read_model_info(example_fmu("dc_drive")).variables[divisor].start)
    return {"channel": channel, "variable": variable, "basis": basis,
            "coefficient": sign * float(found.group(1)) / parameter}


def example_data_sets(name: str) -> list[DataSet]:
    """The data sets of the example `name` (see EXAMPLES)."""
    return {"vldm": vldm_data_sets, "dc_drive": dc_drive_data_sets}[name]()


def example_variants(name: str) -> tuple[Variant, ...]:
    return {"vldm": VLDM_VARIANTS, "dc_drive": DC_DRIVE_VARIANTS}[name]


def cycle_duration(cycle: DrivingCycle) -> float:
    """Last time stamp of the cycle's target-speed profile [s]."""
    if cycle.duration is not None:
        return cycle.duration
    from .build import repo_root
    path = repo_root() / "examples" / "vldm" / "data" / "cycles" / cycle.profile
    if not path.is_file():
        raise FmuBuilderError(f"cycle profile {path} is missing; restore it from the source tree")
    last = None
    with open(path) as handle:
        for line in handle:
            first = line.split(",", 1)[0].strip()
            if first and not first.startswith("#"):
                last = first
    try:
        return float(last)
    except (TypeError, ValueError):
        raise FmuBuilderError(f"{path} has no time column; restore the cycle profile from the source tree") from None


def write_example(name: str, output: Path, *, force: bool = False, workers: int | None = None) -> ExampleFolder:
    """Write the example ``name`` into the folder ``output`` (created if missing)."""
    if name not in EXAMPLES:
        raise FmuBuilderError(f"unknown example '{name}': choose one of {', '.join(EXAMPLES)}")
    output = Path(output)
    _prepare_folder(output, force)
    from .build import example_fmu

    fmus = {}
    for variant in example_variants(name):
        if variant.fmu in fmus:
            continue
        source = example_fmu(variant.fmu)
        fmus[variant.fmu] = output / source.name
        copy_atomically(source, fmus[variant.fmu])

    started = time.perf_counter()
    sets = example_data_sets(name)
    cached, generated = cached_data(sets, workers=workers)
    seconds = time.perf_counter() - started if generated else 0.0
    data = {}
    for data_set, csv_path in zip(sets, cached):
        data[data_set.file_name] = output / data_set.file_name
        copy_atomically(csv_path, output / data_set.file_name)
        copy_atomically(sidecar_path(csv_path), sidecar_path(output / data_set.file_name))
    readme = _readme(sets, data) if name == "vldm" else _dc_drive_readme(sets)
    write_atomically(output / "README.md", readme)
    print(f"wrote the '{name}' example to {output}/: {len(fmus)} FMUs, {len(data)} data sets"
          + (f" (generated {generated} in {seconds:.0f} s)" if generated else " (data from the cache)"))
    return ExampleFolder(output, fmus, data, seconds)


def _prepare_folder(output: Path, force: bool) -> None:
    if output.exists() and not output.is_dir():
        raise FmuBuilderError(f"{output} is a file; give a folder for the example with -o")
    if output.is_dir() and any(output.iterdir()) and not force:
        raise FmuBuilderError(f"{output} exists and is not empty; choose another folder or pass --force to overwrite its files")
    output.mkdir(parents=True, exist_ok=True)


# ---------------------------------------------------------------------------------------
# Cached generation


def bench_settings(data_set: DataSet):
    from .synth import BenchSettings
    return BenchSettings(seed=data_set.seed, **dict(data_set.bench))


def cached_data(sets: list[DataSet], workers: int | None = None) -> tuple[list[Path], int]:
    """CSV paths of the data sets in the cache, generating the missing ones.
    Returns (paths, number generated now)."""
    from .build import example_fmu
    jobs = [(example_fmu(s.variant.fmu), s) for s in sets]
    paths = [_cache_folder(fmu, s) / s.file_name for fmu, s in jobs]
    missing = [(fmu, s, path) for (fmu, s), path in zip(jobs, paths) if not path.is_file()]
    if len(missing) > 1 and (workers or os.cpu_count() or 1) > 1:
        import multiprocessing
        count = min(len(missing), workers or os.cpu_count() or 1)
        # fork, not spawn: spawn re-imports the caller's main module, which breaks scripts
        # without a __main__ guard; the workers only simulate FMUs, so they need none of
        # the parent's threads.
        with ProcessPoolExecutor(count, mp_context=multiprocessing.get_context("fork")) as pool:
            list(counted(pool.map(_generate, *zip(*missing)), *_GENERATING, total=len(missing)))
    else:
        for job in counted(missing, *_GENERATING):
            _generate(*job)
    return paths, len(missing)


_GENERATING = ("simulating the example's data sets (once; cached)", "data set")


def data_cache_dir() -> Path:
    """Where generated example data are kept: <fmubuilder cache>/example_data."""
    from .build import cache_dir
    return cache_dir() / "example_data"


def _cache_folder(fmu: Path, data_set: DataSet) -> Path:
    key = json.dumps({
        "format": _CACHE_FORMAT, "fmu": file_sha256(fmu), "file": data_set.file_name,
        "truth_parameters": data_set.variant.truth_parameters,
        "stop_time": data_set.stop_time, "start_values": data_set.start_values,
        "bench": bench_settings(data_set).as_dict(), "generator": _generator_source_hash(),
    }, sort_keys=True)
    return data_cache_dir() / hashlib.sha256(key.encode()).hexdigest()[:20]


def _generator_source_hash() -> str:
    """Hash of the code that turns an FMU into data: a change there regenerates the cache."""
    package = Path(__file__).resolve().parent
    digest = hashlib.sha256()
    for path in [package / "synth.py", *sorted((package / "simulation").glob("*.py"))]:
        if path.is_file():
            digest.update(path.name.encode() + b"\0" + path.read_bytes())
    return digest.hexdigest()


def _generate(fmu: Path, data_set: DataSet, target: Path) -> None:
    """Simulate one data set into the cache; its folder appears complete or not at all."""
    from .build import cached_folder
    from .synth import measure, write_measurement

    def simulate_into(staged: Path, scratch: Path) -> None:
        measurement = measure(fmu, stop_time=data_set.stop_time, start_values=data_set.start_values,
                              settings=bench_settings(data_set), truth_parameters=data_set.variant.truth_parameters)
        extra = {"example": {"variant": data_set.variant.key, "effect": data_set.variant.summary,
                             "cycle": data_set.cycle.title, "role": data_set.cycle.role}}
        write_measurement(measurement, staged / target.name, extra_metadata=extra)
    cached_folder(target.parent.parent, target.parent.name, simulate_into)


# ---------------------------------------------------------------------------------------
# README


def consumption_kwh_per_100km(csv_path: Path) -> tuple[float, float]:
    """(distance [km], consumption [kWh/100 km]) from measured speed and energy."""
    import numpy as np
    from .simulation.inputs import read_csv_signals
    time_s, columns = read_csv_signals(csv_path)
    distance_km = float(np.trapezoid(columns["speed"], time_s)) / 1000.0
    energy_kwh = float(columns["energy"][-1] - columns["energy"][0]) / 3.6e6
    return distance_km, 100.0 * energy_kwh / distance_km


def _dc_drive_readme(sets: list[DataSet]) -> str:
    variants = "\n".join(f"- `{v.fmu}.fmu` ({v.key}): {v.summary}." for v in DC_DRIVE_VARIANTS)
    rows = "\n".join(f"| `{s.file_name}` | `{s.variant.fmu}.fmu` | {s.cycle.title} ({s.cycle.role}) | "
                     f"`--start profile_repeats={s.cycle.number}` | {s.stop_time:g} |" for s in sets)
    noise = ", ".join(f"{k} {v:g}" for k, v in DC_DRIVE_BENCH["noise_std"].items())
    return f"""# DC drive example: effects outside a term library

`dc_drive.fmu` is the declared model: a permanent-magnet DC motor whose PI controller holds the
speed on a set-point profile against a load profile (30 s; the parameter `profile_repeats` drives it
several times in a row). The truth FMUs have the same interface but contain physics that
`dc_drive.fmu` lacks; the measured data come from them.

{variants}

Each CSV was made by the test bench of `fmubuilder synth`: {", ".join(DC_DRIVE_BENCH["signals"])}
at about 10 Hz with jittered stamps, 0.1 s sensor lag and noise through a 0.2 s low-pass (standard
deviation of one run: {noise}), averaged over two runs; `<signal>_std` is the spread of the runs.

| file | truth model | run | start option | duration [s] |
|---|---|---|---|---|
{rows}
"""


def _readme(sets: list[DataSet], data: dict[str, Path]) -> str:
    rows = []
    for s in sets:
        distance, consumption = consumption_kwh_per_100km(data[s.file_name])
        changed = "".join(f" with {name}={value:g}" for name, value in s.variant.parameters)
        rows.append(f"| `{s.file_name}` | `{s.variant.fmu}.fmu`{changed} | {s.cycle.title} ({s.cycle.role}) | "
                    f"`--start cycle={s.cycle.number}` | {s.stop_time:g} | {distance:.2f} | {consumption:.2f} |")
    variants = "\n".join(f"- `{v.fmu}.fmu` ({v.key}): {v.summary}." for v in VLDM_VARIANTS)
    roles = {"train": "training", "test": "test"}
    cycles = "\n".join(f"- `cycle={c.number}`: {c.title}, the {roles[c.role]} cycle." for c in VLDM_CYCLES)
    example = sets[1] if len(sets) > 1 else sets[0]
    return f"""# VLDM example: electric Smart fortwo on a chassis dynamometer

`vldm.fmu` is the declared first-principle model (vehicle longitudinal dynamics with a PI
driver following a driving cycle). The truth FMUs have the same interface, but contain physics
that `vldm.fmu` lacks; the measured data come from them.

{variants}

The FMU parameter `cycle` selects the driving cycle:

{cycles}

## Data sets

Each CSV was made by `fmubuilder synth` from the truth FMU named in the table: speed [m/s],
electrical power [W] and cumulative electrical energy [J], logged at about 10 Hz with jittered
time stamps, 0.1 s sensor lag and coloured sensor noise (each sensor's noise passes a 0.2 s
first-order low-pass: successive samples correlate by about 0.6), averaged over two runs. The
`mass_mismatch` data come from `vldm.fmu` itself with a 10 % larger mass; their sidecar names
that mass only under `truth`. The `<signal>_std`
columns are the spread of the two runs (sample standard deviation, ddof=1): an uncertainty,
not a signal. Every CSV has a sidecar `<file>.csv.json` with the truth model, start values,
noise settings and seed.

Simulate or train with the start values of the data set, e.g. for `{example.file_name}`:

    fmubuilder simulate vldm.fmu --start cycle={example.cycle.number} --stop-time {example.stop_time:g} -o sim.csv

| file | truth model | cycle | start option | duration [s] | distance [km] | consumption [kWh/100 km] |
|---|---|---|---|---|---|---|
{chr(10).join(rows)}

Distance and consumption are computed from the measured speed and energy.

The driving cycles inside the FMUs are from the TUMFTM Component Library for Full Vehicle
Simulations (LGPL-3.0) and FMIZoo.jl (based on TUMFTM's VVUQ-Framework, LGPL-2.1).
"""
