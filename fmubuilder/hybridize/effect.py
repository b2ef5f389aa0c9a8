"""The effect a hybrid adds, drawn against its inputs: what the chosen candidate learned and, where
the data were made by a known "truth" model, what the truth adds.

Both are evaluated along one run of the declared FMU over the training data (its states and the
term's input variables every few samples):

    learned(t) = p_ann * net(u(t))                          the exported network or fitted term
    truth(t)   = f_truth(x(t), t)[c] - f_declared(x(t), t)[c]   derivatives of channel c at the same
                                                            state, inputs and time

The truth is the FMU the data's sidecar names (`truth_model`, checked by its sha256, with the
sidecar's `truth` parameters); it is found only when it is one of the bundled examples. Without it
the plot shows the learned term alone.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..data import read_sidecar
from ..errors import FmuBuilderError
from ..export.network import OnnxNetwork
from ..export.spec import HybridSpec
from ..files import file_sha256
from ..fmi import Fmu, read_model_info
from .evaluate import Scoring, simulate_over

# Points of the declared FMU's run at which the effects are evaluated.
EFFECT_POINTS = 600


@dataclass
class Effect:
    channel: str                          # der(x) the term corrects
    kind: str                             # "network" or "fitted term"
    inputs: dict[str, np.ndarray]         # the term's input variables along the run
    learned: np.ndarray                   # the correction the hybrid adds to the channel
    truth: np.ndarray | None = None       # what the truth model adds (None: unknown)
    truth_source: str = ""                # where the truth came from, or why there is none


def effect_of(spec_path: Path, declared_fmu: Path, data, start_values: dict, scoring: Scoring) -> Effect:
    """The learned (and, if known, true) effect along the declared FMU's run over `data`, simulated
    as every model is scored (`scoring`)."""
    spec = HybridSpec.load(spec_path)
    info_states = [s.name for s in read_model_info(declared_fmu).states]
    interval = max(scoring.step, (data.stop - data.start) / EFFECT_POINTS)
    run = simulate_over(declared_fmu, data, start_values, dict.fromkeys([*spec.inputs, *info_states]), scoring,
                        output_interval=interval, record_events=False)
    channel = spec.channels[0]
    network = OnnxNetwork(spec.onnx)
    inputs = {name: np.asarray(run[name], dtype=float) for name in spec.inputs}
    learned = spec.p_ann[0] * np.array([network(row)[0] for row in np.column_stack(list(inputs.values()))])
    effect = Effect(channel, spec.term, inputs, learned)
    try:
        truth_fmu, parameters, effect.truth_source = _truth_model(data)
        if truth_fmu is not None:
            states = np.column_stack([np.asarray(run[name], dtype=float) for name in info_states])
            # f_truth - f_declared of the channel at the same times, states and inputs
            effect.truth = (_derivatives(truth_fmu, channel, run.time, states, data, {**start_values, **parameters})
                            - _derivatives(declared_fmu, channel, run.time, states, data, start_values))
    except FmuBuilderError as exc:
        effect.truth, effect.truth_source = None, f"the truth could not be evaluated ({exc})"
    return effect


def _truth_model(data) -> tuple[Path | None, dict, str]:
    """The bundled example FMU that made the data (by the sidecar's name and sha256), its parameters."""
    from ..build import example_fmu, list_examples
    sidecar = read_sidecar(data.path) if data.path else None
    model = (sidecar or {}).get("truth_model") or {}
    name = Path(str(model.get("file", ""))).stem
    if not name:
        return None, {}, "the data name no truth model"
    if name not in list_examples():
        return None, {}, f"the truth model {name} is not a bundled example"
    fmu = example_fmu(name)
    if model.get("sha256") and file_sha256(fmu) != model["sha256"]:
        return None, {}, f"the bundled {name} differs from the one that made the data"
    parameters = dict(((sidecar.get("truth") or {}).get("parameters")) or {})
    return fmu, parameters, f"{name}.fmu" + (f" with {_listed(parameters)}" if parameters else "")


def _listed(values: dict) -> str:
    return ", ".join(f"{k} = {v:g}" if isinstance(v, (int, float)) else f"{k} = {v}" for k, v in values.items())


def _derivatives(fmu_path: Path, channel: str, time: np.ndarray, states: np.ndarray, data,
                 start_values: dict) -> np.ndarray:
    from ..simulation.events import event_mode
    with Fmu(fmu_path) as fmu:
        index = fmu.info.state_index(channel)
        instance = fmu.instantiate("effect")
        try:
            instance.setup_experiment(float(time[0]))
            instance.set(start_values)
            instance.enter_initialization_mode()
            instance.exit_initialization_mode()
            event_mode(instance, entered=True, resume_on_terminate=True)
            inputs = {name: np.interp(time, data.time, values) for name, values in (data.inputs or {}).items()}
            out = np.empty(time.size)
            for k, t in enumerate(time):
                instance.set_time(float(t))
                if inputs:
                    instance.set({name: float(values[k]) for name, values in inputs.items()})
                instance.set_continuous_states(states[k])
                out[k] = instance.get_derivatives()[index]
            return out
        finally:
            instance.free()
