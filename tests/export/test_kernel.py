"""The generated C kernel against onnxruntime running the same ONNX model."""

from __future__ import annotations

import subprocess
from pathlib import Path

import cffi
import numpy as np
import onnx
import onnxruntime
import pytest
import torch
from onnx import TensorProto, helper, numpy_helper

from fmubuilder.errors import FmuBuilderError
from fmubuilder.export import SUPPORTED_OPS, freeze, generate_kernel

# onnxruntime is the reference; both sides compute in float64, differing only in round-off
# (e.g. fused multiply-adds and libm versus vectorised tanh/exp).
RTOL = 1e-13
ATOL = 1e-13
N_SAMPLES = 300

# Warnings are errors: the generated code must be clean, strictly conforming C99.
CFLAGS = ["-std=c99", "-O2", "-Wall", "-Wextra", "-pedantic", "-Werror"]


class KernelLibrary:
    """Shared library built from one or more generated kernels, called through cffi (ABI mode)."""

    def __init__(self, kernels, directory: Path):
        sources = [kernel.write(directory)[1] for kernel in kernels]
        library = directory / "libkernels.so"
        subprocess.run(
            ["gcc", *CFLAGS, "-shared", "-fPIC", "-o", str(library), *map(str, sources), "-lm"],
            check=True,
            capture_output=True,
            text=True,
        )
        self.ffi = cffi.FFI()
        self.ffi.cdef("".join(f"void {k.prefix}_run(const double *input, double *output);\n" for k in kernels))
        self.lib = self.ffi.dlopen(str(library))
        self.kernels = {k.prefix: k for k in kernels}

    def run(self, prefix: str, x: np.ndarray) -> np.ndarray:
        kernel = self.kernels[prefix]
        x = np.ascontiguousarray(x, dtype=np.float64).ravel()
        assert x.size == kernel.n_inputs
        out = np.empty(kernel.n_outputs)
        getattr(self.lib, f"{prefix}_run")(
            self.ffi.from_buffer("double[]", x), self.ffi.from_buffer("double[]", out)
        )
        return out


@pytest.fixture
def build_library(tmp_path):
    """build_library(kernel, ...) -> KernelLibrary compiled in a fresh directory."""

    def build(*kernels) -> KernelLibrary:
        return KernelLibrary(kernels, tmp_path)

    return build


def onnxruntime_outputs(model: onnx.ModelProto | str | Path, inputs: np.ndarray) -> np.ndarray:
    """Reference: run the ONNX model with onnxruntime on each row of `inputs` (one sample per call)."""
    source = model.SerializeToString() if isinstance(model, onnx.ModelProto) else str(model)
    session = onnxruntime.InferenceSession(source, providers=["CPUExecutionProvider"])
    graph_input = session.get_inputs()[0]
    shape = [d if isinstance(d, int) else 1 for d in graph_input.shape]
    return np.array([session.run(None, {graph_input.name: x.reshape(shape)})[0].ravel() for x in inputs])


ACTIVATIONS = {
    "tanh": torch.nn.Tanh,
    "sigmoid": torch.nn.Sigmoid,
    "relu": torch.nn.ReLU,
    "identity": torch.nn.Identity,
}


class Normalize(torch.nn.Module):
    """Elementwise pre-processing (x - shift) / scale, with the constants as buffers."""

    def __init__(self, shift: torch.Tensor, scale: torch.Tensor):
        super().__init__()
        self.register_buffer("shift", shift)
        self.register_buffer("scale", scale)

    def forward(self, x):
        return (x - self.shift) / self.scale


class Denormalize(torch.nn.Module):
    """Elementwise post-processing y * scale + shift, with a scalar scale (ONNX Constant node)."""

    def __init__(self, scale: float, shift: torch.Tensor):
        super().__init__()
        self.scale = scale
        self.register_buffer("shift", shift)

    def forward(self, y):
        return y * self.scale + self.shift


class VectorLinear(torch.nn.Module):
    """Linear layers on a 1-D tensor: torch exports Reshape, MatMul + Add and Unsqueeze."""

    def __init__(self, n_in: int, n_hidden: int, n_out: int):
        super().__init__()
        self.hidden = torch.nn.Linear(n_in, n_hidden)
        self.out = torch.nn.Linear(n_hidden, n_out)

    def forward(self, x):
        v = x.reshape(-1)
        return self.out(torch.sigmoid(self.hidden(v))).unsqueeze(0)


