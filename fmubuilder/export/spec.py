"""HybridSpec: everything needed to turn a trained hybrid model back into an FMU.

A hybrid model is an original FMI 2.0 Model-Exchange FMU whose derivatives of some states
(the *channels*) are corrected by a neural network:

    der(x_c) = p_fmu_c * f_c(x) + p_ann_c * net(u)_c        for each channel c
    der(x_k) = f_k(x)                                        for every other state

where f is the original FMU's derivative function, u the values of the FMU variables listed
in ``inputs`` (read from the original FMU, so a derivative among them is the original's
value), and net the network stored as ONNX: it maps the raw input values to one value per
channel, with any scaling of inputs and outputs inside the graph. A gate that is exactly 0
switches its term off completely (so p_ann = 0, p_fmu = 1 reproduces the original model
even if the network returned NaN). The gates are tunable parameters of the exported FMU;
the values here are their start values.

``overrides`` gives parameters of the original new values ({name: value}): the hybrid declares them
as its start values and sets them in the original at instantiation and reset, so that an importer
that sets no start values simulates them too. A calibrated parameter is a hybrid with overrides and
no channels (then neither inputs nor a network).

``aliases`` maps an output of the original that is the same quantity as a channel's
derivative (e.g. a power whose integral is the energy state) to that channel. The hybrid
corrects it like the derivative, y = p_fmu_c * y_original + p_ann_c * net(u)_c, so that the
output stays consistent with the state it is the rate of.

JSON form (paths relative to the JSON file's folder)::

    {
      "format": "fmubuilder.hybrid_spec", "version": 1,
      "original_fmu": "plant.fmu", "original_guid": "{...}",
      "channels": ["der(speed)"],
      "inputs": ["speed", "der(speed)", "force"],
      "onnx": "network.onnx",
      "p_ann": [1.0], "p_fmu": [1.0],
      "aliases": {"acceleration": "der(speed)"},
      "overrides": {"mass": 1100.0},
      "term": "network"
    }

("aliases" and "overrides" may be left out; "onnx" too when there are no channels.) ``term`` says
what the ONNX graph holds, so that the exported FMU names it truthfully: "network" (the default) or
"fitted term", with its ``expression`` for the description.
"""
from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path

from fmubuilder.errors import FmuBuilderError

from .network import onnx_io_sizes

FORMAT = "fmubuilder.hybrid_spec"
VERSION = 1
# Variable types a network input may have: their values are passed to the network as doubles.
INPUT_TYPES = ("Real", "Integer", "Enumeration", "Boolean")
# Causalities an alias of a derivative may have: values computed by the model, not parameters.
ALIAS_CAUSALITIES = ("output", "local")
# What the ONNX graph may hold.
TERMS = ("network", "fitted term")


