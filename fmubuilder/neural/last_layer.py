"""The ANN's last layer refined through the simulation, after the training (Levenberg-Marquardt).

A few loss evaluations of L-BFGS leave the effect's level off by a fraction of a percent, and the
signals that integrate it (an energy, a temperature) turn that into tens of times their noise. The
correction is linear in the last layer's weights and bias, and the simulated signals nearly so: a
small least-squares problem (at most 17 unknowns per channel of 16 hidden units), which
Gauss-Newton solves in a few steps where a gradient method crawls.

    unknowns   -> moves of the last Linear layer's free entries (the blocks of its sub-networks) and
                  biases along the directions its hidden units span over the reference run
                  (_directions: orthogonal there, each moving the output by a root mean square of 1)
    residuals  -> (the hybrid's signals seen through the sensor lag - measured) / sqrt(N scale count),
                  over the training data, squared sum: the training loss (Trainer.scale)
    simulation -> the engine with the training's solver and step (no gradient: cheap)
    search     -> Levenberg-Marquardt, the Jacobian by forward differences (one simulation per
                  unknown), then kept up to date by Broyden's update after every trial (one
                  simulation each); a step kept only if it lowers the loss; at most `simulations`
                  simulations, fewer when the Gauss-Newton step promises next to nothing
                  (CONVERGED_BELOW). On the DC drive's Coulomb friction (budget 5, the 17 entries
                  as unknowns) the training loss 16.0 fell to 11.0 with fresh differences every
                  step (200 simulations), to 10.3 with Broyden's update and the ridge (100;
                  docs/MEASUREMENTS.md)
    validation -> with the trainer's validation data, every step kept is scored there too (a
                  simulation of the validation run each, not counted in `simulations`), and the
                  trainer keeps the best scored (Trainer.track_validation): the search stops early
                  where the held-out data say so, not only where the training loss ends (the
                  VLDM's wrong mass: the warm start's search lowered the training loss 15,316 ->
                  1141 by moving the speed and the power off to fit the energy; each of its steps
                  scored 8766 or more on the validation data, the plain model 1968, which the
                  trainer keeps; docs/MEASUREMENTS.md, "Each step of the last layer's search scored
                  on the validation data")
"""
from __future__ import annotations

import math

import numpy as np
import torch

from ..errors import FmuBuilderError
from ..progress import progress

# Finite-difference step of an unknown, relative to the largest move so far and at least 1e-2 of it
# (a move of 1 shifts the layer's output by a root mean square of 1 over the reference run).
PERTURBATION = 1e-3
# The directions searched: those of the hidden units' outputs and the bias' 1 over the reference
# run whose singular value is above this share of the largest. The units of one input are nearly
# dependent there (the VLDM's 16 tanh units of the speed: singular values from 1 down to 1e-8), and so
# are the layer's entries' Jacobian columns: Broyden's updates of it stalled, and the steps along the
# weakest directions grew weights of opposite signs that cancel and steer the output only where the
# data are sparse. The demo's warm start (its two searches, 65 simulations): along the 17 entries its
# training loss ended at 1.0183, the fastest speeds 3 % off, its validation score 12.7; along the 8
# directions above 1e-4 at 1.0172, 0.5 % off, 1.63; along the 6 above 1e-3 at 1.0172, 1 % off, 3.18
# (docs/MEASUREMENTS.md, "The last layer searched along its data's directions").
DIRECTIONS_ABOVE = 1e-4
DAMPING = 1e-3            # Marquardt's, relative to the diagonal of J^T J
DAMPING_FACTOR = 10.0
MAX_DAMPING = 1e3         # beyond it the Jacobian is taken by differences again (or, fresh, the search ends)
RIDGE = 1e-8              # weight of |unknowns - start|^2, relative to the mean diagonal of J^T J
# The search ends when the undamped Gauss-Newton step promises less than this share of the loss (by
# the Jacobian it has): on the VLDM's first 16 s the last 34 of 60 simulations moved the loss by 2e-6.
CONVERGED_BELOW = 1e-5


