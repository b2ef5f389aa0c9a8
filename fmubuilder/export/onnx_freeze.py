"""Freeze a trained torch network into a float64 ONNX file, checked against torch with onnxruntime.

The ONNX file is the hand-over point between training and code generation: everything after it
(the C kernel, the exported FMU) is derived from the file alone, so it must reproduce the torch
network to float64 round-off before it is written.
"""

from __future__ import annotations

import copy
import io
import os
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from fmubuilder.errors import FmuBuilderError
from fmubuilder.files import write_atomically

if TYPE_CHECKING:
    import torch

INPUT_NAME = "input"
OUTPUT_NAME = "output"
# Opset 17 is read by every onnxruntime >= 1.13 and covers all operators an MLP needs.
OPSET = 17
# Agreement required between onnxruntime and torch, relative to max(1, largest |output| over the
# samples): float64 round-off of differently ordered sums stays orders of magnitude below this. Not
# relative to each output: an output near zero comes out of sums of terms as large as the others'.
CHECK_TOLERANCE = 1e-12
# A network's own round-off can exceed that: the VLDM's NeuralFMU shifts its input by 32,087 and
# scales its output by 324, so that outputs of 0.2 carry a float64 round-off of about 1e-12 (1.01e-12
# between onnxruntime and torch). The check allows ROUND_OFF_FACTOR times the round-off the network
# shows, estimated from its float32 evaluation: |float32 - float64| * eps64 / eps32. A traced branch
# or randomness differs by the size of the outputs, far above either bound.
ROUND_OFF_FACTOR = 100.0
# Random inputs (standard normal, seeded) on which onnxruntime and torch are compared.
CHECK_SAMPLES = 256


@dataclass(frozen=True)
class FrozenNetwork:
    """A network written to `path` as ONNX, with input shape [1, n_inputs] and output [1, n_outputs]."""

    path: Path
    n_inputs: int
    n_outputs: int
    max_abs_diff: float  # largest |onnxruntime - torch| over the check samples


def freeze(module: torch.nn.Module, n_inputs: int, path: str | os.PathLike) -> FrozenNetwork:
    """Export `module` (one sample of `n_inputs` values in, a vector out) to ONNX in float64.

    The ONNX model is run with onnxruntime on CHECK_SAMPLES random inputs and compared with the
    torch network before the file is written atomically. `module` itself is left untouched (a
    float64 copy is exported).
    """
    import torch  # deferred: importing fmubuilder.export must not load torch

    _check_arguments(module, n_inputs)
    network = copy.deepcopy(module).to(torch.float64).eval()
    n_outputs = _probe_outputs(network, n_inputs)
    onnx_bytes = _export(network, n_inputs)
    samples = np.random.default_rng(0).standard_normal((CHECK_SAMPLES, n_inputs))
    max_abs_diff = _check_against_torch(network, onnx_bytes, samples)
    target = Path(path)
    write_atomically(target, onnx_bytes)
    return FrozenNetwork(target, n_inputs, n_outputs, max_abs_diff)


def _check_arguments(module, n_inputs):
    import torch

    if not isinstance(module, torch.nn.Module):
        raise FmuBuilderError(f"freeze() needs a torch.nn.Module, got {type(module).__name__}")
    if isinstance(n_inputs, bool) or not isinstance(n_inputs, int) or n_inputs < 1:
        raise FmuBuilderError(f"n_inputs must be a positive integer, got {n_inputs!r}")


def _probe_outputs(network: torch.nn.Module, n_inputs: int) -> int:
    """Run the network once on a [1, n_inputs] input and return its number of outputs."""
    import torch

    try:
        with torch.no_grad():
            out = network(torch.zeros(1, n_inputs, dtype=torch.float64))
    except Exception as exc:  # the user's forward() can raise anything
        raise FmuBuilderError(
            f"the network does not accept an input of shape [1, {n_inputs}] ({exc}); "
            "pass the number of inputs its first layer expects") from exc
    if not isinstance(out, torch.Tensor):
        raise FmuBuilderError(
            f"the network returns {type(out).__name__}, not one tensor; wrap it so forward() returns one tensor")
    return int(out.numel())


