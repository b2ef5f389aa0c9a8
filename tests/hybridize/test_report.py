"""The hybridize report as a person reads it: the summary line, units from the modelDescription, the
published FMU's name, a self-contained report.html, and the plots, including the effect the hybrid
learned drawn against its inputs and against the truth that made the data.

References: units from fmpy's reading of the modelDescription; the learned network evaluated by
torch (the report runs its ONNX export with onnxruntime); the true windage term from the C source
of examples/dc_drive (WINDAGE = 3e-6 N.m.s2/rad2, inertia 0.01 kg.m2); the VLDM's extra loss from
examples/vldm/model.c (10 % of |motor_torque * motor_speed| in the power demand, clamped to the
battery's limits).
"""
import base64
import re
from html.parser import HTMLParser

import numpy as np
import pytest
import torch
from fmpy import read_model_description

from fmubuilder import synth
from fmubuilder.build import example_fmu
from fmubuilder.data import MeasuredData, load_data
from fmubuilder.diagnose.plots import cumulative_signals, pyplot, robust_ylim
from fmubuilder.export import freeze
from fmubuilder.export.network import OnnxNetwork
from fmubuilder.export.spec import HybridSpec
from fmubuilder.fmi import read_model_info
from fmubuilder.hybridize import hybridize
from fmubuilder.hybridize.effect import Effect, effects_of, followed_effect, inputs_read
from fmubuilder.hybridize.evaluate import Scoring
from fmubuilder.hybridize.plots import plot_effects
from fmubuilder.hybridize.report import _candidate_note

BENCH = dict(signals=("speed", "current", "power", "temperature"),
             noise_std={"speed": 0.1, "current": 0.02, "power": 1.0, "temperature": 0.02})
TRUTH = "dc_drive_truth_windage"
WINDAGE_PER_INERTIA = 3e-6 / 0.01      # der(speed) += -WINDAGE / inertia * speed * |speed|
PNG = b"\x89PNG\r\n\x1a\n"


def measure(folder, window, seed):
    settings = synth.BenchSettings(seed=seed, **BENCH)
    measurement = synth.measure(example_fmu(TRUTH), start_time=window[0], stop_time=window[1], settings=settings)
    return synth.write_measurement(measurement, folder / f"{TRUTH}_{window[0]:g}-{window[1]:g}_{seed}.csv")


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    folder = tmp_path_factory.mktemp("report_data")
    return {"train": measure(folder, (0.0, 10.0), 0), "test": measure(folder, (20.5, 26.0), 1)}


@pytest.fixture(scope="module")
def published(files, tmp_path_factory):
    """A small hybridize run (one epoch, no ANN on the term: tests/hybridize/test_hybridize.py's
    runs report it): the fitted term is published."""
    folder = tmp_path_factory.mktemp("report")
    result = hybridize(example_fmu("dc_drive"), files["train"], files["test"], folder / "windage_hybrid.fmu",
                       folder / "report", budget=1, ann_on_term=False, progress=False)
    assert result.hybrid_fmu is not None, "the windage must be found and published for these tests"
    return result


def section(markdown: str, title: str) -> str:
    match = re.search(rf"^## {re.escape(title)}\n(.*?)(?=^## |\Z)", markdown, flags=re.S | re.M)
    assert match, f"no section {title!r}"
    return match.group(1)


def test_units_from_the_model_description_appear_for_every_signal_and_the_channel(published):
    markdown = (published.report_dir / "report.md").read_text()
    declared = {v.name: v.unit or (v.declaredType.unit if v.declaredType else None)
                for v in read_model_description(str(example_fmu("dc_drive"))).modelVariables}
    for signal in BENCH["signals"]:
        assert declared[signal], signal
        # in every table of errors per role
        assert markdown.count(f"| `{signal}` [{declared[signal]}] |") == 3, signal
    assert f"`der(speed)` [{declared['der(speed)']}]" in markdown.splitlines()[2]    # the summary line