def make_mlp(widths, activations, *, pre=False, post=False, seed=0) -> torch.nn.Module:
    generator = torch.Generator().manual_seed(seed)
    torch.manual_seed(seed)
    layers = []
    if pre:
        n = widths[0]
        layers.append(Normalize(torch.randn(n, generator=generator), torch.rand(n, generator=generator) + 0.2))
    for i, (n_in, n_out) in enumerate(zip(widths[:-1], widths[1:])):
        layers.append(torch.nn.Linear(n_in, n_out))
        layers.append(ACTIVATIONS[activations[i % len(activations)]]())
    if post:
        layers.append(Denormalize(-2.5, torch.randn(widths[-1], generator=generator)))
    return torch.nn.Sequential(*layers)


def sample_inputs(n_inputs: int, seed: int = 1) -> np.ndarray:
    """Inputs over several magnitudes, so activations are both linear and saturated."""
    rng = np.random.default_rng(seed)
    magnitude = 10.0 ** rng.uniform(-2, 1.5, size=(N_SAMPLES, 1))
    return rng.standard_normal((N_SAMPLES, n_inputs)) * magnitude


def assert_kernel_matches_onnxruntime(library, prefix, model, n_inputs):
    inputs = sample_inputs(n_inputs)
    expected = onnxruntime_outputs(model, inputs)
    actual = np.array([library.run(prefix, x) for x in inputs])
    np.testing.assert_allclose(actual, expected, rtol=RTOL, atol=ATOL)


def make_model(nodes, inputs, outputs, initializers=()) -> onnx.ModelProto:
    graph = helper.make_graph(nodes, "g", inputs, outputs, initializer=list(initializers))
    # IR version 8 / opset 17: readable by every onnxruntime this project supports.
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)], ir_version=8)
    onnx.checker.check_model(model)
    return model


def double_info(name, shape):
    return helper.make_tensor_value_info(name, TensorProto.DOUBLE, shape)


def constant(name, values) -> onnx.TensorProto:
    return numpy_helper.from_array(np.asarray(values, dtype=np.float64), name)


MLP_CASES = {
    "2-16-16-1 tanh": dict(widths=[2, 16, 16, 1], activations=["tanh", "tanh", "identity"]),
    "4-32-32-2 tanh scaled": dict(
        widths=[4, 32, 32, 2], activations=["tanh", "tanh", "identity"], pre=True, post=True
    ),
    "3-8-2 sigmoid": dict(widths=[3, 8, 2], activations=["sigmoid"], pre=True),
    "5-24-12-6-3 relu": dict(widths=[5, 24, 12, 6, 3], activations=["relu"], post=True),
    "1-7-1 mixed": dict(widths=[1, 7, 5, 1], activations=["sigmoid", "relu", "tanh"], pre=True, post=True),
    "6-3 linear": dict(widths=[6, 3], activations=["identity"]),
}


@pytest.mark.parametrize("case", MLP_CASES, ids=list(MLP_CASES))
def test_random_mlp_matches_onnxruntime(case, tmp_path, build_library):
    config = MLP_CASES[case]
    network = make_mlp(config["widths"], config["activations"], pre=config.get("pre", False),
                       post=config.get("post", False), seed=len(case))
    frozen = freeze(network, config["widths"][0], tmp_path / "net.onnx")
    kernel = generate_kernel(frozen.path, prefix="mlp")
    assert (kernel.n_inputs, kernel.n_outputs) == (config["widths"][0], config["widths"][-1])
    library = build_library(kernel)
    assert_kernel_matches_onnxruntime(library, "mlp", frozen.path, kernel.n_inputs)


def test_vector_network_with_shape_ops_from_torch(tmp_path, build_library):
    frozen = freeze(VectorLinear(3, 10, 2), 3, tmp_path / "net.onnx")
    op_types = {node.op_type for node in onnx.load(frozen.path).graph.node}
    assert {"MatMul", "Add", "Reshape", "Unsqueeze"} <= op_types  # the path under test
    library = build_library(generate_kernel(frozen.path, prefix="vec"))
    assert_kernel_matches_onnxruntime(library, "vec", frozen.path, 3)


def test_shape_computations_from_torch_are_folded(tmp_path, build_library):
    """torch exports Flatten(0) as Shape -> Slice -> Concat -> Reshape: evaluated at generation time."""
    torch.manual_seed(6)
    network = torch.nn.Sequential(torch.nn.Linear(3, 4), torch.nn.Flatten(0), Denormalize(0.5, torch.randn(4)))
    frozen = freeze(network, 3, tmp_path / "net.onnx")
    op_types = {node.op_type for node in onnx.load(frozen.path).graph.node}
    assert {"Shape", "Slice", "Concat", "Reshape"} <= op_types  # the path under test
    library = build_library(generate_kernel(frozen.path, prefix="flat"))
    assert_kernel_matches_onnxruntime(library, "flat", frozen.path, 3)


