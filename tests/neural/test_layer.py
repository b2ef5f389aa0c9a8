"""The FMU layer: values and Jacobians against central finite differences of the FMU itself,
with and without fmi2GetDirectionalDerivative."""
import numpy as np
import pytest
import torch

from fmubuilder.fmi import Fmu, read_model_info
from fmubuilder.neural.layer import FmuEvaluator, fmu_call


def initialized(fmu, **start):
    inst = fmu.instantiate()
    inst.setup_experiment(start_time=0.0)
    inst.set(start)
    inst.enter_initialization_mode()
    inst.exit_initialization_mode()
    inst.update_discrete_states()
    inst.enter_continuous_time_mode()
    return inst


def central_jacobian(evaluator, t, x, step=1e-6):
    """d(derivatives, variables)/dx by central differences of forward evaluations only."""
    columns = []
    for i in range(x.size):
        dx = np.zeros_like(x)
        dx[i] = step * max(1.0, abs(x[i]))
        plus, _, _ = evaluator.evaluate([0], np.array([t]), (x + dx)[None])
        minus, _, _ = evaluator.evaluate([0], np.array([t]), (x - dx)[None])
        columns.append((plus[0] - minus[0]) / (2 * dx[i]))
    return np.stack(columns, axis=1)


@pytest.mark.parametrize("method", ["directional", "fd"])
def test_ball_jacobian(ball_fmu, method):
    with Fmu(ball_fmu) as fmu:
        inst = initialized(fmu)
        try:
            ev = FmuEvaluator([inst], fmu.info, jacobian=method)
            x = np.array([0.7, -1.3])
            out, J, _ = ev.evaluate([0], np.array([0.2]), x[None], jac_x=True)
            np.testing.assert_allclose(out[0], [-1.3, -9.81])
            np.testing.assert_allclose(J[0], [[0.0, 1.0], [0.0, 0.0]], atol=1e-7)
            np.testing.assert_allclose(J[0], central_jacobian(ev, 0.2, x), atol=1e-7)
        finally:
            inst.free()


def test_vldm_jacobian_with_variables(vldm_fmu):
    """A model without directional derivatives; outputs as extra rows of the layer."""
    with Fmu(vldm_fmu) as fmu:
        inst = initialized(fmu, cycle=2)
        try:
            ev = FmuEvaluator([inst], fmu.info, variables=["power", "acceleration", "drive_force"])
            assert not fmu.info.capabilities.provides_directional_derivative
            x = inst.get_continuous_states()
            x[0] = 0.3   # throttle integrator: the throttle is active and unsaturated
            x[4] = 8.0   # speed
            out, J, _ = ev.evaluate([0], np.array([0.0]), x[None], jac_x=True)
            reference = central_jacobian(ev, 0.0, x)
            scale = np.abs(reference).max(axis=1, keepdims=True) + 1e-12
            assert np.abs(J[0] - reference).max() > 0  # not trivially zero
            np.testing.assert_allclose(J[0] / scale, reference / scale, atol=2e-6)
        finally:
            inst.free()


def test_autograd_applies_the_jacobian(ball_fmu):
    """backward of fmu_call is J^T v, checked against the FD Jacobian, batched over two instances."""
    with Fmu(ball_fmu) as fmu:
        insts = [initialized(fmu), initialized(fmu)]
        try:
            ev = FmuEvaluator(insts, fmu.info, jacobian="fd")
            x = torch.tensor([[0.5, 2.0], [1.5, -3.0]], dtype=torch.float64, requires_grad=True)
            p = torch.zeros(0, dtype=torch.float64)
            out = fmu_call(ev, [0, 1], np.array([0.0, 0.1]), x, p)
            weights = torch.tensor([[1.0, 2.0], [-3.0, 0.5]], dtype=torch.float64)
            (out * weights).sum().backward()
            # der(h) = v, der(v) = -g: d/dh = 0, d/dv = weight of der(h)
            np.testing.assert_allclose(x.grad.numpy(), [[0.0, 1.0], [0.0, -3.0]], atol=1e-7)
        finally:
            for inst in insts:
                inst.free()


def test_no_jacobian_without_grad(ball_fmu):
    with Fmu(ball_fmu) as fmu:
        inst = initialized(fmu)
        try:
            ev = FmuEvaluator([inst], fmu.info)
            x = torch.tensor([[0.5, 2.0]], dtype=torch.float64)
            fmu_call(ev, [0], np.array([0.0]), x, torch.zeros(0, dtype=torch.float64))
            assert ev.n_jacobian_columns == 0
        finally:
            inst.free()


def unfolded_hybrid(topology, x, out):
    """The topology's definition term by term (module docstring of topology.py): the reference
    for its folded evaluation."""
    der = out[:, : topology.n_states]
    r = topology.correction(topology.ann_inputs(x, out))
    channels = topology.channels_t
    mixed = topology.gate_ann * r + topology.gate_fmu * der.index_select(1, channels)
    return der.index_copy(1, channels, mixed)