def test_the_summary_line_says_what_was_found_shipped_and_gained(published):
    report = published.report
    summary = (published.report_dir / "report.md").read_text().splitlines()[2]
    assert summary == report["summary"]
    chosen = next(m for m in report["models"] if m["chosen"])
    assert "**Found**" in summary and "der(speed)" in summary and "`speed`" in summary
    assert f"**Shipped** `{published.hybrid_fmu.name}`" in summary and chosen["name"] in summary
    assert "mean over the signals" not in summary


def test_the_summary_line_speaks_per_signal_of_the_gain_and_the_noise_floor(published, files):
    """Per signal: the held-out MSE factor of the published model against the declared FMU, and its
    MSE over the noise variance of the test data's `_std` columns (data.MeasuredData.noise_variance)."""
    report = published.report
    summary = report["summary"]
    test = load_data(files["test"], read_model_info(example_fmu("dc_drive")))
    for signal in BENCH["signals"]:
        factors = [report["mse_factor"][role][signal] for role in ("validation", "test")]
        gains = [f"{f:.3g}× lower on {role}" if f >= 1 else f"{1 / f:.3g}× higher on {role}"
                 for f, role in zip(factors, ("validation", "test"))]
        floor = report["errors"]["test"]["after"][signal]["mse"] / test.noise_variance(signal)
        assert report["noise_variance"]["test"][signal] == pytest.approx(test.noise_variance(signal), rel=1e-12)
        assert re.search(rf"`{signal}` \[[^]]*\] {re.escape(', '.join(gains))}, [0-9.e+-]+× and "
                         rf"{re.escape(f'{floor:.3g}')}× the noise", summary), signal


def test_the_round_trip_names_the_published_fmu_not_a_temporary_file(published):
    markdown = (published.report_dir / "report.md").read_text()
    assert f"`{published.hybrid_fmu}`" in section(markdown, "Round trip of the published FMU")
    assert f"validation of {published.hybrid_fmu}" in section(markdown, "Appendix: the round trip in detail")
    assert "fmubuilder-hybridize-" not in markdown


def test_the_candidate_table_explains_each_row(published):
    candidates = section((published.report_dir / "report.md").read_text(), "Candidates")
    neural = next(line for line in candidates.splitlines() if line.startswith("| neural |"))
    # the warm start leaves every training signal at the noise floor here: no step through the solver
    floor = next(m for m in published.report["models"] if m["name"] == "neural")["at_noise_floor"]
    assert "not trained through the solver (0 of 1 loss evaluations)" in neural
    assert "no training step scored better" not in neural       # it took none
    assert ", ".join(f"{name} {ratio:.3g}" for name, ratio in floor["ratios"].items()) in neural
    assert all(ratio <= floor["factor"] for ratio in floor["ratios"].values())
    fitted = next(line for line in candidates.splitlines() if line.startswith("| fitted term |"))
    # the term's bars (and stars) are escaped: they do not split the row
    assert "speed\\*\\|speed\\|" in fitted and fitted.count(" | ") == 8


def test_the_test_data_are_scored_on_the_scale_the_choice_was_made_on(published, files):
    """The test score is the validation score's measure on the test data: the geometric mean over
    the signals of the test MSE over the noise variance the test data's spread columns give."""
    report = published.report
    test = load_data(files["test"], read_model_info(example_fmu("dc_drive")))
    chosen = next(m for m in report["models"] if m["chosen"])
    for model, errors in ((chosen, report["errors"]["test"]["after"]), (report, report["errors"]["test"]["before"])):
        ratios = [errors[name]["mse"] / test.noise_variance(name) for name in test.names]
        expected = float(np.exp(np.mean(np.log(ratios))))
        score = model["test_score"] if model is chosen else model["test_plain_score"]
        assert score == pytest.approx(expected, rel=1e-9)
    assert chosen["test_score"] < report["test_plain_score"]
    assert f"{chosen['test_score']:.3g}" in section((published.report_dir / "report.md").read_text(), "Candidates")


def test_a_network_that_trained_zero_epochs_says_why():
    row = {"name": "neural", "loss_evaluations": 0, **{f"{r}_relative_mse": 1.0 for r in ("train", "validation", "test")}}
    note = _candidate_note(row, {"budget": 10, "cut_short_by_time_budget": True})
    assert "trained with 0 of 10 loss evaluations" in note and "cap ran out before the first loss evaluation" in note
    assert "adds nothing" in note


