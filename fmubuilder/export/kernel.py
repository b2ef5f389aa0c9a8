"""Generate a plain C99 inference kernel from an ONNX graph (one sample in, one vector out).

The graph is lowered to a short list of steps over flat float64 arrays -- dense layer,
elementwise binary operation, activation, copy -- which the jinja2 templates in c_templates/
turn into C. Data is row-major and a single sample, so shape-only operators (Reshape, Flatten,
Squeeze, Unsqueeze, Identity) move no data: their output is an alias of their input. Operators
whose inputs are all constants are evaluated here with onnx's reference implementation.

Arithmetic follows onnxruntime: dot products summed in ascending index order, then
`alpha * sum + beta * C` for Gemm; elementwise operations keep their operand order; Sigmoid
uses onnxruntime's formula. Results agree with onnxruntime to float64 round-off.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import onnx
from onnx import numpy_helper

from fmubuilder.errors import FmuBuilderError
from fmubuilder.files import write_atomically

from .c_text import C_IDENTIFIER, c_comment, c_double, templates

BINARY_OPS = {"Add": "+", "Sub": "-", "Mul": "*", "Div": "/"}
# Elementwise unary operations (Abs and Neg appear in fitted symbolic terms such as k*w*|w|).
ACTIVATIONS = {"Tanh": "tanh", "Sigmoid": "sigmoid", "Relu": "relu", "Abs": "fabs", "Neg": "neg"}
SHAPE_OPS = ("Identity", "Reshape", "Flatten", "Squeeze", "Unsqueeze")
SUPPORTED_OPS = tuple(sorted({"Gemm", "MatMul", "Constant", "Shape", *BINARY_OPS, *ACTIVATIONS, *SHAPE_OPS}))

_DEFAULT_DOMAINS = ("", "ai.onnx")


@dataclass(frozen=True)
class GeneratedKernel:
    """C source of one kernel: `<prefix>.h` declares `void <prefix>_run(const double *, double *)`."""

    prefix: str
    n_inputs: int
    n_outputs: int
    header: str
    source: str

    @property
    def header_name(self) -> str:
        return f"{self.prefix}.h"

    @property
    def source_name(self) -> str:
        return f"{self.prefix}.c"

    def write(self, directory: str | os.PathLike) -> tuple[Path, Path]:
        """Write `<prefix>.h` and `<prefix>.c` into `directory`; returns (header path, source path)."""
        directory = Path(directory)
        header = write_atomically(directory / self.header_name, self.header)
        source = write_atomically(directory / self.source_name, self.source)
        return header, source


def generate_kernel(model: onnx.ModelProto | str | os.PathLike, prefix: str = "ann") -> GeneratedKernel:
    """C99 kernel computing the ONNX `model` (a file path or a loaded ModelProto) for one sample.

    `prefix` names every symbol of the kernel, so kernels with different prefixes can be linked
    into one library.
    """
    if not isinstance(prefix, str) or not C_IDENTIFIER.match(prefix):
        raise FmuBuilderError(
            f"kernel prefix {prefix!r} is not a C identifier; use letters, digits and '_' (not leading digit)")
    program = _Lowering(_load_model(model), prefix).run()
    return _render(program)


def _load_model(model) -> onnx.ModelProto:
    if isinstance(model, onnx.ModelProto):
        return model
    try:
        return onnx.load(os.fspath(model))
    except Exception as exc:  # missing file, protobuf decode errors, ...
        raise FmuBuilderError(f"cannot read ONNX model {model} ({exc}); pass the file written by freeze()") from exc


# ---------------------------------------------------------------------------------------------
# Lowering: ONNX nodes -> steps over named tensors


@dataclass(frozen=True)
class _Operand:
    """Operand of an elementwise step: a computed tensor, a constant array or a scalar literal."""

    kind: str  # "tensor" | "array" | "scalar"
    ref: str  # tensor name, constant array name, or C literal


@dataclass
class _Step:
    """One loop of the kernel, writing `size` elements of tensor `dst`."""

    kind: str  # "dense" | "binary" | "unary" | "copy"
    dst: str
    size: int
    node: str  # ONNX operator and node name, for the comment in the C code
    reads: tuple[str, ...] = ()  # computed tensors read
    params: dict = field(default_factory=dict)

    @property
    def arrays(self) -> set[str]:
        """Names of the constant arrays the step reads."""
        names = {self.params.get("weight"), self.params.get("bias")}
        names.update(p.ref for p in self.params.values() if isinstance(p, _Operand) and p.kind == "array")
        return names - {None}

    @property
    def elementwise(self) -> bool:
        """Element i of the output depends only on element i of the inputs (so may run in place)."""
        return self.kind != "dense"


@dataclass
class _Program:
    prefix: str
    n_inputs: int
    n_outputs: int
    steps: list[_Step]
    arrays: list[tuple[str, np.ndarray]]  # static const arrays: (C name, flat values)
    input_tensor: str
    output_tensor: str
    op_types: list[str]


class _Lowering:
    """Walks the (topologically sorted) ONNX graph once, tracking a static shape per computed tensor."""

    def __init__(self, model: onnx.ModelProto, prefix: str):
        self.graph = model.graph
        self.prefix = prefix
        self.opset = next((o.version for o in model.opset_import if o.domain in _DEFAULT_DOMAINS), 17)
        self.constants = {init.name: numpy_helper.to_array(init) for init in self.graph.initializer}
        self.shapes: dict[str, tuple[int, ...]] = {}  # computed tensors
        self.root: dict[str, str] = {}  # computed tensor -> tensor that owns its storage
        self.steps: list[_Step] = []
        self.arrays: list[tuple[str, np.ndarray]] = []

    def run(self) -> _Program:
        input_name, input_shape = self._graph_input()
        self.shapes[input_name] = input_shape
        self.root[input_name] = input_name
        for node in self.graph.node:
            self._lower_node(node)
        output_name = self._graph_output()
        if output_name in self.shapes and self.root[output_name] != input_name:
            output_tensor = self.root[output_name]
            n_outputs = math.prod(self.shapes[output_name])
        else:  # the network is the identity or a constant: copy into the output array
            output_tensor = "<output>"
            n_outputs = self._copy_output(output_name)
        steps = _live_steps(self.steps, output_tensor)
        used_arrays = set().union(*(step.arrays for step in steps))
        return _Program(prefix=self.prefix, n_inputs=math.prod(input_shape), n_outputs=n_outputs, steps=steps,
                        arrays=[(name, values) for name, values in self.arrays if name in used_arrays],
                        input_tensor=input_name, output_tensor=output_tensor,
                        op_types=sorted({node.op_type for node in self.graph.node}))

    # graph boundary ---------------------------------------------------------------------------

    def _graph_input(self) -> tuple[str, tuple[int, ...]]:
        inputs = [i for i in self.graph.input if i.name not in self.constants]
        if len(inputs) != 1:
            raise FmuBuilderError(
                f"the ONNX graph has {len(inputs)} inputs; the C kernel needs exactly one input vector")
        tensor_type = inputs[0].type.tensor_type
        if tensor_type.elem_type != onnx.TensorProto.DOUBLE:
            type_name = onnx.TensorProto.DataType.Name(tensor_type.elem_type)
            raise FmuBuilderError(
                f"the ONNX graph input is {type_name}, the C kernel computes in DOUBLE; "
                "export the network in float64 with freeze()")
        # A symbolic (batch) dimension is one sample.
        shape = tuple(d.dim_value if d.HasField("dim_value") else 1 for d in tensor_type.shape.dim)
        return inputs[0].name, shape

    def _graph_output(self) -> str:
        if len(self.graph.output) != 1:
            raise FmuBuilderError(
                f"the ONNX graph has {len(self.graph.output)} outputs; the C kernel needs exactly one output")
        name = self.graph.output[0].name
        if name not in self.shapes and name not in self.constants:
            raise FmuBuilderError(f"the ONNX graph output {name!r} is computed by no node; the model is malformed")
        return name

    def _copy_output(self, name: str) -> int:
        if name in self.shapes:
            source, size = _Operand("tensor", self.root[name]), math.prod(self.shapes[name])
        else:
            values = self._float_constant(name).ravel()
            source, size = _Operand("array", self._add_array("output_value", values)), values.size
        reads = (source.ref,) if source.kind == "tensor" else ()
        self.steps.append(_Step("copy", "<output>", size, "graph output", reads, {"src": source}))
        return size

    # nodes ------------------------------------------------------------------------------------

    def _lower_node(self, node: onnx.NodeProto) -> None:
        if node.domain not in _DEFAULT_DOMAINS:
            raise _unsupported(node)
        if node.op_type == "Constant":
            self.constants[node.output[0]] = _constant_node_value(node)
            return
        for name in node.input:
            if name and name not in self.shapes and name not in self.constants:
                raise FmuBuilderError(
                    f"input {name!r} of ONNX node {_describe(node)} is produced by no earlier node; "
                    "the graph is malformed or not topologically sorted")
        if not any(name in self.shapes for name in node.input):
            self._fold(node)
        elif node.op_type == "Shape":  # shapes are static: Shape of a computed tensor is a constant
            self._fold(node, {node.input[0]: np.zeros(self.shapes[node.input[0]])})
        elif node.op_type in SHAPE_OPS:
            self._lower_shape_op(node)
        elif node.op_type in BINARY_OPS:
            self._lower_binary(node)
        elif node.op_type in ACTIVATIONS:
            self._lower_activation(node)
        elif node.op_type == "Gemm":
            self._lower_gemm(node)
        elif node.op_type == "MatMul":
            self._lower_matmul(node)
        else:
            raise _unsupported(node)

    def _fold(self, node: onnx.NodeProto, feeds: dict[str, np.ndarray] | None = None) -> None:
        """Evaluate a node on constant inputs now, with onnx's reference implementation."""
        from onnx.reference import ReferenceEvaluator

        feeds = feeds or {}
        feeds.update({n: self.constants[n] for n in node.input if n and n not in feeds})
        try:
            results = ReferenceEvaluator(node, opsets={"": self.opset}).run(None, feeds)
        except Exception as exc:  # the reference implementation raises many types
            raise FmuBuilderError(
                f"cannot evaluate ONNX node {_describe(node)} on its constant inputs ({exc}); "
                "check the exported model with onnx.checker") from exc
        for name, value in zip(node.output, results):
            self.constants[name] = np.asarray(value)

    def _lower_shape_op(self, node: onnx.NodeProto) -> None:
        source = node.input[0]
        shape_inputs = {source: np.zeros(self.shapes[source])}
        if any(n in self.shapes for n in node.input[1:]):
            raise FmuBuilderError(
                f"ONNX node {_describe(node)} takes its target shape from a computed tensor; "
                "the C kernel needs constant shapes")
        self._fold(node, shape_inputs)
        new_shape = self.constants.pop(node.output[0]).shape
        if math.prod(new_shape) != math.prod(self.shapes[source]):
            raise FmuBuilderError(
                f"ONNX node {_describe(node)} changes the element count from "
                f"{math.prod(self.shapes[source])} to {math.prod(new_shape)}; the C kernel supports "
                "shape operators only on a single sample")
        self._alias(node.output[0], source, new_shape)

    def _lower_binary(self, node: onnx.NodeProto) -> None:
        lhs, rhs = node.input
        shape_of = lambda n: self.shapes[n] if n in self.shapes else self.constants[n].shape  # noqa: E731
        try:
            out_shape = tuple(np.broadcast_shapes(shape_of(lhs), shape_of(rhs)))
        except ValueError as exc:
            raise FmuBuilderError(f"the operands of ONNX node {_describe(node)} do not broadcast ({exc})") from exc
        size = math.prod(out_shape)
        operands = [self._elementwise_operand(node, name, out_shape) for name in (lhs, rhs)]
        reads = tuple(o.ref for o in operands if o.kind == "tensor")
        params = {"lhs": operands[0], "rhs": operands[1], "op": BINARY_OPS[node.op_type]}
        self._add_step(_Step("binary", node.output[0], size, _describe(node), reads, params), out_shape)

    def _elementwise_operand(self, node, name: str, out_shape: tuple[int, ...]) -> _Operand:
        if name in self.shapes:
            if math.prod(self.shapes[name]) != math.prod(out_shape):
                raise FmuBuilderError(
                    f"ONNX node {_describe(node)} broadcasts the computed tensor {name!r} of shape "
                    f"{list(self.shapes[name])} to {list(out_shape)}; the C kernel only broadcasts constants")
            return _Operand("tensor", self.root[name])
        values = self._float_constant(name)
        if values.size == 1:
            literal = c_double(values.item())
            # Parenthesised so that `x - -2.0` cannot turn into a decrement.
            return _Operand("scalar", f"({literal})" if literal.startswith(("-", "(")) else literal)
        broadcast = self._broadcast_constant(node, name, out_shape)
        return _Operand("array", self._add_array(node.op_type.lower(), broadcast))

    def _lower_activation(self, node: onnx.NodeProto) -> None:
        source = node.input[0]
        shape = self.shapes[source]
        params = {"function": ACTIVATIONS[node.op_type], "src": self.root[source]}
        step = _Step("unary", node.output[0], math.prod(shape), _describe(node), (self.root[source],), params)
        self._add_step(step, shape)

    def _lower_gemm(self, node: onnx.NodeProto) -> None:
        """Y = alpha * op(A) @ op(B) + beta * C with one of A, B a computed vector."""
        attrs = {a.name: onnx.helper.get_attribute_value(a) for a in node.attribute}
        alpha, beta = float(attrs.get("alpha", 1.0)), float(attrs.get("beta", 1.0))
        trans_a, trans_b = bool(attrs.get("transA", 0)), bool(attrs.get("transB", 0))
        a_name, b_name = node.input[0], node.input[1]
        c_name = node.input[2] if len(node.input) > 2 else ""
        if a_name in self.shapes and b_name not in self.shapes:
            a_shape = self.shapes[a_name][::-1] if trans_a else self.shapes[a_name]
            b = self._matrix_constant(node, b_name)
            b = b.T if trans_b else b
            if len(a_shape) != 2 or a_shape[0] != 1:
                raise self._not_one_sample(node, a_name)
            vector, weight, out_shape = a_name, b.T, (1, b.shape[1])
        elif b_name in self.shapes and a_name not in self.shapes:
            b_shape = self.shapes[b_name][::-1] if trans_b else self.shapes[b_name]
            a = self._matrix_constant(node, a_name)
            a = a.T if trans_a else a
            if len(b_shape) != 2 or b_shape[1] != 1:
                raise self._not_one_sample(node, b_name)
            vector, weight, out_shape = b_name, a, (a.shape[0], 1)
        else:
            raise self._two_computed_operands(node)
        self._check_contraction(node, vector, weight)
        if c_name in self.shapes:
            raise FmuBuilderError(
                f"ONNX node {_describe(node)} adds a computed tensor as C; the C kernel needs a constant bias")
        bias = None
        if c_name and beta != 0.0:
            # beta * C is one rounding either way; doing it here gives the same doubles as at run time.
            bias = beta * self._broadcast_constant(node, c_name, out_shape)
        self._add_dense(node, vector, weight, out_shape, alpha=alpha, bias=bias)

    def _lower_matmul(self, node: onnx.NodeProto) -> None:
        """numpy-style matmul of a computed vector with a constant 1-D or 2-D matrix."""
        a_name, b_name = node.input
        if a_name in self.shapes and b_name not in self.shapes:
            b = self._float_constant(b_name)
            vector, weight = a_name, (b.T if b.ndim == 2 else b[np.newaxis, :])
            shapes = (self.shapes[a_name], b.shape)
        elif b_name in self.shapes and a_name not in self.shapes:
            a = self._float_constant(a_name)
            vector, weight = b_name, (a if a.ndim == 2 else a[np.newaxis, :])
            shapes = (a.shape, self.shapes[b_name])
        else:
            raise self._two_computed_operands(node)
        if weight.ndim != 2:
            raise FmuBuilderError(
                f"ONNX node {_describe(node)} multiplies by a {weight.ndim}-D constant; "
                "the C kernel supports 1-D and 2-D weight matrices")
        self._check_contraction(node, vector, weight)
        try:
            out_shape = np.matmul(np.zeros(shapes[0]), np.zeros(shapes[1])).shape
        except ValueError as exc:
            raise FmuBuilderError(f"the operands of ONNX node {_describe(node)} do not match ({exc})") from exc
        self._add_dense(node, vector, weight, out_shape)

    def _check_contraction(self, node, vector: str, weight: np.ndarray) -> None:
        """The dot products must run over the whole computed tensor (it is one sample)."""
        if weight.shape[1] != math.prod(self.shapes[vector]):
            raise self._not_one_sample(node, vector)

    def _add_dense(self, node, vector: str, weight: np.ndarray, out_shape, *, alpha=1.0, bias=None) -> None:
        n_out, n_in = weight.shape
        params = {
            "src": self.root[vector],
            "n_in": n_in,
            # Row j holds the weights of output j, contiguous for the dot product.
            "weight": self._add_array("weight", np.ascontiguousarray(weight).ravel()),
            "alpha": None if alpha == 1.0 else c_double(alpha),
            "bias": None if bias is None else self._add_array("bias", bias),
        }
        step = _Step("dense", node.output[0], n_out, _describe(node), (self.root[vector],), params)
        self._add_step(step, tuple(out_shape))

    # bookkeeping ------------------------------------------------------------------------------

    def _add_step(self, step: _Step, shape: tuple[int, ...]) -> None:
        self.steps.append(step)
        self.shapes[step.dst] = shape
        self.root[step.dst] = step.dst

    def _alias(self, name: str, source: str, shape: tuple[int, ...]) -> None:
        self.shapes[name] = tuple(shape)
        self.root[name] = self.root[source]

    def _add_array(self, role: str, values: np.ndarray) -> str:
        name = f"{self.prefix}_{role}_{len(self.arrays)}"
        self.arrays.append((name, np.asarray(values, dtype=np.float64).ravel()))
        return name

    def _float_constant(self, name: str) -> np.ndarray:
        return np.asarray(self.constants[name], dtype=np.float64)

    def _matrix_constant(self, node, name: str) -> np.ndarray:
        matrix = self._float_constant(name)
        if matrix.ndim != 2:
            raise FmuBuilderError(
                f"ONNX node {_describe(node)} has a {matrix.ndim}-D operand {name!r}; Gemm needs 2-D matrices")
        return matrix

    def _broadcast_constant(self, node, name: str, shape: tuple[int, ...]) -> np.ndarray:
        """The constant expanded to `shape`, flat in row-major order."""
        try:
            return np.broadcast_to(self._float_constant(name), shape).ravel()
        except ValueError as exc:
            raise FmuBuilderError(
                f"the constant {name!r} of ONNX node {_describe(node)} does not broadcast to {list(shape)}") from exc

    def _not_one_sample(self, node, name: str) -> FmuBuilderError:
        return FmuBuilderError(
            f"ONNX node {_describe(node)} treats the computed tensor {name!r} of shape "
            f"{list(self.shapes[name])} as a batch; the C kernel evaluates one sample, export with batch size 1")

    @staticmethod
    def _two_computed_operands(node) -> FmuBuilderError:
        return FmuBuilderError(
            f"ONNX node {_describe(node)} multiplies two computed tensors; the C kernel needs constant weights")