@pytest.mark.parametrize("kind, activation", [("gates", "tanh"), ("gates", "sigmoid"), ("residual", "relu")])
def test_folded_topology_matches_its_definition(vldm_fmu, kind, activation):
    """Values and gradients of the folded hybrid (Topology.forward, as the solver evaluates it)
    against the term-by-term definition, through fmu_call with a discrete-state correction c and
    an FMU variable as ANN input."""
    from fmubuilder.neural import NeuralFMU, TopologyConfig

    torch.manual_seed(2)
    model = NeuralFMU(vldm_fmu, TopologyConfig(channels=["der(speed)", "der(energy)"],
                                               inputs=["speed", "der(speed)", "power"], hidden=[5, 3],
                                               activation=activation, kind=kind), start_values={"cycle": 2})
    with torch.no_grad():
        for p in model.topology.parameters():
            p.copy_(torch.randn_like(p))
    insts = model.instances(2)
    for inst in insts:
        inst.reset()
        inst.setup_experiment(0.0)
        inst.set({"cycle": 2})
        inst.enter_initialization_mode()
        inst.exit_initialization_mode()
        inst.update_discrete_states()
        inst.enter_continuous_time_mode()
    ev = FmuEvaluator(insts, model.info, variables=model.topology.fmu_variables)
    x0 = np.array([[0.3, 0.0, 5.0, 4.0, 8.0, 1e4], [0.1, 0.0, 50.0, 45.0, 12.0, 2e5]])
    t = np.array([0.0, 0.0])
    c0 = torch.randn(2, ev.width, dtype=torch.float64)
    weights = torch.randn(2, 6, dtype=torch.float64), torch.randn(2, ev.width, dtype=torch.float64)

    def gradients(hybrid):
        x = torch.tensor(x0, requires_grad=True)
        c = c0.clone().requires_grad_(True)
        model.topology.zero_grad()
        out = fmu_call(ev, [0, 1], t, x, model.topology.fmu_parameters) + c
        dx = hybrid(x, out)
        ((dx * weights[0]).sum() + (out * weights[1]).sum()).backward()
        grads = [x.grad, c.grad] + [q.grad.clone() if q.grad is not None else torch.zeros_like(q)
                                    for q in model.topology.parameters()]
        return dx.detach(), grads

    dx_folded, folded = gradients(model.topology)
    dx_reference, reference = gradients(lambda x, out: unfolded_hybrid(model.topology, x, out))
    torch.testing.assert_close(dx_folded, dx_reference, rtol=1e-12, atol=1e-12)
    assert any(float(g.abs().max()) > 0 for g in reference[2:])
    for a, b in zip(folded, reference):
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-9)
    model.close()


class _SwitchingInstance:
    """A stand-in FMU instance with der = [x1 if x0 > 0 else 0, -x0]: the first derivative's
    dependence on x1 appears only when x0 turns positive (a regime change)."""

    def __init__(self):
        self.x = np.zeros(2)

    def real_getter(self, vrs):
        return lambda: np.zeros(len(vrs))

    def real_reader(self, vrs):
        def fill(out):
            if out is None:
                return np.zeros(len(vrs))
            out[:] = 0.0
            return out
        return fill

    def real_setter(self, vrs):
        return lambda values: None

    def set_time(self, t):
        pass

    def set_continuous_states(self, x):
        self.x = np.array(x, dtype=float)

    def get_derivatives(self):
        return np.array([self.x[1] if self.x[0] > 0 else 0.0, -self.x[0]])

    def derivatives_into(self, out):
        out[:] = self.get_derivatives()


@pytest.mark.parametrize("declared", [False, True])
def test_a_column_zero_at_first_is_computed_after_a_regime_change(ball_fmu, declared):
    """Without a ModelStructure, the column of x1 is zero while x0 < 0 and must be non-zero at once
    when x0 > 0; with one (der 0 depends on x1, der 1 on x0) nothing needs probing."""
    import dataclasses
    info = read_model_info(ball_fmu)   # two states; the instance below replaces its binary
    names = [v.name for v in info.states]
    dependencies = {d.name: (names[1],) if i == 0 else (names[0],) for i, d in enumerate(info.derivatives)}
    info = dataclasses.replace(info, dependencies=dependencies if declared else {},
                               capabilities=dataclasses.replace(info.capabilities,
                                                                provides_directional_derivative=False))
    ev = FmuEvaluator([_SwitchingInstance()], info)
    for x0 in [-1.0, -0.5, -0.2, -0.1, -0.05, 0.5]:
        x = np.array([x0, 2.0])
        _, J, _ = ev.evaluate([0], np.array([0.0]), x[None], jac_x=True)
        expected = [[0.0, 1.0 if x0 > 0 else 0.0], [-1.0, 0.0]]
        np.testing.assert_allclose(J[0], expected, atol=1e-6)
    assert ev.sparsity.skipped == []
    assert ev.sparsity.complete == declared


def test_model_structure_columns_are_skipped(ball_fmu):
    """The ball declares der(h) on v and der(v) on nothing: the column of h is never computed."""
    with Fmu(ball_fmu) as fmu:
        inst = initialized(fmu)
        try:
            ev = FmuEvaluator([inst], fmu.info, jacobian="fd")
            assert ev.sparsity.complete and ev.sparsity.skipped == [0]
            x = np.array([0.4, 1.1])
            _, J, _ = ev.evaluate([0], np.array([0.0]), x[None], jac_x=True)
            assert ev.n_jacobian_columns == 1
            np.testing.assert_allclose(J[0], central_jacobian(ev, 0.0, x), atol=1e-7)
        finally:
            inst.free()
