"""The report takes names, units, descriptions and file names from the user's FMU and data: a
hostile one must show as text in report.html, never as markup that runs.

The DC drive and its windage truth (examples/dc_drive) are copied with the state the effect depends
on renamed, its unit and descriptions replaced by markup; the data are measured from the renamed
truth into a file whose name is markup too. The page is read with the standard library's HTML
parser, independent of the markdown converter the report uses.
"""
import html
import zipfile
from html.parser import HTMLParser

import pytest

from fmubuilder import synth
from fmubuilder.build import example_fmu
from fmubuilder.hybridize import hybridize

NAME = "speed`<img src=x onerror=alert(1)>`[x](javascript:alert(2))"
UNIT = "<script>alert(3)</script>"
DESCRIPTION = "<img src=x onerror=alert(4)>"
FILE_STEM = "run <img src=x onerror=alert(5)> ``"
BENCH = dict(signals=(NAME, "current", "power", "temperature"),
             noise_std={NAME: 0.1, "current": 0.02, "power": 1.0, "temperature": 0.02})


def hostile_copy(original, target):
    """`original` with the state `speed` renamed to NAME, its unit UNIT and descriptions DESCRIPTION
    (flat names: any string is a legal name)."""
    def edit(xml: str) -> str:
        xml = xml.replace('variableNamingConvention="structured"', 'variableNamingConvention="flat"')
        for old, new in (('name="speed"', f'name="{NAME}"'), ('name="der(speed)"', f'name="der({NAME})"'),
                         ('"rad/s"', f'"{UNIT}"'), ('description="Motor speed"', f'description="{DESCRIPTION}"')):
            assert old in xml, old
            xml = xml.replace(old, new.replace("<", "&lt;").replace(">", "&gt;"))
        return xml

    with zipfile.ZipFile(original) as source, zipfile.ZipFile(target, "w") as copy:
        for item in source.infolist():
            data = source.read(item)
            copy.writestr(item, edit(data.decode()).encode() if item.filename == "modelDescription.xml" else data)
    return target


def measure(truth, folder, window, seed):
    settings = synth.BenchSettings(seed=seed, **BENCH)
    measurement = synth.measure(truth, start_time=window[0], stop_time=window[1], settings=settings)
    return synth.write_measurement(measurement, folder / f"{FILE_STEM} {seed}.csv")


class Tags(HTMLParser):
    def __init__(self):
        super().__init__()
        self.tags, self.text = [], []

    def handle_starttag(self, tag, attrs):
        self.tags.append((tag, dict(attrs)))

    def handle_data(self, data):
        self.text.append(data)


@pytest.fixture(scope="module")
def page(tmp_path_factory):
    folder = tmp_path_factory.mktemp("hostile")
    model = hostile_copy(example_fmu("dc_drive"), folder / "dc_drive.fmu")
    truth = hostile_copy(example_fmu("dc_drive_truth_windage"), folder / "truth.fmu")
    train, test = measure(truth, folder, (0.0, 10.0), 0), measure(truth, folder, (20.5, 26.0), 1)
    result = hybridize(model, train, test, folder / "hybrid.fmu", folder / "report", budget=1, ann_on_term=False,
                       progress=False)
    assert result.report["roundtrip"]["passed"], "the renamed FMU must be legal, and its hybrid too"
    parser = Tags()
    parser.feed((result.report_dir / "report.html").read_text())
    return parser


def test_hostile_strings_from_the_fmu_and_the_data_are_no_markup_in_report_html(page):
    for tag, attrs in page.tags:
        assert tag not in ("script", "iframe", "object"), tag
        assert not [a for a in attrs if a.startswith("on")], (tag, attrs)
        if tag == "img":
            assert attrs["src"].startswith("data:image/png;base64,"), attrs
        if tag == "a":
            assert not attrs.get("href", "").lower().startswith("javascript"), attrs


def test_the_hostile_strings_show_as_the_text_they_are(page):
    text = html.unescape("".join(page.text))
    for hostile in (NAME, UNIT, FILE_STEM):
        assert hostile in text, hostile
