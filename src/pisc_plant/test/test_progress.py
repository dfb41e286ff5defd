"""Progress bars of long commands: pisc_msgs_py.progress draws a tqdm bar
on stderr when stderr is a terminal, writes nothing otherwise, and leaves stdout's figures
as they are."""

from __future__ import annotations

import io
import os
import pty
import re
import select
import subprocess
import sys
import tempfile
import time
from pathlib import Path

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


def test_a_total_told_late_is_shown_with_the_count(terminal):
    """The region of attraction and pisc_batch_bench learn the cycles' count only from
    the batch's first progress call: the bar begins without a total."""
    stream, read = terminal
    with progress_bar(0, "cycle", "batch", stream=stream) as bar:
        bar.to(1, 101)
        time.sleep(0.15)  # tqdm redraws at most every 0.1 s
        bar.to(51, 101)
        shown = read()
    assert re.search(r"batch: +50%\|.*\| 51/101 ", shown), repr(shown)


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


# --- the commands -----------------------------------------------------------------------

BIN = Path(sys.executable).parent


def _run(argv: list[str], cwd: Path, terminal: bool) -> tuple[str, str]:
    """(stdout, stderr) of a command whose stdout is a pipe and whose stderr is a pipe or,
    with ``terminal``, a pseudo-terminal (read while the command runs: a full pty blocks
    its writer)."""
    if not terminal:
        done = subprocess.run(argv, cwd=cwd, capture_output=True, text=True, timeout=900)
        assert done.returncode == 0, done.stderr
        return done.stdout, done.stderr
    master, slave = pty.openpty()
    with tempfile.TemporaryFile("w+") as stdout:
        process = subprocess.Popen(argv, cwd=cwd, stdout=stdout, stderr=slave, text=True)
        os.close(slave)
        chunks = []
        try:
            while process.poll() is None:
                chunks.append(_drain(master))
            chunks.append(_drain(master))
            process.wait(timeout=900)
        finally:
            if process.poll() is None:
                process.kill()
            os.close(master)
        assert process.returncode == 0, "".join(chunks)
        stdout.seek(0)
        return stdout.read(), "".join(chunks)


def _figures(text: str) -> list[str]:
    """The table rows without their wall-time column (the one figure a run changes)."""
    rows = []
    for line in text.splitlines():
        if re.match(r"(exprk4|rk4|solve_ivp|control) ", line):
            head, wall, *rest = line[:50], *line[50:].split()
            rows.append(" ".join([head.strip(), *rest]))
    return rows


@pytest.mark.integration
def test_pisc_integrators_bar_on_a_terminal_only_and_the_same_figures(tmp_path):
    argv = [str(BIN / "pisc_integrators"), "--duration", "0.05", "--conservative-duration",
            "0.5", "--quick", "--png", str(tmp_path / "wp.png")]
    piped, piped_err = _run(argv, tmp_path, terminal=False)
    shown, bar = _run(argv, tmp_path, terminal=True)
    # through a pipe: not a character of a bar, the tables on stdout
    assert piped_err == ""
    rows = _figures(piped)
    # playback: 7 exprk4 + 5 rk4 counts + 4 methods x 2 tolerances; conservative: 7 + 5 + 2
    assert len(rows) == 20 + 14, piped
    assert "run/s" not in piped and "\r" not in piped
    # on a terminal: a bar counting the integrations, the references' included:
    # playback 2 + 20 rows, conservative 1 + 14 rows
    counts = [int(n) for n in re.findall(r"\| *(\d+)/37 \[", bar)]
    assert "integrators" in bar and counts and counts == sorted(counts), bar
    assert 0 < counts[-1] <= 37
    assert re.search(r"\r +\r$", bar)  # erased at the end
    # and stdout holds the same figures, nothing of the bar
    assert _figures(shown) == rows
    assert "\r" not in shown


def test_set_up_names_each_kernel_step_before_it_compiles_then_its_seconds():
    """./pisc set-up runs ``python -m pisc_plant.warm_cli run``: the step's name and number
    come first, so a first compile's minutes are not spent silent; then its seconds."""
    from pisc_plant.warm import warm_up

    said: list[str] = []
    total = warm_up("run", said.append)
    assert said[0] == "  kernel full + RC filters: one rig (1/1) ..."
    assert re.fullmatch(r" \d+\.\d s\n", said[1]), said
    assert len(said) == 2 and float(said[1].split()[0]) <= total + 0.05
