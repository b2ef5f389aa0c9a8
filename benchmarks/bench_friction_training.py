"""What the training through the solver does to the DC drive's frictions, loss evaluation by loss evaluation.

The NeuralFMU as `hybridize` trains it on the Stribeck and Coulomb truths' training part (the
first 80 % of the training run; der(speed) <- speed, the inputs the workflow chooses; the loss on
current, power, energy and temperature, the signals the diagnosis finds the effect in; the
collocation warm start; L-BFGS; RK4 at 0.01 s), without the rest of `hybridize` (no diagnosis,
no other candidates). After the warm start and after every optimizer step the hybrid is simulated
over the test run and the whole training run and scored as MSE / noise variance per signal (1 =
the noise floor): a measurement of how the test error moves with the work, which `hybridize`
itself never looks at. Also printed: the loss, its terms per signal (each signal's MSE over its
divisor, see --loss), the CPU time of the training.

Variants of the training, to compare on equal work: `--elements N` (the training part in N
elements, hybridize: recipe.MIN_ELEMENTS), `--loss` (`noise`, hybridize's for a run of one
element: the mean over the signals of MSE / noise variance, TrainSettings.loss_scale, the loss and
its terms printed in noise variances; `relative`: of MSE / the plain FMU's MSE, hybridize's before
and for runs of several elements; `log`: of log(MSE / the plain FMU's MSE), Trainer.batch_loss
replaced for this run),
`--validation` (end at the best score on the held-out late 20 % of the run,
Trainer.validation_score, as hybridize's ANN candidates do, instead of the lowest loss).

    python benchmarks/bench_friction_training.py [--cases stribeck,coulomb] [--budget N] [--elements N]
                                                 [--loss noise|relative|log] [--validation]
"""
from __future__ import annotations

import argparse
import time

import numpy as np
import torch

from fmubuilder.build import example_fmu
from fmubuilder.data import read_sidecar
from fmubuilder.examples_zoo import cached_data, example_data_sets
from fmubuilder.fmi import read_model_info
from fmubuilder.hybridize import recipe
from fmubuilder.hybridize.evaluate import read_data
from fmubuilder.neural import train_neural_fmu
from fmubuilder.neural.train import Trainer, TrainSettings, Validation

STEP = 0.01
LOSS_SIGNALS = ["current", "power", "energy", "temperature"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", default="stribeck,coulomb")
    parser.add_argument("--budget", type=int, default=5, help="loss evaluations")
    parser.add_argument("--elements", type=int, default=recipe.MIN_ELEMENTS)
    parser.add_argument("--loss", choices=["noise", "relative", "log"], default=recipe.LOSS_SCALE)
    parser.add_argument("--validation", action="store_true", help="end at the best validation score")
    args = parser.parse_args()
    if args.loss == "log":
        Trainer.batch_loss = _log_loss
    rows = []
    for case in args.cases.split(","):
        rows += run_case(case.strip(), args)
    print(f"\nTest MSE / noise variance, {args.budget} loss evaluations, {args.elements} element(s), "
          f"loss {args.loss}, ending at {'the best validation score' if args.validation else 'the lowest loss'}:\n")
    print("| case | after | loss (mean of the terms) | speed | current | power | energy | temperature |")
    print("|---|---|---|---|---|---|---|---|")
    for row in rows:
        print("| " + " | ".join(row) + " |")


def _log_loss(self, batch, carry: bool = True) -> torch.Tensor:
    errors = self._signal_errors(batch, keep_final_state=carry)
    return sum(torch.log(errors[name] / self.scale[name]) for name in self.loss_signals) / len(self.loss_signals)


def run_case(variant: str, args) -> list[list[str]]:
    sets = [s for s in example_data_sets("dc_drive") if s.variant.key == variant]
    paths, _ = cached_data(sets)
    by_role = {s.cycle.role: p for s, p in zip(sets, paths)}
    declared = example_fmu("dc_drive")
    info = read_model_info(declared)
    run, test = read_data(by_role["train"], info), read_data(by_role["test"], info)
    fit_window, held_out = recipe.held_out_windows(run)
    train = run.window(*fit_window)
    bench = read_sidecar(by_role["test"])["bench"]
    floor = {s: bench["noise_std"][s] ** 2 / bench["runs"] for s in run.signals}
    validation = Validation(run, held_out, run.start_values) \
        if args.validation else None
    rows = []

    def scored(trainer, label: str) -> None:
        errors = {"test": trainer.errors(test, test.start_values), "run": trainer.errors(run, run.start_values)}
        ratios = {role: {s: e[s]["mse"] / floor[s] for s in e} for role, e in errors.items()}
        terms = trainer.signal_losses()
        loss = float(np.mean(list(terms.values())))
        print(f"{variant} after {label}: loss {loss:.4g}, terms {_format(terms)}, "
              f"whole training run {_format(ratios['run'])}, test {_format(ratios['test'])}", flush=True)
        rows.append([variant, label, f"{loss:.4g}", *(f"{ratios['test'][s]:.3g}" for s in run.signals)])

    def on_epoch(epoch: int, trainer) -> bool:
        if epoch == 1:   # the warm start alone: the parameters the first step started from
            scored(_Snapshot(trainer, trainer.best_state), "the warm start")
        scored(trainer, f"{trainer.loss_evaluations} evaluations")
        return False

    cpu = time.process_time()
    result = train_neural_fmu(declared, train, targets=["der(speed)"], inputs=["speed"],
                              start_values=train.start_values, topology="residual", budget=args.budget, seed=0,
                              solver="rk4", step_size=STEP, progress=False, on_epoch=on_epoch,
                              validation=validation, loss_signals=LOSS_SIGNALS, warm_start=True,
                              element_length=(train.stop - train.start) / args.elements,
                              ccpt_window=recipe.COLLOCATION_WINDOW, optimizer="lbfgs",
                              loss_scale="noise" if args.loss == "noise" else "plain")
    cpu = time.process_time() - cpu
    print(f"{variant}: warm start {result.metrics['warm_start']}; validation {result.metrics['validation']}; "
          f"{result.metrics['loss_evaluations']} evaluations, {cpu:.0f} s CPU", flush=True)
    model = result.model
    try:
        trainer = Trainer(model, train, _scoring_settings(train), 0.0)
        errors = trainer.errors(test, test.start_values)
        rows.append([variant, "the end", "", *(f"{errors[s]['mse'] / floor[s]:.3g}" for s in run.signals)])
    finally:
        model.close()
    return rows


def _scoring_settings(train) -> TrainSettings:
    """The training's step, solver and sensor lag, for Trainer.errors."""
    return TrainSettings(solver="rk4", step_size=STEP, sensor_lag=train.sensor_lag, progress=False)


class _Snapshot:
    """The trainer's errors at other parameters (those the first step started from)."""

    def __init__(self, trainer, state):
        self.trainer, self.state = trainer, state

    def _with_state(self, call):
        topology = self.trainer.model.topology
        current = {k: v.detach().clone() for k, v in topology.state_dict().items()}
        topology.load_state_dict(self.state)
        try:
            return call()
        finally:
            topology.load_state_dict(current)

    def errors(self, data, start_values):
        return self._with_state(lambda: self.trainer.errors(data, start_values))

    def signal_losses(self):
        return self._with_state(self.trainer.signal_losses)


def _format(ratios: dict) -> str:
    return ", ".join(f"{s} {v:.3g}" for s, v in ratios.items())


if __name__ == "__main__":
    main()
