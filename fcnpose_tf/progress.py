"""One reporter for a command's messages and progress: bars on a terminal, plain lines in a log.

Training, compression, data preparation and the synthetic generator report through a `Reporter`
instead of print calls, tqdm bars and Keras verbosity levels side by side. On a terminal a loop
shows a tqdm bar and training Keras' progress bar. When the output is not a terminal (a log file,
nohup, CI) or the command runs with --quiet, nothing is redrawn with a carriage return: a loop
writes one line per ~10 % and training one line per epoch, so a log reads top to bottom and an
`error:` line always starts a line of its own (`end_line`, called by the CLI before it).

Standard library only (tqdm is imported when a bar is drawn): the Pi runtime may import it.
"""

from __future__ import annotations

import contextlib
import sys
from typing import Any, Iterable, Iterator, Sequence, TextIO

LINE_STEPS = 10
"""Without a bar a loop reports every 1/LINE_STEPS of its length (and its end)."""


class Reporter:
    """Where a command's messages and progress go, and how they are drawn.

    Args:
        quiet: no progress bars even on a terminal and no loop progress, one line per epoch; --quiet (logs).
        silent: no messages and no progress at all (library use, tests, parallel workers' noise).
        stream: where messages and progress lines go (default: sys.stdout at the time of each call).
    """

    def __init__(self, *, quiet: bool = False, silent: bool = False, stream: TextIO | None = None) -> None:
        self.quiet = quiet
        self.silent = silent
        self._stream = stream
        self._bars: list[Any] = []

    @property
    def stream(self) -> TextIO:
        return self._stream if self._stream is not None else sys.stdout

    @property
    def bars(self) -> bool:
        """Whether progress is drawn as redrawn bars: on a terminal (stdout and stderr), unless quiet or silent."""
        return not (self.quiet or self.silent) and _is_terminal(self.stream) and _is_terminal(sys.stderr)

    @property
    def keras_verbose(self) -> int:
        """Keras' fit verbosity: 1 (its progress bar) with bars, 2 (one line per epoch) without, 0 when silent."""
        return 0 if self.silent else 1 if self.bars else 2

    def say(self, line: str) -> None:
        """One message line, at the start of a line of its own."""
        if self.silent:
            return
        self.end_line()
        print(line, file=self.stream, flush=True)

    def progress(self, items: Iterable, desc: str, *, total: int | None = None, unit: str = "frame") -> Iterator:
        """Iterate `items`, showing how far: a tqdm bar, or a line at every ~10 % ("desc: 30/100 frames (30 %)")."""
        if total is None:
            try:
                total = len(items)  # type: ignore[arg-type]
            except TypeError:
                total = None
        if self.silent or self.quiet:
            yield from items
            return
        if self.bars:
            from tqdm import tqdm

            bar = tqdm(items, desc=desc, total=total, unit=unit, leave=False)
            self._bars.append(bar)
            try:
                yield from bar
            finally:
                bar.close()
                if bar in self._bars:
                    self._bars.remove(bar)
            return
        done, next_step = 0, 1
        for item in items:
            yield item
            done += 1
            if total and done * LINE_STEPS >= next_step * total:
                self.say(f"{desc}: {done}/{total} {unit}s ({100 * done // total} %)")
                next_step = done * LINE_STEPS // total + 1
        if not total:
            self.say(f"{desc}: {done} {unit}s")

    def lines(self) -> Reporter:
        """This reporter drawing no bars: the same stream, Keras one line per epoch (a retraining inside a longer
        run, whose own steps are lines)."""
        return Reporter(quiet=True, silent=self.silent, stream=self._stream)

    def counter(self, total: int, desc: str, *, unit: str = "frame") -> Counter:
        """A progress count advanced by hand (`update(n)`), for work that finishes out of order (worker pools)."""
        return Counter(self, total, desc, unit)

    def end_line(self) -> None:
        """Close any bar being drawn, so that what is written next starts a line of its own."""
        for bar in list(self._bars):
            bar.close()
        self._bars.clear()


class Counter:
    """A progress count for `Reporter.counter`: a bar, or a line at every ~10 %."""

    def __init__(self, reporter: Reporter, total: int, desc: str, unit: str) -> None:
        self.reporter, self.total, self.desc, self.unit = reporter, total, desc, unit
        self.done, self._next = 0, 1
        self._bar = None
        if reporter.bars:
            from tqdm import tqdm

            self._bar = tqdm(total=total, desc=desc, unit=unit)
            reporter._bars.append(self._bar)

    def update(self, n: int = 1) -> None:
        self.done += n
        if self.reporter.silent or self.reporter.quiet:
            return
        if self._bar is not None:
            self._bar.update(n)
        elif self.total and self.done * LINE_STEPS >= self._next * self.total:
            self.reporter.say(f"{self.desc}: {self.done}/{self.total} {self.unit}s ({100 * self.done // self.total} %)")
            self._next = self.done * LINE_STEPS // self.total + 1

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()
            if self._bar in self.reporter._bars:
                self.reporter._bars.remove(self._bar)
            self._bar = None

    def __enter__(self) -> Counter:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


def _is_terminal(stream: Any) -> bool:
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):
        return False


_current = Reporter()
SILENT = Reporter(silent=True)
"""A reporter that says nothing: library calls and tests that want no output."""


def current() -> Reporter:
    """The running command's reporter (`use`), else one that draws bars on a terminal and lines elsewhere."""
    return _current


def use(reporter: Reporter) -> Reporter:
    """Make `reporter` the one library calls without their own report through; returns the previous one."""
    global _current
    previous, _current = _current, reporter
    return previous


@contextlib.contextmanager
def using(reporter: Reporter) -> Iterator[Reporter]:
    """`reporter` as the current one (`use`) within the block, the previous one again after it."""
    previous = use(reporter)
    try:
        yield reporter
    finally:
        reporter.end_line()
        use(previous)


def resolve(reporter: Reporter | None) -> Reporter:
    """`reporter`, else the current one."""
    return reporter if reporter is not None else _current


def report_items(items: Sequence, progress: Reporter | bool | None, desc: str) -> Iterable:
    """`items`, their progress reported when `progress` is a Reporter (True: the current one; False or None: not
    reported), for data preparation whose callers pass either."""
    if progress is False or progress is None:
        return items
    return resolve(None if progress is True else progress).progress(items, desc)

