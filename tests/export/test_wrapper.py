"""The exported hybrid FMU (wrapper around the original binary) against independent references:
fmpy's validation and simulation, the original FMU, the Python reference (original FMU +
onnxruntime), a C host that loads the FMU with RTLD_GLOBAL, and valgrind."""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import fmpy
import numpy as np
import pytest
from fmpy.validation import validate_fmu

from fmubuilder.build import build_cmake_project, example_fmu
from fmubuilder.errors import FmuBuilderError
from fmubuilder.export import HybridSpec, export_hybrid, validate_hybrid
from fmubuilder.export.reference import HybridReference
from fmubuilder.export.validate import FIXED_STEP_TOLERANCE, simulate_fmpy_euler
from fmubuilder.fmi import Fmu, FmuCallError, read_model_info
from fmubuilder.fmi.binding import ffi

HERE = Path(__file__).resolve().parent
FMI_HEADERS = Path(fmpy.__file__).parent / "c-code"


# -- building blocks ---------------------------------------------------------------------------

def make_network(path: Path, n_inputs: int, n_outputs: int, seed: int) -> Path:
    """A small random MLP as float64 ONNX: freeze() when torch is there, else onnx.helper."""
    try:
        import torch
        from fmubuilder.export import freeze
    except ImportError:
        return _onnx_mlp(path, n_inputs, n_outputs, seed)
    torch.manual_seed(seed)
    network = torch.nn.Sequential(torch.nn.Linear(n_inputs, 6), torch.nn.Tanh(), torch.nn.Linear(6, n_outputs))
    freeze(network, n_inputs, path)
    return path


def _onnx_mlp(path: Path, n_inputs: int, n_outputs: int, seed: int) -> Path:
    import onnx
    from onnx import TensorProto, helper, numpy_helper
    rng = np.random.default_rng(seed)
    weights = {"w1": rng.normal(size=(n_inputs, 6)), "b1": rng.normal(size=6),
               "w2": rng.normal(size=(6, n_outputs)), "b2": rng.normal(size=n_outputs)}
    nodes = [helper.make_node("Gemm", ["input", "w1", "b1"], ["h1"]), helper.make_node("Tanh", ["h1"], ["a1"]),
             helper.make_node("Gemm", ["a1", "w2", "b2"], ["output"])]
    graph = helper.make_graph(
        nodes, "mlp", [helper.make_tensor_value_info("input", TensorProto.DOUBLE, [1, n_inputs])],
        [helper.make_tensor_value_info("output", TensorProto.DOUBLE, [1, n_outputs])],
        [numpy_helper.from_array(v.astype(np.float64), k) for k, v in weights.items()])
    onnx.save(helper.make_model(graph, opset_imports=[helper.make_opsetid("", 17)]), path)
    return path


def make_hybrid(folder: Path, original: Path, channels, inputs, seed: int = 0, **gates):
    folder.mkdir(parents=True, exist_ok=True)
    info = read_model_info(original)
    network = make_network(folder / "network.onnx", len(inputs), len(channels), seed)
    spec = HybridSpec(original_fmu=original, original_guid=info.guid, channels=channels, inputs=inputs,
                      onnx=network, **gates)
    spec_path = spec.save(folder / "spec.json")
    hybrid = export_hybrid(spec_path, folder / f"{info.model_identifier}_hybrid.fmu")
    return HybridSpec.load(spec_path), hybrid


class Hybrid:
    def __init__(self, spec, fmu):
        self.spec, self.fmu = spec, fmu
        self.info = read_model_info(fmu)
        self.original_info = read_model_info(spec.original_fmu)

    def gate(self, channel: str, which: str) -> str:
        """Name of a gate parameter, found through the variable's description."""
        for var in self.info.variables.values():
            if var.name.endswith("." + which) and var.description and channel in var.description:
                return var.name
        raise KeyError(channel)


@pytest.fixture(scope="module")
def ball(tmp_path_factory):
    spec, fmu = make_hybrid(tmp_path_factory.mktemp("ball"), example_fmu("bouncing_ball"),
                            ["der(v)"], ["h", "v", "der(v)"], seed=1)
    return Hybrid(spec, fmu)