def test_no_final_error_column_for_signals_that_do_not_accumulate(published):
    markdown = (published.report_dir / "report.md").read_text()
    assert published.report["cumulative_signals"] == []    # speed, current, power, temperature all turn
    assert "final" not in section(markdown, "Errors per data role")


class _Links(HTMLParser):
    def __init__(self):
        super().__init__()
        self.images, self.links = [], []

    def handle_starttag(self, tag, attrs):
        attrs = dict(attrs)
        if tag == "img":
            self.images.append(attrs.get("src", ""))
        for key in ("href", "src"):
            if key in attrs and tag != "img":
                self.links.append(attrs[key])


def test_report_html_is_one_self_contained_page_with_every_plot(published):
    folder = published.report_dir
    page = (folder / "report.html").read_text()
    parser = _Links()
    parser.feed(page)
    assert parser.links == []
    assert len(parser.images) == len(published.report["plots"]) >= 6
    for src, plot in zip(parser.images, published.report["plots"]):
        assert src.startswith("data:image/png;base64,"), src[:60]
        assert base64.b64decode(src.split(",", 1)[1]) == (folder / plot).read_bytes()
    assert "<table>" in page and published.report["models"][0]["name"] in page


def test_the_plots_of_a_fitted_term_hybrid_are_pngs_with_the_effect(published):
    plots = published.report["plots"]
    assert {"train.png", "test.png", "effect.png"} <= set(plots)
    for plot in plots:
        assert (published.report_dir / plot).read_bytes().startswith(PNG), plot
    notes = " ".join(published.report["plot_notes"])
    assert f"{TRUTH}.fmu" in notes      # the truth was found and drawn


