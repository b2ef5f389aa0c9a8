"""The hybridize report: report.json for tools; report.md and report.html (the same page, its plots
inline) for people.

The page reads top-down in a minute: one summary line (what was found, what was shipped, and per
signal how much lower the held-out error is and how far it stays above the noise), the data's roles, the diagnosis, the candidates, the errors per role, the round trip
of the published FMU, the plots. Every quantity carries the unit its modelDescription declares.
"""
from __future__ import annotations

import base64
import html
import json
import re
from pathlib import Path

import numpy as np

from ..diagnose.plots import RESIDUAL, cumulative_signals, units_of
from ..errors import FmuBuilderError
from ..files import write_atomically
from ..fmi import read_model_info
from ..score import floors_of, validation_score
from .evaluate import relative_mse

ROLES = ("train", "validation", "test")
ROLE_TITLES = {"train": "training (the samples the fit saw)",
               "validation": "validation (chose the candidate and decided to publish)",
               "test": "test (touched once, after everything was decided)"}
TEST_NOTE = ("The test numbers were computed once, after the candidate and the decision to publish were fixed "
             "on the validation data; they chose nothing.")


def write_report(folder: Path, *, model_fmu, diagnosis, plain, candidates, chosen, selection, roundtrip, hybrid_fmu,
                 roles, scoring, training, seconds: float, timings: dict | None = None) -> dict:
    info = read_model_info(model_fmu)
    first = roles.train[0]
    units = _units(info, first.data.names, diagnosis)
    cumulative = cumulative_signals(first.data.names, plain.runs[id(first.data)].predicted,
                                    {s.name for s in info.states})
    after = chosen.scores if chosen else plain
    test_floors = _test_floors(plain, roles)
    report = {
        "summary": "",
        "diagnosis": {
            "significant": bool(diagnosis.significant),
            "p_value": float(diagnosis.p_value),
            "channel": diagnosis.channel,
            "inputs": list(diagnosis.inputs),
            "candidates": [{"channel": c.channel, "inputs": list(c.inputs), "score": float(c.score),
                            "form": c.form} for c in diagnosis.candidates],
            "fitted_term": diagnosis.fitted_term,
            "data": first.label,
            "trace_window": list(diagnosis.trace_window) if diagnosis.trace_window else None,
        },
        "units": units,
        "cumulative_signals": sorted(cumulative),
        "data": roles.describe(),
        "scoring": scoring.describe(),
        "training": training,
        "selection": selection,
        "chosen": chosen.name if chosen else None,
        "errors": {role: {"before": plain.errors[role], "after": after.errors[role]} for role in ROLES},
        "mse_factor": {role: _factors(plain.errors[role], after.errors[role]) for role in ROLES},
        "models": [{"name": c.name, "description": c.description,
                    **{f"{role}_relative_mse": relative_mse(plain.errors[role], c.scores.errors[role])
                       for role in ROLES},
                    **{f"{role}_mse_factor": _factors(plain.errors[role], c.scores.errors[role]) for role in ROLES},
                    "test_score": validation_score(c.scores.errors["test"], test_floors),
                    "chosen": c is chosen, **c.details}
                   for c in candidates],
        "test_plain_score": validation_score(plain.errors["test"], test_floors),
        "noise_variance": _held_out_noise(plain, roles),
        "test_note": TEST_NOTE,
        "roundtrip": {key: roundtrip[key] if roundtrip else None
                      for key in ("max_rel_error", "passed", "not_compared", "span")},
        "hybrid_fmu": str(hybrid_fmu) if hybrid_fmu else None,
        "model_fmu": str(model_fmu),
        "seconds": seconds,
        "timings": dict(timings or {}),     # wall seconds per stage
    }
    report["summary"] = summary_line(report)
    if roundtrip and hybrid_fmu:
        # The file validated was the candidate in a work folder, since deleted; the published FMU is
        # its byte copy, so the table names that.
        roundtrip = {**roundtrip, "table": roundtrip["table"].replace(str(chosen.fmu), str(hybrid_fmu))}
    report["plots"], report["plot_notes"] = _plots(folder, diagnosis, plain, chosen, roles, scoring, model_fmu, units)
    page = markdown(report, roundtrip)
    write_atomically(folder / "report.json", json.dumps(report, indent=2, default=_json_default) + "\n")
    write_atomically(folder / "report.md", page)
    write_atomically(folder / "report.html", to_html(page, folder))
    return report