@pytest.fixture(scope="module")
def plant(tmp_path_factory):
    """Two channels; network inputs of all kinds: states, an FMU input, a discrete Real, an Integer."""
    spec, fmu = make_hybrid(tmp_path_factory.mktemp("plant"), example_fmu("sampled_plant"),
                            ["der(i)", "der(w)"], ["i", "w", "setpoint", "u", "samples"], seed=2,
                            p_ann=[0.5, 1.0], p_fmu=[1.0, 0.9])
    return Hybrid(spec, fmu)


@pytest.fixture(scope="module")
def corner(tmp_path_factory):
    spec, fmu = make_hybrid(tmp_path_factory.mktemp("corner"), example_fmu("event_corner_cases"),
                            ["der(r)"], ["r", "p"], seed=3)
    return Hybrid(spec, fmu)


@pytest.fixture(scope="module")
def self_calling(tmp_path_factory):
    """An original whose fmi2GetReal calls its own exported fmi2GetDerivatives."""
    build = build_cmake_project(HERE / "self_calling", tmp_path_factory.mktemp("self_calling_build"))
    original = build.fmus()[0]
    spec, fmu = make_hybrid(tmp_path_factory.mktemp("self_calling"), original, ["der(x)"], ["x", "der(x)"], seed=4)
    return Hybrid(spec, fmu)


@pytest.fixture(scope="module")
def drive(tmp_path_factory):
    """The DC drive's output `power` is der(energy) in the original: an alias of the channel."""
    spec, fmu = make_hybrid(tmp_path_factory.mktemp("drive"), example_fmu("dc_drive"), ["der(energy)"],
                            ["temperature", "speed"], seed=6, p_ann=[40.0], aliases={"power": "der(energy)"})
    return Hybrid(spec, fmu)


@pytest.fixture(scope="module")
def host(tmp_path_factory):
    if shutil.which("cc") is None:
        pytest.skip("no C compiler")
    binary = tmp_path_factory.mktemp("host") / "fmu_host"
    subprocess.run(["cc", "-O1", "-g", "-I", str(FMI_HEADERS), str(HERE / "host" / "fmu_host.c"), "-o", str(binary),
                    "-ldl"], check=True)
    return binary


def extracted(fmu: Path, folder: Path):
    """(library path, resources URI) of an FMU extracted to `folder`."""
    with zipfile.ZipFile(fmu) as archive:
        archive.extractall(folder)
    identifier = read_model_info(fmu).model_identifier
    return folder / "binaries" / "linux64" / f"{identifier}.so", (folder / "resources").as_uri() + "/"


def compared_signals(hybrid: Hybrid) -> list[str]:
    info = hybrid.original_info
    names = [v.name for v in info.outputs] + [s.name for s in info.states]
    return list(dict.fromkeys(names + [d.name for d in info.derivatives]))


def plant_input():
    time = np.linspace(0.0, 2.0, 5)
    data = np.zeros(time.size, dtype=[("time", float), ("setpoint", float)])
    data["time"], data["setpoint"] = time, [1.0, 2.0, 2.0, 0.5, 1.5]
    return data


# -- the model description ----------------------------------------------------------------------

@pytest.mark.parametrize("name", ["ball", "plant", "corner", "self_calling"])
def test_fmpy_validation_passes(name, request):
    hybrid = request.getfixturevalue(name)
    assert validate_fmu(str(hybrid.fmu)) == []


def test_model_description_keeps_original_and_adds_gates(ball):
    original, info = ball.original_info, ball.info
    for name, var in original.variables.items():
        assert info.variables[name].value_reference == var.value_reference
        assert info.variables[name].unit == var.unit
    assert info.guid != original.guid
    assert info.model_identifier == "bouncing_ball_hybrid"
    assert info.generation_tool == "fmubuilder"
    p_ann = info.variable(ball.gate("der(v)", "p_ann"))
    assert (p_ann.causality, p_ann.variability, float(p_ann.start)) == ("parameter", "tunable", 1.0)
    added = set(info.variables) - set(original.variables)
    assert added == {"hybrid.v.p_ann", "hybrid.v.p_fmu", "hybrid.v.ann"}
    original_vrs = {v.value_reference for v in original.variables.values()}
    assert not {info.variables[n].value_reference for n in added} & original_vrs
    # Honest capabilities: FMU state as the original, no directional derivatives.
    assert info.capabilities.can_get_and_set_fmu_state == original.capabilities.can_get_and_set_fmu_state
    assert original.capabilities.provides_directional_derivative
    assert not info.capabilities.provides_directional_derivative
    # der(v) now depends on the states the network reads (h and v, indices 1 and 3).
    md = fmpy.read_model_description(str(ball.fmu))
    der_v = next(u for u in md.derivatives if u.variable.name == "der(v)")
    assert sorted(v.name for v in der_v.dependencies) == ["h", "v"]


