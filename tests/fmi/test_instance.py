"""The cffi binding against fmpy's ctypes binding of the same FMU (an independent importer)."""
import numpy as np
import pytest

from fmubuilder.errors import FmuBuilderError
from fmubuilder.fmi import Fmu, FmuCallError
from tests.reference_fmus import reference_fmu


def initialized(fmu, **start):
    inst = fmu.instantiate()
    inst.setup_experiment(start_time=0.0)
    inst.set(start)
    inst.enter_initialization_mode()
    inst.exit_initialization_mode()
    inst.update_discrete_states()
    inst.enter_continuous_time_mode()
    return inst


def fmpy_initialized(path, unzipdir, md, **start):
    from fmpy.fmi2 import FMU2Model
    model = FMU2Model(guid=md.guid, unzipDirectory=unzipdir,
                      modelIdentifier=md.modelExchange.modelIdentifier, instanceName="reference")
    model.instantiate()
    model.setupExperiment(startTime=0.0)
    by_name = {v.name: v for v in md.modelVariables}
    for name, value in start.items():
        model.setReal([by_name[name].valueReference], [value])
    model.enterInitializationMode()
    model.exitInitializationMode()
    model.newDiscreteStates()
    model.enterContinuousTimeMode()
    return model


@pytest.fixture
def fmu(bouncing_ball_fmu):
    with Fmu(bouncing_ball_fmu) as fmu:
        yield fmu


def test_values_agree_with_fmpy(fmu, bouncing_ball_fmu):
    from fmpy import read_model_description
    md = read_model_description(str(bouncing_ball_fmu))
    ours = initialized(fmu, h=2.0)
    theirs = fmpy_initialized(bouncing_ball_fmu, str(fmu.archive.directory), md, h=2.0)
    n, nz = fmu.info.n_states, fmu.info.n_event_indicators
    state_vrs = [v.value_reference for v in fmu.info.states]
    for x in ([2.0, 0.0], [0.5, -3.0], [1.25, 4.0]):
        ours.set_time(0.1)
        ours.set_continuous_states(x)
        theirs.setTime(0.1)
        theirs.setContinuousStates(_c_doubles(x), n)
        np.testing.assert_array_equal(ours.get_continuous_states(), x)
        np.testing.assert_array_equal(ours.get_derivatives(), _fmpy_derivatives(theirs, n))
        np.testing.assert_array_equal(ours.get_event_indicators(), _fmpy_indicators(theirs, nz))
        # the readers that write into a given array (the NeuralFMU's evaluation row)
        row = np.full(n + 2, np.nan)
        ours.derivatives_into(row[:n])
        ours.real_reader(state_vrs)(row[n:])
        np.testing.assert_array_equal(row, np.concatenate([_fmpy_derivatives(theirs, n), theirs.getReal(state_vrs)]))
    ours.free()
    theirs.terminate()
    theirs.freeInstance()


def _c_doubles(values):
    import ctypes
    return (ctypes.c_double * len(values))(*values)


def _fmpy_derivatives(model, n):
    out = _c_doubles([0.0] * n)
    model.getDerivatives(out, n)
    return np.array(out)


def _fmpy_indicators(model, nz):
    out = _c_doubles([0.0] * nz)
    model.getEventIndicators(out, nz)
    return np.array(out)


def test_instances_are_independent(fmu):
    a = initialized(fmu, h=1.0)
    b = initialized(fmu, h=5.0)
    a.set_continuous_states([0.3, 1.0])
    assert b.get_continuous_states()[0] == 5.0
    assert a.get_continuous_states()[0] == 0.3
    a.free()
    b.free()


def test_fmu_state_round_trip_and_serialization(fmu):
    inst = initialized(fmu, h=1.0)
    snapshot = inst.get_fmu_state()
    blob = inst.serialize_fmu_state(snapshot)
    inst.set_time(0.2)
    inst.set_continuous_states([0.1, -2.0])
    restored = inst.deserialize_fmu_state(blob)
    inst.set_fmu_state(restored)
    np.testing.assert_array_equal(inst.get_continuous_states(), [1.0, 0.0])
    inst.free_fmu_state(snapshot)
    inst.free_fmu_state(restored)
    inst.free()


def test_directional_derivative_matches_finite_differences(fmu):
    inst = initialized(fmu, h=1.0)
    states = [v.value_reference for v in fmu.info.states]
    ders = [v.value_reference for v in fmu.info.derivatives]
    x = np.array([0.7, 1.5])
    inst.set_continuous_states(x)
    for i in range(2):
        seed = np.eye(2)[i]
        jv = inst.get_directional_derivative(ders, states, seed)
        eps = 1e-6
        inst.set_continuous_states(x + eps * seed)
        up = inst.get_derivatives()
        inst.set_continuous_states(x - eps * seed)
        down = inst.get_derivatives()
        inst.set_continuous_states(x)
        np.testing.assert_allclose(jv, (up - down) / (2 * eps), atol=1e-8)
    inst.free()


def test_wrong_state_call_raises_with_the_fmus_message(fmu):
    inst = fmu.instantiate()
    with pytest.raises(FmuCallError, match="fmi2GetDerivatives returned fmi2Error: .*Instantiated"):
        inst.get_derivatives()
    inst.free()


def test_get_and_set_by_name(fmu):
    inst = initialized(fmu, h=3.0, e=0.5)
    assert inst.get(["h", "e"]) == [3.0, 0.5]
    with pytest.raises(FmuBuilderError, match="unknown variable 'hh'.*did you mean 'h'"):
        inst.set({"hh": 1.0})
    inst.free()


def test_a_call_in_the_wrong_state_raises_through_the_generic_path_too(fmu):
    """The status test inlined in FmuInstance._call: an error raises, OK passes."""
    inst = fmu.instantiate()
    with pytest.raises(FmuCallError, match="fmi2EnterContinuousTimeMode returned fmi2Error"):
        inst.enter_continuous_time_mode()
    inst.setup_experiment(start_time=0.0)
    inst.free()


def test_values_of_every_type_pass_through_the_feedthrough():
    """Set and read by name, one variable of each FMI type: the Reference FMUs' Feedthrough copies
    each input to its output."""
    inputs = {"Float64_continuous_input": 2.5, "Int32_input": -7, "Boolean_input": True, "String_input": "a \"b\" c",
              "Enumeration_input": 2}
    with Fmu(reference_fmu("Feedthrough")) as fmu:
        inst = fmu.instantiate()
        inst.setup_experiment(start_time=0.0)
        inst.enter_initialization_mode()
        inst.exit_initialization_mode()
        inst.set(inputs)
        outputs = inst.get([name.replace("input", "output") for name in inputs])
        assert inst.get(list(inputs)) == outputs == list(inputs.values())
        assert [type(v) for v in outputs] == [np.float64, int, bool, str, int]
        inst.free()
