"""File output shared by the export steps."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

from fmubuilder.errors import FmuBuilderError


def write_atomically(target: str | os.PathLike, data: bytes | str) -> Path:
    """Write `data` to `target` via a temporary file in the same directory and os.replace.

    Readers (and a crash half-way) never see a partial file.
    """
    target = Path(target)
    if not target.parent.is_dir():
        raise FmuBuilderError(f"cannot write {target}: directory {target.parent} does not exist; create it first")
    payload = data.encode("utf-8") if isinstance(data, str) else data
    fd, tmp_name = tempfile.mkstemp(dir=target.parent, prefix=f".{target.name}.", suffix=".tmp")
    try:
        # mkstemp creates 0600; give the file the permissions of an ordinary new file.
        os.fchmod(fd, 0o644)
        with os.fdopen(fd, "wb") as tmp:
            tmp.write(payload)
            tmp.flush()
            os.fsync(tmp.fileno())
        os.replace(tmp_name, target)
    except BaseException:
        Path(tmp_name).unlink(missing_ok=True)
        raise
    return target