def test_fmu_ships_original_binary_resources_and_sources(tmp_path):
    original = example_fmu("bouncing_ball")
    with_resource = tmp_path / "ball_with_resource.fmu"
    with zipfile.ZipFile(original) as source, zipfile.ZipFile(with_resource, "w") as target:
        for item in source.infolist():
            target.writestr(item, source.read(item))
        target.writestr("resources/tables/data.txt", "1 2 3\n")
    _, hybrid = make_hybrid(tmp_path / "out", with_resource, ["der(v)"], ["h", "v"])
    names = set(zipfile.ZipFile(hybrid).namelist())
    assert {"resources/bouncing_ball.so", "resources/tables/data.txt", "binaries/linux64/bouncing_ball_hybrid.so",
            "sources/hybrid_wrapper.c", "sources/hybrid_ann.c", "sources/hybrid_ann.h",
            "modelDescription.xml"} <= names


# -- p_ann = 0, p_fmu = 1: the original model exactly ------------------------------------------

@pytest.mark.parametrize("solver", ["Euler", "CVode"])
@pytest.mark.parametrize("name", ["ball", "plant", "corner", "self_calling"])
def test_gates_off_reproduce_the_original_exactly(name, solver, request):
    hybrid = request.getfixturevalue(name)
    gates = {hybrid.gate(c, "p_ann"): 0.0 for c in hybrid.spec.channels}
    gates.update({hybrid.gate(c, "p_fmu"): 1.0 for c in hybrid.spec.channels})
    signals = compared_signals(hybrid)
    options = dict(solver=solver, step_size=1e-3 if solver == "Euler" else None, output=signals,
                   input=plant_input() if name == "plant" else None)
    original = fmpy.simulate_fmu(str(hybrid.spec.original_fmu), **options)
    wrapped = fmpy.simulate_fmu(str(hybrid.fmu), start_values=gates, **options)
    assert original.shape == wrapped.shape
    for signal in ["time", *signals]:
        np.testing.assert_array_equal(wrapped[signal], original[signal], err_msg=signal)


# -- the network on: the hybrid FMU against the Python reference -----------------------------------

def test_ball_round_trip_matches_reference(ball):
    report = validate_hybrid(ball.fmu)
    assert report.passed, report.format_table()
    for comparison in report.comparisons[:2]:   # the fixed-step ones
        assert comparison.max_rel <= FIXED_STEP_TOLERANCE
    # The network matters: the hybrid leaves the original by far more than the tolerances.
    options = dict(solver="Euler", step_size=1e-3, output=["v"], record_events=False)
    original = fmpy.simulate_fmu(str(ball.spec.original_fmu), **options)
    wrapped = fmpy.simulate_fmu(str(ball.fmu), **options)
    assert np.max(np.abs(original["v"] - wrapped["v"])) > 1e-2


def test_plant_round_trip_with_inputs_and_gates(plant, tmp_path):
    data = tmp_path / "data.csv"
    rows = ["time,setpoint,not_an_input"] + [f"{float(t)!r},{float(s)!r},7" for t, s in plant_input()]
    data.write_text("\n".join(rows) + "\n")
    start = {plant.gate("der(w)", "p_ann"): 0.25, "Kp": 0.3}
    report = validate_hybrid(plant.fmu, spec=plant.spec, data_csv=data, start_values=start)
    assert report.passed, report.format_table()


def test_corner_cases_round_trip_with_event_at_start_time(corner):
    report = validate_hybrid(corner.fmu)
    assert report.passed, report.format_table()
    result = fmpy.simulate_fmu(str(corner.fmu), output=["start_ticks", "start_ticks_seen", "resets"])
    assert result["start_ticks"][0] == 1 and result["start_ticks_seen"][0] == 1
    assert result["resets"][-1] == 3   # terminated at t_terminate = 3.5


