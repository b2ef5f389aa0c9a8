"""The hybrid right-hand side as one autograd node.

A solver stage evaluates the FMU (with its Jacobian when a gradient is wanted), adds the
discrete-state correction c, and passes the result through the topology: some thirty tiny torch
operations, whose autograd bookkeeping cost more than the arithmetic. `HybridRhs` does the same in
numpy and writes the vector-Jacobian product by hand:

    out = fmu(x, p) + c                         [B, n + k]: derivatives, FMU variables
    a   = gather(x, out)                        ANN inputs
    z   = (a - pre_shift) * pre_scale
    o   = L_m(act(... act(L_1(z))))             Linear layers W_i, b_i
    r   = o * post_scale + post_shift
    dx  = out[:, :n] with dx[:, ch] = gate_ann * r + gate_fmu * out[:, ch]

Backward, from (g_dx, g_out): the gates, post-processing, layers (reverse), pre-processing and the
gather are differentiated in turn; the result reaches x directly, and through the FMU's
Jacobian (g_out J), and the packed topology tensors theta. The values equal the torch topology's to
round-off; the gradients are checked against finite differences in tests/neural.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np
import torch
from torch import nn

from .topology import Topology

_FORWARD = {nn.Tanh: np.tanh, nn.Sigmoid: lambda z: 0.5 * (1.0 + np.tanh(0.5 * z)),
            nn.ReLU: lambda z: np.maximum(z, 0.0)}


def _activation_grad(kind, y: np.ndarray) -> np.ndarray:
    """d act / d pre-activation, from the activation's output y."""
    if kind is nn.Tanh:
        return 1.0 - y * y
    if kind is nn.Sigmoid:
        return y * (1.0 - y)
    return (y > 0.0).astype(y.dtype)


class RhsPlan:
    """How to unpack theta and run the topology in numpy, built once per simulation."""

    def __init__(self, topology: Topology):
        self.n = topology.n_states
        self.k_top = len(topology.fmu_variables)
        self.source = topology.input_source.numpy().copy()
        self.channels = np.array(topology.channel_index, dtype=int)
        names = ["pre_shift", "pre_scale", "post_scale", "post_shift", "gate_ann", "gate_fmu"]
        self.tensors: list[torch.Tensor] = [getattr(topology, name) for name in names]
        self.layers = []   # (index of W in tensors, index of b, activation type or None)
        modules = list(topology.ann)
        for i, module in enumerate(modules):
            if isinstance(module, nn.Linear):
                act = type(modules[i + 1]) if i + 1 < len(modules) and not isinstance(modules[i + 1], nn.Linear) else None
                self.layers.append((len(self.tensors), len(self.tensors) + 1, act))
                self.tensors += [module.weight, module.bias]
        self.trainable = [t.requires_grad for t in self.tensors]
        self.offsets = np.cumsum([0] + [t.numel() for t in self.tensors])
        self.shapes = [tuple(t.shape) for t in self.tensors]
        self.unique_sources = len(set(self.source.tolist())) == len(self.source)

    def pack(self) -> torch.Tensor:
        """theta: all topology tensors in one vector (differentiable w.r.t. the trainable ones)."""
        return torch.cat([t.reshape(-1) for t in self.tensors])

    def unpack(self, theta: np.ndarray) -> list[np.ndarray]:
        return [theta[a:b].reshape(shape) for a, b, shape in zip(self.offsets[:-1], self.offsets[1:], self.shapes)]


def hybrid_rhs(plan: RhsPlan, evaluator, rows: Sequence[int], t: np.ndarray, x: torch.Tensor, c, theta: torch.Tensor,
               p: torch.Tensor, u: np.ndarray | None):
    """(dx [R, n], out [R, n + k]) of the hybrid model, as one autograd node."""
    if c is None:
        c = _NO_CORRECTION
    return HybridRhs.apply(x, c, theta, p, plan, evaluator, rows, t, u)


_NO_CORRECTION = torch.zeros(0, dtype=torch.float64)


