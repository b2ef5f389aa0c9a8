"""The effect a hybrid adds, drawn against its inputs: what the chosen candidate learned and, where
the data were made by a known "truth" model, what the truth adds.

Both are evaluated along one run of the declared FMU over the training data (its states and the
term's input variables every few samples):

    learned(t) = p_ann * net(u(t))                          the exported network or fitted term
    truth(t)   = f_truth(x(t), t)[c] - f_declared(x(t), t)[c]   derivatives of channel c at the same
                                                            state, inputs and time

With a truth, both are drawn along the declared run as each FMU follows it: every state set to
the run's after every step (neural/collocation.forced_run), the inputs and the declared FMU's
derivative from the declared FMU's such run, the truth's from its own. A sampled controller then
updates at its ticks from the same states in both. Set to a state at single points instead, an FMU
keeps its discrete states where they started (the VLDM's driver: a throttle of 0, no motor torque,
and no extra loss drawn where the truth adds 0.77 kW rms). The followed runs can miss a state event
the run had (a relay whose switch, inside a step, undoes its own crossing by the step's end): the
two FMUs then miss it alike, and inputs, learned and true effect stay at the same points.
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
from ..fmi import read_model_info
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
    channel = spec.channels[0]
    inputs, truth = None, None
    try:
        truth_fmu, parameters, truth_source = _truth_model(data)
        if truth_fmu is not None:
            inputs, truth = followed_effect(truth_fmu, declared_fmu, spec.inputs, channel, data, start_values,
                                            parameters, scoring)
    except FmuBuilderError as exc:
        truth_source = f"the truth could not be evaluated ({exc})"
    if inputs is None:
        interval = max(scoring.step, (data.stop - data.start) / EFFECT_POINTS)
        run = simulate_over(declared_fmu, data, start_values, spec.inputs, scoring, output_interval=interval,
                            record_events=False)
        inputs = {name: np.asarray(run[name], dtype=float) for name in spec.inputs}
    network = OnnxNetwork(spec.onnx)
    learned = spec.p_ann[0] * np.array([network(row)[0] for row in np.column_stack(list(inputs.values()))])
    return Effect(channel, spec.term, inputs, learned, truth, truth_source)


def followed_effect(truth_fmu: Path, declared_fmu: Path, inputs: list[str], channel: str, data, start_values: dict,
                    parameters: dict, scoring: Scoring) -> tuple[dict[str, np.ndarray], np.ndarray]:
    """({input: values}, f_truth - f_declared of `channel`) at about EFFECT_POINTS points of the
    declared FMU's run over `data`, both FMUs following it (the module docstring); the truth starts
    with its `parameters` on top of `start_values`."""
    states = [s.name for s in read_model_info(declared_fmu).states]
    if [s.name for s in read_model_info(truth_fmu).states] != states:
        raise FmuBuilderError("its continuous states are not the declared FMU's")
    run = simulate_over(declared_fmu, data, start_values, states, scoring, record_events=False)
    grid = np.asarray(run.time, dtype=float)
    columns = [np.asarray(run[name], dtype=float) for name in states]

    def along_run(t):
        t = np.atleast_1d(np.asarray(t, dtype=float))
        return np.stack([np.interp(t, grid, column) for column in columns], axis=1)
    declared = _following(declared_fmu, data, start_values, scoring, states, along_run, [*inputs, channel])
    truth = _following(truth_fmu, data, {**start_values, **parameters}, scoring, states, along_run, [channel])
    points = slice(None, None, max(1, len(truth[channel]) // EFFECT_POINTS))
    return ({name: declared[name][points] for name in inputs},
            truth[channel][points] - declared[channel][points])


def _following(fmu_path: Path, data, start_values: dict, scoring: Scoring, states: list[str], along_run,
               record: list[str]) -> dict[str, np.ndarray]:
    """{name: values on the scoring grid} of the FMU run over `data` with every state set to
    along_run(t) after every step."""
    from ..neural import NeuralFMU, TopologyConfig
    from ..neural.collocation import forced_run
    model = NeuralFMU(fmu_path, TopologyConfig(), start_values=start_values)
    try:
        solver = scoring.solver if scoring.solver in ("euler", "rk4") else "rk4"   # the states are set every step
        trajectory = forced_run(model, data, scoring.step, solver, states, along_run, list(dict.fromkeys(record)),
                                data.input_signals(model.info))
        return {name: trajectory.numpy(name)[:, 0] for name in record}
    finally:
        model.close()


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
