"""What an FMU declares: its variables by name, its states and capabilities.

Built from fmpy's parsed modelDescription; the rest of fmubuilder talks to this
small, flat view instead of the XML object model.
"""
from __future__ import annotations

from dataclasses import dataclass, field

from ..errors import FmuBuilderError, suggestion

# FMI 2.0 types and the C API family that reads/writes them.
API_TYPE = {"Real": "Real", "Integer": "Integer", "Enumeration": "Integer",
            "Boolean": "Boolean", "String": "String"}


@dataclass(frozen=True)
class Variable:
    name: str
    value_reference: int
    type: str                      # Real, Integer, Enumeration, Boolean, String
    causality: str                 # parameter, calculatedParameter, input, output, local, independent
    variability: str               # constant, fixed, tunable, discrete, continuous
    start: str | None = None
    unit: str | None = None
    description: str | None = None
    initial: str | None = None
    derivative_of: str | None = None  # for der(x): the name of x

    @property
    def api_type(self) -> str:
        return API_TYPE[self.type]

    @property
    def is_parameter(self) -> bool:
        return self.causality in ("parameter", "calculatedParameter")


@dataclass(frozen=True)
class Capabilities:
    can_get_and_set_fmu_state: bool = False
    can_serialize_fmu_state: bool = False
    provides_directional_derivative: bool = False
    completed_integrator_step_not_needed: bool = False
    can_be_instantiated_only_once_per_process: bool = False


@dataclass(frozen=True)
class DefaultExperiment:
    start_time: float | None = None
    stop_time: float | None = None
    tolerance: float | None = None
    step_size: float | None = None


@dataclass
class ModelInfo:
    """The parts of a modelDescription a simulator needs, indexed by name."""
    model_name: str
    model_identifier: str
    guid: str
    fmi_version: str
    generation_tool: str | None
    variables: dict[str, Variable]
    states: list[Variable]          # continuous states, in the FMU's state-vector order
    derivatives: list[Variable]     # der(states[i]) at index i
    n_event_indicators: int
    capabilities: Capabilities
    default_experiment: DefaultExperiment
    outputs: list[Variable] = field(default_factory=list)
    # ModelStructure: the knowns each derivative and output depends on (None: not declared)
    dependencies: dict[str, tuple[str, ...] | None] = field(default_factory=dict)

    @property
    def n_states(self) -> int:
        return len(self.states)

    @property
    def inputs(self) -> list[Variable]:
        return [v for v in self.variables.values() if v.causality == "input"]

    @property
    def parameters(self) -> list[Variable]:
        return [v for v in self.variables.values() if v.is_parameter]

    def variable(self, name: str, what: str = "variable") -> Variable:
        """Look a variable up by name, with a helpful error for a typo (naming it as `what`)."""
        try:
            return self.variables[name]
        except KeyError:
            raise FmuBuilderError(
                f"unknown {what} '{name}' in model '{self.model_name}'"
                f"{suggestion(name, self.variables)}; `fmubuilder inspect` lists the variables"
            ) from None

    def state_index(self, name: str) -> int:
        """Index in the state vector of a state `x` or its derivative `der(x)`."""
        var = self.variable(name)
        for i, (state, der) in enumerate(zip(self.states, self.derivatives)):
            if var.name in (state.name, der.name):
                return i
        raise FmuBuilderError(f"'{name}' is not a continuous state or state derivative of '{self.model_name}'")


def _float(literal) -> float | None:
    return None if literal is None else float(literal)


# FMI 2.0's enumerations (modelDescription schema, fmi2ScalarVariable)
CAUSALITIES = ("parameter", "calculatedParameter", "input", "output", "local", "independent")
VARIABILITIES = ("constant", "fixed", "tunable", "discrete", "continuous")
INITIALS = ("exact", "approx", "calculated")


