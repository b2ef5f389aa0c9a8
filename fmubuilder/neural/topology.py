"""NeuralFMU topologies: how a small ANN is wired around the FMU's state derivatives.

The structure follows the NeuralFMU workflow of Thummerer et al.: the FMU computes all state
derivatives (and any other variable the ANN needs), an ANN corrects a chosen subset of them
(the *channels*), and learnable pre-/post-processing and gates keep the start of training at the
first-principle model:

    a     = inputs                                 FMU variables: states, derivatives, outputs, inputs, locals
    z     = (a - pre_shift) * pre_scale            roughly standard normal on the reference simulation
    o     = ann(z)                                 Linear + Tanh/Sigmoid/ReLU layers, one output per channel
    r     = o * post_scale + post_shift            scaled to the channel's magnitude
    dx_c  = gate_ann * r + gate_fmu * der_fmu_c    for each channel c; other derivatives pass through

Kinds (`TopologyConfig.kind`):
* "gates"    - gate_ann = 0 and gate_fmu = 1 at the start, both trainable: the untrained hybrid
               equals the FMU exactly; training blends ANN and FMU per channel. post_shift starts
               at the channel's mean, so the ANN (after neutral pre-training) predicts the whole
               derivative.
* "residual" - gates fixed at 1 and 1 (buffers, not trained), the last Linear starts at zero and
               post_shift at 0: dx_c = der_fmu_c + correction, zero at the start.

Per-channel inputs (`channel_inputs`, with several channels): the ANN is one sub-network per
channel, each reading only its channel's inputs, held in one MLP whose weights are block-diagonal
(the blocks outside are zero and get no gradient), so the export sees an ordinary MLP. With all
channels reading the union of the inputs, one channel's correction learns from variables its own
input choice rejected: on the DC drive's two effects the friction in der(speed) read the current,
which put a bias into the current at high speed and into the winding's heating with it.

Trained tunable FMU parameters (`parameters`) are part of the topology too (`fmu_parameters`).
Everything is float64. `config.to_dict()` is JSON-able and, with the state_dict, regenerates the
module; the export stage reads `ann` (an ONNX-exportable nn.Sequential) and the plain tensors
pre_shift, pre_scale, post_scale, post_shift, gate_ann, gate_fmu.
"""
from __future__ import annotations

import itertools
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from ..errors import FmuBuilderError
from ..fmi import ModelInfo

KINDS = ("gates", "residual")
ACTIVATIONS = {"tanh": nn.Tanh, "sigmoid": nn.Sigmoid, "relu": nn.ReLU}
_ACTIVATION_FN = {nn.Tanh: torch.tanh, nn.Sigmoid: torch.sigmoid, nn.ReLU: torch.relu}
DTYPE = torch.float64