def test_the_effect_of_a_network_against_the_truth(files, tmp_path):
    """A small network frozen to ONNX as a hybrid spec: the effect the report draws is the network's
    output (checked with torch) and the truth's is the windage term of the C source."""
    torch.manual_seed(0)
    network = torch.nn.Sequential(torch.nn.Linear(1, 5), torch.nn.Tanh(), torch.nn.Linear(5, 1)).double()
    freeze(network, 1, tmp_path / "network.onnx")
    info = read_model_info(example_fmu("dc_drive"))
    HybridSpec(original_fmu=example_fmu("dc_drive"), original_guid=info.guid, channels=["der(speed)"],
               inputs=["speed"], onnx=tmp_path / "network.onnx", p_ann=[0.5]).save(tmp_path / "spec.json")
    data = load_data(files["train"], info)
    [effect] = effects_of(tmp_path / "spec.json", example_fmu("dc_drive"), data, {}, Scoring("euler", 1e-3))
    speed = effect.inputs["speed"]
    assert effect.kind == "network" and speed.min() < 1.0 and speed.max() > 140.0
    with torch.no_grad():
        expected = 0.5 * network(torch.from_numpy(speed[:, None])).numpy().ravel()
    np.testing.assert_allclose(effect.learned, expected, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(effect.truth, -WINDAGE_PER_INERTIA * speed * np.abs(speed), rtol=1e-6, atol=1e-9)
    path = plot_effects(tmp_path / "effect.png", [effect], {"speed": "rad/s", "der(speed)": "rad/s2"}, "network")
    assert path.read_bytes().startswith(PNG)


def test_each_channel_is_drawn_against_the_inputs_its_output_reads(tmp_path):
    """Two outputs: output 0 reads input 0 alone, output 1 both (hidden units set by hand, one of
    them reading both inputs); the probe on the ONNX network finds which."""
    network = torch.nn.Sequential(torch.nn.Linear(2, 3), torch.nn.Tanh(), torch.nn.Linear(3, 2)).double()
    with torch.no_grad():
        network[0].weight.copy_(torch.tensor([[0.7, 0.0], [0.0, -0.4], [0.3, 0.5]]))
        network[2].weight.copy_(torch.tensor([[1.5, 0.0, 0.0], [0.0, 2.0, -1.0]]))
    freeze(network, 2, tmp_path / "network.onnx")
    rows = np.random.default_rng(0).uniform(-2.0, 2.0, (50, 2))
    reads = inputs_read(OnnxNetwork(tmp_path / "network.onnx"), rows)
    np.testing.assert_array_equal(reads, [[True, False], [True, True]])
    effects = [Effect("der(a)", "network", {"u": rows[:, 0]}, np.tanh(rows[:, 0])),
               Effect("der(b)", "network", {"u": rows[:, 0], "v": rows[:, 1]}, rows[:, 1], rows[:, 1] * 1.1, "truth")]
    path = plot_effects(tmp_path / "effects.png", effects, {}, "two channels")
    assert path.read_bytes().startswith(PNG)


def test_the_true_effect_behind_a_sampled_controller():
    """The VLDM's driver sets the throttle at its 100 Hz ticks: the truth's extra loss, 10 % of the
    motor's mechanical power, shows only where the followed runs update the throttle as the run did
    (at single points an FMU keeps the throttle it started with: 0, no loss drawn)."""
    declared, truth = example_fmu("vldm"), example_fmu("vldm_truth_extra_loss")
    info = read_model_info(declared)
    window = MeasuredData(time=np.array([0.0, 40.0]), signals={"speed": np.zeros(2)})   # its span alone matters
    names = ["motor_torque", "motor_speed", "power_demand"]
    inputs, effects = followed_effect(truth, declared, names, ["der(energy)"], window, {}, {}, Scoring("rk4", 0.01))
    effect = effects[:, 0]
    limits = [float(info.variable(name).start) for name in ("min_power", "max_power")]
    loss = 0.1 * np.abs(inputs["motor_torque"] * inputs["motor_speed"])
    expected = np.clip(inputs["power_demand"] + loss, *limits) - np.clip(inputs["power_demand"], *limits)
    assert effect.size >= 500 and np.sqrt(np.mean(expected ** 2)) > 100.0      # W: the car drives
    np.testing.assert_allclose(effect, expected, rtol=1e-9, atol=1e-6)


def test_one_spike_does_not_set_the_y_range_and_the_plot_says_so():
    plt = pyplot()
    fig, ax = plt.subplots()
    values = np.sin(np.linspace(0.0, 6.0, 400))
    values[200] = 1e3
    assert robust_ylim(ax, values) == 1
    low, high = ax.get_ylim()
    assert -1.3 < low < -0.9 and 0.9 < high < 1.3
    assert any("1 point outside" in t.get_text() for t in ax.texts)
    plt.close(fig)


def test_cumulative_signals_are_monotone_states():
    ramp, wave = np.linspace(0.0, 5.0, 50), np.sin(np.linspace(0.0, 6.0, 50))
    found = cumulative_signals(["energy", "speed", "distance_output"],
                               {"energy": ramp, "speed": wave, "distance_output": ramp}, {"energy", "speed"})
    assert found == {"energy"}


def test_candidate_notes_say_how_each_kind_was_made():
    from fmubuilder.hybridize.report import _candidate_note
    scores = {f"{role}_relative_mse": 0.5 for role in ("train", "validation", "test")}
    term = _candidate_note({"name": "fitted term", "fitted_on": "a.csv", **scores}, None)
    calibrated = _candidate_note({"name": "calibrated mass", "calibrated": {"mass": 1.0}, "simulations": 7,
                                  "fitted_on": "a.csv", **scores}, None)
    on_term = _candidate_note({"name": "neural on the fitted term", "loss_evaluations": 4, **scores}, {"budget": 10})
    assert term.startswith("fitted by the diagnosis on `a.csv`")
    forms = {"chosen": "v + v*|v|", "margin": 1.19, "fitted": [{"form": "v", "validation_score": 349.0},
                                                              {"form": "v + v*|v|", "validation_score": None}]}
    chosen_form = _candidate_note({"name": "fitted term", "fitted_on": "a.csv", "forms": forms, **scores}, None)
    assert chosen_form.startswith("fitted through the simulation on `a.csv`")
    assert "`v` 349, `v + v*|v|` does not simulate" in chosen_form and "lower by x1.19" in chosen_form
    refinement = {"kept": True, "coefficients_before": "-0.000298", "coefficients_after": "-0.0003", "simulations": 5}
    refined = _candidate_note({"name": "fitted term", "fitted_on": "a.csv", "refinement": refinement, **scores}, None)
    assert "coefficient refined through the simulation: -0.000298 -> -0.0003 (5 sims)" in refined
    unrefined = _candidate_note({"name": "fitted term", "fitted_on": "a.csv", **scores,
                                 "refinement": {**refinement, "kept": False}}, None)
    assert "coefficient kept" in unrefined and "->" not in unrefined
    assert calibrated.startswith("calibrated by Gauss-Newton on `a.csv` in 7 simulations")
    assert on_term.startswith("trained with 4 of 10 loss evaluations")
    last_layer = {"kept": True, "loss_before": 3.7257, "loss_after": 1.5942, "simulations": 37}
    refined_ann = _candidate_note({"name": "neural", "loss_evaluations": 5, "last_layer": last_layer, **scores},
                                  {"budget": 5})
    assert "last layer refined through the simulation: training loss 3.726 -> 1.594 (37 sims)" in refined_ann
    unrefined_ann = _candidate_note({"name": "neural", "loss_evaluations": 5, **scores,
                                     "last_layer": {**last_layer, "kept": False}}, {"budget": 5})
    assert "last layer's refinement not kept (37 sims)" in unrefined_ann and "->" not in unrefined_ann
    warm = {"samples": 900, "kept": True, "estimate": ["plain"], "loss_before": 111e3, "loss_after": 31.3,
            "trials": [{}] * 4, "through_simulation": None}
    warmed = _candidate_note({"name": "neural", "loss_evaluations": 5, "warm_start": warm, **scores}, {"budget": 5})
    assert "warm start: fitted to the plain run's estimate, training loss 1.11e+05 -> 31.3" in warmed
    through = {**warm, "estimate": None, "through_simulation": {"kept": True}}
    assert "warm start: last layer through the simulation, training loss" in _candidate_note(
        {"name": "neural", "loss_evaluations": 5, "warm_start": through, **scores}, {"budget": 5})
    cold = _candidate_note({"name": "neural", "loss_evaluations": 5, "warm_start": {**warm, "kept": False}, **scores},
                           {"budget": 5})
    assert "warm start not kept (4 fits tried)" in cold
    stopped = {stage: _candidate_note({"name": "neural", "loss_evaluations": 5, "steps": 4, **scores,
                                       "validation_checkpoint": {"best_stage": stage, "best_epoch": 3}}, {"budget": 5})
               for stage in ("start", "warm start", "epoch", "last layer")}
    assert "ended at its start (nothing it learned scored better on the validation data)" in stopped["start"]
    assert "ended at its warm start" in stopped["warm start"]
    assert "ended after step 3 of 4, its best on the validation data" in stopped["epoch"]
    assert "ended after the last layer's refinement" in stopped["last layer"]
    floor = {"factor": 1.11, "ratios": {"speed": 0.97, "energy": 1.0654}}
    at_floor = _candidate_note({"name": "neural", "loss_evaluations": 0, "at_noise_floor": floor, **scores,
                                "validation_checkpoint": {"best_stage": "warm start"}}, {"budget": 5})
    assert at_floor.startswith("not trained through the solver (0 of 5 loss evaluations): after the warm start every "
                               "training signal lay at its noise floor (MSE / noise variance speed 0.97, energy 1.07; "
                               "the noise alone gives up to 1.11)")
    assert "no training was asked for" not in at_floor and "no training step scored better" not in at_floor
    assert "ended at its warm start, its best on the validation data" in at_floor


def test_the_summary_names_what_each_kind_of_candidate_ships():
    from fmubuilder.hybridize.report import summary_line
    found = {"significant": True, "p_value": 1e-9, "channel": "der(v)", "inputs": ["v"]}

    def shipped(model: dict) -> str:
        chosen = {"chosen": True, "validation_relative_mse": 0.5, "test_relative_mse": 0.5, **model}
        return summary_line({"diagnosis": found, "units": {}, "hybrid_fmu": "out.fmu", "models": [chosen],
                             "mse_factor": {"validation": {"v": 2.0}, "test": {"v": 2.0}},
                             "errors": {role: {"after": {"v": {"mse": 1.0}}} for role in ("validation", "test")},
                             "noise_variance": {"validation": {"v": 1.0}, "test": {"v": 1.0}}})

    calibrated = shipped({"name": "calibrated b", "description": "b = 0.2 (declared 0.1)", "calibrated": {"b": 0.2}})
    assert "with the calibrated parameter b = 0.2 (declared 0.1)." in calibrated and "neural" not in calibrated
    assert "with the fitted term `der(v) += -0.1*v`." in shipped({"name": "fitted term",
                                                                "description": "der(v) += -0.1*v"})
    assert "with a neural network (ANN on der(v))." in shipped({"name": "neural", "description": "ANN on der(v)",
                                                                  "loss_evaluations": 3})


def test_the_headline_keeps_a_signal_at_its_floor_apart_from_a_large_gain_on_another():
    """The demo's shape: the speed near its noise floor already, the energy far above it before;
    a mean of the ratios would read as one middling gain. Units from the report, numbers to 3 digits,
    a rise said as a rise, a signal without a `_std` column said to have no known noise."""
    from fmubuilder.hybridize.report import summary_line
    errors = {"validation": {"speed": 0.997, "energy": 1.07, "power": 4.0},
              "test": {"speed": 0.994, "energy": 0.992, "power": 2.0}}
    report = {"diagnosis": {"significant": True, "p_value": 1e-9, "channel": "der(speed)", "inputs": ["speed"]},
              "units": {"speed": "m/s", "energy": "J"}, "hybrid_fmu": "/tmp/out.fmu",
              "models": [{"chosen": True, "name": "fitted term", "description": "der(speed) += -0.1*speed"}],
              "mse_factor": {"validation": {"speed": 1.2, "energy": 1.09e8, "power": 0.5},
                             "test": {"speed": 1.04, "energy": 1.2e7, "power": 3.0}},
              "errors": {role: {"after": {s: {"mse": v} for s, v in values.items()}} for role, values in errors.items()},
              "noise_variance": {role: {"speed": 1.0, "energy": 1.0, "power": None} for role in errors}}
    summary = summary_line(report)
    assert ("`speed` [m/s] 1.2× lower on validation, 1.04× lower on test, 0.997× and 0.994× the noise; "
            "`energy` [J] 1.09e+08× lower on validation, 1.2e+07× lower on test, 1.07× and 0.992× the noise; "
            "`power` 2× higher on validation, 3× lower on test, the noise not known (no `_std` column).") in summary
    assert "1× is the noise floor" in summary and "mean" not in summary


def test_a_hybrid_built_without_a_significant_effect_is_said_to_be_shipped():
    """`--allow-insignificant`: the diagnosis found nothing, the candidates were built anyway and one
    was published; the summary and the diagnosis section say so instead of "shipped nothing"."""
    from fmubuilder.hybridize.report import _diagnosis_section, summary_line
    report = {"diagnosis": {"significant": False, "p_value": 1.0, "channel": None, "inputs": []}, "units": {},
              "hybrid_fmu": "out.fmu",
              "models": [{"chosen": True, "name": "calibrated mu", "description": "mu = 1.3 (declared 1)",
                          "calibrated": {"mu": 1.3}}],
              "mse_factor": {"validation": {"x": 100.0}, "test": {"x": 50.0}},
              "errors": {role: {"after": {"x": {"mse": 1.0}}} for role in ("validation", "test")},
              "noise_variance": {"validation": {"x": 1.0}, "test": {"x": 1.0}}}
    summary = summary_line(report)
    assert summary.startswith("**No effect found**") and "built anyway (`--allow-insignificant`)" in summary
    assert "**Shipped** `out.fmu` with the calibrated parameter mu = 1.3 (declared 1)" in summary
    assert "Shipped: nothing" not in summary
    assert "No hybrid FMU was written" not in "\n".join(_diagnosis_section(report))
    nothing = {**report, "models": [], "hybrid_fmu": None}
    assert "**Shipped: nothing**" in summary_line(nothing)
    assert "No hybrid FMU was written" in "\n".join(_diagnosis_section(nothing))
