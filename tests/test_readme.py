"""The README and the guide in docs/ as a reader uses them: their commands and snippets run as
written, the README stays short with its set-up first, and every command's --help names a page
that exists.

Quick stand-ins keep this fast: the Python snippets run in a folder laid out like the demo's
(`example/` with the VLDM and the extra-resistance data) on data files of the same names cut to a
short window; the README's "Use it on your own FMU and data" runs on the DC drive as `model.fmu`
with short windows of its windage truth's measurements."""
import contextlib
import io
import json
import re
import shlex
import shutil
from pathlib import Path

import pytest

from fmubuilder import synth
from fmubuilder.build import example_fmu
from fmubuilder.cli import build_parser, run
from fmubuilder.examples_zoo import SENSOR_NOISE

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
DOCS = ROOT / "docs"
WINDOW = 20.0     # seconds of each cycle
SET_UP = ('pip install -e . && fmubuilder demo', 'pip install -e ".[test]" && python -m pytest -q')


def section_text(page: Path, section: str | None = None) -> str:
    text = page.read_text()
    if section is None:
        return text
    start = text.index(section)
    level = section.split(" ")[0]
    end = text.find(f"\n{level} ", start + len(section))
    return text[start:end if end > 0 else None]


def blocks(page: Path, section: str | None = None, languages=("python", "bash")) -> list[tuple[str, str]]:
    """The fenced blocks of a page (or of one of its sections), in order, as (language, text)."""
    found = re.findall(r"^ *```(\w*)\n(.*?)^ *```", section_text(page, section), flags=re.S | re.M)
    return [(language, _dedent(text)) for language, text in found if language in languages]


def _dedent(text: str) -> str:
    lines = text.splitlines()
    indent = min((len(line) - len(line.lstrip()) for line in lines if line.strip()), default=0)
    return "\n".join(line[indent:] for line in lines) + "\n"


def run_block(language: str, text: str, capsys, name: str) -> str:
    """Run a block as a reader would; returns what it printed. A bash block holds `fmubuilder`
    command lines (run in this process, exit code 0 required)."""
    if language == "python":
        printed = io.StringIO()
        with contextlib.redirect_stdout(printed):
            exec(compile(text, name, "exec"), {})
        return printed.getvalue()
    output = []
    for line in text.splitlines():
        line = line.split(" #")[0].strip()
        if not line:
            continue
        argv = shlex.split(line)
        assert argv[0] == "fmubuilder", f"{name}: only fmubuilder commands run here: {line}"
        capsys.readouterr()
        assert run(argv[1:] + ["--quiet"]) == 0, f"{name}: {line}\n{capsys.readouterr().err}"
        output.append(capsys.readouterr().out)
    return "".join(output)


# -- the README's shape ---------------------------------------------------------------------------

def test_the_readme_is_short_and_opens_with_what_it_is_and_the_two_set_up_commands():
    lines = README.read_text().splitlines()
    assert len(lines) <= 200
    first = "\n".join(lines[:40])
    assert "FMI 2.0 Model-Exchange" in first and "hybrid FMU" in first
    for command in SET_UP:
        assert command in first, command
    assert "## Use it on your own FMU and data" in README.read_text()


def test_ci_runs_the_readme_test_command():
    ci = (ROOT / ".ci" / "run").read_text()
    install, test = SET_UP[1].split(" && ")
    assert f"python -m {install}" in ci and test in ci


# The data folder beside a development checkout, which users do not have.
OUTSIDE_FOLDER = "/".join(("..", "shared"))


def test_the_readme_depends_on_nothing_outside_the_repository():
    for page in (README, *DOCS.glob("*.md")):
        assert OUTSIDE_FOLDER not in page.read_text(), page.name


def _anchors(text: str) -> set[str]:
    """The anchors a markdown renderer gives the headings (a repeated heading gets -1, -2, ...)."""
    found, seen = set(), {}
    for heading in re.findall(r"^#+ (.*)$", text, flags=re.M):
        anchor = re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")
        seen[anchor] = seen.get(anchor, -1) + 1
        found.add(f"{anchor}-{seen[anchor]}" if seen[anchor] else anchor)
    return found


def test_every_link_of_the_readme_and_the_guide_resolves():
    for page in (README, *DOCS.glob("*.md")):
        for target in re.findall(r"\]\(([^)\s]+)\)", page.read_text()):
            if target.startswith("http"):
                continue
            path, _, anchor = target.partition("#")
            linked = (page.parent / path).resolve() if path else page
            assert linked.exists(), f"{page.name}: {target}"
            if anchor and linked.suffix == ".md":
                assert anchor in _anchors(linked.read_text()), f"{page.name}: {target}"


def test_every_json_block_is_valid_json():
    for page in (README, *DOCS.glob("*.md")):
        for text in re.findall(r"```json\n(.*?)```", page.read_text(), flags=re.S):
            assert isinstance(json.loads(text), dict), page.name


# -- --help points to the guide --------------------------------------------------------------------

def _parsers():
    parser = build_parser()
    commands = next(a for a in parser._actions if a.dest == "command").choices
    return {"fmubuilder": parser, **commands}


@pytest.mark.parametrize("command", sorted(_parsers()))
def test_every_help_names_a_page_of_the_guide_that_exists(command):
    epilog = _parsers()[command].epilog or ""
    pages = re.findall(r"(README\.md|docs/[\w-]+\.md)", epilog)
    assert pages, f"`{command} --help` names no page: {epilog!r}"
    for page in pages:
        assert (ROOT / page).is_file(), page
    for page, section in re.findall(r"(README\.md|docs/[\w-]+\.md), section \"([^\"]+)\"", epilog):
        assert re.search(rf"^#+ {re.escape(section)}$", (ROOT / page).read_text(), flags=re.M), (page, section)


