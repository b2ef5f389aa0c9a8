"""The compiled simulation core (fmubuilder/simulation/core) against the Python loop it replaces:
with Euler and RK4 the same rows, values, events and counts, to the bit, on every example FMU and
on the Reference FMUs we did not write, with inputs (continuous and discrete), events recorded,
termination and failures; with DOPRI5 the same steps and events, values to round-off; and a build
that cannot happen is one line."""
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from fmubuilder.build import example_fmu, list_examples
from fmubuilder.errors import FmuBuilderError
from fmubuilder.fmi.instance import FmuCallError
from fmubuilder.simulation import simulate

from ..reference_fmus import reference_fmu


def both_loops(monkeypatch, path, **options):
    """(Python loop, compiled core) results of the same simulate() call."""
    monkeypatch.setenv("FMUBUILDER_ENGINE", "python")
    python = simulate(path, **options)
    monkeypatch.delenv("FMUBUILDER_ENGINE")
    return python, simulate(path, **options)


def assert_identical(python, compiled):
    assert python.names == compiled.names
    np.testing.assert_array_equal(compiled.time, python.time)
    for name in python.names:
        assert compiled[name].dtype == python[name].dtype, name
        np.testing.assert_array_equal(compiled[name], python[name], err_msg=name)
    assert compiled.events == python.events
    assert (compiled.terminated_early, compiled.stop_time) == (python.terminated_early, python.stop_time)
    counts = {**python.stats.as_dict(), "wall_time": 0.0}
    assert {**compiled.stats.as_dict(), "wall_time": 0.0} == counts


@pytest.mark.parametrize("solver", ["euler", "rk4"])
@pytest.mark.parametrize("name", [n for n in list_examples() if not n.startswith("vldm_")])
def test_examples_to_the_bit(monkeypatch, name, solver):
    stop = {"vldm": 60.0, "dc_drive": 5.0}
    options = dict(solver=solver, step_size=0.005, record_events=True)
    if name.split("_truth")[0] in stop:
        options["stop_time"] = stop[name.split("_truth")[0]]
    python, compiled = both_loops(monkeypatch, example_fmu(name), **options)
    assert_identical(python, compiled)
    assert compiled.stats.steps > 0


def assert_close(python, compiled, rtol):
    """DOPRI5 sums its stages in another order than numpy: the same events, values to round-off
    amplified by the step control at most to the tolerance, the steps and rejections alike (an
    error estimate within round-off of the acceptance limit may be taken either way)."""
    assert python.names == compiled.names
    assert [kind for _, kind in compiled.events] == [kind for _, kind in python.events]
    np.testing.assert_allclose([t for t, _ in compiled.events], [t for t, _ in python.events], rtol=0, atol=1e-9)
    np.testing.assert_allclose(compiled.time, python.time, rtol=0, atol=1e-9)
    for name in python.names:
        values, reference = compiled[name].astype(float), python[name].astype(float)
        scale = max(1.0, float(np.abs(reference).max()))
        np.testing.assert_allclose(values, reference, rtol=0, atol=rtol * scale, err_msg=name)
    for count in ("time_events", "state_events", "step_events"):
        assert getattr(compiled.stats, count) == getattr(python.stats, count), count
    for count in ("steps", "rejected_steps", "rhs_evaluations"):
        ours, theirs = getattr(compiled.stats, count), getattr(python.stats, count)
        assert abs(ours - theirs) <= 0.02 * theirs + 2, (count, ours, theirs)


@pytest.mark.parametrize("rtol", [1e-6, 1e-10])
@pytest.mark.parametrize("name", [n for n in list_examples() if not n.startswith("vldm_")])
def test_dopri5_takes_the_python_steps(monkeypatch, name, rtol):
    options = dict(rtol=rtol, atol=rtol, record_events=True)
    if name.split("_truth")[0] in ("vldm", "dc_drive"):
        options["stop_time"] = 30.0 if name == "vldm" else 5.0
    python, compiled = both_loops(monkeypatch, example_fmu(name), **options)
    assert_close(python, compiled, rtol=1e-7)


def test_dopri5_with_inputs_and_its_step_underflow(monkeypatch):
    path = example_fmu("sampled_plant")
    inputs = {"time": np.linspace(0.0, 2.0, 23), "setpoint": np.sin(3 * np.linspace(0.0, 2.0, 23))}
    python, compiled = both_loops(monkeypatch, path, stop_time=2.0, output_interval=0.05, inputs=inputs)
    assert_close(python, compiled, rtol=1e-9)
    messages = []
    for engine in ("python", "c"):      # a tolerance no step size can meet: the same one line
        monkeypatch.setenv("FMUBUILDER_ENGINE", engine)
        with pytest.raises(FmuBuilderError) as caught:
            simulate(example_fmu("dc_drive"), rtol=1e-300, atol=1e-300, stop_time=1.0)
        messages.append(str(caught.value))
    assert messages[0] == messages[1] and messages[0].startswith("step size underflow at t=")


def test_termination_and_every_event_kind(monkeypatch):
    """event_corner_cases asks to terminate at t = 3.5 after time, state and step events."""
    python, compiled = both_loops(monkeypatch, example_fmu("event_corner_cases"), stop_time=10.0, solver="rk4",
                                  step_size=0.01)
    assert_identical(python, compiled)
    assert compiled.terminated_early and compiled.stop_time == pytest.approx(3.5)
    stats = compiled.stats
    assert stats.time_events and stats.state_events and stats.step_events


