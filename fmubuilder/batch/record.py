"""What a case folder holds and whether a re-run may skip it.

Each case folder carries `case.json`: the case's key (a hash of its input files' contents, their
roles, start values and options), its status, its failure reason and its time. A re-run skips a
case whose folder is complete (status ok, the report and, when the report says one was shipped,
the hybrid FMU in place) under the same key; it reruns a failed or unfinished one. A completed
case whose inputs or options changed since is redone only with --force.
"""
from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path

from ..data import sidecar_path
from ..errors import FmuBuilderError
from ..files import file_sha256, foreign_content, kind_of
from .case import HYBRID_NAME, REPORT_NAME, Outcome
from .manifest import Case

RECORD_NAME = "case.json"
RECORD_FORMAT = "fmubuilder-batch-case/1"


def case_key(case: Case) -> str:
    """A hash of everything that decides the case's results: each input file's content in its role,
    the start values and the options (not the case's name, not where the files lie)."""
    roles = [("model", case.model), *(("train", p) for p in case.train),
             *([("validation", case.validation)] if case.validation else []), ("test", case.test)]
    sidecars = [(f"{role} sidecar", sidecar_path(path)) for role, path in roles if role != "model"]
    content = {
        "files": [[role, file_sha256(path) if path.is_file() else None] for role, path in [*roles, *sidecars]],
        "starts": {"train": case.train_start, "validation": case.validation_start, "test": case.test_start},
        "options": case.options,
    }
    return hashlib.sha256(json.dumps(content, sort_keys=True).encode()).hexdigest()


def record(case: Case, key: str, outcome: Outcome, command: str) -> dict:
    return {"format": RECORD_FORMAT, "name": case.name, "key": key, "status": outcome.status,
            "reason": outcome.reason, "seconds": round(outcome.seconds, 3), "command": command}


def read_record(folder: Path) -> dict | None:
    try:
        found = json.loads((folder / RECORD_NAME).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return found if isinstance(found, dict) and found.get("format") == RECORD_FORMAT else None


def read_report(folder: Path) -> dict | None:
    try:
        return json.loads((folder / REPORT_NAME / "report.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None


@dataclass
class Found:
    """What a case's output folder holds: "absent", "done" (complete, same key), "changed" (complete,
    but its inputs or options changed since), or "unfinished" (failed, cut short, never recorded)."""
    state: str
    record: dict | None = None


def inspect_folder(folder: Path, key: str) -> Found:
    if kind_of(folder) is None:
        return Found("absent")
    found = read_record(folder)
    if not _complete(folder, found):
        return Found("unfinished", found)
    return Found("done" if found["key"] == key else "changed", found)


def _complete(folder: Path, found: dict | None) -> bool:
    if not found or found.get("status") != "ok":
        return False
    report = read_report(folder)
    if report is None:
        return False
    return not report.get("hybrid_fmu") or (folder / HYBRID_NAME).is_file()


def refuse_replacing(folder: Path, found: Found, force: bool) -> None:
    """An error, before any work, unless the case folder may be replaced by a new run of its case: a
    folder fmubuilder wrote, unchanged since, and with --force when it holds a completed case."""
    if found.state == "absent":
        return
    if kind_of(folder) != "folder":
        raise FmuBuilderError(f"{folder} is a {kind_of(folder)}, not a case folder; move it away or choose "
                              "another output folder")
    why = foreign_content(folder)
    if why:
        raise FmuBuilderError(f"will not replace the case folder {folder}: {why}; move it away or choose another "
                              "output folder")
    if found.state == "changed" and not force:
        raise FmuBuilderError(f"case '{folder.name}': its input files, start values or options changed since "
                              f"{folder} was written; pass --force to redo it (its results are replaced when "
                              "the new run ends) or choose another output folder")
