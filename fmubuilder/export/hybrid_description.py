"""The modelDescription.xml of a hybrid FMU, derived from the original's.

Everything the original declares stays as it is (variables, value references, units, types,
log categories, default experiment), so tools and scripts written for the original work on
the hybrid. Changed or added:

* a new GUID and modelIdentifier (``<original>_hybrid``), generationTool "fmubuilder";
* Model Exchange only; no directional derivatives (the network part has no derivative code);
  every other capability flag as the original's;
* per channel der(x), three Real variables appended after the original's (so the original's
  indices in ModelStructure stay valid), with value references beyond all of the original's:
  ``hybrid.<x>.p_ann`` and ``hybrid.<x>.p_fmu`` (tunable parameters, the gates, unit "1") and
  ``hybrid.<x>.ann`` (local: the network output before gating); for a fitted term
  ``hybrid.<x>.p_term``, ``hybrid.<x>.p_fmu`` and ``hybrid.<x>.term``, and the names and
  descriptions speak of the term, not of a network;
* the spec's overrides as the start values of their parameters;
* ModelStructure: the dependencies of each channel's derivative gain those of the network
  inputs; where they are not known (e.g. a local variable feeds the network) the attribute is
  dropped, which per FMI 2.0 means "depends on everything". An output listed in the spec's
  ``aliases`` is corrected like its channel's derivative and gains the same dependencies.
"""
from __future__ import annotations

import datetime
import re
import uuid
import zipfile
from dataclasses import dataclass

from lxml import etree

from fmubuilder.errors import FmuBuilderError

from .spec import HybridSpec

WRAPPER_LOG_CATEGORY = "logStatusError"
DIMENSIONLESS = "1"     # the unit of the gates
GENERATION_TOOL = "fmubuilder"
_STRUCTURED_NAME = re.compile(r"[A-Za-z_]\w*(\[\d+(,\d+)*\])?(\.[A-Za-z_]\w*(\[\d+(,\d+)*\])?)*\Z")
# Children of fmiModelDescription in schema order (for inserting a missing LogCategories).
_ELEMENT_ORDER = ("ModelExchange", "CoSimulation", "UnitDefinitions", "TypeDefinitions", "LogCategories",
                  "DefaultExperiment", "VendorAnnotations", "ModelVariables", "ModelStructure")


@dataclass(frozen=True)
class _Words:
    """How the hybrid's variables and descriptions name what the ONNX graph holds."""

    gate: str       # name of the gate parameter
    value: str      # name of the value before gating
    thing: str      # what it is, in a sentence


def _words(spec: HybridSpec) -> _Words:
    if spec.term == "fitted term":
        expression = f" {spec.expression}" if spec.expression else ""
        return _Words(gate="p_term", value="term", thing=f"the fitted term{expression}")
    return _Words(gate="p_ann", value="ann", thing="the neural network")


@dataclass(frozen=True)
class ChannelLayout:
    """Where one channel lives in the original FMU and which variables the hybrid adds for it."""

    channel: str            # der(x)
    state: str              # x
    state_index: int        # index of x in the state vector
    der_vr: int
    p_ann: str
    p_ann_vr: int
    p_fmu: str
    p_fmu_vr: int
    ann: str
    ann_vr: int


@dataclass(frozen=True)
class HybridDescription:
    xml: bytes
    guid: str
    model_identifier: str
    channels: list[ChannelLayout]
    log_categories: list[str]   # the original's


def hybrid_identifier(original_identifier: str) -> str:
    return f"{original_identifier}_hybrid"


def derive_model_description(original_xml: bytes, spec: HybridSpec, info) -> HybridDescription:
    """The hybrid's modelDescription.xml from the original's XML and its ModelInfo `info`."""
    try:
        root = etree.fromstring(original_xml)
    except etree.XMLSyntaxError as exc:
        raise FmuBuilderError(f"the original modelDescription.xml is not valid XML ({exc})") from None
    identifier = hybrid_identifier(info.model_identifier)
    guid = _set_header(root, info, spec)
    _set_model_exchange(root, identifier)
    log_categories = _log_categories(root)
    variables = root.find("ModelVariables")
    layout = _add_channel_variables(variables, spec, info)
    _set_overrides(variables, spec.overrides)
    if layout:
        _define_dimensionless_unit(root)
    _update_structure(root, spec, info)
    etree.indent(root, space="  ")
    xml = etree.tostring(root, xml_declaration=True, encoding="UTF-8", pretty_print=True)
    return HybridDescription(xml=xml, guid=guid, model_identifier=identifier, channels=layout,
                             log_categories=log_categories)


def channel_layouts(spec: HybridSpec) -> list[ChannelLayout]:
    """The channels of the hybrid of `spec` as its export lays them out (the gates' names among them)."""
    from ..fmi import read_model_info
    with zipfile.ZipFile(spec.original_fmu) as archive:
        original_xml = archive.read("modelDescription.xml")
    return derive_model_description(original_xml, spec, read_model_info(spec.original_fmu)).channels


