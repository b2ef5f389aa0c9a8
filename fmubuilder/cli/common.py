"""Argument helpers shared by the commands."""
from __future__ import annotations

import argparse
import math

from ..errors import FmuBuilderError

EXIT_INTERRUPTED = 130      # as a shell reports a process ended by SIGINT (128 + 2)
EXIT_TERMINATED = 143       # ... and by SIGTERM (128 + 15)


def guide(page: str, section: str | None = None) -> str:
    """The epilog of a command's --help: the documentation page that explains it (paths in the
    fmubuilder source tree)."""
    where = f"{page}, section \"{section}\"" if section else page
    return f"Guide: {where} (in the fmubuilder source)."


def parse_assignments(items: list[str] | None, option: str = "--start") -> dict[str, str]:
    """Parse repeated NAME=VALUE options into a dict (values stay strings; the FMU's
    variable types decide their conversion)."""
    values = {}
    for item in items or []:
        name, sep, value = item.partition("=")
        if not sep or not name.strip() or not value.strip():
            raise FmuBuilderError(f"malformed {option} '{item}': write {option} NAME=VALUE, e.g. {option} mass=1000")
        values[name.strip()] = value.strip()
    return check_assignment_numbers(values, option)


def parse_floats(items: list[str] | None, option: str) -> dict[str, float]:
    values = {}
    for name, text in parse_assignments(items, option).items():
        try:
            values[name] = float(text)
            if not math.isfinite(values[name]):
                raise ValueError
        except ValueError:
            raise FmuBuilderError(f"{option} {name}={text}: the value must be a number (finite), e.g. {option} {name}=0.05") from None
    return values


def parse_names(text: str | None, option: str = "--variables") -> list[str] | None:
    if text is None:
        return None
    names = [n.strip() for n in text.split(",") if n.strip()]
    if not names:
        raise FmuBuilderError(f"empty {option} list: give comma-separated names, e.g. {option} h,v")
    return names


def positive(value: float, option: str) -> float:
    if not (math.isfinite(value) and value > 0):
        raise FmuBuilderError(f"{option} {value:g}: give a positive number")
    return value


def loss_evaluations(text: str) -> int:
    """--budget: a whole number of loss evaluations, 0 or more."""
    return _whole_number(text, 0, "loss evaluations")


def processes(text: str) -> int:
    """--jobs: a whole number of processes, 1 or more."""
    return _whole_number(text, 1, "processes")


def _whole_number(text: str, least: int, unit: str) -> int:
    of = f" of {unit}" if unit else ""
    try:
        if "_" in text:
            raise ValueError
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not a whole number{of}") from None
    if value < least:
        raise argparse.ArgumentTypeError(f"{value}: give {least} or more{' ' + unit if unit else ''}")
    return value


# -- option types: numbers written as numbers, in their range -----------------------------------

MAX_SEED = 2**32 - 1


def plain_number(text: str) -> float:
    """A decimal number as a user writes one: Python's float() also reads '1_000', which is a typo
    more often than a thousand; refused here."""
    if "_" in text:
        raise argparse.ArgumentTypeError(f"'{text}' is not a number (write it without '_', e.g. 1000)")
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not a number") from None


def number(text: str) -> float:
    """Any finite number."""
    value = plain_number(text)
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"'{text}': give a finite number")
    return value


def positive_number(text: str) -> float:
    value = number(text)
    if not value > 0:
        raise argparse.ArgumentTypeError(f"{value:g}: give a number > 0")
    return value


def non_negative_number(text: str) -> float:
    value = number(text)
    if not value >= 0:
        raise argparse.ArgumentTypeError(f"{value:g}: give a number >= 0")
    return value


def fraction(text: str) -> float:
    """A factor in (0, 1], e.g. a learning-rate decay per epoch."""
    value = number(text)
    if not 0 < value <= 1:
        raise argparse.ArgumentTypeError(f"{value:g}: give a number in (0, 1]")
    return value


def whole_number(least: int, most: int | None = None, unit: str = ""):
    """An argparse type: a whole number in [least, most]."""
    def parse(text: str) -> int:
        value = _whole_number(text, least, unit)
        if most is not None and value > most:
            raise argparse.ArgumentTypeError(f"{value}: give at most {most}{' ' + unit if unit else ''}")
        return value
    return parse


seed = whole_number(0, MAX_SEED)


def check_assignment_numbers(values: dict[str, str], option: str) -> dict[str, str]:
    """NAME=VALUE pairs whose VALUE is a number only by Python's reading of '_' (1_000) are refused."""
    for name, text in values.items():
        if "_" in text:
            try:
                float(text)
            except ValueError:
                continue  # a string value, e.g. a file name: the variable's type decides
            raise FmuBuilderError(f"{option} {name}={text}: write the number without '_' (e.g. {text.replace('_', '')})")
    return values
