"""pisc_graph's child processes: their standard error is read as it comes, and a child
that is stopping is waited for while it works (a faulted 10-minute soak froze
when the driver's unread stderr pipe filled; a recorder finishing a 10-minute
bag on a loaded machine was killed after 20 s)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time

import pytest

from conftest import spin_until
from pisc_bringup import children
from pisc_bringup.graph import recorded_counts
from pisc_bringup.run_start import EXECUTORS


def _child(code: str, tmp_path):
    return children.spawn([sys.executable, "-c", code], dict(os.environ), subprocess.PIPE)


def test_a_child_writing_much_to_stderr_is_not_blocked_and_its_last_lines_are_kept(tmp_path):
    done = tmp_path / "done"
    # 400 KB of log lines, then a file: with the pipe unread it would block at 64 KB
    code = ("import sys, pathlib\n"
            "for k in range(4000): print(f'line {k} ' + 'x' * 90, file=sys.stderr, flush=True)\n"
            f"pathlib.Path({str(done)!r}).write_text('ok')\n"
            "print('bye', file=sys.stderr); sys.exit(3)")
    child = _child(code, tmp_path)
    deadline = time.monotonic() + 60
    while not done.exists() and time.monotonic() < deadline:
        time.sleep(0.05)
    assert done.exists()
    child.wait(timeout=60)  # its own exit (a SIGTERM from _stop could come first: -15)
    problem, _ = children.stop(child)
    assert problem.startswith(f"{os.path.basename(sys.executable)} exited with status 3: ")
    lines = problem.split(": ", 1)[1].splitlines()
    assert lines[-1] == "bye" and len(lines) == children.STDERR_TAIL_LINES
    assert lines[0].startswith("line 3801 ")


def test_a_stopping_child_is_waited_for_while_it_works_and_killed_when_idle(tmp_path,
                                                                            monkeypatch):
    monkeypatch.setattr(children, "STOP_PATIENCE_S", 1.0)
    # on SIGTERM it computes for 3 s more (a recorder finishing a long bag), then ends
    busy = _child("import signal, time\n"
                  "asked = []\n"
                  "signal.signal(signal.SIGTERM, lambda *a: asked.append(time.monotonic()))\n"
                  "print('ready', flush=True)\n"
                  "while not asked: time.sleep(0.01)\n"
                  "while time.monotonic() < asked[0] + 3: pass\n", tmp_path)
    assert busy.stdout.readline() == b"ready\n"
    started = time.monotonic()
    problem, _ = children.stop(busy)
    assert problem == "" and busy.returncode == 0 and time.monotonic() - started >= 2.0
    # ignores SIGTERM and sleeps: no CPU for the patience, so it is killed
    idle = _child("import signal, time\nsignal.signal(signal.SIGTERM, lambda *a: None)\n"
                  "print('waiting', flush=True)\ntime.sleep(60)", tmp_path)
    assert idle.stdout.readline() == b"waiting\n"
    problem, _ = children.stop(idle)
    assert idle.returncode == -signal.SIGKILL
    assert problem.startswith(f"{os.path.basename(sys.executable)} exited with status -9")


SPINS_ON_SIGTERM = ("import signal, time\n"
                    "asked = []\n"
                    "signal.signal(signal.SIGTERM, lambda *a: asked.append(1))\n"
                    "print('ready', flush=True)\n"
                    "while True: pass\n")


def test_a_controller_that_spins_after_sigterm_is_killed_with_a_warning(tmp_path, monkeypatch,
                                                                       capsys):
    """A supervisor process spun for minutes in Fast DDS's participant teardown after a
    run (2026-12-04: DomainParticipant::set_listener waiting, busy, for a discovery
    callback in flight); pisc_graph waited for it, busy, up to STOP_LIMIT_S. A controller
    is now killed STOP_PATIENCE_S after SIGTERM, busy or not, with a warning; the source
    (plant or driver) stopped first, and a hang of the source stays a failure."""
    monkeypatch.setattr(children, "STOP_PATIENCE_S", 1.0)
    monkeypatch.setattr(children, "STOP_LIMIT_S", 30.0)  # what a busy child was granted
    controller = _child(SPINS_ON_SIGTERM, tmp_path)
    source = _child("print('ready', flush=True)\nimport time\ntime.sleep(60)", tmp_path)
    assert controller.stdout.readline() == b"ready\n" == source.stdout.readline()
    started = time.monotonic()
    assert children.stop_all([controller, source]) == ["", ""]
    assert time.monotonic() - started < children.STOP_LIMIT_S  # killed before the busy limit
    assert controller.returncode == -signal.SIGKILL and source.returncode == -signal.SIGTERM
    err = capsys.readouterr().err
    assert f"pisc_graph: {os.path.basename(sys.executable)} had not exited " in err, err
    assert " s after SIGTERM, " in err, err
    assert " CPU s meanwhile; killed (docs/limitations.md" in err, err
    # the same hang in the source is a failure
    hung = _child(SPINS_ON_SIGTERM, tmp_path)
    assert hung.stdout.readline() == b"ready\n"
    monkeypatch.setattr(children, "STOP_LIMIT_S", 1.5)
    problem = children.stop_all([hung])
    assert hung.returncode == -signal.SIGKILL
    assert problem[0].startswith(f"{os.path.basename(sys.executable)} exited with status -9")


@pytest.mark.skipif(sys.platform != "linux",
                    reason="CPU ticks are read from /proc, which only Linux has")
def test_cpu_ticks_grow_with_work():
    before = children.cpu_ticks(os.getpid())
    end = time.process_time() + 0.3
    while time.process_time() < end:
        pass
    assert children.cpu_ticks(os.getpid()) > before


def test_the_recorders_counts_are_read_past_fast_dds_log_lines_on_its_stdout():
    output = ("/pisc/joint_states 2001\n"
              "\x1b[37;1m2026-12-03 14:39:37.461 \x1b[31;1m[\x1b[37;1mXMLProfileManager\x1b[31;1m "
              "Error] \x1b[37mCould not extract any profile\x1b[34;1m -> Function "
              "\x1b[36mextractProfiles\x1b[m\n"
              "/clock 2001\n/pisc/motor/voltage_sent 0\n")
    assert recorded_counts(output) == {"/pisc/joint_states": 2001, "/clock": 2001,
                                             "/pisc/motor/voltage_sent": 0}


_POLICY = "import os; print(os.sched_getscheduler(0))"


def test_the_recorder_runs_at_sched_batch_and_other_children_at_the_runners_policy():
    """The recorder (batch_scheduling) must not preempt the graph's threads on each
    message it is woken by (docs/soak.md); the nodes' processes keep the runner's."""
    recorder = children.spawn([sys.executable, "-c", _POLICY], dict(os.environ),
                              subprocess.PIPE, batch_scheduling=True)
    node = children.spawn([sys.executable, "-c", _POLICY], dict(os.environ), subprocess.PIPE)
    assert int(recorder.communicate(timeout=60)[0]) == os.SCHED_BATCH
    assert int(node.communicate(timeout=60)[0]) == os.sched_getscheduler(0)


def test_under_sched_fifo_the_recorder_still_runs_at_sched_batch():
    """pisc_graph --realtime: the runner at SCHED_FIFO, its nodes' processes inherit it,
    the recorder does not."""
    code = ("import os, subprocess, sys\n"
            "try:\n"
            "    os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))\n"
            "except PermissionError:\n"
            "    print('no SCHED_FIFO here'); sys.exit(0)\n"
            "from pisc_bringup import children\n"
            f"spawn = lambda **kw: children.spawn([sys.executable, '-c', {_POLICY!r}], "
            "dict(os.environ), subprocess.PIPE, **kw)\n"
            "print(int(spawn(batch_scheduling=True).communicate(timeout=60)[0]), "
            "int(spawn().communicate(timeout=60)[0]))\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=120)
    assert done.returncode == 0, done.stderr
    if done.stdout.strip() == "no SCHED_FIFO here":
        pytest.skip("SCHED_FIFO is not allowed here (CAP_SYS_NICE)")
    assert done.stdout.split() == [str(os.SCHED_BATCH), str(os.SCHED_FIFO)]


def _until_stdin_closes() -> subprocess.Popen:
    """A child that runs until the test closes its standard input."""
    return subprocess.Popen([sys.executable, "-c", "import sys; sys.stdin.read()"],
                            stdin=subprocess.PIPE)


@pytest.fixture
def spun_node(request):
    """(a node, an executor of the kind ``request.param`` names spinning it), torn down
    after the test."""
    import rclpy
    from rclpy.context import Context
    from rclpy.node import Node

    context = Context()
    rclpy.init(context=context)
    node = Node("alarm_probe", context=context)
    executor = EXECUTORS[getattr(request, "param", "events")](context=context)
    executor.add_node(node)
    yield node, executor
    executor.shutdown()
    node.destroy_node()
    context.try_shutdown()


@pytest.mark.parametrize("spun_node", ["events", "single"], indirect=True)
def test_a_childs_exit_runs_the_check_in_the_executors_thread_and_nothing_wakes_before(
        spun_node):
    """The runner sees a child's exit as it happens (timers looking every 20 and
    50 ms woke its main thread 70 times a second): the check runs once the child is gone,
    in the thread spinning the executor; until then the alarm's thread sleeps (its
    context switches counted from /proc), and a child gone before the watch started is
    seen at once."""
    from rclpy.task import Future

    node, executor = spun_node
    early = subprocess.Popen([sys.executable, "-c", "pass"])
    early.wait()  # reaped: no pidfd for it any more
    child = _until_stdin_closes()
    seen: list[tuple[str, int | None, str]] = []
    done = Future(executor=executor)

    def on_exit(name: str, proc: subprocess.Popen) -> None:
        seen.append((name, proc.poll(), threading.current_thread().name))
        if name == "late" and proc.poll() is not None:
            done.set_result(None)

    alarms = [children.ExitAlarm(node, [early], lambda: on_exit("early", early)),
              children.ExitAlarm(node, [child], lambda: on_exit("late", child))]
    try:
        for alarm in alarms:
            alarm.start(executor)
        tid = alarms[1]._thread.native_id
        switches = _context_switches(tid)
        assert spin_until(executor, lambda: seen, 30.0)
        executor.spin_until_future_complete(done, 0.3)  # (the child runs on)
        assert seen == [("early", 0, "MainThread")]  # the early exit, and nothing else yet
        assert _context_switches(tid) - switches <= 2  # asleep, not polling
        child.stdin.close()
        executor.spin_until_future_complete(done, 30.0)
        assert seen[1:] == [("late", 0, "MainThread")]
    finally:
        for alarm in alarms:
            alarm.close()
        child.kill()
        child.wait()


def _context_switches(tid: int) -> int:
    with open(f"/proc/self/task/{tid}/status") as f:
        return sum(int(line.split()[1]) for line in f if "ctxt_switches" in line)


def test_without_pidfds_the_alarm_looks_on_a_timer(monkeypatch, spun_node):
    """Where ``os.pidfd_open`` fails (a kernel before 5.3), the exit is looked for every
    EXIT_POLL_S on a timer of the runner's node, and still seen."""
    from rclpy.task import Future

    def no_pidfd(pid: int) -> int:
        raise OSError(38, "Function not implemented")

    monkeypatch.setattr(children.os, "pidfd_open", no_pidfd)
    node, executor = spun_node
    child = _until_stdin_closes()
    looks = [0]
    done = Future(executor=executor)

    def on_exit() -> None:
        looks[0] += 1
        if child.poll() is not None and not done.done():
            done.set_result(None)

    alarm = children.ExitAlarm(node, [child], on_exit)
    try:
        alarm.start(executor)
        assert alarm._thread is None  # no thread: the timer looks
        assert spin_until(executor, lambda: looks[0] >= 3, 30.0)  # looks while it runs
        assert not done.done()
        child.stdin.close()
        executor.spin_until_future_complete(done, 30.0)
        assert done.done()
    finally:
        alarm.close()
        child.kill()
        child.wait()