def new_identity(root) -> str:
    """A derived FMU's own GUID (returned) and generation stamp on the root of its modelDescription."""
    guid = "{" + str(uuid.uuid4()) + "}"
    root.set("guid", guid)
    root.set("generationTool", GENERATION_TOOL)
    now = datetime.datetime.now(datetime.timezone.utc).replace(microsecond=0)
    root.set("generationDateAndTime", now.strftime("%Y-%m-%dT%H:%M:%SZ"))
    return guid


def _set_header(root, info, spec: HybridSpec) -> str:
    words = _words(spec)
    root.set("modelName", f"{info.model_name}_hybrid")
    changes = [f"{', '.join(spec.channels)} corrected by {words.thing} (gates {words.gate}, p_fmu per corrected "
               "derivative)"] if spec.channels else []
    if spec.overrides:
        changes.append("calibrated " + ", ".join(f"{name} = {value:.6g}" for name, value in spec.overrides.items()))
    root.set("description", f"{info.model_name} with {' and '.join(changes)}")
    return new_identity(root)


def _set_overrides(variables, overrides: dict[str, float]) -> None:
    for variable in variables.findall("ScalarVariable"):
        if variable.get("name") in overrides:
            variable.find("Real").set("start", repr(overrides[variable.get("name")]))


def _set_model_exchange(root, identifier: str) -> None:
    for cs in root.findall("CoSimulation"):
        root.remove(cs)
    me = root.find("ModelExchange")
    me.set("modelIdentifier", identifier)
    me.set("providesDirectionalDerivative", "false")
    # Other capability flags hold for the hybrid as for the original: the wrapper forwards those
    # calls, keeps the FMU state capabilities, and with canNotUseMemoryManagementFunctions it
    # allocates through the C library as the original does.
    # No SourceFiles: the hybrid's sources wrap the original's binaries (linux64, win64) and
    # build nowhere on their own.
    for source_files in me.findall("SourceFiles"):
        me.remove(source_files)
    if len(me) == 0:
        me.text = None


def _log_categories(root) -> list[str]:
    """The original's categories; adds the one the wrapper logs its errors under."""
    element = root.find("LogCategories")
    if element is None:
        element = etree.Element("LogCategories")
        _insert_in_order(root, element)
    names = [c.get("name") for c in element.findall("Category")]
    if WRAPPER_LOG_CATEGORY not in names:
        etree.SubElement(element, "Category", name=WRAPPER_LOG_CATEGORY,
                         description="Calls rejected with fmi2Error")
    return names


def _define_dimensionless_unit(root) -> None:
    """The gates' unit "1" in UnitDefinitions, unless the original defines it already."""
    units = root.find("UnitDefinitions")
    if units is None:
        units = etree.Element("UnitDefinitions")
        _insert_in_order(root, units)
    if all(unit.get("name") != DIMENSIONLESS for unit in units.findall("Unit")):
        etree.SubElement(units, "Unit", name=DIMENSIONLESS)


def _insert_in_order(root, element) -> None:
    rank = _ELEMENT_ORDER.index(element.tag)
    for position, child in enumerate(root):
        if isinstance(child.tag, str) and child.tag in _ELEMENT_ORDER and _ELEMENT_ORDER.index(child.tag) > rank:
            root.insert(position, element)
            return
    root.append(element)


def _variable_label(state: str) -> str:
    """A readable name part for state x: x itself when it composes into a structured name."""
    if _STRUCTURED_NAME.match(state):
        return state
    label = re.sub(r"\W+", "_", state).strip("_")
    return label if label and not label[0].isdigit() else f"x_{label}"


def _name_prefix(existing: set[str]) -> str:
    """'hybrid', or 'hybrid_<n>' if the original already uses names under 'hybrid'."""
    for prefix in ("hybrid", *(f"hybrid_{n}" for n in range(1, 1000))):
        if not any(name == prefix or name.startswith(prefix + ".") or name.startswith(prefix + "[")
                   for name in existing):
            return prefix
    raise FmuBuilderError("the original FMU uses every variable prefix hybrid_1..999; rename its variables")