def _live_steps(steps: list[_Step], output_tensor: str) -> list[_Step]:
    """Drop steps whose result never reaches the output."""
    needed, live = {output_tensor}, []
    for step in reversed(steps):
        if step.dst in needed:
            live.append(step)
            needed.update(step.reads)
    return live[::-1]


def _constant_node_value(node: onnx.NodeProto) -> np.ndarray:
    attr = node.attribute[0]
    if attr.name == "value":
        return numpy_helper.to_array(attr.t)
    if attr.name in ("value_float", "value_floats", "value_int", "value_ints"):
        return np.asarray(onnx.helper.get_attribute_value(attr))
    raise FmuBuilderError(
        f"ONNX Constant node {node.name!r} holds a {attr.name}; the C kernel supports dense numeric constants")


def _describe(node: onnx.NodeProto) -> str:
    return f"{node.op_type} {node.name!r}" if node.name else node.op_type


def _unsupported(node: onnx.NodeProto) -> FmuBuilderError:
    op = f"{node.domain}.{node.op_type}" if node.domain not in _DEFAULT_DOMAINS else node.op_type
    where = f" (node {node.name!r})" if node.name else ""
    return FmuBuilderError(
        f"ONNX operator {op}{where} is not supported by the C kernel generator; "
        f"supported: {', '.join(SUPPORTED_OPS)}; build the network from Linear layers, Tanh/Sigmoid/ReLU "
        "and elementwise scaling")