def refine_last_layer(trainer, simulations: int, label: str = "refining the ANN's last layer",
                      stage: tuple[int, str] = (0, "last layer")) -> dict | None:
    """Levenberg-Marquardt on the last layer of `trainer`'s ANN over its training data (see the
    module docstring); the parameters are left at the lowest loss found, every step kept scored on
    the trainer's validation data as `stage` (epoch, name; Trainer.track_validation). Returns what
    it did, or None when there is no layer to refine or no budget for one step. `label`: the
    progress bar's."""
    topology = trainer.model.topology
    if not topology.has_ann:
        return None
    problem = _Problem(trainer, topology, stage)
    start = problem.start()
    if simulations < start.size + 2:       # the start, a column per unknown, one trial
        return None
    with progress(simulations, label, "simulation", show=trainer.settings.progress) as bar:
        problem.bar = bar
        residual = problem.residual(start)
        before = _cost(residual)
        if not math.isfinite(before):
            bar.stop("the trained hybrid does not simulate over the training data")
            return {"simulations": problem.simulations, "loss_before": None, "loss_after": None, "kept": False}
        theta, after, ended = _levenberg_marquardt(problem, start, residual, simulations)
        problem.set(theta)
        bar.stop(ended)
    scores = problem.validation_scores
    return {"simulations": problem.simulations, "loss_before": before, "loss_after": after,
            "kept": after < before, "unknowns": start.size, "entries": problem.origin.size, "ended": ended,
            "validation_scores": scores, "best_validation": min(scores) if scores else None}


class _Problem:
    """The last layer's move from its start along `_directions` as a vector, and the training
    residuals at a move."""

    def __init__(self, trainer, topology, stage: tuple[int, str] = (0, "last layer")):
        self.trainer, self.layer, self.free = trainer, topology.ann[-1], topology.last_layer_free()
        self.simulations = 0
        self.stage, self.validation_scores = stage, []
        self.bar = None
        data = trainer.data
        count = len(trainer.loss_signals)
        self.norm = {name: math.sqrt(data.time.size * trainer.scale[name] * count) for name in trainer.loss_signals}
        self.origin = self._entries()
        self.directions = _directions(topology, trainer.reference_samples()[0], self.free.numpy())

    def start(self) -> np.ndarray:
        return np.zeros(self.directions.shape[1])

    def set(self, move: np.ndarray) -> None:
        self._set_entries(self.origin + self.directions @ move)

    def score_kept(self, move: np.ndarray) -> None:
        """A step kept: scored on the trainer's validation data, if it has any."""
        if self.trainer.validation is None:
            return
        self.set(move)
        self.validation_scores.append(self.trainer.track_validation(*self.stage))

    def _entries(self) -> np.ndarray:
        values = torch.cat([self.layer.weight.detach()[self.free], self.layer.bias.detach()])
        return values.numpy().copy()

    def _set_entries(self, theta: np.ndarray) -> None:
        n = int(self.free.sum())
        with torch.no_grad():
            weight = self.layer.weight.detach().clone()
            weight[self.free] = torch.from_numpy(theta[:n])
            self.layer.weight.copy_(weight)
            self.layer.bias.copy_(torch.from_numpy(theta[n:]))

    def residual(self, theta: np.ndarray) -> np.ndarray:
        """One simulation of the training data; all residuals inf when it fails."""
        trainer = self.trainer
        self.set(theta)
        self.simulations += 1
        if self.bar is not None:
            self.bar.advance(1)
        try:
            differences = trainer.engine_differences()
        except (FmuBuilderError, ArithmeticError):   # a trial step that makes the hybrid fail is not taken
            return np.full(trainer.data.time.size * len(trainer.loss_signals), math.inf)
        return np.concatenate([differences[name] / self.norm[name] for name in trainer.loss_signals])


