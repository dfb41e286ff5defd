"""Progress bars of long commands (issue 17 item 5): pisc_msgs_py.progress draws a tqdm bar
on stderr when stderr is a terminal, writes nothing otherwise, and leaves stdout's figures
as they are."""

from __future__ import annotations

import io
import os
import pty
import re
import select
import time

import pytest

from pisc_msgs_py.progress import progress_bar

#: what a tqdm bar writes: a carriage return, a percentage and a "done/total" count
BAR = re.compile(r"\r.*\d+%.*\d+/\d+")


def _drain(fd: int) -> str:
    """Everything the pty's master side has to read now."""
    chunks = []
    while select.select([fd], [], [], 0.2)[0]:
        try:
            data = os.read(fd, 65536)
        except OSError:  # the slave side is closed
            break
        if not data:
            break
        chunks.append(data)
    return b"".join(chunks).decode(errors="replace")


@pytest.fixture
def terminal():
    """(a text file on a pseudo-terminal, read everything written to it so far)."""
    master, slave = pty.openpty()
    stream = os.fdopen(slave, "w", buffering=1)
    try:
        yield stream, lambda: (stream.flush(), _drain(master))[1]
    finally:
        stream.close()
        os.close(master)


def test_a_stream_that_is_not_a_terminal_receives_nothing():
    stream = io.StringIO()
    with progress_bar(10, "row", "bench", stream=stream) as bar:
        bar(3)
        bar.to(7)
        bar.describe("best 99.0 %")
        out = io.StringIO()
        assert bar.above(out) is out  # lines go straight to the file
        assert not bar.shown
    assert stream.getvalue() == ""


def test_a_terminal_shows_the_count_the_unit_and_the_label(terminal):
    stream, read = terminal
    with progress_bar(10, "row", "bench", stream=stream) as bar:
        assert bar.shown
        bar(3)
        time.sleep(0.15)  # tqdm redraws at most every 0.1 s
        bar(1)
        shown = read()
        bar.to(9)
        bar.describe("best 97.5 %")
        bar(0)
        later = read()
    assert BAR.search(shown), shown
    assert "bench" in shown and "4/10" in shown and "40%" in shown and "row" in shown
    assert "9/10" in later and "best 97.5 %" in later
    # leave=False: the bar is erased at the end (a carriage return, then blanks)
    assert re.search(r"\r +\r", read())


def test_lines_above_the_bar_clear_it_first_and_arrive_whole(terminal):
    stream, read = terminal
    rows = io.StringIO()
    with progress_bar(2, "row", stream=stream) as bar:
        bar(1)
        read()
        out = bar.above(rows)
        print("exprk4   2 steps/period", end="", file=out)
        assert rows.getvalue() == ""  # a partial line waits for its end
        print("   1.2e-09", file=out, flush=True)
        assert rows.getvalue() == "exprk4   2 steps/period   1.2e-09\n"
        redrawn = read()
    # the bar was cleared (blanks between carriage returns) and drawn again
    assert re.search(r"\r +\r\r?[^\r]*1/2", redrawn), repr(redrawn)


def test_a_negative_total_is_refused():
    with pytest.raises(ValueError, match="total -1: a count of steps"):
        progress_bar(-1, "row")