def test_vldm_hybrid_with_local_inputs(tmp_path):
    """A realistic plant; the network reads locals, whose dependencies are not declared."""
    inputs = ["speed", "der(speed)", "motor_torque", "air_resistance_force"]
    spec, fmu = make_hybrid(tmp_path, example_fmu("vldm"), ["der(speed)"], inputs, seed=5)
    assert validate_fmu(str(fmu)) == []
    report = validate_hybrid(fmu, stop_time=5.0)
    assert report.passed, report.format_table()


def test_validation_detects_a_different_network(ball, tmp_path):
    """The round trip fails when the FMU does not compute what the spec says."""
    other_network = make_network(tmp_path / "other.onnx", 3, 1, seed=99)
    other = HybridSpec(original_fmu=ball.spec.original_fmu, original_guid=ball.spec.original_guid,
                       channels=ball.spec.channels, inputs=ball.spec.inputs, onnx=other_network)
    report = validate_hybrid(ball.fmu, spec=other)
    assert not report.passed
    assert report.comparisons[0].max_rel > 1e-3


def test_reference_derivative_matches_fmu_derivative_pointwise(plant):
    """fmi2GetDerivatives of the hybrid vs the reference at random states."""
    rng = np.random.default_rng(0)
    with Fmu(plant.fmu) as hybrid_fmu, Fmu(plant.spec.original_fmu) as original:
        wrapped = hybrid_fmu.instantiate()
        reference = HybridReference(original, plant.spec, variables=["i"])
        reference.initialize(0.0, 1.0)
        wrapped.setup_experiment(0.0, 1.0)
        wrapped.enter_initialization_mode()
        wrapped.exit_initialization_mode()
        wrapped.update_discrete_states()
        wrapped.enter_continuous_time_mode()
        for t in rng.uniform(0, 1, 20):
            x = rng.normal(size=2)
            wrapped.set_time(t)
            wrapped.set_continuous_states(x)
            expected = reference.derivatives(t, x)
            np.testing.assert_allclose(wrapped.get_derivatives(), expected, rtol=1e-13, atol=1e-13)
            der = wrapped.get(["der(i)", "der(w)"])
            np.testing.assert_allclose(der, expected, rtol=1e-13, atol=1e-13)
        wrapped.free()
        reference.close()


# -- several instances ------------------------------------------------------------------------

def euler_run(instance, steps: int, h: float, start: dict) -> np.ndarray:
    """Plain Euler without events, one step at a time; returns the state trajectory."""
    instance.set(start)
    instance.setup_experiment(0.0)
    instance.enter_initialization_mode()
    instance.exit_initialization_mode()
    instance.update_discrete_states()
    instance.enter_continuous_time_mode()
    x = instance.get_continuous_states()
    trajectory = [x]
    for n in range(steps):
        yield
        x = x + h * instance.get_derivatives()
        instance.set_time((n + 1) * h)
        instance.set_continuous_states(x)
        trajectory.append(x)
    instance.terminate()
    yield np.array(trajectory)


def test_instances_are_independent(ball):
    settings = [{"hybrid.v.p_ann": 0.0, "e": 0.5}, {"hybrid.v.p_ann": 2.0, "g": 3.0}, {}]
    with Fmu(ball.fmu) as fmu:
        alone = []
        for start in settings:
            instance = fmu.instantiate()
            *_, trajectory = euler_run(instance, 200, 1e-3, start)
            instance.free()
            alone.append(trajectory)
        instances = [fmu.instantiate() for _ in settings]
        runs = [euler_run(inst, 200, 1e-3, start) for inst, start in zip(instances, settings)]
        together = [None] * len(runs)
        while any(t is None for t in together):
            for k, run in enumerate(runs):   # interleave the instances step by step
                if together[k] is None:
                    value = next(run)
                    if value is not None:
                        together[k] = value
        for instance in instances:
            instance.free()
    for a, b in zip(alone, together):
        np.testing.assert_array_equal(a, b)
    assert not np.allclose(alone[0], alone[1])


# -- symbol binding: the original calls its own exported functions ----------------------------------