@dataclass
class HybridSpec:
    """The hand-over from training to export; see the module docstring for the semantics."""

    original_fmu: Path
    original_guid: str
    channels: list[str]
    inputs: list[str]
    onnx: Path | None
    p_ann: list[float] = field(default_factory=list)
    p_fmu: list[float] = field(default_factory=list)
    aliases: dict[str, str] = field(default_factory=dict)   # output name -> channel der(x)
    term: str = "network"       # or "fitted term"
    expression: str = ""        # of a fitted term, for the FMU's description
    overrides: dict[str, float] = field(default_factory=dict)   # parameter name -> its new value

    def __post_init__(self):
        self.original_fmu = Path(self.original_fmu)
        self.onnx = Path(self.onnx) if self.onnx is not None else None
        self.channels = [str(c) for c in self.channels]
        self.inputs = [str(i) for i in self.inputs]
        n = len(self.channels)
        # Gates default to "both on": the trained hybrid as it was trained.
        self.p_ann = _gates(self.p_ann, n, "p_ann")
        self.p_fmu = _gates(self.p_fmu, n, "p_fmu")
        self.overrides = _overrides(self.overrides)
        if n == 0 and not self.overrides:
            raise FmuBuilderError("the hybrid spec has neither channels nor overrides; list the derivatives the "
                                  "network corrects or the parameters it sets")
        if len(set(self.channels)) != n:
            raise FmuBuilderError(f"the hybrid spec lists a channel twice ({self.channels}); list each derivative once")
        if n and not self.inputs:
            raise FmuBuilderError("the hybrid spec has no network inputs; list the FMU variables fed to the network")
        if n and self.onnx is None:
            raise FmuBuilderError("the hybrid spec has channels but no network; give its \"onnx\" file")
        self.aliases = _aliases(self.aliases)
        if self.term not in TERMS:
            raise FmuBuilderError(f"the hybrid spec's term {self.term!r} is unknown; give one of {', '.join(TERMS)}")
        self.expression = str(self.expression or "")

    @classmethod
    def calibration(cls, original_fmu, overrides: dict[str, float]) -> "HybridSpec":
        """The original with new values of some of its parameters, and no network."""
        from fmubuilder.fmi import read_model_info
        return cls(original_fmu, read_model_info(original_fmu).guid, channels=[], inputs=[], onnx=None,
                   overrides=overrides)

    # -- JSON ------------------------------------------------------------------------------
    @classmethod
    def load(cls, path: str | os.PathLike) -> "HybridSpec":
        """Read a spec written by save(); relative paths are resolved against its folder."""
        path = Path(path)
        try:
            data = json.loads(path.read_text())
        except FileNotFoundError:
            raise FmuBuilderError(f"{path}: no such file; give the hybrid spec JSON written at training") from None
        except (OSError, ValueError) as exc:
            raise FmuBuilderError(f"{path}: not a readable JSON file ({exc}); give a hybrid spec JSON") from None
        return cls.from_dict(data, path.resolve().parent, str(path))

    @classmethod
    def from_dict(cls, data, base: Path, source: str) -> "HybridSpec":
        """The spec of a dict in the JSON form, its paths relative to `base`; `source` names it in errors."""
        if not isinstance(data, dict) or data.get("format") != FORMAT:
            raise FmuBuilderError(f"{source} is not a hybrid spec (no \"format\": \"{FORMAT}\"); give the spec JSON")
        if data.get("version") != VERSION:
            raise FmuBuilderError(
                f"{source} is a hybrid spec of version {data.get('version')}; this fmubuilder reads version {VERSION}")
        missing = [k for k in ("original_fmu", "original_guid", "channels", "inputs") if k not in data]
        if missing:
            raise FmuBuilderError(
                f"{source}: the hybrid spec lacks {', '.join(missing)}; add them or re-export the spec")
        return cls(
            original_fmu=base / data["original_fmu"], original_guid=str(data["original_guid"]),
            channels=list(data["channels"]), inputs=list(data["inputs"]),
            onnx=base / data["onnx"] if data.get("onnx") else None,
            p_ann=list(data.get("p_ann", [])), p_fmu=list(data.get("p_fmu", [])),
            aliases=data.get("aliases", {}), term=data.get("term", "network"),
            expression=data.get("expression", ""), overrides=data.get("overrides", {}))

    def to_dict(self, relative_to: str | os.PathLike | None = None) -> dict:
        def where(p: Path) -> str:
            # Files beside the JSON are written relative, so the folder can move as a whole.
            if relative_to is not None and Path(relative_to).resolve() in p.resolve().parents:
                return p.resolve().relative_to(Path(relative_to).resolve()).as_posix()
            return str(p.resolve()) if relative_to is not None else str(p)
        return {
            "format": FORMAT, "version": VERSION,
            "original_fmu": where(self.original_fmu), "original_guid": self.original_guid,
            "channels": list(self.channels), "inputs": list(self.inputs),
            "onnx": where(self.onnx) if self.onnx is not None else None,
            "p_ann": list(self.p_ann), "p_fmu": list(self.p_fmu), "aliases": dict(self.aliases),
            "term": self.term, **({"expression": self.expression} if self.expression else {}),
            **({"overrides": dict(self.overrides)} if self.overrides else {}),
        }

    def save(self, path: str | os.PathLike) -> Path:
        """Write the spec as JSON (atomically), with paths relative to the JSON's folder."""
        from fmubuilder.files import write_atomically
        path = Path(path)
        return write_atomically(path, json.dumps(self.to_dict(relative_to=path.parent), indent=2) + "\n")

    # -- consistency with the original FMU and the network ----------------------------------
    def check(self, info=None) -> None:
        """Check the spec against the original FMU (a ModelInfo, read if not given) and the ONNX file."""
        if info is None:
            from fmubuilder.fmi import read_model_info
            info = read_model_info(self.original_fmu)
        if info.guid != self.original_guid:
            raise FmuBuilderError(
                f"{self.original_fmu} has GUID {info.guid}, the hybrid spec was trained on {self.original_guid}; "
                "export with the FMU the network was trained on")
        derivative_names = {d.name for d in info.derivatives}
        for channel in self.channels:
            if channel not in derivative_names:
                raise FmuBuilderError(
                    f"channel '{channel}' is not a state derivative of {info.model_name} "
                    f"(its derivatives: {', '.join(sorted(derivative_names))}); fix 'channels' in the spec")
        for name in self.inputs:
            var = info.variable(name)
            if var.type not in INPUT_TYPES:
                raise FmuBuilderError(
                    f"network input '{name}' is a {var.type} variable; only {', '.join(INPUT_TYPES)} can feed "
                    "the network")
        self._check_aliases(info)
        self._check_overrides(info)
        if not self.channels:
            return
        n_in, n_out = onnx_io_sizes(self.onnx)
        if n_in != len(self.inputs) or n_out != len(self.channels):
            raise FmuBuilderError(
                f"{self.onnx} maps {n_in} inputs to {n_out} outputs, the spec has {len(self.inputs)} inputs and "
                f"{len(self.channels)} channels; export the network that belongs to this spec")

    def _check_aliases(self, info) -> None:
        derivative_names = {d.name for d in info.derivatives}
        state_names = {s.name for s in info.states}
        for name, channel in self.aliases.items():
            if channel not in self.channels:
                raise FmuBuilderError(
                    f"alias '{name}' refers to '{channel}', which is not a channel of the hybrid spec (channels: "
                    f"{', '.join(self.channels)}); fix 'aliases' in the spec")
            var = info.variable(name)   # unknown names fail here with a suggestion
            if var.type != "Real":
                raise FmuBuilderError(f"alias '{name}' is a {var.type} variable; only a Real output can equal "
                                      f"{channel}; fix 'aliases' in the spec")
            if name in derivative_names or name in state_names or var.causality not in ALIAS_CAUSALITIES \
                    or var.variability != "continuous":
                raise FmuBuilderError(
                    f"alias '{name}' is not a continuous output of {info.model_name} ({var.causality}, "
                    f"{var.variability}); list only outputs that equal {channel} in 'aliases'")

    def _check_overrides(self, info) -> None:
        for name in self.overrides:
            var = info.variable(name)   # unknown names fail here with a suggestion
            if var.type != "Real" or var.causality != "parameter" or var.variability not in ("fixed", "tunable"):
                raise FmuBuilderError(f"override '{name}' is a {var.causality} {var.type} ({var.variability}); only "
                                      "a Real parameter (fixed or tunable) can be given a new value")

    def channel_states(self, info) -> list[str]:
        """Name of the state x of each channel der(x)."""
        by_name = {d.name: s.name for s, d in zip(info.states, info.derivatives)}
        return [by_name[c] for c in self.channels]