def test_continuous_inputs_restart_at_their_samples(monkeypatch):
    path = example_fmu("sampled_plant")
    from fmubuilder.fmi import read_model_info
    names = [v.name for v in read_model_info(path).inputs if v.type == "Real" and v.variability == "continuous"]
    time = np.linspace(0.0, 2.0, 23)
    inputs = {"time": time, **{name: np.sin(3 * time + k) for k, name in enumerate(names)}}
    python, compiled = both_loops(monkeypatch, path, solver="rk4", step_size=0.013, stop_time=2.0,
                                  output_interval=0.05, inputs=inputs)
    assert_identical(python, compiled)


@pytest.mark.parametrize("name", ["BouncingBall", "Dahlquist", "Stair", "VanDerPol", "Resource"])
def test_reference_fmus(monkeypatch, name):
    python, compiled = both_loops(monkeypatch, reference_fmu(name), solver="rk4", step_size=1e-3,
                                  record_events=True)
    assert_identical(python, compiled)


def test_reference_feedthrough_with_discrete_inputs(monkeypatch):
    """Real, Integer and Boolean inputs: the discrete ones change in event mode at their samples."""
    path = reference_fmu("Feedthrough")
    from fmubuilder.fmi import read_model_info
    info = read_model_info(path)
    python, compiled = both_loops(monkeypatch, path, solver="euler", step_size=0.01, stop_time=2.0,
                                  inputs=feedthrough_inputs(info, enumeration=[1, 2, 2, 1, 2]),
                                  variables=[v.name for v in info.outputs if v.api_type != "String"],
                                  record_events=True)
    assert_identical(python, compiled)
    assert compiled.stats.time_events >= 3      # the discrete inputs' changes


def feedthrough_inputs(info, enumeration):
    time = np.array([0.0, 0.3, 0.55, 1.0, 1.7])
    inputs = {"time": time}
    for var in info.inputs:
        if var.type == "Real":
            inputs[var.name] = np.array([0.0, 1.5, -2.0, 0.25, 3.0])
        elif var.type == "Integer":
            inputs[var.name] = np.array([1, 2, 2, 5, 3])
        elif var.type == "Enumeration":
            inputs[var.name] = np.array(enumeration)
        elif var.type == "Boolean":
            inputs[var.name] = np.array([0, 1, 0, 0, 1])
    return inputs


def test_a_failing_fmi_call_is_the_same_error(monkeypatch):
    """Feedthrough refuses an enumeration value it does not declare when the input changes to it in
    the loop's event mode (t = 1): both loops raise the FMU's error with its message."""
    path = reference_fmu("Feedthrough")
    from fmubuilder.fmi import read_model_info
    inputs = feedthrough_inputs(read_model_info(path), enumeration=[1, 2, 2, 5, 1])
    errors = []
    for engine in ("python", "c"):
        monkeypatch.setenv("FMUBUILDER_ENGINE", engine)
        with pytest.raises(FmuCallError) as caught:
            simulate(path, solver="rk4", step_size=0.01, stop_time=2.0, inputs=inputs)
        errors.append((caught.value.function, caught.value.status, str(caught.value)))
    assert errors[0] == errors[1]
    assert errors[0][0] == "fmi2SetInteger" and "not a legal value" in errors[0][2]


def test_an_event_storm_is_the_same_error(monkeypatch):
    """A model that keeps scheduling events at one instant stops both loops with the same line; the
    limit lowered to 0 makes the sampled plant's first time event one too many."""
    from fmubuilder.simulation import core, events
    monkeypatch.setattr(events, "MAX_EVENTS_AT_ONE_TIME", 0)
    monkeypatch.setattr(core, "MAX_EVENTS_AT_ONE_TIME", 0)
    messages = []
    for engine in ("python", "c"):
        monkeypatch.setenv("FMUBUILDER_ENGINE", engine)
        with pytest.raises(FmuBuilderError) as caught:
            simulate(example_fmu("sampled_plant"), solver="rk4", step_size=0.01, stop_time=1.0)
        messages.append(str(caught.value))
    assert messages[0] == messages[1]
    assert messages[0].startswith("more than 0 events at t=")


def test_a_build_that_cannot_happen_is_one_line(tmp_path):
    """No C compiler: one line that says what to install, or how to go on without the core."""
    script = textwrap.dedent("""
        import sys
        from fmubuilder.errors import FmuBuilderError
        from fmubuilder.simulation import core
        try:
            core.library()
        except FmuBuilderError as exc:
            print(exc)
            sys.exit(3)
    """)
    env = {**os.environ, "FMUBUILDER_CACHE": str(tmp_path / "cache"), "CC": "", "PATH": str(tmp_path)}
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env, timeout=120)
    assert proc.returncode == 3, proc.stderr
    lines = proc.stdout.strip().splitlines()
    assert len(lines) == 1, proc.stdout
    assert "cannot build fmubuilder's compiled simulation core" in lines[0]
    assert "FMUBUILDER_ENGINE=python" in lines[0] and "install" in lines[0]