def test_self_calling_original_under_rtld_global_host(self_calling, host, tmp_path):
    library, resources = extracted(self_calling.fmu, tmp_path / "fmu")
    der_x = self_calling.info.variable("der(x)").value_reference
    ann = self_calling.info.variable("hybrid.x.ann").value_reference
    steps, h = 100, 0.01
    result = subprocess.run([str(host), str(library), self_calling.info.guid, resources, "1", "0", "1",
                             str(steps), repr(h), str(der_x), str(ann)], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    x_end, der_end, ann_end = (float(v) for v in result.stdout.split())

    with Fmu(self_calling.spec.original_fmu) as original:
        reference = HybridReference(original, self_calling.spec, variables=["x", "der(x)"])
        run = simulate_fmpy_euler(reference, 0.0, steps * h, h)
        network = reference.network(np.array([x_end, -0.5 * x_end]))
    assert x_end == pytest.approx(run.values["x"][-1], rel=1e-12)
    assert der_end == pytest.approx(run.values["der(x)"][-1], rel=1e-12)
    assert ann_end == pytest.approx(network[0], rel=1e-12)


FMPY_AFTER_GLOBAL_LOAD = """
import ctypes, os, sys, fmpy
ctypes.CDLL(sys.argv[1], mode=os.RTLD_NOW | os.RTLD_GLOBAL)
result = fmpy.simulate_fmu(sys.argv[2], solver="Euler", step_size=0.01, output=["x", "der(x)"],
                           record_events=False)
print(repr(float(result["x"][-1])), repr(float(result["der(x)"][-1])))
"""


def test_self_calling_original_in_fmpy_after_rtld_global_load(self_calling, tmp_path):
    """A Python host that loaded the wrapper with RTLD_GLOBAL, then simulates with fmpy.

    Runs in a subprocess: the global fmi2* symbols would capture any other FMU this test
    process loads without RTLD_DEEPBIND (the original FMU of the reference, for one)."""
    library, _ = extracted(self_calling.fmu, tmp_path / "global")
    result = subprocess.run([sys.executable, "-c", FMPY_AFTER_GLOBAL_LOAD, str(library), str(self_calling.fmu)],
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr[-2000:]
    x_end, der_end = (float(v) for v in result.stdout.split())
    with Fmu(self_calling.spec.original_fmu) as original:
        reference = HybridReference(original, self_calling.spec, variables=["x", "der(x)"])
        run = simulate_fmpy_euler(reference, 0.0, 2.0, 0.01)
    assert x_end == pytest.approx(run.values["x"][-1], rel=1e-12)
    assert der_end == pytest.approx(run.values["der(x)"][-1], rel=1e-12)


# -- capabilities and the state machine -----------------------------------------------------------

def started(instance):
    instance.setup_experiment(0.0)
    instance.enter_initialization_mode()
    instance.exit_initialization_mode()
    instance.update_discrete_states()
    instance.enter_continuous_time_mode()
    return instance


def test_no_directional_derivatives(plant):
    assert not plant.info.capabilities.provides_directional_derivative
    with Fmu(plant.fmu) as fmu:
        instance = started(fmu.instantiate())
        vr = ffi.new("fmi2ValueReference[]", [1])
        out = ffi.new("double[]", 1)
        status = fmu.lib.fmi2GetDirectionalDerivative(instance.component, vr, 1, vr, 1, out, out)
        assert status == 3  # fmi2Error
        assert "does not support" in instance.messages[-1]
        instance.free()


def test_wrong_state_calls_return_error_with_message(ball):
    with Fmu(ball.fmu) as fmu:
        instance = fmu.instantiate()
        with pytest.raises(FmuCallError, match="must not be called in state Instantiated"):
            instance.get_derivatives()
        with pytest.raises(FmuCallError, match="must not be called in state Instantiated"):
            instance.enter_continuous_time_mode()
        started(instance)
        with pytest.raises(FmuCallError, match="tunable parameter hybrid.v.p_ann can be set"):
            instance.set({"hybrid.v.p_ann": 0.0})
        with pytest.raises(FmuCallError, match="computed and cannot be set"):
            instance.set({"hybrid.v.ann": 0.0})
        instance.enter_event_mode()
        instance.set({"hybrid.v.p_ann": 0.0})   # tunable: allowed in event mode
        assert instance.get(["hybrid.v.p_ann"]) == [0.0]
        instance.terminate()
        with pytest.raises(FmuCallError, match="must not be called in state Terminated"):
            instance.set_time(1.0)
        instance.free()


def test_null_component_and_bad_instantiation_do_not_crash(ball):
    with Fmu(ball.fmu) as fmu:
        lib = fmu.lib
        vr = ffi.new("fmi2ValueReference[]", [0])
        value = ffi.new("double[]", 1)
        assert lib.fmi2GetReal(ffi.NULL, vr, 1, value) == 3
        assert lib.fmi2GetDerivatives(ffi.NULL, value, 1) == 3
        assert lib.fmi2EnterEventMode(ffi.NULL) == 3
        lib.fmi2FreeInstance(ffi.NULL)
        instance = fmu.instantiate()
        callbacks = instance._callbacks
        resources = ffi.new("char[]", fmu.archive.resources_uri.encode())
        wrong_guid = lib.fmi2Instantiate(b"x", 0, b"{not-the-guid}", resources, callbacks, 0, 0)
        assert wrong_guid == ffi.NULL
        assert "does not match" in instance.messages[-1]
        co_simulation = lib.fmi2Instantiate(b"x", 1, ball.info.guid.encode(), resources, callbacks, 0, 0)
        assert co_simulation == ffi.NULL
        assert "Model Exchange only" in instance.messages[-1]
        # Without a resource location the original's binary is found next to the wrapper's.
        located = lib.fmi2Instantiate(b"x", 0, ball.info.guid.encode(), ffi.NULL, callbacks, 0, 0)
        assert located != ffi.NULL
        lib.fmi2FreeInstance(located)
        instance.free()


def test_fmu_state_includes_gates(ball):
    with Fmu(ball.fmu) as fmu:
        instance = started(fmu.instantiate())
        instance.enter_event_mode()
        instance.enter_continuous_time_mode()
        snapshot = instance.get_fmu_state()
        x0, dx0 = instance.get_continuous_states(), instance.get_derivatives()
        instance.enter_event_mode()
        instance.set({"hybrid.v.p_ann": 3.0})
        instance.enter_continuous_time_mode()
        instance.set_continuous_states(x0 + 0.5)
        assert not np.array_equal(instance.get_derivatives(), dx0)
        serialized = instance.serialize_fmu_state(snapshot)
        instance.set_fmu_state(snapshot)
        assert instance.get(["hybrid.v.p_ann"]) == [1.0]
        np.testing.assert_array_equal(instance.get_continuous_states(), x0)
        np.testing.assert_array_equal(instance.get_derivatives(), dx0)
        instance.free_fmu_state(snapshot)
        restored = instance.deserialize_fmu_state(serialized)
        instance.set_fmu_state(restored)
        np.testing.assert_array_equal(instance.get_derivatives(), dx0)
        instance.free_fmu_state(restored)
        instance.free()


def test_fmu_state_unsupported_when_the_original_lacks_it(self_calling):
    assert not self_calling.info.capabilities.can_get_and_set_fmu_state
    with Fmu(self_calling.fmu) as fmu:
        instance = started(fmu.instantiate())
        state = ffi.new("fmi2FMUstate*")
        assert fmu.lib.fmi2GetFMUstate(instance.component, state) == 3
        assert "does not support" in instance.messages[-1]
        instance.free()


@pytest.mark.slow
@pytest.mark.skipif(shutil.which("valgrind") is None, reason="valgrind is not installed")
def test_valgrind_finds_no_leaks_over_1000_cycles(ball, host, tmp_path):
    library, resources = extracted(ball.fmu, tmp_path / "fmu")
    ann = ball.info.variable("hybrid.v.ann").value_reference
    command = ["valgrind", "--leak-check=full", "--errors-for-leak-kinds=definite,indirect", "--error-exitcode=99",
               str(host), str(library), ball.info.guid, resources, "2", "1", "1000", "20", "0.05", str(ann)]
    result = subprocess.run(command, capture_output=True, text=True, timeout=600,
                            env={**os.environ, "FMU_HOST_FMU_STATE": "1"})
    assert result.returncode == 0, result.stderr[-3000:]
    assert "ERROR SUMMARY: 0 errors" in result.stderr
    assert "definitely lost: 0 bytes" in result.stderr or "no leaks are possible" in result.stderr


# -- export API, spec and command line --------------------------------------------------------------

def test_export_refuses_to_overwrite_without_force(ball, tmp_path):
    target = tmp_path / "hybrid.fmu"
    target.write_bytes(b"keep me")
    with pytest.raises(FmuBuilderError, match="exists"):
        export_hybrid(ball.spec, target)
    assert target.read_bytes() == b"keep me"
    export_hybrid(ball.spec, target, force=True)
    assert zipfile.is_zipfile(target)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["hybrid.fmu"]   # no temporary files left


def test_spec_json_round_trip_and_checks(ball, tmp_path):
    spec = ball.spec
    copy = HybridSpec.load(spec.save(tmp_path / "spec.json"))
    assert (copy.channels, copy.inputs, copy.p_ann, copy.p_fmu) == (spec.channels, spec.inputs, spec.p_ann, spec.p_fmu)
    assert copy.onnx.resolve() == spec.onnx.resolve()
    bad = [dict(channels=["h"]), dict(inputs=["h", "v", "nope"]), dict(inputs=["h", "v"]),
           dict(original_guid="{other}")]
    for change in bad:
        fields = dict(original_fmu=spec.original_fmu, original_guid=spec.original_guid, channels=spec.channels,
                      inputs=spec.inputs, onnx=spec.onnx)
        fields.update(change)
        with pytest.raises(FmuBuilderError):
            HybridSpec(**fields).check()
    with pytest.raises(FmuBuilderError, match="one per channel"):
        HybridSpec(original_fmu=spec.original_fmu, original_guid="g", channels=["der(v)"], inputs=["h"],
                   onnx=spec.onnx, p_ann=[1.0, 2.0])
    (tmp_path / "broken.json").write_text("{not json")
    with pytest.raises(FmuBuilderError, match="not a readable JSON"):
        HybridSpec.load(tmp_path / "broken.json")


def run_cli(*argv):
    import argparse
    from fmubuilder.cli.export import add_export_parsers
    parser = argparse.ArgumentParser(prog="fmubuilder")
    add_export_parsers(parser.add_subparsers())
    args = parser.parse_args([str(a) for a in argv])
    args.func(args)


def test_cli_export_and_validate(ball, tmp_path, capsys):
    spec_path = ball.spec.save(tmp_path / "spec.json")
    output = tmp_path / "cli_hybrid.fmu"
    run_cli("export", spec_path, "-o", output)
    assert validate_fmu(str(output)) == []
    with pytest.raises(FmuBuilderError, match="exists"):
        run_cli("export", spec_path, "-o", output)
    run_cli("validate", output, "--start", "hybrid.v.p_ann=0.5", "--stop-time", "1")
    table = capsys.readouterr().out
    assert "round trip: passed" in table and "der(v)" in table
    other = HybridSpec(original_fmu=ball.spec.original_fmu, original_guid=ball.spec.original_guid,
                       channels=ball.spec.channels, inputs=ball.spec.inputs,
                       onnx=make_network(tmp_path / "other.onnx", 3, 1, seed=42))
    with pytest.raises(FmuBuilderError, match="failed the round-trip"):
        run_cli("validate", output, "--against", other.save(tmp_path / "other.json"), "--stop-time", "1")
    assert "round trip: FAILED" in capsys.readouterr().out


# -- an output that equals a channel's derivative (alias) ----------------------------------------

def test_alias_output_is_corrected_like_its_derivative_in_fmpy(drive):
    assert validate_fmu(str(drive.fmu)) == []
    # The network reads temperature, on which the original's power does not depend.
    original = {u.variable.name: u for u in fmpy.read_model_description(str(drive.spec.original_fmu)).outputs}
    assert "temperature" not in [v.name for v in original["power"].dependencies]
    md = fmpy.read_model_description(str(drive.fmu))
    power = next(u for u in md.outputs if u.variable.name == "power")
    der_energy = next(u for u in md.derivatives if u.variable.name == "der(energy)")
    assert sorted(v.name for v in power.dependencies) == sorted(v.name for v in der_energy.dependencies)
    assert "temperature" in [v.name for v in power.dependencies]

    signals = ["power", "der(energy)", "energy"]
    plain = fmpy.simulate_fmu(str(drive.spec.original_fmu), output=signals)
    hybrid = fmpy.simulate_fmu(str(drive.fmu), output=signals)
    gates_off = fmpy.simulate_fmu(str(drive.fmu), output=signals,
                                  start_values={drive.gate("der(energy)", "p_ann"): 0.0})
    np.testing.assert_array_equal(plain["power"], plain["der(energy)"])   # an alias in the original
    np.testing.assert_array_equal(hybrid["power"], hybrid["der(energy)"])
    np.testing.assert_array_equal(gates_off["power"], plain["power"])
    # The correction is visible in power, and energy is its integral in the hybrid too.
    assert np.max(np.abs(hybrid["power"] - plain["power"])) > 1e-2 * np.max(np.abs(plain["power"]))
    steps = np.diff(hybrid["time"]) * (hybrid["power"][1:] + hybrid["power"][:-1]) / 2
    integral = np.concatenate([[0.0], np.cumsum(steps)])
    correction = np.max(np.abs(hybrid["energy"] - plain["energy"]))
    assert np.max(np.abs(hybrid["energy"] - hybrid["energy"][0] - integral)) < 1e-2 * correction


def test_alias_output_in_the_engine_and_the_reference_pointwise(drive):
    """fmi2GetReal of the alias vs the hybrid's own fmi2GetDerivatives and vs the reference."""
    rng = np.random.default_rng(1)
    energy = drive.original_info.state_index("energy")
    with Fmu(drive.fmu) as hybrid_fmu, Fmu(drive.spec.original_fmu) as original:
        wrapped = started(hybrid_fmu.instantiate())
        reference = HybridReference(original, drive.spec, variables=["power", "der(energy)"])
        reference.initialize(0.0, 1.0)
        x0 = wrapped.get_continuous_states()
        for t in rng.uniform(0, 1, 10):
            x = x0 * rng.uniform(0.5, 1.5, size=x0.size) + rng.normal(size=x0.size)
            wrapped.set_time(t)
            wrapped.set_continuous_states(x)
            power = wrapped.get(["power"])[0]
            assert power == wrapped.get_derivatives()[energy]
            expected = reference.outputs(np.array([t]), x[None, :])[0]
            np.testing.assert_allclose([power, power], expected, rtol=1e-13)
        wrapped.free()
        reference.close()
    from fmubuilder.simulation import simulate
    result = simulate(drive.fmu, stop_time=2.0, variables=["power", "der(energy)"])
    np.testing.assert_array_equal(result["power"], result["der(energy)"])


def test_alias_round_trip_matches_reference(drive):
    report = validate_hybrid(drive.fmu, stop_time=5.0)
    assert report.passed, report.format_table()
    assert all("power" in [s.name for s in c.signals] for c in report.comparisons if c.error is None)


def test_spec_aliases_json_and_checks(drive, tmp_path):
    spec = drive.spec
    assert spec.aliases == {"power": "der(energy)"}
    copy = HybridSpec.load(spec.save(tmp_path / "spec.json"))
    assert copy.aliases == spec.aliases
    # Specs written before aliases existed still load.
    path = tmp_path / "old.json"
    data = spec.to_dict(relative_to=tmp_path)
    del data["aliases"]
    path.write_text(__import__("json").dumps(data))
    assert HybridSpec.load(path).aliases == {}
    fields = dict(original_fmu=spec.original_fmu, original_guid=spec.original_guid, channels=spec.channels,
                  inputs=spec.inputs, onnx=spec.onnx)
    for aliases, message in [({"powr": "der(energy)"}, "unknown variable"),
                             ({"power": "der(speed)"}, "not a channel"),
                             ({"energy": "der(energy)"}, "not a continuous output"),
                             ({"nominal_resistance": "der(energy)"}, "not a continuous output")]:
        with pytest.raises(FmuBuilderError, match=message):
            HybridSpec(**fields, aliases=aliases).check()
    with pytest.raises(FmuBuilderError, match="mapping"):
        HybridSpec(**fields, aliases=["power"])
