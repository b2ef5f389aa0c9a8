"""The batch manifest: a TOML file that lists the cases, each one `hybridize` run.

    [defaults]                      # optional: options for every case
    budget = 10

    [[case]]
    name = "seed-1000"              # its output folder's name
    model = "seed-1000/declared.fmu"
    train = ["seed-1000/train.csv"]
    train_start = { x0 = 1.0 }      # optional; a list of tables gives one per training file
    validation = "seed-1000/validation.csv"   # optional, with validation_start
    test = "seed-1000/test.csv"               # with test_start
    budget = 5                      # any option overrides its default

Paths are relative to the manifest's folder. Every mistake is found here, before any case runs,
and named with its case and key.
"""
from __future__ import annotations

import math
import re
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

from ..data import sidecar_path
from ..errors import FmuBuilderError, suggestion

# hybridize's options by their long name with "_", and the type of value each takes
OPTIONS = {"budget": "count", "seed": "seed", "time_budget": "seconds", "allow_insignificant": "flag",
           "ann_on_term": "flag", "jobs": "processes"}
DATA_KEYS = ("name", "model", "train", "train_start", "validation", "validation_start", "test", "test_start")
CASE_KEYS = (*DATA_KEYS, *OPTIONS)
MAX_SEED = 2**32 - 1
# a case's name is its folder's: no path separators, no hidden or special names
NAME_PATTERN = re.compile(r"[A-Za-z0-9][A-Za-z0-9._+-]*")
RESERVED_NAMES = ("summary.csv", "summary.md", "summary.html")


@dataclass
class Case:
    name: str
    model: Path
    train: list[Path]
    test: Path
    train_start: list[dict] = field(default_factory=list)    # one dict per training file
    validation: Path | None = None
    validation_start: dict = field(default_factory=dict)
    test_start: dict = field(default_factory=dict)
    options: dict = field(default_factory=dict)               # hybridize's, by OPTIONS' names

    def input_files(self) -> list[Path]:
        """The files the case reads: the model, the data and the data's sidecars where they exist."""
        files = [self.model]
        for data in (*self.train, self.validation, self.test):
            if data is not None:
                files.append(data)
                if sidecar_path(data).is_file():
                    files.append(sidecar_path(data))
        return files


def read_manifest(path: str | Path) -> list[Case]:
    """The cases of a manifest, each checked: known keys, values of the right type, input files present."""
    path = Path(path)
    text = _read_text(path)
    try:
        content = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise FmuBuilderError(f"cannot read the manifest {path}: {exc}; write it in TOML as docs/batch.md shows") from None
    where = _Where(path)
    _refuse_unknown(content, ("defaults", "case"), where.top())
    defaults = content.get("defaults", {})
    if not isinstance(defaults, dict):
        raise FmuBuilderError(f"{where.top()}: [defaults] must be a table of options, e.g. [defaults] budget = 10")
    _refuse_unknown(defaults, tuple(OPTIONS), f"{where.top()}, [defaults]")
    default_options = _options(defaults, f"{where.top()}, [defaults]")
    entries = content.get("case")
    if not isinstance(entries, list) or not entries or not all(isinstance(e, dict) for e in entries):
        raise FmuBuilderError(f"{where.top()} lists no cases: add one [[case]] table per case with name, model, "
                              "train and test (see docs/batch.md)")
    cases = [_case(entry, where.case(i, entry), path.parent, default_options) for i, entry in enumerate(entries)]
    _refuse_repeated_names(cases, where)
    return cases


def _read_text(path: Path) -> str:
    if not path.is_file():
        raise FmuBuilderError(f"manifest {path} not found; give the path of a TOML file that lists the cases")
    try:
        return path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise FmuBuilderError(f"cannot read the manifest {path}: {exc}; give a UTF-8 TOML file") from None


class _Where:
    """Names a place in the manifest for an error message."""

    def __init__(self, path: Path):
        self.path = path

    def top(self) -> str:
        return f"manifest {self.path}"

    def case(self, index: int, entry: dict) -> str:
        name = entry.get("name")
        named = f" '{name}'" if isinstance(name, str) else ""
        return f"manifest {self.path}, case{named} (number {index + 1})"