def _units(info, signals, diagnosis) -> dict[str, str]:
    """Units of the signals, the traced variables and the corrected channel ("" if undeclared)."""
    known = units_of(info)
    names = [*signals, *diagnosis.inputs, *([diagnosis.channel] if diagnosis.channel else [])]
    return {name: known.get(name, "") for name in dict.fromkeys(names)}


def _factors(before: dict, after: dict) -> dict:
    return {s: (before[s]["mse"] / after[s]["mse"] if after[s]["mse"] > 0 else float("inf")) for s in before}


def _json_default(value):
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    return str(value)


# -- the page ----------------------------------------------------------------------------------

# Names, units, descriptions and file names come from the user's FMU and data: whatever they hold
# must stay text on the page, never markup, a link or the end of a code span. Every such string goes
# through _code or _text; to_html also refuses raw HTML, in case one is missed.

_MARKDOWN_SPECIAL = re.compile(r"([\\`*_\[\]|])")


def _text(value) -> str:
    """Text from outside for running markdown: HTML's specials as entities, markdown's escaped."""
    return _MARKDOWN_SPECIAL.sub(r"\\\1", html.escape(str(value), quote=False))


def _code(value) -> str:
    """A code span holding any text: its fence is longer than any run of backticks inside it."""
    text = " ".join(str(value).splitlines())
    fence = "`" * (1 + max((len(run) for run in re.findall(r"`+", text)), default=0))
    pad = " " if text.startswith("`") or text.endswith("`") else ""
    return f"{fence}{pad}{text}{pad}{fence}"


def _code_block(text: str) -> list[str]:
    """A fenced block that no line of `text` can close."""
    fence = "`" * max(3, 1 + max((len(run) for run in re.findall(r"^`+", text, flags=re.M)), default=0))
    return [fence, text, fence]


def _with_unit(name: str, units: dict) -> str:
    unit = units.get(name)
    return f"{_code(name)} [{_text(unit)}]" if unit else _code(name)


def _gain(ratio: float) -> str:
    """An MSE ratio after/before as the factor it improves by."""
    if not np.isfinite(ratio):
        return "diverged"
    if ratio <= 0:
        return "exact"
    return f"{1 / ratio:.3g}× lower" if ratio < 1 else f"{ratio:.3g}× higher"


def _held_out_noise(plain, roles) -> dict:
    """Each held-out role's noise variance per signal (None where its data carry no `_std` spread):
    the floor the headline measures every signal against. The validation role reads its first
    part's data, as the choice does."""
    parts = {"validation": roles.validation[0] if roles.validation else None, "test": roles.test}
    return {role: {name: (part.data.noise_variance(name) if part else None) for name in plain.errors[role]}
            for role, part in parts.items()}


def _test_floors(plain, roles) -> dict:
    """The validation score's floors on the test data (its noise variance), so that the test
    numbers can be read on the scale the choice was made on."""
    noise = {name: roles.test.data.noise_variance(name) for name in plain.errors["test"]}
    return floors_of(plain.errors["test"], noise)


def summary_line(report: dict) -> str:
    d, units = report["diagnosis"], report["units"]
    if d["significant"] and d["channel"] is None:
        found = f"**Found** an effect no term form traced to one derivative (joint p = {d['p_value']:.2g})."
    elif d["significant"]:
        leading = f" depending most likely on {_with_unit(d['inputs'][0], units)}" if d["inputs"] else ""
        found = f"**Found** an effect on {_with_unit(d['channel'], units)}{leading} (joint p = {d['p_value']:.2g})."
    else:
        found = f"**No effect found** beyond the measurement noise (joint p = {d['p_value']:.2g})."
        if not report["models"]:
            return f"{found} **Shipped: nothing**, the declared FMU explains the data."
        found += " The candidates were built anyway (`--allow-insignificant`)."
    chosen = next((m for m in report["models"] if m["chosen"]), None)
    if not report["models"] and report["selection"].get("failed"):
        return f"{found} **Shipped: nothing**: no candidate could be built (their reasons under Candidates)."
    if chosen is None:
        best = min((m["validation_relative_mse"] for m in report["models"]), default=float("nan"))
        return (f"{found} **Shipped: nothing**: no candidate beat the declared FMU on the validation data "
                f"(best MSE ratio {best:.3g}).")
    if report["hybrid_fmu"] is None:
        return (f"{found} **Shipped: nothing**: the chosen {_text(chosen['name'])} hybrid failed its round trip "
                "(below); a hybrid that does not compute what was scored is not published.")
    if chosen["name"] == "fitted term":
        what = f"the fitted term {_code(chosen['description'])}"
    elif chosen.get("calibrated"):
        what = f"the calibrated parameter {_text(chosen['description'])}"
    else:
        what = f"a neural network ({_text(chosen['description'])})"
    return (f"{found} **Shipped** {_code(Path(report['hybrid_fmu']).name)} with {what}. "
            f"**Held out, per signal** (MSE against the declared FMU's, and against the data's noise variance: "
            f"1× is the noise floor): {per_signal_gain(report)}.")