def check_model_description(md, source) -> None:
    """What fmpy reads without validating, checked: a GUID, unique variable names, the declared
    enumerations (causality, variability, initial), start values that are values of their type, and
    value references shared only by true aliases (never by two states or two derivatives, nor with
    different start values). One FmuBuilderError naming the variable."""
    where = f"{source}: modelDescription.xml"
    if not (md.guid or "").strip():
        raise FmuBuilderError(f"{where} has no guid attribute; FMI 2.0 requires one: re-export the model")
    seen = {}
    for sv in md.modelVariables:
        if sv.name in seen:
            raise FmuBuilderError(f"{where} declares the variable '{sv.name}' twice; variable names must be unique: "
                                  "re-export the model")
        seen[sv.name] = sv
        for attribute, value, allowed in (("causality", sv.causality, CAUSALITIES),
                                          ("variability", sv.variability, VARIABILITIES),
                                          ("initial", sv.initial, INITIALS)):
            if value is not None and value not in allowed:
                raise FmuBuilderError(f"{where}: variable '{sv.name}' has {attribute}=\"{value}\", which FMI 2.0 does "
                                      f"not define (one of {', '.join(allowed)}); fix the model description")
        if sv.start is not None and not _is_value_of(sv.type, sv.start):
            raise FmuBuilderError(f"{where}: variable '{sv.name}' ({sv.type}) has start=\"{sv.start}\", not a "
                                  f"{sv.type} value; fix the model description")
        try:
            int(sv.valueReference)
        except (TypeError, ValueError):
            raise FmuBuilderError(f"{where}: variable '{sv.name}' has valueReference=\"{sv.valueReference}\", not a "
                                  "whole number; fix the model description") from None
    _check_aliases(md, where)


def _is_value_of(kind: str, text) -> bool:
    text = str(text).strip()
    if kind in ("Real", "Integer", "Enumeration") and "_" in text:
        return False
    try:
        if kind == "Real":
            float(text)
        elif kind in ("Integer", "Enumeration"):
            int(text)
        elif kind == "Boolean":
            return text in ("true", "false", "1", "0")
    except ValueError:
        return False
    return True


def _check_aliases(md, where: str) -> None:
    """Variables of one base type sharing a value reference are one value (aliases): two of them that
    are different states, different derivatives, or start from different values are a wrong reference."""
    states = {id(u.variable.derivative) for u in md.derivatives if u.variable.derivative is not None}
    derivatives = {id(u.variable) for u in md.derivatives}
    first = {}
    for sv in md.modelVariables:
        key = (API_TYPE.get(sv.type, sv.type), int(sv.valueReference))
        other = first.setdefault(key, sv)
        if other is sv:
            continue
        clash = ((id(sv) in states and id(other) in states) or (id(sv) in derivatives and id(other) in derivatives)
                 or (sv.start is not None and other.start is not None and str(sv.start) != str(other.start)))
        if clash:
            raise FmuBuilderError(f"{where}: variables '{other.name}' and '{sv.name}' share the value reference "
                                  f"{key[1]} but are different values; give each its own valueReference")


def model_info_from_fmpy(md) -> ModelInfo:
    """Convert fmpy's ModelDescription of an FMI 2.0 ME FMU into a ModelInfo."""
    by_fmpy_var = {}
    variables = {}
    for sv in md.modelVariables:
        var = Variable(
            name=sv.name, value_reference=int(sv.valueReference), type=sv.type,
            causality=sv.causality or "local", variability=sv.variability or "continuous",
            start=sv.start, unit=sv.unit or (sv.declaredType.unit if sv.declaredType else None),
            description=sv.description, initial=sv.initial,
            derivative_of=sv.derivative.name if sv.derivative is not None else None,
        )
        variables[var.name] = var
        by_fmpy_var[id(sv)] = var
    derivatives = [by_fmpy_var[id(u.variable)] for u in md.derivatives]
    states = [variables[d.derivative_of] for d in derivatives]
    me = md.modelExchange
    caps = Capabilities(
        can_get_and_set_fmu_state=bool(me.canGetAndSetFMUstate),
        can_serialize_fmu_state=bool(me.canSerializeFMUstate),
        provides_directional_derivative=bool(me.providesDirectionalDerivative),
        # fmpy fills needsCompletedIntegratorStep for FMI 2.0 (from completedIntegratorStepNotNeeded,
        # whose own field it leaves False)
        completed_integrator_step_not_needed=not me.needsCompletedIntegratorStep,
        can_be_instantiated_only_once_per_process=bool(me.canBeInstantiatedOnlyOncePerProcess),
    )
    de = md.defaultExperiment
    experiment = DefaultExperiment() if de is None else DefaultExperiment(
        _float(de.startTime), _float(de.stopTime), _float(de.tolerance), _float(de.stepSize))
    return ModelInfo(
        model_name=md.modelName, model_identifier=me.modelIdentifier, guid=md.guid,
        fmi_version=md.fmiVersion, generation_tool=md.generationTool, variables=variables,
        states=states, derivatives=derivatives,
        n_event_indicators=int(md.numberOfEventIndicators or 0), capabilities=caps,
        default_experiment=experiment,
        outputs=[by_fmpy_var[id(u.variable)] for u in md.outputs],
        dependencies={u.variable.name: None if u.dependencies is None else tuple(d.name for d in u.dependencies)
                      for u in md.derivatives + md.outputs},
    )
