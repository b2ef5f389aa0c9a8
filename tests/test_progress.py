"""Progress bars (fmubuilder/progress.py): honest totals, and a bar always closes, at its total
or with a note that says where and why it stopped."""
import pytest

from fmubuilder import progress
from fmubuilder.progress import Bar


@pytest.fixture
def shown():
    progress.set_enabled(True)
    yield
    progress.set_enabled(None)


def last_line(err: str) -> str:
    """What a terminal shows last: tqdm redraws the line with carriage returns."""
    return err.replace("\r", "\n").strip().splitlines()[-1]


def test_a_bar_closes_at_its_total(shown, capsys):
    with progress.progress(4, "trials", unit="trial") as bar:
        for _ in range(4):
            bar.advance()
    assert bar.closed and bar.reason is None and bar.note == "4/4 trials"
    line = last_line(capsys.readouterr().err)
    assert line.startswith("trials: 100%") and "4/4" in line


def test_a_bar_stopped_early_says_where_and_why(shown, capsys):
    with progress.progress(10, "training", unit="batch") as bar:
        bar.advance(3)
        bar.stop("time budget used up")
    assert bar.note == "stopped at 3/10 batches: time budget used up"
    line = last_line(capsys.readouterr().err)
    assert line.startswith("training (stopped: time budget used up):  30%") and "| 3/10 [" in line


def test_a_failure_closes_the_bar_with_a_note(shown, capsys):
    with pytest.raises(ValueError):
        with progress.progress(5, "rows", unit="row") as bar:
            bar.advance(2)
            raise ValueError("boom")
    assert bar.closed and bar.note == "stopped at 2/5 rows: failed"
    assert last_line(capsys.readouterr().err).startswith("rows (stopped: failed):  40%")


def test_quiet_when_stderr_is_no_terminal(capsys):
    progress.set_enabled(None)          # pytest's captured stderr is no terminal
    with progress.progress(3, "quiet") as bar:
        bar.advance(3)
    assert capsys.readouterr().err == "" and bar.note == "3/3 steps"
    assert Bar(2, "off", "step", show=False).note == "0/2 steps"


def test_the_build_bar_reads_the_percentage_cmake_prints():
    from fmubuilder.build import _build_percent
    assert _build_percent("[ 42%] Building C object CMakeFiles/x.dir/model.c.o\n") == 42
    assert _build_percent("[100%] Built target x\n") == 100
    assert _build_percent("[3/24] Building C object x.o\n") == 12          # Ninja: steps done / all
    assert _build_percent("-- Configuring done\n") is None


def test_a_loop_left_early_closes_its_bar_with_a_note(shown, capsys):
    seen = []
    bars = progress.counted([1, 2, 3, 4], "items", "item")
    for item in bars:
        seen.append(item)
        if item == 2:
            break
    bars.close()
    assert seen == [1, 2]
    line = last_line(capsys.readouterr().err)
    assert line.startswith("items (stopped: cut short):  25%") and "| 1/4 [" in line


def test_a_status_line_shows_under_a_bar_and_is_cleared(shown, capsys):
    with progress.progress(2, "batch: cases", unit="case") as bar, progress.StatusLine() as line:
        line.show(["a: 1/5 diagnosing", "b: 2/5 training"])
        bar.advance(2)
    err = capsys.readouterr().err
    assert "a: 1/5 diagnosing; b: 2/5 training" in err
    assert last_line(err).startswith("batch: cases: 100%")      # the line went with the work


def test_no_status_line_when_bars_are_off(capsys):
    progress.set_enabled(False)
    with progress.StatusLine() as line:
        line.show(["a: starting"])
    progress.set_enabled(None)
    assert capsys.readouterr().err == ""