HELD_OUT = ("validation", "test")


def per_signal_gain(report: dict) -> str:
    """Per signal: how many times lower the published model's MSE is than the declared FMU's on the
    validation and the test data, and how far it is from the noise floor there (its MSE over the
    data's noise variance; 1 is the floor). A mean over the signals would hide a signal at its floor
    behind another's large gain."""
    noise = report.get("noise_variance") or {}
    parts = []
    for signal in report["errors"]["test"]["after"]:
        gains = ", ".join(f"{_gain(1 / factor if factor else float('inf'))} on {role}"
                          for role in HELD_OUT if (factor := report["mse_factor"][role].get(signal)) is not None)
        ratios = [_noise_ratio(report["errors"][role]["after"].get(signal), (noise.get(role) or {}).get(signal))
                  for role in HELD_OUT]
        known = [f"{ratio:.3g}×" if ratio is not None else "?" for ratio in ratios]
        floor = (f", {' and '.join(known)} the noise" if any(r is not None for r in ratios)
                 else ", the noise not known (no `_std` column)")
        parts.append(f"{_with_unit(signal, report['units'])} {gains}{floor}")
    return "; ".join(parts)


def _noise_ratio(errors: dict | None, variance: float | None) -> float | None:
    if errors is None or variance is None or not variance > 0:
        return None
    return errors["mse"] / variance


def markdown(report: dict, roundtrip: dict | None) -> str:
    lines = ["# fmubuilder hybridize report", "", report["summary"], "",
             f"Model: {_code(Path(report['model_fmu']).name)}; wall time {report['seconds']:.0f} s."]
    for section in (_data_section, _diagnosis_section, _candidates_section, _errors_section):
        lines += ["", *section(report)]
    lines += ["", *_roundtrip_section(report, roundtrip), "", *_plots_section(report)]
    if roundtrip:
        lines += ["", "## Appendix: the round trip in detail", "", *_code_block(roundtrip["table"])]
    return "\n".join(lines) + "\n"


def _data_section(report: dict) -> list[str]:
    data = report["data"]
    return ["## Data and their roles", "",
            f"- training (the diagnosis and the fit): {_code_list(data['train'])}",
            f"- validation (the choice and the decision to publish; {_text(data['validation_from'])}): "
            f"{_code_list(data['validation'])}",
            f"- test (touched once, after everything was decided): {_code_list(data['test'])}",
            f"- every model simulated the same way: {_text(report['scoring'])}"]