@dataclass
class TopologyConfig:
    """A JSON-able description of a NeuralFMU topology."""
    channels: list[str] = field(default_factory=list)   # derivatives the ANN acts on, e.g. ["der(v)"]
    inputs: list[str] = field(default_factory=list)     # FMU variables fed to the ANN
    hidden: list[int] = field(default_factory=lambda: [16, 16])
    activation: str = "tanh"
    kind: str = "gates"
    parameters: list[str] = field(default_factory=list)  # tunable FMU parameters trained as well
    base_terms: list[dict] = field(default_factory=list)  # a fitted term added to the ANN (base_term.py)
    # Per channel the inputs it reads (a subset of `inputs`); empty: every channel reads all of them.
    # With several channels each gets its own sub-network of `hidden` units per layer.
    channel_inputs: list[list[str]] = field(default_factory=list)

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> "TopologyConfig":
        known = {f for f in cls.__dataclass_fields__}
        unknown = set(data) - known
        if unknown:
            raise FmuBuilderError(f"unknown topology fields {sorted(unknown)}; known fields: {sorted(known)}")
        fields = {k: list(v) if isinstance(v, (list, tuple)) else v for k, v in data.items()}
        if "channel_inputs" in fields:
            fields["channel_inputs"] = [list(names) for names in fields["channel_inputs"]]
        return cls(**fields)

    def input_blocks(self) -> list[list[int]] | None:
        """Per channel the indices of the inputs it reads, or None when the ANN is one network
        over all inputs (one channel, or no per-channel inputs given)."""
        if len(self.channels) < 2 or not self.channel_inputs:
            return None
        return [[self.inputs.index(name) for name in names] for names in self.channel_inputs]

    def validate(self, info: ModelInfo) -> None:
        if self.kind not in KINDS:
            raise FmuBuilderError(f"unknown topology '{self.kind}': choose one of {', '.join(KINDS)}")
        if self.activation not in ACTIVATIONS:
            raise FmuBuilderError(f"unknown activation '{self.activation}': choose one of {', '.join(ACTIVATIONS)}")
        if any(not isinstance(h, int) or h < 1 for h in self.hidden):
            raise FmuBuilderError(f"hidden layer sizes must be positive integers, got {self.hidden}")
        derivatives = {v.name for v in info.derivatives}
        for name in self.channels:
            info.variable(name)
            if name not in derivatives:
                raise FmuBuilderError(
                    f"target '{name}' is not a state derivative of {info.model_name}; "
                    f"choose among {', '.join(sorted(derivatives)) or '(none)'}")
        if len(set(self.channels)) != len(self.channels):
            raise FmuBuilderError(f"duplicate targets in {self.channels}")
        if self.channels and not self.inputs:
            raise FmuBuilderError("the ANN needs at least one input: give FMU variable names, e.g. --inputs v,der(v)")
        for name in self.inputs:
            var = info.variable(name)
            if var.type != "Real":
                raise FmuBuilderError(f"ANN input '{name}' is a {var.type} variable; use Real variables")
        if self.inputs and not self.channels:
            raise FmuBuilderError("ANN inputs given but no targets: give at least one derivative, e.g. --target 'der(v)'")
        if self.base_terms:
            from .base_term import term_inputs
            if self.kind != "residual" or len(self.channels) != 1:
                raise FmuBuilderError("a base term needs the residual topology with one target derivative")
            missing = [name for name in term_inputs(self.base_terms) if name not in self.inputs]
            if missing:
                raise FmuBuilderError(f"the base term reads {', '.join(missing)}: add it to the ANN inputs")
        if self.channel_inputs:
            if len(self.channel_inputs) != len(self.channels):
                raise FmuBuilderError(f"{len(self.channel_inputs)} lists of channel inputs for "
                                      f"{len(self.channels)} targets; give one per target")
            for channel, names in zip(self.channels, self.channel_inputs):
                unknown = [n for n in names if n not in self.inputs]
                if not names or unknown or len(set(names)) != len(names):
                    raise FmuBuilderError(f"the inputs of {channel} must be distinct ANN inputs, at least one; "
                                          f"got {', '.join(names) or '(none)'}")