def _directions(topology, inputs: np.ndarray, free: np.ndarray) -> np.ndarray:
    """[entries, m]: directions of the layer's free entries and biases over the raw ANN inputs
    [N, n_in] (`free`: the layer's free entries, [C, H]): per channel the right singular vectors
    of [its hidden units' outputs, 1] whose singular value is above DIRECTIONS_ABOVE of the largest,
    each scaled to move the channel's output (before the post-processing) by a root mean square of 1."""
    with torch.no_grad():
        units = topology.hidden_units(torch.from_numpy(np.ascontiguousarray(inputs))).numpy()
    count, n_weights = units.shape[0], int(free.sum())
    columns, offset = [], 0
    for channel, own in enumerate(free):
        width = int(own.sum())
        features = np.column_stack([units[:, own], np.ones(count)])
        _, singular, right = np.linalg.svd(features, full_matrices=False)
        for value, vector in zip(singular, right):
            if value > DIRECTIONS_ABOVE * singular[0]:
                column = np.zeros(n_weights + free.shape[0])
                column[offset:offset + width] = vector[:-1]
                column[n_weights + channel] = vector[-1]
                columns.append(column * math.sqrt(count) / value)
        offset += width
    return np.column_stack(columns)


def _levenberg_marquardt(problem: _Problem, theta: np.ndarray, residual: np.ndarray, budget: int):
    """(unknowns, their loss, why it ended). The Jacobian by forward differences, then corrected by
    Broyden's rank-one update after every trial (one simulation each instead of n + 1); taken by
    differences again when a step the updated one proposes fails at a large damping. The objective
    adds a ridge on the move from the start (RIDGE): hidden units with nearly the same output along
    the data leave directions the loss hardly sees, and steps along them grow weights of opposite
    signs that cancel (an ONNX export of such a layer no longer agrees with torch to round-off)."""
    origin, n = theta.copy(), theta.size
    ridge, damping = 0.0, DAMPING
    objective = lambda at, r: _cost(r) + ridge * float((at - origin) @ (at - origin))   # noqa: E731
    jacobian, fresh = None, False
    while problem.simulations < budget:
        if jacobian is None:
            if problem.simulations + n + 1 > budget:
                break
            jacobian, fresh, damping = _jacobian(problem, theta, residual), True, DAMPING
            if not np.all(np.isfinite(jacobian)):
                return theta, _cost(residual), "a perturbed run failed"
            ridge = ridge or RIDGE * float(np.sum(jacobian ** 2)) / n
        curvature = jacobian.T @ jacobian + ridge * np.eye(n)
        gradient = jacobian.T @ residual + ridge * (theta - origin)
        if _promised(curvature, gradient) < CONVERGED_BELOW * objective(theta, residual):
            return theta, _cost(residual), "converged"
        # Least squares, not solve: a derivative the measured signals do not see gives a zero Jacobian
        # (and no ridge), and its step is then none.
        step = np.linalg.lstsq(curvature + damping * np.diag(np.diag(curvature)), -gradient, rcond=None)[0]
        trial = problem.residual(theta + step)
        if np.all(np.isfinite(trial)) and step @ step > 0:
            jacobian = jacobian + np.outer(trial - residual - jacobian @ step, step) / (step @ step)
        if objective(theta + step, trial) < objective(theta, residual):
            theta, residual, fresh = theta + step, trial, False
            problem.score_kept(theta)
            damping /= DAMPING_FACTOR
            continue
        damping *= DAMPING_FACTOR
        if damping > MAX_DAMPING:
            if fresh:           # the differences' own Jacobian finds no lower loss
                return theta, _cost(residual), "no lower training loss found"
            jacobian = None
    return theta, _cost(residual), "the budget is spent"


def _jacobian(problem: _Problem, theta: np.ndarray, residual: np.ndarray) -> np.ndarray:
    """Forward differences, one simulation per unknown."""
    delta = PERTURBATION * max(float(np.max(np.abs(theta))), 1e-2)
    columns = []
    for k in range(theta.size):
        moved = theta.copy()
        moved[k] += delta
        columns.append((problem.residual(moved) - residual) / delta)
    return np.column_stack(columns)


def _promised(curvature: np.ndarray, gradient: np.ndarray) -> float:
    """The fall of the objective that the undamped Gauss-Newton step promises, by the linear model:
    g^T C^-1 g (the objective is |r|^2 + ridge term; its gradient 2g, its Hessian model 2C)."""
    try:
        return float(gradient @ np.linalg.solve(curvature, gradient))
    except np.linalg.LinAlgError:
        return math.inf


def _cost(residual: np.ndarray) -> float:
    return float(residual @ residual)