def _diagnosis_section(report: dict) -> list[str]:
    d, units = report["diagnosis"], report["units"]
    lines = ["## Diagnosis", ""]
    if d["significant"] and d["channel"] is None:
        lines.append(f"The residual exceeds the measurement noise (joint p = {d['p_value']:.2g}). No term form traced "
                     "it to one derivative; the NeuralFMU's search over the derivatives decided on the validation data.")
    elif d["significant"]:
        lines.append(f"The residual exceeds the measurement noise (joint p = {d['p_value']:.2g}). It is traced to "
                     f"**{_with_unit(d['channel'], units)}**, depending most likely on "
                     f"{', '.join(_with_unit(v, units) for v in d['inputs'][:3])}.")
        if d["fitted_term"]:
            lines += ["", f"Fitted term: {_code(d['fitted_term']['expression'])}."]
    else:
        lines.append(f"No significant effect: the residual is at the level of the measurement noise "
                     f"(joint p = {d['p_value']:.2g})."
                     + ("" if report["models"] else " No hybrid FMU was written."))
    estimated = [e for e in d.get("errors", []) if not e.get("noise_from_spread", True) and e["noise"] > 0]
    if estimated:
        lines += ["", "Noise estimated from the data (no `_std` column: the noise fit of the declared model's "
                  "residual, away from the frequencies the model moves at); every score is measured against it: "
                  + ", ".join(f"{_with_unit(e['signal'], units)} σ = {e['noise']:.3g} (variance "
                              f"±{(2.0 / max(e['noise_dof'], 1.0)) ** 0.5:.0%})" for e in estimated) + "."]
    training = report.get("training")
    if training:
        cut = (" The wall-clock cap of {:g} s cut it short.".format(training["time_budget"])
               if training["cut_short_by_time_budget"] else "")
        if training.get("at_noise_floor"):
            lines.append(f"\nThe NeuralFMU was not trained through the solver ({training['budget']} loss evaluations "
                         f"were allowed): after its warm start on {_code(training['trained_on'])} every training signal lay "
                         "at its noise floor.")
        else:
            lines.append(f"\nThe NeuralFMU trained with {training['loss_evaluations']} of {training['budget']} loss "
                         f"evaluations ({training['optimizer']}, {training['steps']} steps, seed {training['seed']}) "
                         f"on {_code(training['trained_on'])}.{cut}")
        lines += _repeat_training(training)
    return lines


def _repeat_training(training: dict) -> list[str]:
    """How to train the same network with `fmubuilder train` (its settings: report.json, "training")."""
    if training.get("command"):
        return ["", "The same training on its own (its settings: report.json, \"training\"):", "",
                *_code_block(training["command"])]
    if training.get("command_not_given"):
        return [f"\n`fmubuilder train --recipe hybridize` cannot repeat this training: "
                f"{_text(training['command_not_given'])} (its settings: report.json, \"training\")."]
    return []


def _candidates_section(report: dict) -> list[str]:
    selection = report["selection"]
    failed = [f"\nFailed: {_text(name)}; {_text(why)}." for name, why in (selection.get("failed") or {}).items()]
    if not report["models"]:
        return ["## Candidates", "", "No candidate could be built.", *failed] if failed else []
    scores = selection.get("scores", {})
    lines = ["## Candidates", "",
             "Train, validation, test: MSE after / MSE before, mean over the signals (below 1: better than the "
             "declared FMU). Validation score (chooses): validation MSE / noise variance, geometric mean over the signals "
             f"(the declared FMU: {selection.get('plain_score', float('nan')):.3g}); test score: the same on the test "
             f"data (the declared FMU: {report.get('test_plain_score', float('nan')):.3g}).", "",
             "| candidate | what it adds | train | validation | validation score (chooses) | test (touched once) "
             "| test score | chosen | note |",
             "|:---|:---|---:|---:|---:|---:|---:|:---|:---|"]
    for m in report["models"]:
        lines.append(f"| {_text(m['name'])} | {_text(m['description'])} | {m['train_relative_mse']:.3g} | "
                     f"{m['validation_relative_mse']:.3g} | {scores.get(m['name'], float('nan')):.3g} | "
                     f"{m['test_relative_mse']:.3g} | {m.get('test_score', float('nan')):.3g} | "
                     f"{'**yes**' if m['chosen'] else 'no'} | {_candidate_note(m, report.get('training'))} |")
    chosen = _text(selection["chosen"]) if selection["chosen"] else "none (no candidate improved it)"
    lines.append(f"\nChosen on the validation data: **{chosen}** ({_text(selection['rule'])}). {report['test_note']}")
    lines += [f"\nNot trained: {_text(name)}; {_text(why)}." for name, why in (selection.get("not_trained") or {}).items()]
    return lines + failed


def _code_list(names) -> str:
    return ", ".join(_code(name) for name in names)


def _score(value) -> str:
    return "does not simulate" if value is None else f"{value:.3g}"


def _warm_start_note(warm: dict) -> str:
    """What the warm start (neural/warm_start.py) kept, and the training loss it started from."""
    if not warm.get("samples"):
        return "no warm start (no channel's state measured)"
    if not warm["kept"]:
        return f"warm start not kept ({len(warm.get('trials', []))} fits tried)"
    estimates = warm.get("estimate") or []
    parts = [f"fitted to the {' / '.join(_text(e) for e in dict.fromkeys(estimates))} run's estimate"] if estimates else []
    through = warm.get("through_simulation")
    if through and through["kept"]:
        parts.append("last layer through the simulation")
    return f"warm start: {', then '.join(parts)}, training loss {warm['loss_before']:.4g} -> {warm['loss_after']:.4g}"