class Topology(nn.Module):
    """The trainable part of a NeuralFMU (see the module docstring)."""

    def __init__(self, config: TopologyConfig, info: ModelInfo, parameter_values: list[float]):
        super().__init__()
        config.validate(info)
        self.config = config
        n = info.n_states
        self.n_states = n
        state_names = [v.name for v in info.states]
        derivative_names = [v.name for v in info.derivatives]
        self.channel_index = [derivative_names.index(c) for c in config.channels]
        # Variables the FMU must report besides its derivatives, in the order of `out[:, n:]`.
        self.fmu_variables = [name for name in config.inputs if name not in state_names and name not in derivative_names]
        # ANN input i is column source[i] of cat([x, out[:, :n + len(fmu_variables)]]).
        source = []
        for name in config.inputs:
            if name in state_names:
                source.append(state_names.index(name))
            elif name in derivative_names:
                source.append(n + derivative_names.index(name))
            else:
                source.append(2 * n + self.fmu_variables.index(name))
        self.register_buffer("input_source", torch.tensor(source, dtype=torch.long), persistent=False)
        self._inputs_from_states = all(i < n for i in source)
        self.register_buffer("channels_t", torch.tensor(self.channel_index, dtype=torch.long), persistent=False)
        n_in, n_out = len(config.inputs), len(config.channels)
        blocks = config.input_blocks()
        hidden = [size * n_out for size in config.hidden] if blocks else config.hidden
        self.ann = build_ann(n_in, hidden, n_out, config.activation) if n_out else None
        if blocks:
            block_diagonal(self.ann, blocks, config.hidden)
        self.base = None
        if config.base_terms:
            from .base_term import FittedTerm
            self.base = FittedTerm(config.base_terms, config.inputs)
        ones_in, ones_out = torch.ones(n_in, dtype=DTYPE), torch.ones(n_out, dtype=DTYPE)
        self.pre_shift = nn.Parameter(torch.zeros(n_in, dtype=DTYPE))
        self.pre_scale = nn.Parameter(ones_in.clone())
        self.post_scale = nn.Parameter(ones_out.clone())
        self.post_shift = nn.Parameter(torch.zeros(n_out, dtype=DTYPE))
        if config.kind == "gates":
            self.gate_ann = nn.Parameter(torch.zeros(n_out, dtype=DTYPE))
            self.gate_fmu = nn.Parameter(ones_out.clone())
        else:
            self.register_buffer("gate_ann", ones_out.clone())
            self.register_buffer("gate_fmu", ones_out.clone())
            if self.ann is not None:
                last = self.ann[-1]
                nn.init.zeros_(last.weight)
                nn.init.zeros_(last.bias)
        self.fmu_parameters = nn.Parameter(torch.tensor(parameter_values, dtype=DTYPE).reshape(len(config.parameters)),
                                           requires_grad=bool(config.parameters))

    @contextmanager
    def ann_off(self, fmu_gate_one: bool = False):
        """Within the block the hybrid is the plain FMU: gate_ann = 0 (and, with fmu_gate_one,
        gate_fmu = 1, for a gates hybrid whose trained FMU gate is not 1); restored after."""
        saved = self.gate_ann.detach().clone(), self.gate_fmu.detach().clone()
        with torch.no_grad():
            self.gate_ann.zero_()
            if fmu_gate_one:
                self.gate_fmu.fill_(1.0)
        try:
            yield
        finally:
            with torch.no_grad():
                self.gate_ann.copy_(saved[0])
                self.gate_fmu.copy_(saved[1])

    def processing_parameters(self) -> list[nn.Parameter]:
        """The pre-/post-processing scales and shifts (trained at their own step size)."""
        return [self.pre_shift, self.pre_scale, self.post_scale, self.post_shift]

    @property
    def has_ann(self) -> bool:
        return self.ann is not None

    def is_neutral(self) -> bool:
        """Whether the hybrid equals the FMU exactly: no ANN, a zero ANN gate, or (residual) a zero
        last layer with a zero post-shift."""
        if self.ann is None or not bool(self.gate_ann.any()):
            return True
        if self.base is not None:
            return False
        last = self.ann[-1]
        return not (bool(last.weight.any()) or bool(last.bias.any()) or bool(self.post_shift.any()))

    def last_layer_free(self) -> torch.Tensor:
        """[C, H] bool: the last Linear layer's entries that may be non-zero (each channel's own
        hidden units with per-channel inputs, see block_diagonal; all of them otherwise)."""
        weight = self.ann[-1].weight
        if not self.config.input_blocks():
            return torch.ones_like(weight, dtype=torch.bool)
        owner = torch.arange(weight.shape[1]) // self.config.hidden[-1]
        return owner[None, :] == torch.arange(weight.shape[0])[:, None]

    def row_channels(self) -> list[torch.Tensor] | None:
        """Per parameter of `ann` (in parameters() order) the channel each row (dim 0) belongs to,
        with per-channel sub-networks (see block_diagonal: no weight joins two of them); None for
        one network over all inputs."""
        if not self.config.input_blocks():
            return None
        owners = []
        for _, owner in _row_owners(self.ann, self.config.hidden):
            owners += [owner, owner]        # weight, bias
        return owners

    def ann_inputs(self, x: torch.Tensor, out: torch.Tensor) -> torch.Tensor:
        """The raw ANN inputs [B, n_in] from states x [B, n] and FMU results out [B, n + k]."""
        if self._inputs_from_states:
            return x.index_select(1, self.input_source)
        width = 2 * self.n_states + len(self.fmu_variables)
        return torch.cat([x, out[:, : width - self.n_states]], dim=1).index_select(1, self.input_source)

    def correction(self, inputs: torch.Tensor) -> torch.Tensor:
        """r = post(ann(pre(inputs))) for raw ANN inputs [B, n_in]: the channel values [B, C]."""
        last = self.ann[-1]
        r = F.linear(self.hidden_units(inputs), last.weight, last.bias) * self.post_scale + self.post_shift
        return r if self.base is None else r + self.base(inputs)

    def hidden_units(self, inputs: torch.Tensor) -> torch.Tensor:
        """The last hidden layer's outputs [B, H] for raw ANN inputs [B, n_in]: what the last Linear
        layer combines."""
        z = (inputs - self.pre_shift) * self.pre_scale
        # The layers called directly: nn.Module dispatch costs more than these tiny products.
        for layer in itertools.islice(self.ann, len(self.ann) - 1):
            z = F.linear(z, layer.weight, layer.bias) if isinstance(layer, nn.Linear) else _ACTIVATION_FN[type(layer)](z)
        return z

    def folded(self, transposed: bool = False) -> list:
        """The ANN with the pre-processing folded into its first Linear layer and the post-processing
        and the ANN gate into its last: [(W, b) or activation, ...], differentiable; with it a hybrid
        evaluation is a few matrix products (`mix`). Fold once per simulation, not per step.

            W1' = W1 diag(pre_scale)                b1' = b1 - W1' pre_shift
            WL' = diag(gate_ann post_scale) WL      bL' = gate_ann (post_scale bL + post_shift)

        `transposed` gives (W'^T, b') pairs, the form `mix` takes: F.linear transposes W at every
        call, a node of the autograd graph per layer and solver stage; transposed once here, a
        stage is addmm(b, z, W^T) alone, the same product (F.linear calls exactly that)."""
        linears = [i for i, layer in enumerate(self.ann) if isinstance(layer, nn.Linear)]
        layers = []
        for i, layer in enumerate(self.ann):
            if not isinstance(layer, nn.Linear):
                layers.append(_ACTIVATION_FN[type(layer)])
                continue
            W, b = layer.weight, layer.bias
            if i == linears[0]:
                W = W * self.pre_scale
                b = b - W @ self.pre_shift
            if i == linears[-1]:
                W = (self.gate_ann * self.post_scale)[:, None] * W
                b = self.gate_ann * (self.post_scale * b + self.post_shift)
            layers.append((W.t(), b) if transposed else (W, b))
        return layers

    def mix(self, layers: list, x: torch.Tensor, out: torch.Tensor) -> torch.Tensor:
        """Hybrid state derivatives [B, n] from states x, FMU results out = [der | variables] and
        the folded ANN `layers` (folded(transposed=True)): dx_c = ANN'(inputs) + gate_fmu der_fmu_c
        (see the module docstring)."""
        raw = z = self.ann_inputs(x, out)
        for layer in layers:
            z = torch.addmm(layer[1], z, layer[0]) if isinstance(layer, tuple) else layer(z)
        if self.base is not None:        # not foldable: the term on the raw inputs, through the gate
            z = z + self.gate_ann * self.base(raw)
        derivatives = out[:, : self.n_states]
        mixed = torch.addcmul(z, self.gate_fmu, derivatives.index_select(1, self.channels_t))
        return derivatives.index_copy(1, self.channels_t, mixed)

    def forward(self, x: torch.Tensor, out: torch.Tensor) -> torch.Tensor:
        """Hybrid state derivatives [B, n] from states x and FMU results out = [der | variables]."""
        derivatives = out[:, : self.n_states]
        if self.ann is None:
            return derivatives
        if not torch.is_grad_enabled() and self.gate_ann.count_nonzero() == 0:
            return derivatives  # 0 * ann + 1 * der: the FMU's derivatives (the untrained hybrid)
        return self.mix(self.folded(transposed=True), x, out)

    # -- initialisation from a reference simulation of the plain FMU -------------------------
    def initialise_scaling(self, inputs: np.ndarray, channels: np.ndarray) -> None:
        """Set pre-/post-processing from samples of the raw ANN inputs [N, n_in] and of the FMU's
        channel derivatives [N, C] along a reference simulation of the plain FMU."""
        if self.ann is None:
            return
        with torch.no_grad():
            mean, std = inputs.mean(axis=0), inputs.std(axis=0)
            self.pre_shift.copy_(torch.from_numpy(mean))
            self.pre_scale.copy_(torch.from_numpy(1.0 / _safe_scale(std, mean)))
            c_mean, c_std = channels.mean(axis=0), channels.std(axis=0)
            self.post_scale.copy_(torch.from_numpy(_safe_scale(c_std, c_mean)))
            if self.config.kind == "gates":
                self.post_shift.copy_(torch.from_numpy(c_mean))

    def neutral_target(self, channels: torch.Tensor) -> torch.Tensor:
        """What the ANN part r should output to leave the hybrid unchanged whatever the gates:
        the FMU's channel derivative (gates) or zero (residual)."""
        return channels if self.config.kind == "gates" else torch.zeros_like(channels)


