"""Progress bars for the long stages, on stderr, drawn by tqdm.

Every bar counts work known before it starts (epochs x batches, trials, data sets, rows), so
its total and ETA are honest. A bar always closes: at its total, or, when the work stops early,
with a note that says where and why ("stopped at 3/10 batches: time budget used up").

Bars show only when stderr is a terminal, unless `set_enabled` says otherwise (the CLI's
`--quiet` turns them off; tests turn them on to read them). A caller's `show=False` keeps its own
bar off (a run without progress); `show=True` leaves it to that rule, never forces it.

    with progress(len(trials), "diagnosis: trials", unit="trial") as bar:
        for trial in trials:
            run(trial)
            bar.advance()
"""
from __future__ import annotations

import contextlib
import shutil
import sys

_enabled: bool | None = None     # None: when stderr is a terminal


def set_enabled(enabled: bool | None) -> None:
    """True/False: always/never show bars; None: when stderr is a terminal."""
    global _enabled
    _enabled = enabled


def enabled() -> bool:
    if _enabled is not None:
        return _enabled
    try:
        return sys.stderr.isatty()
    except (AttributeError, ValueError):   # a replaced or closed stream
        return False


class Bar:
    """One bar: `advance` as work completes, `stop(reason)` when it ends before its total."""

    def __init__(self, total: int, description: str, unit: str, initial: int = 0, show: bool = True):
        self.total = max(int(total), 0)
        self.done = int(initial)
        self.description = description
        self.unit = unit
        self.reason: str | None = None     # why it stopped before its total
        self.closed = False
        self._tqdm = None
        if show and enabled():
            from tqdm import tqdm
            # mininterval: redraw at most twice a second
            size = shutil.get_terminal_size((100, 24))     # tqdm draws nothing on a terminal of size 0
            self._tqdm = tqdm(total=self.total, initial=self.done, desc=description, unit=unit, file=sys.stderr,
                              leave=True, mininterval=0.5, ncols=size.columns, nrows=size.lines)

    def advance(self, count: int = 1, **status) -> None:
        """`count` more units done; `status` (e.g. loss=0.3) is shown after the bar."""
        self.done += count
        if self._tqdm is not None:
            if status:
                self._tqdm.set_postfix(status, refresh=False)
            self._tqdm.update(count)

    def stop(self, reason: str) -> None:
        """End the bar early, saying why; it closes at the work done, not at its total."""
        if self.done < self.total and self.reason is None:
            self.reason = reason
        self.close()

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        if self.done < self.total and self.reason is None:
            self.reason = "cut short"
        if self._tqdm is not None:
            if self.reason is not None:
                # the last line: where it stopped and why, with no time left to wait for
                self._tqdm.set_description_str(f"{self.description} (stopped: {self.reason})", refresh=False)
                self._tqdm.bar_format = "{desc}: {percentage:3.0f}%|{bar}| {n_fmt}/{total_fmt} [{elapsed}{postfix}]"
            self._tqdm.close()

    @property
    def note(self) -> str:
        """The bar's closing words for a log: '10/10 epochs' or 'stopped at 3/10 epochs: why'."""
        if self.reason is not None:
            return f"stopped at {self.done}/{self.total} {_plural(self.unit)}: {self.reason}"
        return f"{self.done}/{self.total} {_plural(self.unit)}"


def counted(items, description: str, unit: str = "step", total: int | None = None, show: bool = True):
    """Iterate over `items` with a bar that counts each item when the loop's body is done with it;
    a loop left early (break, error) closes the bar with a note. `total`: for items without len()."""
    bar = Bar(len(items) if total is None else total, description, unit, show=show)
    try:
        for item in items:
            yield item
            bar.advance()
    finally:
        bar.close()


@contextlib.contextmanager
def progress(total: int, description: str, unit: str = "step", initial: int = 0, show: bool = True):
    """A Bar that closes on every way out of the block: at its total, stopped early (the block
    called `stop`), on an error ("failed") or on Ctrl-C ("interrupted")."""
    bar = Bar(total, description, unit, initial=initial, show=show)
    try:
        yield bar
    except KeyboardInterrupt:
        bar.stop("interrupted")
        raise
    except BaseException:
        bar.stop("failed")
        raise
    finally:
        bar.close()


def _plural(unit: str) -> str:
    return unit if unit == "%" else unit + ("es" if unit.endswith(("s", "sh", "ch", "x")) else "s")


class StatusLine:
    """A line of text under a bar, redrawn in place: what each running job is doing. Shows when the
    bars do; a context manager that clears the line on the way out."""

    def __init__(self, show: bool = True):
        self._tqdm = None
        self._text = None
        if show and enabled():
            from tqdm import tqdm
            size = shutil.get_terminal_size((100, 24))
            self._tqdm = tqdm(total=0, bar_format="{desc}", position=1, leave=False, file=sys.stderr,
                              ncols=size.columns, nrows=size.lines)

    def show(self, parts: list[str]) -> None:
        text = "; ".join(parts)
        if self._tqdm is not None and text != self._text:
            self._text = text
            self._tqdm.set_description_str(text[:max(self._tqdm.ncols - 1, 10)])

    def close(self) -> None:
        if self._tqdm is not None:
            self._tqdm.close()
            self._tqdm = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
