"""The README's Python snippets run as written, in a folder laid out like the demo's (`example/`
with the VLDM and the extra-resistance data), on data files of the same names cut to a short
window so that the test stays quick."""
import contextlib
import io
import re
import shutil
from pathlib import Path

import pytest

from fmubuilder import synth
from fmubuilder.build import example_fmu
from fmubuilder.examples_zoo import SENSOR_NOISE

README = Path(__file__).resolve().parents[1] / "README.md"
WINDOW = 20.0     # seconds of each cycle


def python_blocks(section: str = "## Python API") -> list[str]:
    text = README.read_text()
    start = text.index(section)
    end = text.find("\n## ", start + len(section))
    return re.findall(r"```python\n(.*?)```", text[start:end if end > 0 else None], flags=re.S)


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


def test_the_readme_has_python_snippets():
    blocks = python_blocks()
    assert len(blocks) >= 3
    assert all("example/" in block for block in blocks)


@pytest.mark.parametrize("index", range(len(python_blocks())))
def test_a_readme_snippet_runs_as_written(index, demo_folder, monkeypatch):
    monkeypatch.chdir(demo_folder)
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        exec(compile(python_blocks()[index], f"README.md python block {index + 1}", "exec"), {})
    assert printed.getvalue().strip(), "every snippet shows its result"