class HybridRhs(torch.autograd.Function):
    @staticmethod
    def forward(ctx, x, c, theta, p, plan: RhsPlan, evaluator, rows, t, u):
        want_x, want_p = ctx.needs_input_grad[0], ctx.needs_input_grad[3]
        x_np = x.detach().numpy()
        out, Jx, Jp = evaluator.evaluate(rows, t, x_np, u, jac_x=want_x, jac_p=want_p)
        if c.numel():
            out += c.detach().numpy()
        params = plan.unpack(theta.detach().numpy())
        pre_shift, pre_scale, post_scale, post_shift, gate_ann, gate_fmu = params[:6]
        n = plan.n
        a = np.concatenate((x_np, out[:, : n + plan.k_top]), axis=1)[:, plan.source]
        activations = [(a - pre_shift) * pre_scale]
        for w_index, b_index, act in plan.layers:
            z = activations[-1] @ params[w_index].T + params[b_index]
            activations.append(_FORWARD[act](z) if act is not None else z)
        o = activations[-1]
        r = o * post_scale + post_shift
        dx = out[:, :n].copy()
        dx[:, plan.channels] = gate_ann * r + gate_fmu * out[:, plan.channels]
        ctx.saved = (plan, params, a, activations, r, out, Jx, Jp, x_np.shape[0])
        ctx.has_c = bool(c.numel())
        return torch.from_numpy(dx), torch.from_numpy(out)

    @staticmethod
    def backward(ctx, g_dx, g_out):
        plan, params, a, activations, r, out, Jx, Jp, rows = ctx.saved
        pre_shift, pre_scale, post_scale, post_shift, gate_ann, gate_fmu = params[:6]
        n, ch = plan.n, plan.channels
        g_dx = g_dx.numpy()
        g_out = g_out.numpy().copy()
        grads = [None] * len(params)
        # dx: pass-through derivatives and the mixed channels
        g_out[:, :n] += g_dx
        g_mix = g_dx[:, ch]
        g_out[:, ch] += g_mix * gate_fmu - g_dx[:, ch]   # the channels were replaced, not passed through
        grads[4] = (g_mix * r).sum(0)
        grads[5] = (g_mix * out[:, ch]).sum(0)
        g_r = g_mix * gate_ann
        o = activations[-1]
        grads[2] = (g_r * o).sum(0)
        grads[3] = g_r.sum(0)
        g = g_r * post_scale
        for layer in range(len(plan.layers) - 1, -1, -1):
            w_index, b_index, act = plan.layers[layer]
            if act is not None:
                g = g * _activation_grad(act, activations[layer + 1])
            grads[w_index] = g.T @ activations[layer]
            grads[b_index] = g.sum(0)
            g = g @ params[w_index]
        grads[1] = (g * (a - pre_shift)).sum(0)
        grads[0] = -(g * pre_scale).sum(0)
        g_a = g * pre_scale
        # scatter the ANN-input gradient back to x and out
        g_cat = np.zeros((rows, 2 * n + plan.k_top))
        if plan.unique_sources:
            g_cat[:, plan.source] = g_a
        else:
            np.add.at(g_cat, (slice(None), plan.source), g_a)
        g_x = g_cat[:, :n]
        g_out[:, : n + plan.k_top] += g_cat[:, n:]
        if Jx is not None:
            g_x = g_x + np.matmul(g_out[:, None, :], Jx)[:, 0, :]
        g_theta = None
        if ctx.needs_input_grad[2]:
            g_theta = np.zeros(plan.offsets[-1])
            for i, grad in enumerate(grads):
                if plan.trainable[i]:
                    g_theta[plan.offsets[i]:plan.offsets[i + 1]] = grad.reshape(-1)
            g_theta = torch.from_numpy(g_theta)
        g_p = torch.from_numpy(np.matmul(g_out[:, None, :], Jp)[:, 0, :].sum(0)) if Jp is not None else None
        g_c = torch.from_numpy(g_out) if ctx.has_c and ctx.needs_input_grad[1] else None
        return torch.from_numpy(g_x), g_c, g_theta, g_p, None, None, None, None, None
