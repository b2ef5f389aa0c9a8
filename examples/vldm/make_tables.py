#!/usr/bin/env python3
"""Convert the VLDM data files in data/ into C headers of static const arrays.

    python3 examples/vldm/make_tables.py        # rewrites cycles_table.h and maps_table.h

The generated headers are committed, so building the FMU needs no Python step; run this
script only after changing a CSV file. It uses the standard library only.

Driving cycles are stored on their uniform time grid (start time, step, speeds) so that
the model finds the interval by division instead of a search. Every value is written with
Python's shortest round-trip representation, so the headers reproduce the CSV numbers exactly.

The CADC road 100 Hz profile is stored in full: it is not a linear interpolation of 1 Hz
data. Its slope changes at about 76000 of its 110143 samples (the profile is curved within
most seconds), so keeping only slope breakpoints would not shrink it.
"""
import csv
import math
from pathlib import Path

HERE = Path(__file__).resolve().parent
DATA = HERE / "data"

# The order defines the value of the Integer parameter `cycle` (1-based); keep it in sync
# with README.md and the description of `cycle` in modelDescription.xml.
CYCLES = [
    ("CADC_ROAD_100HZ", "CADC_Road_100Hz.csv"),
    ("WLTC_CLASS_2", "WLTP_class_2_1Hz.csv"),
    ("WLTC_CLASS_3", "WLTP_class_3_1Hz.csv"),
    ("ARTEMIS_URBAN", "EUROPE_ARTEMIS_URBAN_1Hz.csv"),
    ("ARTEMIS_ROAD", "EUROPE_ARTEMIS_ROAD_1Hz.csv"),
    ("ARTEMIS_MOTORWAY_130", "EUROPE_ARTEMIS_MOTORWAY_130_1Hz.csv"),
    ("NEDC", "EUROPE_NEDC_1Hz.csv"),
    ("FTP_75", "USA_FTP_75_1Hz.csv"),
    ("FTP_HIGHWAY", "USA_FTP_HIGHWAY_1Hz.csv"),
    ("US06", "USA_SFTP_US06_1Hz.csv"),
    ("JAPAN_10_15", "JAPAN_10_15_MODE_1Hz.csv"),
]

VALUES_PER_LINE = 8


def read_rows(path):
    """Numeric rows of a CSV file, skipping '#' comment lines and a text header line."""
    rows = []
    with open(path, newline="") as f:
        for row in csv.reader(f):
            if not row or row[0].startswith("#"):
                continue
            try:
                rows.append([float(cell) for cell in row])
            except ValueError:
                continue  # the column-name header
    return rows


def c_array(name, values):
    lines = []
    for start in range(0, len(values), VALUES_PER_LINE):
        chunk = values[start:start + VALUES_PER_LINE]
        lines.append("    " + ", ".join(repr(float(v)) for v in chunk) + ",")
    return f"static const double {name}[{len(values)}] = {{\n" + "\n".join(lines) + "\n};\n"


def uniform_step(times, path):
    """The constant sample step of a cycle; refuses files that are not uniformly sampled."""
    step = (times[-1] - times[0]) / (len(times) - 1)
    for i, t in enumerate(times):
        if abs(t - (times[0] + i * step)) > 1e-9:
            raise SystemExit(f"{path}: sample {i} at t={t} is off the uniform {step} s grid")
    return round(step, 12)


def cycles_header():
    parts = [header_comment("driving cycles (target speed [m/s] on a uniform time grid)")]
    entries = []
    for name, file in CYCLES:
        path = DATA / "cycles" / file
        rows = read_rows(path)
        times = [r[0] for r in rows]
        speeds = [r[1] for r in rows]
        step = uniform_step(times, path)
        parts.append(f"/* {file}: {len(rows)} samples, t = {times[0]:g} .. {times[-1]:g} s */\n")
        parts.append(c_array(f"CYCLE_{name}", speeds))
        entries.append(f"    {{\"{name}\", {times[0]!r}, {step!r}, {len(rows)}, CYCLE_{name}}},")
    parts.append(
        "typedef struct {\n"
        "    const char *name;\n"
        "    double start_time; /* [s] time of speed[0] */\n"
        "    double step;       /* [s] uniform sample step */\n"
        "    int length;\n"
        "    const double *speed; /* [m/s] */\n"
        "} CycleTable;\n\n"
        f"#define N_CYCLES {len(CYCLES)}\n\n"
        "/* Indexed by the parameter `cycle` minus 1. */\n"
        "static const CycleTable CYCLES[N_CYCLES] = {\n" + "\n".join(entries) + "\n};\n")
    return guard("VLDM_CYCLES_TABLE_H", "".join(parts))


def curve(path, name):
    rows = read_rows(path)
    return (c_array(f"{name}_OMEGA", [r[0] for r in rows])
            + c_array(f"{name}_TORQUE", [r[1] for r in rows])
            + f"#define {name}_LENGTH {len(rows)}\n\n")


def grid_map(path, name, row_axis, column_axis):
    """A CombiTable2D-style map: first row = column axis, first column = row axis."""
    rows = read_rows(path)
    columns = rows[0][1:]
    speeds = [r[0] for r in rows[1:]]
    values = [v for r in rows[1:] for v in r[1:]]
    if any(len(r) != len(columns) + 1 for r in rows[1:]):
        raise SystemExit(f"{path}: rows have different lengths")
    if any(math.isnan(v) for v in values):
        raise SystemExit(f"{path}: contains empty cells")
    return (f"/* {path.name}: {len(speeds)} x {len(columns)}, row axis {row_axis},"
            f" column axis {column_axis}, values row-major */\n"
            + c_array(f"{name}_OMEGA", speeds)
            + c_array(f"{name}_TORQUE", columns)
            + c_array(f"{name}_VALUES", values)
            + f"#define {name}_ROWS {len(speeds)}\n#define {name}_COLUMNS {len(columns)}\n\n")


def maps_header():
    maps = DATA / "maps"
    body = (header_comment("motor and power-electronics maps")
            + "/* Full-load (maximum) motor torque [N.m] over motor speed [rad/s]. */\n"
            + curve(maps / "motor_full_load.csv", "FULL_LOAD")
            + "/* Minimum (regenerative) motor torque [N.m] over motor speed [rad/s]. */\n"
            + curve(maps / "motor_min_load.csv", "MIN_LOAD")
            + "/* Electrical motor power [W] = f(motor speed [rad/s], torque [N.m]). */\n"
            + grid_map(maps / "motor_electric_power.csv", "MOTOR_POWER", "omega [rad/s]",
                       "torque [N.m]")
            + "/* Power-electronics loss [W] = f(motor speed [rad/s], |torque| [N.m]). */\n"
            + grid_map(maps / "power_electronics_loss.csv", "PE_LOSS", "omega [rad/s]",
                       "|torque| [N.m]"))
    return guard("VLDM_MAPS_TABLE_H", body)


def header_comment(what):
    return (f"/* VLDM {what}.\n"
            " * Generated by make_tables.py from the files in data/ (see NOTICE for their\n"
            " * source and licence). Do not edit; rerun the script instead. */\n\n")


def guard(macro, body):
    return f"#ifndef {macro}\n#define {macro}\n\n{body}\n#endif\n"


def main():
    (HERE / "cycles_table.h").write_text(cycles_header())
    (HERE / "maps_table.h").write_text(maps_header())


if __name__ == "__main__":
    main()
