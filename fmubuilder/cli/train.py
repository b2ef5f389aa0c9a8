"""`fmubuilder train`: the command-line face of fmubuilder.neural.train (torch loads only when it runs).
The training options' defaults are TrainSettings' (neural/settings.py); --recipe hybridize starts
from the settings `hybridize` trains with (hybridize/recipe.py) instead."""
from __future__ import annotations

import argparse
import os

from ..errors import FmuBuilderError
from ..neural.settings import TrainSettings
from .common import (guide, fraction, loss_evaluations, number, parse_assignments, parse_names,
                     positive_number, seed, whole_number)
from .outputs import Plan, inputs_with_sidecars

DEFAULT = TrainSettings()
RECIPES = ("hybridize",)


class _Given(argparse.Action):
    """Stores a training option and notes that it was given: with --recipe, the options given
    change the recipe's settings and the others leave them. `excludes`: the option that may not
    be given with it (argparse's exclusive groups miss an option given at its default value)."""

    def __init__(self, *args, excludes: str | None = None, **kwargs):
        super().__init__(*args, **kwargs)
        self.excludes = excludes

    def __call__(self, parser, namespace, value, option_string=None):
        if self.excludes is not None and self.excludes.lstrip("-").replace("-", "_") in namespace.given:
            parser.error(f"argument {option_string}: not allowed with argument {self.excludes}")
        setattr(namespace, self.dest, value)
        namespace.given = {*namespace.given, self.dest}


def add_train_parser(subparsers, common=None) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "train", parents=[common] if common else [], epilog=guide("docs/how-it-works.md", "Training on its own"),
        help="train a NeuralFMU (FMU + ANN on chosen derivatives) on measured data",
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
    p.add_argument("--recipe", choices=RECIPES,
                   help="hybridize: train as `fmubuilder hybridize` trains its NeuralFMU (docs/how-it-works.md, "
                        "\"Training on its own\"): its settings, the last 20%% of --data held out to pick the "
                        "parameters the training ends with, RK4 at the step hybridize checks; the options given "
                        "change it (default: no recipe, the defaults below)")
    p.set_defaults(given=frozenset())
    _add_training_options(p)
    p.add_argument("--alias", action="append", metavar="OUTPUT=DER",
                   help="a measured output the hybrid sets equal to a corrected derivative, e.g. "
                        "'power=der(energy)' (repeatable; `hybridize` finds them and its report lists them)")
    p.add_argument("--test-data", metavar="CSV", help="held-out data: its errors are added to the metrics")
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


def _add_training_options(p: argparse.ArgumentParser) -> None:
    """The options that set a TrainSettings field of their dest's name, defaults from TrainSettings."""
    from ..hybridize.workflow import DEFAULT_BUDGET
    def option(*flags, dest, **kwargs):
        p.add_argument(*flags, dest=dest, action=_Given, default=getattr(DEFAULT, dest), **kwargs)

    option("--epochs", dest="epochs", excludes="--budget", type=whole_number(0), help=f"default {DEFAULT.epochs}")
    option("--budget", dest="budget", excludes="--epochs", type=loss_evaluations, metavar="N",
           help="train for N loss evaluations (each a simulation of a batch with its gradient) instead of "
                f"epochs (with --recipe hybridize: default {DEFAULT_BUDGET}, hybridize's)")
    option("--optimizer", dest="optimizer", choices=["adam", "lbfgs"],
           help="adam: one step per batch; lbfgs: one step over all elements per epoch, its line search "
                f"up to 10 loss evaluations (default {DEFAULT.optimizer})")
    option("--time-budget", dest="time_budget", type=positive_number, metavar="SECONDS",
           help="stop training after this many seconds")
    option("--element-length", dest="element_length", type=positive_number, metavar="SECONDS",
           help=f"batch element length (default {DEFAULT.element_length:g})")
    option("--batch-size", dest="batch_size", type=whole_number(0), help="elements per optimizer step (default: all)")
    option("--order", dest="order", choices=["random", "sequential"], help=f"default {DEFAULT.order}")
    option("--step-size", dest="step_size", type=positive_number,
           help="solver step (default: the FMU's DefaultExperiment stepSize)")
    option("--solver", dest="solver", choices=["euler", "rk4"], help=f"default {DEFAULT.solver}")
    option("--lr", dest="learning_rate", type=positive_number, metavar="LR", help=f"Adam step size (default {DEFAULT.learning_rate:g})")
    option("--decay", dest="decay", type=fraction, help=f"step-size factor per epoch (default {DEFAULT.decay:g})")
    option("--nipt", dest="nipt_iterations", type=whole_number(0), metavar="ITERATIONS",
           help=f"neutral pre-training iterations (gates; default {DEFAULT.nipt_iterations})")
    option("--ccpt", dest="ccpt_iterations", type=whole_number(0), metavar="ITERATIONS",
           help=f"collocation pre-training iterations (default {DEFAULT.ccpt_iterations}: off)")
    p.add_argument("--loss", metavar="A,B", help="signals in the loss (default: all measured)")
    option("--sensor-lag", dest="sensor_lag", type=number, metavar="SECONDS",
           help="time constant of the sensors' first-order lag, applied to the simulated signals before "
                "they meet the data (default: the bench's, recorded next to data from `fmubuilder synth`; else 0)")
    option("--seed", dest="seed", type=seed, help=f"random seed (0 to 2**32-1, default {DEFAULT.seed})")


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
    from ..neural.train import train_neural_fmu
    try:
        hidden = [int(h) for h in parse_names(args.hidden, "--hidden")]
    except ValueError:
        raise FmuBuilderError(f"--hidden must be comma-separated integers, got '{args.hidden}'") from None
    data, start_values, settings, validation = _training(args)
    result = train_neural_fmu(
        args.fmu, data, targets=args.target, inputs=parse_names(args.inputs, "--inputs"),
        start_values=start_values, topology=args.topology, hidden=hidden,
        activation=args.activation, parameters=parse_names(args.parameters, "--parameters") or [], settings=settings,
        validation=validation, output=args.output, metrics_path=args.json, force=args.force or args.resume,
        test_data=args.test_data)
    try:
        print(summary(result.metrics, args.output))
    finally:
        result.model.close()


def _training(args):
    """(the data, start values, TrainSettings, validation) of the command: the training options over
    TrainSettings' defaults, or the given ones over the recipe's."""
    from dataclasses import replace
    chosen = {dest: getattr(args, dest) for dest in _setting_dests(args)}
    loss_signals = parse_names(args.loss, "--loss")
    command = dict(aliases=parse_assignments(args.alias, "--alias"), resume=args.resume, progress=not args.quiet)
    start_values = parse_assignments(args.start)
    if args.recipe is None:
        return args.data, start_values, replace(DEFAULT, **chosen, **command, loss_signals=loss_signals), None
    from ..hybridize.recipe import recipe_run
    from ..hybridize.workflow import DEFAULT_BUDGET
    if "epochs" in args.given:
        raise FmuBuilderError("--recipe hybridize counts the training's work in loss evaluations: give --budget, "
                              "not --epochs")
    given = {dest: value for dest, value in chosen.items() if dest in args.given and dest != "budget"}
    budget = DEFAULT_BUDGET if args.budget is None else args.budget
    run = recipe_run(args.fmu, args.data, start_values, loss_signals, budget, **given, **command)
    return run.fit, run.start_values, run.settings, run.validation


def _setting_dests(args) -> list[str]:
    """The command's options that are TrainSettings fields."""
    return [name for name in TrainSettings.__dataclass_fields__ if hasattr(args, name) and name != "resume"]


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

