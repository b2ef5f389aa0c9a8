"""Many cases through `hybridize`: a manifest lists them, each runs in a process of its own (local
processes or Ray tasks), a summary compares them, and a re-run skips the cases already done."""
from __future__ import annotations

from .manifest import Case, read_manifest
from .run import BatchResult, run_batch

__all__ = ["BatchResult", "Case", "read_manifest", "run_batch"]
