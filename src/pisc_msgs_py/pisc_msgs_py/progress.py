"""Progress of long commands: one tqdm bar on stderr, silent when stderr is not a terminal.

Every command that can take more than a few seconds shows its progress
with :class:`progress_bar`; its figures go to stdout as before, so a pipe or a file receives
the same text with or without a terminal, and a log captured from stderr holds no bar.

    from pisc_msgs_py.progress import progress_bar

    with progress_bar(len(rows), "row", "parser bench") as bar:
        for row in rows:
            ...
            bar(1)          # one more done
        bar.to(n)           # n done in all (a count reported by the work itself)
        bar.describe("best 97.0 %")
        print(row, file=bar.above(sys.stdout))   # a line that does not cut the bar

The bar is drawn only when ``stream`` (default: ``sys.stderr`` at entry) is a terminal;
otherwise every call is a no-op and nothing is written. ``leave=False``: the bar is erased
when the work ends, so a terminal keeps only the command's figures.
"""

from __future__ import annotations

import io
import os
import sys
from typing import IO, Any

__all__ = ["progress_bar"]


class progress_bar:  # noqa: N801 (a context manager used like a function)
    """A tqdm bar of ``total`` steps named ``unit``, on stderr, quiet unless stderr is a
    terminal; the instance is called with the number of steps just done."""

    def __init__(self, total: int, unit: str, desc: str = "",
                 stream: IO[str] | None = None) -> None:
        if total < 0:
            raise ValueError(f"progress_bar total {total}: a count of steps, at least 0")
        self.total, self.unit, self.desc = total, unit, desc
        self.stream = stream
        self.bar: Any = None

    @property
    def shown(self) -> bool:
        """Whether the bar is drawn (its stream is a terminal)."""
        return self.bar is not None and not self.bar.disable

    def __enter__(self) -> progress_bar:
        from tqdm import tqdm

        stream = self.stream if self.stream is not None else sys.stderr
        columns, rows = _size(stream)
        # disable=None: tqdm draws only when the stream is a terminal (isatty)
        self.bar = tqdm(total=self.total, unit=self.unit, desc=self.desc or None,
                        disable=None, leave=False, file=stream, ncols=columns, nrows=rows,
                        dynamic_ncols=False)
        return self

    def __call__(self, n: int = 1) -> None:
        self.bar.update(n)

    def to(self, done: int, total: int | None = None) -> None:
        """Set the count done so far (work that reports totals, not increments), and the
        total when the work tells it only as it runs (a bar begun with ``total`` 0)."""
        if self.bar.disable:
            return
        if total is not None:
            self.bar.total = total
        self.bar.update(done - self.bar.n)  # redrawn at most every 0.1 s, as by __call__

    def describe(self, text: str) -> None:
        """Replace the bar's label (e.g. the best result so far)."""
        if not self.bar.disable:
            self.bar.set_description(text)

    def above(self, file: IO[str]) -> IO[str]:
        """``file`` itself when the bar is not shown; else a file whose every complete line
        is written while the bar is cleared, then the bar is drawn again below it (a
        command's rows on stdout and its bar on stderr share one terminal)."""
        return _Above(self.bar, file) if self.shown else file

    def __exit__(self, *exc: object) -> None:
        self.bar.close()


def _size(stream: IO[str]) -> tuple[int, int]:
    """(columns, rows) of the bar: the terminal's, at most 120 columns; 100 x 24 when it
    tells none. A terminal that reports 0 x 0 (a pseudo-terminal nobody sized, as under
    ``script`` or a container's exec) would otherwise make tqdm draw nothing at all."""
    try:
        columns, rows = os.get_terminal_size(stream.fileno())
    except (AttributeError, OSError, ValueError):
        columns, rows = 0, 0
    return (min(columns, 120) if columns > 0 else 100), (rows if rows > 0 else 24)


class _Above(io.TextIOBase):
    """Lines to ``file``, each written with the bar cleared; a partial line waits."""

    def __init__(self, bar: Any, file: IO[str]) -> None:
        super().__init__()
        self.bar, self.file, self.pending = bar, file, ""

    def write(self, text: str) -> int:  # type: ignore[override]
        head, newline, self.pending = (self.pending + text).rpartition("\n")
        if newline:
            self._out(head + newline)
        return len(text)

    def flush(self) -> None:
        self.file.flush()

    def _out(self, text: str) -> None:
        self.bar.clear()
        self.file.write(text)
        self.file.flush()
        self.bar.refresh()
