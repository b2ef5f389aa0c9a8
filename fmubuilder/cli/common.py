"""Argument helpers shared by the commands."""
from __future__ import annotations

import argparse
import math

from ..errors import FmuBuilderError


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
    return values


def parse_floats(items: list[str] | None, option: str) -> dict[str, float]:
    values = {}
    for name, text in parse_assignments(items, option).items():
        try:
            values[name] = float(text)
        except ValueError:
            raise FmuBuilderError(f"{option} {name}={text}: the value must be a number, e.g. {option} {name}=0.05") from None
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
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not a whole number of {unit}") from None
    if value < least:
        raise argparse.ArgumentTypeError(f"{value}: give {least} or more {unit}")
    return value