def _gates(values, n: int, what: str) -> list[float]:
    values = [1.0] * n if values is None or len(values) == 0 else list(values)
    if len(values) != n:
        raise FmuBuilderError(f"the hybrid spec has {len(values)} {what} values for {n} channels; give one per channel")
    try:
        gates = [float(v) for v in values]
    except (TypeError, ValueError):
        raise FmuBuilderError(f"the {what} values {values} are not numbers; give one number per channel") from None
    if not all(math.isfinite(g) for g in gates):
        raise FmuBuilderError(f"the {what} values {gates} are not all finite; give finite gate values")
    return gates


def _overrides(overrides) -> dict[str, float]:
    if not isinstance(overrides, dict):
        raise FmuBuilderError(f"the hybrid spec's overrides {overrides!r} are not a mapping of parameter name to "
                              "value; give e.g. {\"mass\": 1100.0}")
    try:
        values = {str(name): float(value) for name, value in overrides.items()}
    except (TypeError, ValueError):
        raise FmuBuilderError(f"the overrides {overrides} are not all numbers; give one number per parameter") from None
    if not all(math.isfinite(v) for v in values.values()):
        raise FmuBuilderError(f"the overrides {values} are not all finite; give finite values")
    return values


def _aliases(aliases) -> dict[str, str]:
    if aliases is None:
        return {}
    if not isinstance(aliases, dict) or not all(isinstance(k, str) and isinstance(v, str)
                                                for k, v in aliases.items()):
        raise FmuBuilderError(f"the hybrid spec's aliases {aliases!r} are not a mapping of output name to channel; "
                              "give e.g. {\"power\": \"der(energy)\"}")
    return dict(aliases)