def test_matmul_add_graph(build_library):
    rng = np.random.default_rng(3)
    model = make_model(
        [
            helper.make_node("MatMul", ["x", "w1"], ["h"]),
            helper.make_node("Add", ["h", "b1"], ["h_biased"]),
            helper.make_node("Tanh", ["h_biased"], ["a"]),
            helper.make_node("MatMul", ["a", "w2"], ["z"]),
            helper.make_node("Add", ["b2", "z"], ["y"]),  # constant on the left
        ],
        [double_info("x", [1, 3])],
        [double_info("y", [1, 2])],
        [constant("w1", rng.standard_normal((3, 6))), constant("b1", rng.standard_normal(6)),
         constant("w2", rng.standard_normal((6, 2))), constant("b2", rng.standard_normal((1, 2)))],
    )
    library = build_library(generate_kernel(model, prefix="mm"))
    assert_kernel_matches_onnxruntime(library, "mm", model, 3)


def test_gemm_attributes(build_library):
    """transA/transB/alpha/beta, with the sample as a column [3, 1] and a broadcast scalar C."""
    rng = np.random.default_rng(4)
    model = make_model(
        [
            # The node name ends up in a C comment and must not end it.
            helper.make_node("Gemm", ["x", "w", "c"], ["h"], name="layer */ one\n",
                             transA=1, transB=1, alpha=0.37, beta=-1.9),
            helper.make_node("Sigmoid", ["h"], ["y"]),
        ],
        [double_info("x", [3, 1])],
        [double_info("y", [1, 4])],
        [constant("w", rng.standard_normal((4, 3))), constant("c", [0.75])],
    )
    library = build_library(generate_kernel(model, prefix="gemm"))
    assert_kernel_matches_onnxruntime(library, "gemm", model, 3)


def test_shape_ops_constants_and_broadcasting(build_library):
    """Reshape/Unsqueeze/Squeeze/Flatten/Identity move no data; constants broadcast either side."""
    rng = np.random.default_rng(5)
    shape_to_vector = helper.make_node(
        "Constant", [], ["shape"], value=numpy_helper.from_array(np.array([-1], dtype=np.int64))
    )
    axes = helper.make_node("Constant", [], ["axes"], value=numpy_helper.from_array(np.array([1], dtype=np.int64)))
    model = make_model(
        [
            shape_to_vector,
            axes,
            helper.make_node("Reshape", ["x", "shape"], ["v"]),  # [3]
            helper.make_node("Unsqueeze", ["v", "axes"], ["column"]),  # [3, 1]
            helper.make_node("MatMul", ["w", "column"], ["z"]),  # constant [4, 3] @ [3, 1] -> [4, 1]
            helper.make_node("Squeeze", ["z", "axes"], ["zv"]),  # [4]
            helper.make_node("Sub", ["half", "zv"], ["d"]),  # scalar - vector
            helper.make_node("Relu", ["d"], ["r"]),
            helper.make_node("Flatten", ["r"], ["f"], axis=0),  # [1, 4]
            helper.make_node("Identity", ["f"], ["g"]),
            helper.make_node("Div", ["g", "scale"], ["q"]),  # [1, 4] / [4]
            helper.make_node("Mul", ["q", "q"], ["y"]),  # two computed operands
        ],
        [double_info("x", [1, 3])],
        [double_info("y", [1, 4])],
        [constant("w", rng.standard_normal((4, 3))), constant("half", 0.5),
         constant("scale", rng.uniform(0.5, 2.0, 4))],
    )
    library = build_library(generate_kernel(model, prefix="shapes"))
    assert_kernel_matches_onnxruntime(library, "shapes", model, 3)


def test_identity_network_copies_input(build_library):
    model = make_model([helper.make_node("Identity", ["x"], ["y"])], [double_info("x", [1, 4])],
                       [double_info("y", [1, 4])])
    library = build_library(generate_kernel(model, prefix="same"))
    assert_kernel_matches_onnxruntime(library, "same", model, 4)


