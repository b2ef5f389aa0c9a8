"""Warm start through the closed loop: Gauss-Newton on the ANN's last layer.

The hybrid's correction is linear in the last layer of the ANN (the hidden layers' random tanh
features of the standardised inputs are a basis), so for an effect that is small against the
model's own dynamics the simulated signals are nearly linear in those weights. Their sensitivities
(the Jacobian of the loss residuals over all elements) are taken by finite differences, one
simulation without gradient per weight (17 for a 16x16 ANN on one channel), and a damped
Gauss-Newton step (Levenberg-Marquardt, the damping picked among a few by the loss it reaches)
solves for the weights at once. Unlike collocation, which forces the measured states into the
model and reads its controllers' reaction to the sensor noise and lag as if it were the effect,
this fits what the loss sees: the closed-loop response of the measured signals. Between
iterations the element starts are captured again from the hybrid, so the unmeasured states (a
controller's integrator) follow the correction.
"""
from __future__ import annotations

import math

import torch

# Damping factors tried per step, relative to the mean diagonal of J^T J.
DAMPING = (1e-6, 1e-4, 1e-2, 1e-1)
# Finite-difference step of a last-layer weight (the ANN output is in units of the channel's spread).
DELTA = 1e-2


def gauss_newton_warm_start(trainer, iterations: int) -> dict:
    """Fit the last layer of the ANN by damped Gauss-Newton steps through the solver (see the
    module docstring). Returns the losses before and after each step and the simulations used."""
    topology = trainer.model.topology
    last = topology.ann[-1]
    parameters = [last.weight, last.bias]
    simulations = 0
    losses = []
    for _ in range(iterations):
        if not topology.is_neutral():
            trainer._capture_starts(plain=False)
            simulations += 1
        residual = trainer.scaled_residuals()
        loss = float(residual @ residual)
        losses.append(loss)
        theta = _flat(parameters)
        jacobian = torch.empty(residual.numel(), theta.numel(), dtype=residual.dtype)
        for k in range(theta.numel()):
            shifted = theta.clone()
            shifted[k] += DELTA
            _assign(parameters, shifted)
            jacobian[:, k] = (trainer.scaled_residuals() - residual) / DELTA
        simulations += 1 + theta.numel()
        best = (loss, theta)
        for candidate in _damped_steps(jacobian, residual, theta):
            _assign(parameters, candidate)
            trial = trainer.scaled_residuals()
            simulations += 1
            value = float(trial @ trial)
            if math.isfinite(value) and value < best[0]:
                best = (value, candidate)
        _assign(parameters, best[1])
        if best[0] >= loss:
            break
        losses.append(best[0])
    if not topology.is_neutral():
        trainer._capture_starts(plain=False)
        simulations += 1
    return {"losses": losses, "simulations": simulations}


def _damped_steps(jacobian: torch.Tensor, residual: torch.Tensor, theta: torch.Tensor):
    """theta + delta for each damping: (J^T J + mu I) delta = -J^T r."""
    normal = jacobian.T @ jacobian
    gradient = jacobian.T @ residual
    scale = float(torch.diagonal(normal).mean()) or 1.0
    for damping in DAMPING:
        matrix = normal + damping * scale * torch.eye(len(theta), dtype=normal.dtype)
        yield theta - torch.linalg.solve(matrix, gradient)


def _flat(parameters) -> torch.Tensor:
    return torch.cat([p.detach().reshape(-1) for p in parameters]).clone()


def _assign(parameters, values: torch.Tensor) -> None:
    offset = 0
    with torch.no_grad():
        for p in parameters:
            p.copy_(values[offset:offset + p.numel()].reshape(p.shape))
            offset += p.numel()