# ---------------------------------------------------------------------------------------------
# Storage and rendering


def _assign_storage(program: _Program) -> tuple[dict[str, str], list[str]]:
    """C array for every computed tensor: `input`, `output` or a reused stack buffer `t<i>`.

    A buffer returns to the pool after the last step reading it; elementwise steps may write
    into a buffer they read (in place), dense steps may not. Returns (storage, buffer names).
    """
    storage = {program.input_tensor: "input", program.output_tensor: "output"}
    last_read = {name: i for i, step in enumerate(program.steps) for name in step.reads}
    buffers: list[str] = []
    free: list[str] = []

    def release(step_index: int, step: _Step) -> None:
        for name in dict.fromkeys(step.reads):
            if last_read[name] == step_index and storage[name] in buffers:
                free.append(storage[name])

    for i, step in enumerate(program.steps):
        if step.elementwise:
            release(i, step)
        if step.dst not in storage:
            if not free:
                buffers.append(f"t{len(buffers)}")
                free.append(buffers[-1])
            storage[step.dst] = free.pop()
        if not step.elementwise:
            release(i, step)
    return storage, buffers


def _render(program: _Program) -> GeneratedKernel:
    storage, buffers = _assign_storage(program)
    buffer_size = max((s.size for s in program.steps if storage[s.dst] in buffers), default=0)

    def operand(op: _Operand) -> str:
        if op.kind == "scalar":
            return op.ref
        return f"{storage[op.ref] if op.kind == 'tensor' else op.ref}[i]"

    steps = []
    for step in program.steps:
        view = {"kind": step.kind, "dst": storage[step.dst], "size": step.size, "node": c_comment(step.node)}
        view.update(step.params)
        for key in ("lhs", "rhs"):
            if key in view:
                view[key] = operand(view[key])
        if step.kind == "copy":
            view["src"] = operand(view["src"])
        elif "src" in view:
            view["src"] = storage[view["src"]]
        steps.append(view)

    context = {
        "prefix": program.prefix, "guard": f"{program.prefix.upper()}_H_INCLUDED",
        "header_name": f"{program.prefix}.h", "n_inputs": program.n_inputs, "n_outputs": program.n_outputs,
        "op_types": [c_comment(op) for op in program.op_types],
        "arrays": [(name, [c_double(v) for v in values]) for name, values in program.arrays],
        "buffers": buffers, "buffer_size": buffer_size, "steps": steps,
        "uses_input": any(program.input_tensor in s.reads for s in program.steps),
        "uses_sigmoid": any(s.get("function") == "sigmoid" for s in steps),
    }
    env = templates()
    header = env.get_template("ann_kernel.h.j2").render(context)
    source = env.get_template("ann_kernel.c.j2").render(context)
    return GeneratedKernel(program.prefix, program.n_inputs, program.n_outputs, header, source)