def _stop_note(checkpoint: dict, steps: int | None, trained: bool = True) -> str:
    """Which parameters the training ended with: those of its best validation score (`trained`:
    whether it took steps through the solver)."""
    stage = checkpoint.get("best_stage")
    if stage == "start":
        return "ended at its start (nothing it learned scored better on the validation data)"
    if stage == "warm start":
        return ("ended at its warm start (no training step scored better on the validation data)" if trained
                else "ended at its warm start, its best on the validation data")
    if stage == "epoch":
        of = f" of {steps}" if steps else ""
        return f"ended after step {checkpoint['best_epoch']}{of}, its best on the validation data"
    if stage == "last layer":
        return "ended after the last layer's refinement, its best on the validation data"
    return "ended at its best validation score"        # a report from before the stages were recorded


def _candidate_note(model: dict, training: dict | None) -> str:
    """Why a row looks the way it does."""
    notes, training = [], training or {}
    if model.get("loss_evaluations") is not None:       # a NeuralFMU, plain or on the fitted term
        done, asked = model["loss_evaluations"], training.get("budget")
        floor = model.get("at_noise_floor")
        if floor:
            ratios = ", ".join(f"{_text(name)} {ratio:.3g}" for name, ratio in floor["ratios"].items())
            notes.append(f"not trained through the solver ({done} of {asked} loss evaluations): after the warm start "
                         f"every training signal lay at its noise floor (MSE / noise variance {ratios}; the noise "
                         f"alone gives up to {floor['factor']:.3g}), where a step can fit only the noise")
        else:
            notes.append(f"trained with {done} of {asked} loss evaluations" if asked is not None
                         else f"trained with {done} loss evaluations")
            if done == 0:
                notes.append("the wall-clock cap ran out before the first loss evaluation"
                             if training.get("cut_short_by_time_budget") else "no training was asked for")
            elif training.get("cut_short_by_time_budget"):
                notes.append("cut short by the wall-clock cap")
        if model.get("warm_start"):
            notes.append(_warm_start_note(model["warm_start"]))
        search = model.get("channel_search")
        if search:
            notes.append(f"its derivative chosen on the validation data after each one's warm start and "
                         f"{search['budget_each']} loss evaluation(s): " + "; ".join(f"{', '.join(f'`{c}`' for c in row['channels'])} "
                                             f"{row['validation_score']:.3g}" for row in search["screened"]))
        refined = model.get("last_layer")
        if refined and refined["kept"]:
            notes.append(f"last layer refined through the simulation: training loss {refined['loss_before']:.4g} -> "
                         f"{refined['loss_after']:.4g} ({refined['simulations']} sims)")
        elif refined:
            notes.append(f"last layer's refinement not kept ({refined['simulations']} sims)")
        if model.get("validation_checkpoint"):
            notes.append(_stop_note(model["validation_checkpoint"], model.get("steps"), trained=not floor))
    elif model.get("calibrated"):
        notes.append(f"calibrated by Gauss-Newton on {_code(model.get('fitted_on', 'the training data'))} in "
                     f"{model.get('simulations', '?')} simulations, no training")
        if model.get("equivalent_parameters"):
            notes.append(f"{_code_list(model['equivalent_parameters'])} moved the signals alike in the screening: "
                         "the same candidate, not fitted apart")
    else:
        forms = model.get("forms")
        if forms and forms["fitted"]:
            scores = ", ".join(f"{_code(f['form'])} {_score(f['validation_score'])}" for f in forms["fitted"])
            notes.append(f"fitted through the simulation on {_code(model.get('fitted_on', 'the training data'))}, no "
                         f"training; its form chosen on the validation data among the diagnosis' and its leading "
                         f"variables' forms (validation scores: {scores}; another than the diagnosis' must score "
                         f"lower by x{forms['margin']:.3g})")
        else:
            notes.append(f"fitted by the diagnosis on {_code(model.get('fitted_on', 'the training data'))}, no training")
        refinement = model.get("refinement")
        if refinement and refinement["kept"]:
            notes.append(f"coefficient refined through the simulation: {_text(refinement['coefficients_before'])} -> "
                         f"{_text(refinement['coefficients_after'])} ({refinement['simulations']} sims)")
        elif refinement:
            notes.append(f"coefficient kept: refining it through the simulation did not lower the training "
                         f"error ({refinement['simulations']} sims)")
    if all(model[f"{role}_relative_mse"] == 1.0 for role in ROLES):
        notes.append("it adds nothing yet: the same errors as the declared FMU")
    return "; ".join(notes)