def _export(network: torch.nn.Module, n_inputs: int) -> bytes:
    """ONNX bytes from the TorchScript exporter.

    The torch.export-based exporter (dynamo=True, the default since torch 2.9) needs the optional
    onnxscript package; the TorchScript exporter does not and produces the same plain Gemm/MatMul
    graphs for MLPs, so it is used explicitly. Its deprecation warning is silenced on purpose.
    """
    import torch

    buffer = io.BytesIO()
    dummy = torch.zeros(1, n_inputs, dtype=torch.float64)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            torch.onnx.export(network, (dummy,), buffer, dynamo=False, export_params=True, opset_version=OPSET,
                              do_constant_folding=True, input_names=[INPUT_NAME], output_names=[OUTPUT_NAME])
    except Exception as exc:  # exporter errors come in many types
        raise FmuBuilderError(
            f"torch could not export the network to ONNX ({exc}); use only standard layers "
            "(Linear, Tanh, Sigmoid, ReLU, elementwise scaling) in forward()") from exc
    return buffer.getvalue()


def _check_against_torch(network: torch.nn.Module, onnx_bytes: bytes, samples: np.ndarray) -> float:
    """Largest |onnxruntime - torch| over the samples; raises if above tolerance."""
    import onnxruntime
    import torch

    options = onnxruntime.SessionOptions()
    options.log_severity_level = 3
    session = onnxruntime.InferenceSession(onnx_bytes, options, providers=["CPUExecutionProvider"])
    expected, actual = [], []
    with torch.no_grad():
        for sample in samples:
            x = sample.reshape(1, -1)
            torch_out = network(torch.from_numpy(x)).numpy().ravel()
            onnx_out = np.asarray(session.run(None, {INPUT_NAME: x})[0], dtype=np.float64).ravel()
            if onnx_out.shape != torch_out.shape:
                raise FmuBuilderError(
                    f"the ONNX export returns {onnx_out.size} values but the network {torch_out.size}; "
                    "make forward() return one tensor without data-dependent shapes")
            expected.append(torch_out)
            actual.append(onnx_out)
    expected, actual = np.array(expected), np.array(actual)
    diff = np.abs(actual - expected)
    allowed = max(CHECK_TOLERANCE * max(1.0, float(np.nanmax(np.abs(expected), initial=0.0))),
                  ROUND_OFF_FACTOR * _float64_round_off(network, samples, expected))
    # NaN == NaN counts as agreement: both sides propagate it the same way.
    bad = (diff > allowed) | (np.isnan(actual) != np.isnan(expected))
    if np.any(bad):
        first = int(np.flatnonzero(bad.any(axis=1))[0])
        raise FmuBuilderError(
            f"the ONNX export disagrees with the torch network (|diff| = {np.max(diff[first]):.3g} "
            f"at input {samples[first].ravel().tolist()}); remove data-dependent control flow and "
            "randomness from forward()")
    return float(np.nanmax(diff, initial=0.0))


def _float64_round_off(network: torch.nn.Module, samples: np.ndarray, expected: np.ndarray) -> float:
    """The network's float64 round-off over the samples, estimated from its float32 evaluation
    (0 where the network does not run in float32, e.g. float64 constants made in forward())."""
    import torch

    try:
        with torch.no_grad():
            single = copy.deepcopy(network).to(torch.float32)
            outputs = np.array([single(torch.from_numpy(x.reshape(1, -1).astype(np.float32))).numpy().ravel()
                                for x in samples], dtype=np.float64)
    except (RuntimeError, TypeError):
        return 0.0
    difference = np.abs(outputs.reshape(expected.shape) - expected)
    difference = difference[np.isfinite(difference)]        # float32 overflow says nothing
    ratio = np.finfo(np.float64).eps / np.finfo(np.float32).eps
    return float(np.nanmax(difference, initial=0.0)) * ratio

