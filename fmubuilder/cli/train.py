"""`fmubuilder train`: the command-line face of fmubuilder.neural.train (torch loads only when it runs)."""
from __future__ import annotations

import argparse
import os

from ..errors import FmuBuilderError
from .common import (guide, fraction, loss_evaluations, number, parse_assignments, parse_names,
                     positive_number, seed, whole_number)
from .outputs import Plan, inputs_with_sidecars


def add_train_parser(subparsers, common=None) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "train", parents=[common] if common else [], epilog=guide("docs/how-it-works.md"), help="train a NeuralFMU (FMU + ANN on chosen derivatives) on measured data",
        description="Train a NeuralFMU: an ANN corrects chosen state derivatives of the FMU; it is fitted to "
                    "measured signals by simulating the hybrid model with the FMU's event handling.")
    p.add_argument("fmu", help="path of an FMI 2.0 Model-Exchange FMU")
    p.add_argument("--data", required=True, metavar="CSV",
                   help="measured data: `time` first, then columns named after FMU states/outputs (and inputs)")
    p.add_argument("--start", action="append", metavar="NAME=VALUE", help="start value of a parameter or state (repeatable)")
    p.add_argument("--target", action="append", required=True, metavar="DER",
                   help="derivative the ANN acts on, e.g. 'der(speed)' (repeatable)")
    p.add_argument("--inputs", required=True, metavar="A,B,...", help="FMU variables fed to the ANN")
    p.add_argument("--topology", default="residual", choices=["residual", "gates"],
                   help="residual: der + ANN correction (zero at the start); gates: gate_ann * ANN + gate_fmu * der "
                        "with gates 0 and 1 at the start (slower to leave the FMU). Default: residual")
    p.add_argument("--hidden", default="16,16", metavar="N,N", help="hidden layer sizes (default 16,16)")
    p.add_argument("--activation", default="tanh", choices=["tanh", "sigmoid", "relu"])
    p.add_argument("--parameters", metavar="A,B", help="tunable FMU parameters to train as well")
    work = p.add_mutually_exclusive_group()
    work.add_argument("--epochs", type=whole_number(0), help="default 30")
    work.add_argument("--budget", type=loss_evaluations, metavar="N",
                      help="train for N loss evaluations (each a simulation of a batch with its gradient) instead of "
                           "epochs")
    p.add_argument("--optimizer", default="adam", choices=["adam", "lbfgs"],
                   help="adam: one step per batch; lbfgs: one step over all elements per epoch, its line search "
                        "up to 10 loss evaluations (default adam)")
    p.add_argument("--time-budget", type=positive_number, metavar="SECONDS", help="stop training after this many seconds")
    p.add_argument("--element-length", type=positive_number, default=100.0, metavar="SECONDS", help="batch element length (default 100)")
    p.add_argument("--batch-size", type=whole_number(0), default=0, help="elements per optimizer step (default: all)")
    p.add_argument("--order", default="random", choices=["random", "sequential"])
    p.add_argument("--step-size", type=positive_number, help="solver step (default: the FMU's DefaultExperiment stepSize)")
    p.add_argument("--solver", default="euler", choices=["euler", "rk4"])
    p.add_argument("--lr", type=positive_number, default=3e-3, help="Adam step size (default 3e-3)")
    p.add_argument("--decay", type=fraction, default=0.95, help="step-size factor per epoch (default 0.95)")
    p.add_argument("--nipt", type=whole_number(0), default=400, metavar="ITERATIONS", help="neutral pre-training iterations (gates)")
    p.add_argument("--ccpt", type=whole_number(0), default=0, metavar="ITERATIONS", help="collocation pre-training iterations (default off)")
    p.add_argument("--loss", metavar="A,B", help="signals in the loss (default: all measured)")
    p.add_argument("--sensor-lag", type=number, metavar="SECONDS",
                   help="time constant of the sensors' first-order lag, applied to the simulated signals before "
                        "they meet the data (default: the bench's, recorded next to data from `fmubuilder synth`; else 0)")
    p.add_argument("--test-data", metavar="CSV", help="held-out data: its errors are added to the metrics")
    p.add_argument("--seed", type=seed, default=0, help=f"random seed (0 to 2**32-1, default 0)")
    p.add_argument("--resume", action="store_true",
                   help="continue from the checkpoint TRAINED.ckpt up to --epochs in all (same settings as before)")
    p.add_argument("--output", "-o", required=True, metavar="TRAINED",
                   help="file for the trained NeuralFMU (input of `fmubuilder export`). Beside it, TRAINED.ckpt "
                        "keeps the training's state after every epoch (network, optimizer, epoch count) for "
                        "--resume; delete it when the training is done")
    p.add_argument("--json", metavar="METRICS.json", help="write the errors before/after training as JSON")
    p.add_argument("--force", action="store_true", help="overwrite existing output files")
    p.set_defaults(func=cmd_train, plan=_plan)
    return p


def _plan(args) -> Plan:
    checkpoint = f"{args.output}.ckpt"
    files = [("--output", args.output)] + ([("--json", args.json)] if args.json else [])
    if args.resume:
        if not os.path.isfile(checkpoint):
            raise FmuBuilderError(f"no checkpoint {checkpoint} to resume from; train without --resume "
                                  "(with --force to replace the earlier output)")
    else:
        files.append(("the checkpoint of --output", checkpoint))
    return Plan(args.force or args.resume, files=files,
                inputs=inputs_with_sidecars(args.fmu, args.data, args.test_data) + ([checkpoint] if args.resume else []))


def cmd_train(args) -> None:
    from ..neural.train import TrainSettings, train_neural_fmu

    try:
        hidden = [int(h) for h in parse_names(args.hidden, "--hidden")]
    except ValueError:
        raise FmuBuilderError(f"--hidden must be comma-separated integers, got '{args.hidden}'") from None
    settings = TrainSettings(
        epochs=TrainSettings.epochs if args.epochs is None else args.epochs, budget=args.budget,
        optimizer=args.optimizer, element_length=args.element_length,
        order=args.order, batch_size=args.batch_size,
        step_size=args.step_size, solver=args.solver, learning_rate=args.lr, decay=args.decay,
        nipt_iterations=args.nipt, ccpt_iterations=args.ccpt, time_budget=args.time_budget, seed=args.seed,
        loss_signals=parse_names(args.loss, "--loss"), sensor_lag=args.sensor_lag, resume=args.resume, progress=not args.quiet)
    result = train_neural_fmu(
        args.fmu, args.data, targets=args.target, inputs=parse_names(args.inputs, "--inputs"),
        start_values=parse_assignments(args.start), topology=args.topology, hidden=hidden,
        activation=args.activation, parameters=parse_names(args.parameters, "--parameters") or [], settings=settings,
        output=args.output, metrics_path=args.json, force=args.force or args.resume, test_data=args.test_data)
    try:
        print(summary(result.metrics, args.output))
    finally:
        result.model.close()


def summary(metrics: dict, output) -> str:
    lines = [f"trained {metrics['epochs']} epoch(s), {metrics['loss_evaluations']} loss evaluation(s), in "
             f"{metrics['seconds']:.1f} s; wrote {output}"]
    for key, label in (("errors", "training data"), ("test_errors", "test data")):
        if key not in metrics:
            continue
        before, after = metrics[key]["before"], metrics[key]["after"]
        for name in before:
            b, a = before[name]["mse"], after[name]["mse"]
            factor = b / a if a > 0 else float("inf")
            lines.append(f"  {label}: {name}: MSE {b:.4g} -> {a:.4g} (factor {factor:.3g})")
    return "\n".join(lines)