def build_ann(n_in: int, hidden: list[int], n_out: int, activation: str) -> nn.Sequential:
    layers, width = [], n_in
    for size in hidden:
        layers += [nn.Linear(width, size, dtype=DTYPE), ACTIVATIONS[activation]()]
        width = size
    layers.append(nn.Linear(width, n_out, dtype=DTYPE))
    return nn.Sequential(*layers)


def block_diagonal(ann: nn.Sequential, blocks: list[list[int]], hidden: list[int]) -> None:
    """Make `ann` (built with hidden widths hidden[k] * len(blocks)) one sub-network per output:
    output j reads the inputs blocks[j] through its own hidden units alone. The weights outside
    the blocks are set to zero and a gradient hook keeps them there, so every use of the weights
    (the fold, the export) sees the block structure. Inside, the weights are drawn again as
    nn.Linear draws them, for the block's own fan-in."""
    n_out = len(blocks)
    owner_in = None          # per column of the next Linear: the output whose block it belongs to
    for layer, owner_out in _row_owners(ann, hidden):
        rows, cols = layer.weight.shape
        if owner_in is None:
            mask = torch.zeros(rows, cols, dtype=DTYPE)
            for j, columns in enumerate(blocks):
                mask[(owner_out == j).nonzero()[:, 0][:, None], torch.tensor(columns)] = 1.0
        else:
            mask = (owner_out[:, None] == owner_in[None, :]).to(DTYPE)
        bound = 1.0 / mask.sum(dim=1, keepdim=True).clamp_min(1.0).sqrt()
        with torch.no_grad():
            layer.weight.copy_((torch.rand(rows, cols, dtype=DTYPE) * 2.0 - 1.0) * bound * mask)
            layer.bias.copy_((torch.rand(rows, dtype=DTYPE) * 2.0 - 1.0) * bound[:, 0])
        layer.weight.register_hook(_masked_gradient(mask))
        owner_in = owner_out
    assert owner_in is not None and len(owner_in) == n_out


def _row_owners(ann: nn.Sequential, hidden: list[int]):
    """(Linear layer, the output each of its rows belongs to) for an ANN of one sub-network per
    output with hidden[k] units each in hidden layer k (block_diagonal)."""
    widths = iter(hidden)
    for layer in (m for m in ann if isinstance(m, nn.Linear)):
        rows = layer.weight.shape[0]
        width = next(widths, None)
        yield layer, torch.arange(rows) // width if width is not None else torch.arange(rows)


def _masked_gradient(mask: torch.Tensor):
    def hook(gradient: torch.Tensor) -> torch.Tensor:
        return gradient * mask
    return hook


def _safe_scale(std: np.ndarray, mean: np.ndarray) -> np.ndarray:
    """A positive scale: the standard deviation, or the magnitude (or 1) for constant signals."""
    fallback = np.where(np.abs(mean) > 0, np.abs(mean), 1.0)
    return np.where(std > 1e-12 * np.maximum(np.abs(mean), 1.0), std, fallback)