# -- "Use it on your own FMU and data" --------------------------------------------------------------

OWN_BENCH = dict(signals=("speed", "current", "power", "temperature"),
                 noise_std={"speed": 0.1, "current": 0.02, "power": 1.0, "temperature": 0.02})


@pytest.fixture(scope="module")
def own_folder(tmp_path_factory):
    """model.fmu, train.csv and test.csv with sidecars, as the README's section has the reader write them."""
    folder = tmp_path_factory.mktemp("own")
    shutil.copy(example_fmu("dc_drive"), folder / "model.fmu")
    truth = example_fmu("dc_drive_truth_windage")
    for name, window, seed in (("train.csv", (0.0, 10.0), 0), ("test.csv", (20.5, 26.0), 1)):
        measurement = synth.measure(truth, start_time=window[0], stop_time=window[1],
                                    settings=synth.BenchSettings(seed=seed, **OWN_BENCH))
        synth.write_measurement(measurement, folder / name)
    return folder


def test_use_it_on_your_own_fmu_and_data_runs_as_written(own_folder, monkeypatch, capsys):
    monkeypatch.chdir(own_folder)
    section = "## Use it on your own FMU and data"
    [(language, commands)] = blocks(README, section, ("bash",))
    assert "fmubuilder hybridize model.fmu --train train.csv --test test.csv" in commands
    assert "fmubuilder inspect model.fmu" in section_text(README, section)
    printed = run_block("bash", "fmubuilder inspect model.fmu\n" + commands, capsys, "README.md: Use it")
    assert "Significant effect" in printed and "wrote hybrid.fmu" in printed
    summary = (own_folder / "report" / "report.md").read_text().splitlines()[2]
    assert "**Held out, per signal**" in summary and "the noise" in summary


# -- docs/data.md: the complete small example -------------------------------------------------------

def test_the_data_guide_example_runs_and_prints_what_the_page_says(tmp_path, monkeypatch, capsys):
    page = DOCS / "data.md"
    monkeypatch.chdir(tmp_path)
    printed = ""
    for index, (language, text) in enumerate(blocks(page, "## A complete small example")):
        printed += run_block(language, text, capsys, f"docs/data.md block {index + 1}")
    shown = re.search(r"```\n(time,.*?)```", section_text(page, "## The CSV file"), flags=re.S).group(1)
    assert (tmp_path / "measured.csv").read_text().startswith(shown)
    stated = re.search(r"joint p = ([0-9.e+-]+)\)", section_text(page, "## A complete small example")).group(1)
    assert f"joint p = {stated} <" in printed and "temperature" in printed


# -- docs/export.md: fmpy on a hybrid -----------------------------------------------------------------

def test_the_export_guide_fmpy_snippet_runs_on_a_hybrid(tmp_path, monkeypatch, capsys):
    import torch
    from fmubuilder.export import HybridSpec, export_hybrid, freeze
    from fmubuilder.fmi import read_model_info
    torch.manual_seed(0)
    network = torch.nn.Sequential(torch.nn.Linear(1, 4), torch.nn.Tanh(), torch.nn.Linear(4, 1)).double()
    freeze(network, 1, tmp_path / "network.onnx")
    original = example_fmu("dc_drive")
    HybridSpec(original_fmu=original, original_guid=read_model_info(original).guid, channels=["der(speed)"],
               inputs=["speed"], onnx=tmp_path / "network.onnx", p_ann=[1.0]).save(tmp_path / "spec.json")
    export_hybrid(tmp_path / "spec.json", tmp_path / "hybrid.fmu")
    monkeypatch.chdir(tmp_path)
    [(language, text)] = blocks(DOCS / "export.md", "## Using it in other tools", ("python",))
    hybrid, off = (float(v) for v in run_block(language, text, capsys, "docs/export.md").split())
    assert hybrid != off


# -- docs/how-it-works.md: the Python API -------------------------------------------------------------

API = DOCS / "how-it-works.md"


def python_blocks() -> list[str]:
    return [text for _, text in blocks(API, "## From Python", ("python",))]


@pytest.fixture(scope="module")
def demo_folder(tmp_path_factory):
    folder = tmp_path_factory.mktemp("readme")
    example = folder / "example"
    example.mkdir()
    shutil.copy(example_fmu("vldm"), example / "vldm.fmu")
    truth = example_fmu("vldm_truth_extra_resistance")
    for name, cycle, seed in (("extra_resistance_train_cadc.csv", 1, 0), ("extra_resistance_test_wltc2.csv", 2, 1)):
        measurement = synth.measure(truth, stop_time=WINDOW, start_values={"cycle": cycle},
                                    settings=synth.BenchSettings(seed=seed, **SENSOR_NOISE))
        synth.write_measurement(measurement, example / name)
    return folder


def test_the_guide_has_python_snippets():
    found = python_blocks()
    assert len(found) >= 3
    assert all("example/" in block for block in found)


@pytest.mark.parametrize("index", range(len(python_blocks())))
def test_a_python_api_snippet_runs_as_written(index, demo_folder, monkeypatch, capsys):
    monkeypatch.chdir(demo_folder)
    printed = run_block("python", python_blocks()[index], capsys, f"docs/how-it-works.md python block {index + 1}")
    assert printed.strip(), "every snippet shows its result"
