"""The network reads its inputs at the current point even from FMUs that evaluate lazily:
an output read after fmi2GetDerivatives may be that of the previous point there (OpenModelica
1.18 does this), so the exported wrapper and the Python reference read the network's inputs
before the original's derivatives. Checked against the test FMU's analytic output y = 2 x."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from fmubuilder.build import build_cmake_project
from fmubuilder.export.network import OnnxNetwork
from fmubuilder.export.reference import HybridReference
from fmubuilder.fmi import Fmu

from .test_wrapper import make_hybrid, started

HERE = Path(__file__).resolve().parent
STATES = [1.0, 3.0, -2.0, 0.25, 0.25, 7.5]


@pytest.fixture(scope="module")
def lazy(tmp_path_factory):
    build = build_cmake_project(HERE / "lazy_outputs", tmp_path_factory.mktemp("lazy_build"))
    original = build.fmus()[0]
    spec, hybrid = make_hybrid(tmp_path_factory.mktemp("lazy"), original, ["der(x)"], ["y"], seed=11)
    return spec, hybrid


def expected_derivative(spec, x: float) -> float:
    """der(x) of the hybrid with the original's own output y = 2 x at this point."""
    return -0.5 * x + OnnxNetwork(spec.onnx)(np.array([2.0 * x]))[0]


def test_the_test_fmu_is_lazy(lazy):
    spec, _ = lazy
    with Fmu(spec.original_fmu) as fmu:
        instance = started(fmu.instantiate())
        instance.set_continuous_states(np.array([1.0]))
        assert instance.get(["y"]) == [2.0]
        instance.set_continuous_states(np.array([3.0]))
        instance.get_derivatives()
        assert instance.get(["y"]) == [2.0]    # stale: the value at x = 1
        instance.free()


def test_exported_wrapper_reads_the_current_output(lazy):
    spec, hybrid = lazy
    with Fmu(hybrid) as fmu:
        instance = started(fmu.instantiate())
        for x in STATES:
            instance.set_continuous_states(np.array([x]))
            assert instance.get_derivatives()[0] == pytest.approx(expected_derivative(spec, x), rel=1e-13)
            instance.set_continuous_states(np.array([x]))
            assert instance.get(["der(x)"])[0] == pytest.approx(expected_derivative(spec, x), rel=1e-13)
        instance.free()


def test_reference_reads_the_current_output(lazy):
    spec, _ = lazy
    with Fmu(spec.original_fmu) as original:
        reference = HybridReference(original, spec, variables=["x"])
        reference.initialize(0.0, 1.0)
        for t, x in enumerate(STATES):
            derivative = reference.derivatives(0.1 * t, np.array([x]))[0]
            assert derivative == pytest.approx(expected_derivative(spec, x), rel=1e-13)
        reference.close()
