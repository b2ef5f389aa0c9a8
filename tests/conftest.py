"""Shared fixtures: example FMUs built on demand (cached between runs).

The suite runs on every core (pytest-xdist, `-n auto --dist loadgroup` in pyproject.toml):
- one worker per core, at most MAX_AUTO_WORKERS, each keeping torch (and the OpenMP/BLAS pools
  of what it starts) to one thread, so a machine with many cores runs single-threaded workers,
  not that many squared threads;
- the tests that share a module-scoped fixture (a build, a data set, a training) run on one
  worker, so the fixture is made once; every other test goes to whichever worker is free."""
import os

import pytest

ONE_THREAD = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS")
SHARED_SCOPES = ("module", "package", "class")


MAX_AUTO_WORKERS = 8   # each worker holds torch and the FMUs (about 1 GB): more cores than this rarely help


def pytest_xdist_auto_num_workers(config):
    """`-n auto`: one worker per core this process may use, at most MAX_AUTO_WORKERS."""
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    return max(1, min(cores, MAX_AUTO_WORKERS))


def pytest_configure(config):
    if os.environ.get("PYTEST_XDIST_WORKER"):
        for variable in ONE_THREAD:
            os.environ.setdefault(variable, "1")    # read when torch/numpy start their pools
        import torch
        torch.set_num_threads(1)


@pytest.hookimpl(tryfirst=True)     # before xdist reads the groups into the test ids
def pytest_collection_modifyitems(config, items):
    if not os.environ.get("PYTEST_XDIST_WORKER"):   # only the workers' collection is scheduled
        return
    for item in items:
        if _uses_shared_fixture(item):
            item.add_marker(pytest.mark.xdist_group(item.nodeid.split("::")[0]))


def _uses_shared_fixture(item) -> bool:
    definitions = getattr(item, "_fixtureinfo", None)
    if definitions is None:
        return False
    return any(chain[-1].scope in SHARED_SCOPES for chain in definitions.name2fixturedefs.values() if chain)


@pytest.fixture(scope="session")
def bouncing_ball_fmu():
    from fmubuilder.build import example_fmu
    return example_fmu("bouncing_ball")