def _errors_section(report: dict) -> list[str]:
    """One table per role; the final error only for accumulating signals (for the others it is one
    noisy sample, says nothing the RMS does not)."""
    units, cumulative = report["units"], set(report["cumulative_signals"])
    hybrid = report["chosen"] is not None
    lines = ["## Errors per data role", "",
             f"Errors are {RESIDUAL}, in the signal's unit. FMU: the declared model"
             + ("; hybrid: the published FMU. Factor: MSE FMU / MSE hybrid (above 1: the hybrid is better)."
                if hybrid else "; no hybrid was published.")]
    final = bool(cumulative)

    def columns(fmu: str, *hybrid_columns: str) -> list[str]:
        return [fmu, *hybrid_columns] if hybrid else [fmu]

    header = ["signal", *columns("RMS FMU", "RMS hybrid", "factor"), *columns("max abs FMU", "max abs hybrid"),
              *(columns("final FMU", "final hybrid") if final else [])]
    for role in ROLES:
        errors = report["errors"][role]
        lines += ["", f"### {ROLE_TITLES[role]}", "", f"Data: {_code_list(report['data'][role])}", "",
                  "| " + " | ".join(header) + " |", "|:---|" + "---:|" * (len(header) - 1)]
        for signal, b in errors["before"].items():
            a = errors["after"][signal]
            row = [_with_unit(signal, units),
                   *columns(f"{np.sqrt(b['mse']):.4g}", f"{np.sqrt(a['mse']):.4g}",
                            _factor(report["mse_factor"][role][signal])),
                   *columns(f"{b['max_abs']:.4g}", f"{a['max_abs']:.4g}")]
            if final:
                row += (columns(f"{b['final']:.4g}", f"{a['final']:.4g}") if signal in cumulative
                        else columns("–", "–"))
            lines.append("| " + " | ".join(row) + " |")
    if final:
        lines.append(f"\nFinal: the error at the last sample, shown for the signals that accumulate "
                     f"({_code_list(sorted(cumulative))}).")
    return lines


def _factor(value: float) -> str:
    text = f"{value:.3g}"
    return f"**{text}**" if value >= 2 else text


def _roundtrip_section(report: dict, roundtrip: dict | None) -> list[str]:
    if not roundtrip:
        return []
    verdict = "passed" if roundtrip["passed"] else "FAILED: not published"
    which = (f"The published FMU {_code(report['hybrid_fmu'])}" if report["hybrid_fmu"]
             else f"The chosen {_text(report['chosen'])} hybrid")
    worst = roundtrip["max_rel_error"]
    lines = [f"## Round trip of the {'published FMU' if report['hybrid_fmu'] else 'chosen hybrid'}", "",
             f"{which} against the Python reference (the original with the network, term or overrides, the network "
             f"run by onnxruntime) over {roundtrip['span'][0]:g} to {roundtrip['span'][1]:g} s of the test data: "
             f"max relative difference {'-' if worst is None else f'{worst:.2g}'} over the rows compared ({verdict})."]
    if roundtrip["not_compared"]:
        lines.append(f"Not compared (no samples left): {_text('; '.join(roundtrip['not_compared']))}.")
    return lines + ["", "Each comparison, signal by signal: in the appendix."]


def _plots_section(report: dict) -> list[str]:
    lines = ["## Plots", ""]
    for plot in report["plots"]:
        lines += [f"![{PLOT_CAPTIONS.get(Path(plot).name, Path(plot).stem)}]({plot})", ""]
    lines += [f"- {_text(note)}" for note in report["plot_notes"]]
    return lines


PLOT_CAPTIONS = {"train.png": "training data: measured, declared FMU and hybrid",
                 "test.png": "test data: measured, declared FMU and hybrid",
                 "effect.png": "the learned effect against its inputs",
                 "signals.png": "diagnosis: signals", "residuals.png": "diagnosis: residuals over time",
                 "residual_vs_inputs.png": "diagnosis: residuals against the traced variables"}