def test_two_kernels_in_one_library(tmp_path, build_library):
    small = freeze(make_mlp([2, 5, 1], ["tanh", "identity"], seed=1), 2, tmp_path / "small.onnx")
    large = freeze(make_mlp([4, 9, 9, 3], ["sigmoid", "relu", "identity"], pre=True, seed=2), 4,
                   tmp_path / "large.onnx")
    library = build_library(generate_kernel(small.path, prefix="small"),
                            generate_kernel(large.path, prefix="large"))
    assert_kernel_matches_onnxruntime(library, "small", small.path, 2)
    assert_kernel_matches_onnxruntime(library, "large", large.path, 4)


def test_kernel_has_no_mutable_globals_and_one_exported_symbol(tmp_path):
    """Re-entrancy and prefixing, checked on the compiled object: read-only data, one global symbol."""
    frozen = freeze(make_mlp([3, 8, 2], ["sigmoid", "identity"], pre=True, post=True), 3, tmp_path / "n.onnx")
    _, source = generate_kernel(frozen.path, prefix="net7").write(tmp_path)
    obj = tmp_path / "net7.o"
    subprocess.run(["gcc", *CFLAGS, "-c", "-fPIC", "-o", str(obj), str(source)], check=True)
    symbols = [line.split() for line in subprocess.run(
        ["nm", str(obj)], check=True, capture_output=True, text=True).stdout.splitlines()]
    defined = {fields[-1]: fields[-2] for fields in symbols if len(fields) == 3}
    assert not {name for name, kind in defined.items() if kind in "bBdDcC"}, defined
    assert {name for name, kind in defined.items() if kind.isupper()} == {"net7_run"}


def test_header_macros(tmp_path):
    frozen = freeze(make_mlp([4, 6, 3], ["tanh", "identity"]), 4, tmp_path / "n.onnx")
    kernel = generate_kernel(frozen.path, prefix="ctl")
    header, _ = kernel.write(tmp_path)
    program = tmp_path / "main.c"
    program.write_text(
        '#include <stdio.h>\n#include "ctl.h"\n'
        "int main(void) { double in[ctl_N_INPUTS] = {0}; double out[ctl_N_OUTPUTS];\n"
        "  ctl_run(in, out); printf(\"%d %d\\n\", ctl_N_INPUTS, ctl_N_OUTPUTS); return 0; }\n"
    )
    exe = tmp_path / "main"
    subprocess.run(["gcc", *CFLAGS, "-o", str(exe), str(program), str(tmp_path / "ctl.c"), "-lm"], check=True)
    assert subprocess.run([str(exe)], check=True, capture_output=True, text=True).stdout.split() == ["4", "3"]


@pytest.mark.parametrize(
    "node",
    [
        helper.make_node("Softmax", ["x"], ["y"], name="probabilities"),
        helper.make_node("LSTM", ["x", "w", "r"], ["y"], hidden_size=2, name="memory"),
    ],
    ids=lambda node: node.op_type,
)
def test_unsupported_operator_is_named(node):
    graph = helper.make_graph([node], "g", [double_info("x", [1, 1, 2])], [double_info("y", None)],
                              initializer=[constant("w", np.zeros((1, 8, 2))), constant("r", np.zeros((1, 8, 2)))])
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)], ir_version=8)
    with pytest.raises(FmuBuilderError) as error:
        generate_kernel(model, prefix="bad")
    message = str(error.value)
    assert f"ONNX operator {node.op_type} (node '{node.name}') is not supported" in message
    assert all(op in message for op in SUPPORTED_OPS)
    assert "\n" not in message


def test_broadcasting_a_computed_tensor_is_rejected():
    model = make_model(
        [helper.make_node("Add", ["x", "c"], ["y"])],
        [double_info("x", [1, 3])],
        [double_info("y", [2, 3])],
        [constant("c", np.ones((2, 3)))],
    )
    with pytest.raises(FmuBuilderError, match="only broadcasts constants"):
        generate_kernel(model)


def test_float32_graph_is_rejected():
    graph = helper.make_graph(
        [helper.make_node("Tanh", ["x"], ["y"])], "g",
        [helper.make_tensor_value_info("x", TensorProto.FLOAT, [1, 2])],
        [helper.make_tensor_value_info("y", TensorProto.FLOAT, [1, 2])],
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)], ir_version=8)
    with pytest.raises(FmuBuilderError, match="computes in DOUBLE"):
        generate_kernel(model)


@pytest.mark.parametrize("prefix", ["", "2net", "my-net", "a b"])
def test_prefix_must_be_a_c_identifier(prefix):
    model = make_model([helper.make_node("Tanh", ["x"], ["y"])], [double_info("x", [1, 2])],
                       [double_info("y", [1, 2])])
    with pytest.raises(FmuBuilderError, match="not a C identifier"):
        generate_kernel(model, prefix=prefix)