def _case(entry: dict, where: str, folder: Path, default_options: dict) -> Case:
    _refuse_unknown(entry, CASE_KEYS, where)
    for key in ("name", "model", "train", "test"):
        if key not in entry:
            raise FmuBuilderError(f"{where} has no '{key}'; every case needs name, model, train and test")
    name = _name(entry["name"], where)
    train = _paths(entry["train"], "train", where, folder)
    validation = _path(entry["validation"], "validation", where, folder) if "validation" in entry else None
    if "validation_start" in entry and validation is None:
        raise FmuBuilderError(f"{where}: validation_start belongs to a validation file; give validation = \"VAL.csv\" "
                              "or put the start values in train_start")
    return Case(name=name, model=_path(entry["model"], "model", where, folder), train=train,
                test=_path(entry["test"], "test", where, folder), validation=validation,
                train_start=_train_starts(entry.get("train_start", {}), len(train), where),
                validation_start=_starts(entry.get("validation_start", {}), "validation_start", where),
                test_start=_starts(entry.get("test_start", {}), "test_start", where),
                options={**default_options, **_options(entry, where)})


def _refuse_unknown(table: dict, known: tuple[str, ...], where: str) -> None:
    for key in table:
        if key not in known:
            hint = suggestion(key, known)
            raise FmuBuilderError(f"{where}: unknown key '{key}'{hint}; the keys are {', '.join(known)}")


def _name(value, where: str) -> str:
    if not isinstance(value, str) or not NAME_PATTERN.fullmatch(value) or value in RESERVED_NAMES:
        raise FmuBuilderError(f"{where}: name {value!r} cannot be a folder name; use letters, digits and . _ + - "
                              "(not first), e.g. name = \"seed-1000\"")
    return value


def _path(value, key: str, where: str, folder: Path) -> Path:
    if not isinstance(value, str) or not value.strip():
        raise FmuBuilderError(f"{where}: {key} must be a file path in quotes, e.g. {key} = \"data/{key}.csv\"")
    path = folder / value
    if not path.is_file():
        raise FmuBuilderError(f"{where}: {key} {value} not found (paths are relative to the manifest's folder "
                              f"{folder}); check the path")
    return path


def _paths(value, key: str, where: str, folder: Path) -> list[Path]:
    values = [value] if isinstance(value, str) else value
    if not isinstance(values, list) or not values:
        raise FmuBuilderError(f"{where}: {key} must be a file path or a list of them, e.g. {key} = [\"train.csv\"]")
    return [_path(v, key, where, folder) for v in values]


def _train_starts(value, runs: int, where: str) -> list[dict]:
    """A table applies to every training file; a list of tables gives one per file."""
    if isinstance(value, list):
        if len(value) != runs:
            raise FmuBuilderError(f"{where}: train_start lists {len(value)} tables for {runs} training files; give "
                                  "one per file, or one table for all")
        return [_starts(v, "train_start", where) for v in value]
    return [_starts(value, "train_start", where)] * runs


def _starts(value, key: str, where: str) -> dict:
    """NAME = VALUE start values, as the command line's --train-start gives them (the FMU's variable
    types convert them)."""
    if not isinstance(value, dict):
        raise FmuBuilderError(f"{where}: {key} must be a table of start values, e.g. {key} = {{ x0 = 1.0 }}")
    starts = {}
    for name, item in value.items():
        if isinstance(item, bool):
            starts[name] = "true" if item else "false"
        elif isinstance(item, (int, float)) and math.isfinite(item):
            starts[name] = repr(item)
        elif isinstance(item, str) and item.strip():
            starts[name] = item
        else:
            raise FmuBuilderError(f"{where}: {key} {name} = {item!r}: give a finite number, true/false or a string")
    return starts


def _options(table: dict, where: str) -> dict:
    return {key: _option(key, table[key], where) for key in OPTIONS if key in table}


def _option(key: str, value, where: str):
    kind = OPTIONS[key]
    if kind == "flag":
        if not isinstance(value, bool):
            raise FmuBuilderError(f"{where}: {key} = {value!r}: give true or false")
        return value
    if kind == "seconds":
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not (math.isfinite(value) and value > 0):
            raise FmuBuilderError(f"{where}: {key} = {value!r}: give a number of seconds > 0")
        return float(value)
    least, most = {"count": (0, None), "seed": (0, MAX_SEED), "processes": (1, None)}[kind]
    if isinstance(value, bool) or not isinstance(value, int) or value < least or (most is not None and value > most):
        limits = f"from {least} to {most}" if most is not None else f"{least} or more"
        raise FmuBuilderError(f"{where}: {key} = {value!r}: give a whole number, {limits}")
    return value


def _refuse_repeated_names(cases: list[Case], where: _Where) -> None:
    seen = set()
    for case in cases:
        if case.name.lower() in seen:     # one folder on a case-insensitive file system too
            raise FmuBuilderError(f"{where.top()}: two cases are named '{case.name}'; give each case its own name "
                                  "(it names its output folder)")
        seen.add(case.name.lower())