# -- plots ------------------------------------------------------------------------------------

def _plots(folder: Path, diagnosis, plain, chosen, roles, scoring, model_fmu, units) -> tuple[list, list]:
    from .plots import plot_effects, plot_signals
    first, test = roles.train[0], roles.test
    label = f"hybrid ({chosen.name})" if chosen else None
    held_out = roles.validation[0].window if roles.held_out_of_training else None

    def signals(name: str, part, title: str, shaded=None) -> Path:
        run = id(part.data)
        return plot_signals(folder / name, part.data, plain.runs[run], chosen.scores.runs[run] if chosen else None,
                            label, units, title, shaded)

    paths = [signals("train.png", first, f"Training run {first.file_name}", held_out),
             signals("test.png", test, f"Test run {test.file_name} (touched once)")]
    notes = []
    if chosen is not None and not chosen.details.get("calibrated"):     # a calibration adds no term to draw
        try:
            from .effect import effects_of
            effects = effects_of(chosen.spec_dir / "spec.json", Path(model_fmu), first.data, first.start_values,
                                 scoring)
            paths.append(plot_effects(folder / "effect.png", effects, {**units_of(read_model_info(model_fmu)),
                                                                       **{k: v for k, v in units.items() if v}},
                                      f"What the {'NeuralFMU' if chosen.name == 'neural' else chosen.name} adds to "
                                      f"{', '.join(e.channel for e in effects)}"))
            source = effects[0]       # every channel's truth comes from the same model
            notes.append("The learned effect is evaluated along the declared FMU's run over the training data"
                         + (f"; the true effect is that of {source.truth_source}, the model that made the data "
                            "(derivatives at the same states, each model following the declared run)."
                            if source.truth is not None else f"; no true effect drawn: {source.truth_source}."))
        except FmuBuilderError as exc:
            notes.append(f"The learned effect could not be drawn: {exc}")
    plots = [str(p.relative_to(folder)) for p in paths] + \
        [str(Path("diagnosis") / Path(p).name) for p in diagnosis.plots]
    return plots, notes


# -- HTML ---------------------------------------------------------------------------------------

STYLE = """
body { font-family: system-ui, -apple-system, "Segoe UI", sans-serif; max-width: 1180px; margin: 2em auto;
       padding: 0 1em; color: #222; line-height: 1.45; }
h1 { border-bottom: 2px solid #ddd; padding-bottom: .2em; }
h2 { margin-top: 1.8em; border-bottom: 1px solid #eee; }
table { border-collapse: collapse; margin: .6em 0; font-size: .92em; }
th, td { border: 1px solid #ccc; padding: .25em .6em; }
th { background: #f3f3f3; }
code { background: #f4f4f4; padding: 0 .2em; border-radius: 3px; }
pre { background: #f7f7f7; padding: .8em; overflow-x: auto; font-size: .85em; }
img { max-width: 100%; border: 1px solid #e4e4e4; margin: .4em 0; }
body > p:first-of-type { background: #eef5ff; border-left: 4px solid #1f77b4; padding: .6em .9em; }
"""


def to_html(page: str, folder: Path) -> str:
    """The markdown page as one self-contained HTML file: the plots embedded as base64 PNG."""
    import markdown as md
    converter = md.Markdown(extensions=["tables", "fenced_code"], output_format="html")
    # The page holds text from the user's FMU and data: raw HTML in it stays text.
    converter.preprocessors.deregister("html_block")
    converter.inlinePatterns.deregister("html")
    body = converter.convert(page)

    def inline(match: re.Match) -> str:
        path = folder / html.unescape(match.group(1))
        if not path.is_file():
            return match.group(0)
        data = base64.b64encode(path.read_bytes()).decode("ascii")
        return f'src="data:image/png;base64,{data}"'

    body = re.sub(r'src="([^"]+\.png)"', inline, body)
    return ("<!DOCTYPE html>\n<html lang=\"en\">\n<head>\n<meta charset=\"utf-8\">\n"
            "<title>fmubuilder hybridize report</title>\n"
            f"<style>{STYLE}</style>\n</head>\n<body>\n{body}\n</body>\n</html>\n")