def _add_channel_variables(variables, spec: HybridSpec, info) -> list[ChannelLayout]:
    scalar_variables = variables.findall("ScalarVariable")
    by_name = {sv.get("name"): sv for sv in scalar_variables}
    prefix = _name_prefix(set(by_name))
    next_vr = max((v.value_reference for v in info.variables.values()), default=-1) + 1
    state_index = {d.name: i for i, d in enumerate(info.derivatives)}
    layout = []
    words = _words(spec)
    for c, (channel, state) in enumerate(zip(spec.channels, spec.channel_states(info))):
        base = f"{prefix}.{_variable_label(state)}"
        if any(f"{base}.{suffix}" in by_name for suffix in (words.gate, "p_fmu", words.value)):
            base = f"{prefix}.channel{c + 1}"
        der_real = by_name[channel].find("Real")
        p_ann = _append_variable(
            variables, f"{base}.{words.gate}", next_vr, causality="parameter", variability="tunable",
            initial="exact", description=f"Gate of {words.thing} in {channel} (0 switches it off)",
            start=spec.p_ann[c], real_attributes={"unit": DIMENSIONLESS})
        p_fmu = _append_variable(
            variables, f"{base}.p_fmu", next_vr + 1, causality="parameter", variability="tunable",
            initial="exact", description=f"Gate of the original model's term in {channel}", start=spec.p_fmu[c],
            real_attributes={"unit": DIMENSIONLESS})
        unit_attributes = {k: der_real.get(k) for k in ("declaredType", "quantity", "unit")
                           if der_real is not None and der_real.get(k) is not None}
        ann = _append_variable(
            variables, f"{base}.{words.value}", next_vr + 2, causality="local", variability="continuous",
            description=f"Value of {words.thing} for {channel} before gating", real_attributes=unit_attributes)
        layout.append(ChannelLayout(
            channel=channel, state=state, state_index=state_index[channel],
            der_vr=info.variable(channel).value_reference, p_ann=p_ann, p_ann_vr=next_vr,
            p_fmu=p_fmu, p_fmu_vr=next_vr + 1, ann=ann, ann_vr=next_vr + 2))
        next_vr += 3
    return layout


def _append_variable(variables, name: str, vr: int, *, causality: str, variability: str, description: str,
                     initial: str | None = None, start: float | None = None,
                     real_attributes: dict | None = None) -> str:
    attributes = {"name": name, "valueReference": str(vr), "description": description,
                  "causality": causality, "variability": variability}
    if initial is not None:
        attributes["initial"] = initial
    element = etree.SubElement(variables, "ScalarVariable", attributes)
    real = etree.SubElement(element, "Real", real_attributes or {})
    if start is not None:
        real.set("start", repr(float(start)))
    return name


# -- ModelStructure -----------------------------------------------------------------------------

def _update_structure(root, spec: HybridSpec, info) -> None:
    structure = root.find("ModelStructure")
    names = [sv.get("name") for sv in root.find("ModelVariables").findall("ScalarVariable")]
    index_of = {name: i + 1 for i, name in enumerate(names)}
    unknowns = {section: {names[int(u.get("index")) - 1]: u for u in structure.iterfind(f"{section}/Unknown")}
                for section in ("Outputs", "Derivatives", "InitialUnknowns")}
    state_names = {s.name for s in info.states}
    network_deps = _network_dependencies(spec, info, unknowns, index_of, state_names)
    corrected = [(channel, "Derivatives") for channel in spec.channels] + [(a, "Outputs") for a in spec.aliases]
    for name, section in corrected:
        unknown = unknowns[section].get(name)
        if unknown is not None:   # a local alias has no entry
            _merge_dependencies(unknown, network_deps)
        initial = unknowns["InitialUnknowns"].get(name)
        if initial is not None:  # initial dependencies through the network are not tracked
            _drop_dependencies(initial)


def _network_dependencies(spec, info, unknowns, index_of, state_names) -> set[int] | None:
    """Indices of the states and inputs the network inputs depend on; None when unknown."""
    dependencies: set[int] = set()
    for name in spec.inputs:
        var = info.variable(name)
        if name in state_names or var.causality == "input":
            dependencies.add(index_of[name])
        elif var.causality in ("parameter", "calculatedParameter", "independent") or var.variability == "constant":
            continue  # not a state or input: no entry in the dependency lists
        else:
            listed = unknowns["Derivatives"].get(name, unknowns["Outputs"].get(name))
            if listed is None or listed.get("dependencies") is None:
                return None
            dependencies.update(int(i) for i in listed.get("dependencies").split())
    return dependencies


def _merge_dependencies(unknown, extra: set[int] | None) -> None:
    if unknown.get("dependencies") is None:
        return  # already "depends on everything"
    if extra is None:
        _drop_dependencies(unknown)
        return
    own = [int(i) for i in unknown.get("dependencies").split()]
    kinds = unknown.get("dependenciesKind")
    kind_of = dict(zip(own, kinds.split())) if kinds is not None else {}
    merged = sorted(set(own) | extra)
    unknown.set("dependencies", " ".join(str(i) for i in merged))
    if kinds is not None:
        # The network term is nonlinear in its inputs.
        unknown.set("dependenciesKind", " ".join(
            kind_of[i] if i in kind_of and i not in extra else "dependent" for i in merged))


def _drop_dependencies(unknown) -> None:
    for attribute in ("dependencies", "dependenciesKind"):
        unknown.attrib.pop(attribute, None)
