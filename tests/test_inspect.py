"""`fmubuilder inspect` and the engine read completedIntegratorStepNotNeeded as the FMU declares it
(fmpy fills needsCompletedIntegratorStep for FMI 2.0, not the attribute's own field)."""
import zipfile

import pytest
from lxml import etree

from fmubuilder.build import example_fmu
from fmubuilder.cli import run as cli
from fmubuilder.fmi import read_model_info
from fmubuilder.fmi.instance import FmuInstance
from fmubuilder.simulation import simulate

from .fmi.broken_fmus import rewrite_fmu
from .reference_fmus import reference_fmu

NEEDED_LINE = "completedIntegratorStep needed"


def declaring(tmp_path, value: str | None):
    """The bouncing ball (which declares nothing) with completedIntegratorStepNotNeeded=value."""
    if value is None:
        return example_fmu("bouncing_ball")
    attribute = f'<ModelExchange\n    completedIntegratorStepNotNeeded="{value}"'
    return rewrite_fmu(example_fmu("bouncing_ball"), tmp_path / f"ball_{value}.fmu",
                       xml=lambda text: text.replace("<ModelExchange", attribute, 1))


def declared_not_needed(fmu) -> bool:
    """The attribute straight from the XML (default false)."""
    with zipfile.ZipFile(fmu) as archive:
        root = etree.fromstring(archive.read("modelDescription.xml"))
    return root.find("ModelExchange").get("completedIntegratorStepNotNeeded", "false") in ("true", "1")


def inspect_line(fmu, capsys) -> str:
    assert cli(["inspect", str(fmu)]) == 0
    return next(line for line in capsys.readouterr().out.splitlines() if NEEDED_LINE in line).split()[-1]


@pytest.mark.parametrize("value, needed", [("true", "no"), ("false", "yes"), (None, "yes")])
def test_inspect_reports_what_the_fmu_declares(value, needed, tmp_path, capsys):
    fmu = declaring(tmp_path, value)
    assert declared_not_needed(fmu) == (value == "true")
    assert read_model_info(fmu).capabilities.completed_integrator_step_not_needed == (value == "true")
    assert inspect_line(fmu, capsys) == needed


def test_the_vldm_and_a_reference_fmu(capsys):
    vldm = example_fmu("vldm")                       # declares completedIntegratorStepNotNeeded="true"
    assert declared_not_needed(vldm) and inspect_line(vldm, capsys) == "no"
    ball = reference_fmu("BouncingBall")             # declares nothing: needed
    assert not declared_not_needed(ball) and inspect_line(ball, capsys) == "yes"


@pytest.mark.parametrize("engine", ["python", "compiled"])
@pytest.mark.parametrize("value", ["true", "false"])
def test_the_engine_calls_completed_integrator_step_only_when_needed(value, engine, tmp_path, monkeypatch):
    calls = []
    if engine == "python":
        monkeypatch.setenv("FMUBUILDER_ENGINE", "python")
        original = FmuInstance.completed_integrator_step

        def counting(self, *args, **kwargs):
            calls.append(1)
            return original(self, *args, **kwargs)
        monkeypatch.setattr(FmuInstance, "completed_integrator_step", counting)
    else:
        count_core_calls(monkeypatch, calls)
    result = simulate(declaring(tmp_path, value), stop_time=1.0, solver="rk4", step_size=0.01)
    assert len(result.time) > 10
    assert (len(calls) > 0) == (value == "false")


def count_core_calls(monkeypatch, calls):
    """The compiled core's fmi2CompletedIntegratorStep passes through a counting callback."""
    from fmubuilder.simulation import core
    original, kept = core._fmu, []

    def with_counter(ffi, system, plan):
        fmu = original(ffi, system, plan)
        binary = fmu.completed_integrator_step

        def counting(component, no_prior_state, enter_event_mode, terminate):
            calls.append(1)
            return binary(component, no_prior_state, enter_event_mode, terminate)
        kept.append(ffi.callback("core_completed_step_fn", counting))
        fmu.completed_integrator_step = kept[-1]
        return fmu
    monkeypatch.setattr(core, "_fmu", with_counter)
