"""A case as the executors run it."""
from __future__ import annotations

import shutil
from dataclasses import dataclass, field
from pathlib import Path

from ..files import staging_folder
from .manifest import Case


@dataclass
class Job:
    case: Case
    key: str                 # case_key: what a re-run compares
    argv: list[str]          # its hybridize command, with its own input files
    folder: Path             # OUT/<name>, where its results are published
    side_by_side: int = 1    # cases running at once (the case's command runs with --jobs 1 then)
    call_timeout: float = 60.0
    _staging: Path | None = field(default=None, repr=False)

    def staging(self) -> Path:
        """The hidden folder beside OUT/<name> that the case is written into, made on first use."""
        if self._staging is None:
            self._staging = staging_folder(self.folder)
        return self._staging

    def discard(self) -> None:
        """Remove the staged folder if it was not published (a batch that stopped early)."""
        if self._staging is not None:
            shutil.rmtree(self._staging, ignore_errors=True)
