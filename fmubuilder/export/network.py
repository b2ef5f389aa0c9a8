"""A frozen network run by onnxruntime, the independent reference for the generated C kernel."""
from __future__ import annotations

import os

import numpy as np

from fmubuilder.errors import FmuBuilderError


class OnnxNetwork:
    """A one-sample ONNX network run by onnxruntime: 1-D float64 array in, 1-D array out."""

    def __init__(self, path: str | os.PathLike):
        import onnxruntime
        options = onnxruntime.SessionOptions()
        options.log_severity_level = 3
        # One thread: no parallel reduction, so the summation order matches the kernel's.
        options.intra_op_num_threads = 1
        options.inter_op_num_threads = 1
        try:
            self.session = onnxruntime.InferenceSession(os.fspath(path), options,
                                                        providers=["CPUExecutionProvider"])
        except Exception as exc:  # missing file, invalid model, ...
            raise FmuBuilderError(f"onnxruntime cannot load {path} ({exc}); give the network written by "
                                  "freeze()") from None
        inputs = self.session.get_inputs()
        if len(inputs) != 1 or len(self.session.get_outputs()) != 1:
            raise FmuBuilderError(f"{path} must have exactly one input and one output tensor; export it with freeze()")
        if inputs[0].type != "tensor(double)":
            raise FmuBuilderError(f"{path} takes {inputs[0].type}, not tensor(double); export it with freeze()")
        self.input_name = inputs[0].name
        self.input_shape = [d if isinstance(d, int) else 1 for d in inputs[0].shape]
        self.n_inputs = int(np.prod(self.input_shape))
        self.n_outputs = self(np.zeros(self.n_inputs)).size

    def __call__(self, values: np.ndarray) -> np.ndarray:
        feed = np.asarray(values, dtype=np.float64).reshape(self.input_shape)
        return np.asarray(self.session.run(None, {self.input_name: feed})[0], dtype=np.float64).ravel()


def onnx_io_sizes(path: str | os.PathLike) -> tuple[int, int]:
    """(number of input values, number of output values) of a one-sample ONNX network.

    The output size is found by running the network once on zeros, since exporters do not
    always record the output shape in the graph.
    """
    network = OnnxNetwork(path)
    return network.n_inputs, network.n_outputs
