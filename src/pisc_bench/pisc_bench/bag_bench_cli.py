"""The bag tools on a long bag: finish, repair, analyse and replay, each timed (the
targets: <= 200 MB and >= 100,000 messages a second, a 10-minute bag in <= 10 s;
``pisc_bench`` judges them).

    .venv/bin/python -m pisc_bench.bag_bench_cli [--seconds 600] [--from BAG] [--dir DIR]
                                                   [--keep] [--only finish repair ...]

The bag is made as the recorder makes one (:func:`pisc_bench.bag_bench.make_stream`).
Then each tool runs as a process of its own, on a copy of the stream where needed:

* finish: what :meth:`BagWriter.close` does at the end of a recording;
* repair: ``pisc_bag repair`` of the stream with its last record cut;
* analyse: ``pisc_bag analyse`` of the finished bag;
* replay: ``pisc_bag replay`` of the finished bag (through the controller cores).

Each prints its wall time (the command's, interpreter start included), CPU time
(``wait4``), messages a second, and the process's own peak resident memory (``VmHWM``
read by the child at its end; a child's ``ru_maxrss`` starts from its parent's); the
date and load average go first, the load again at the end.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from pisc_bench.bag_bench import DEFAULT_SOURCE, make_stream

__all__ = ["main"]

STEPS = ("finish", "repair", "analyse", "replay")


def _finish(directory: str) -> int:
    """The finish step, in its own process."""
    from pisc_bag.bag import _finish_stream  # noqa: PLC2701 - what close() runs

    path = Path(directory) / f"{Path(directory).name}_0.mcap"
    written = _finish_stream(Path(directory), path)
    print(f"finished {path}: {written.messages} messages"
          + (" (through the external merge)" if written.merged else ""))
    return 0


def _run_measured(label: str, command: list[str], messages: int) -> dict:
    """``command`` (``[python, "-m", module, *args]``) as a child process: its wall and
    CPU time (``wait4``) and its own peak resident memory (``VmHWM``, which the child
    reads when the module returns: ``ru_maxrss`` of a child starts from its parent's
    high-water mark, the forked copy's)."""
    python, _, module, *rest = command
    with tempfile.TemporaryDirectory() as scratch:
        peak_file = Path(scratch) / "peak"
        out, err = Path(scratch) / "out", Path(scratch) / "err"
        with out.open("wb") as stdout, err.open("wb") as stderr:
            started = time.perf_counter()
            child = subprocess.Popen([python, "-m", "pisc_bench.bag_bench_cli", "--measure",
                                      str(peak_file), module, *rest],
                                     stdout=stdout, stderr=stderr)
            _, status, usage = os.wait4(child.pid, 0)
            wall = time.perf_counter() - started
        child.returncode = os.waitstatus_to_exitcode(status)
        peak = peak_file.read_text() if peak_file.exists() else "nan"
        return {"step": label, "rc": child.returncode, "wall_s": wall, "messages": messages,
                "rss_mb": float(peak) / 1024, "cpu_s": usage.ru_utime + usage.ru_stime,
                "stdout": out.read_text(errors="replace"),
                "stderr": err.read_text(errors="replace")}


def _measure(peak_file: str, module: str, args: list[str]) -> int:
    """Run ``module`` as ``python -m module args`` would, then write this process's
    peak resident memory (kB, ``VmHWM``) to ``peak_file``."""
    import runpy

    sys.argv = [module, *args]
    code: Any = 0
    try:
        runpy.run_module(module, run_name="__main__", alter_sys=True)
    except SystemExit as exc:
        code = exc.code
    finally:
        status = Path("/proc/self/status").read_text()
        peak = next(line.split()[1] for line in status.splitlines()
                    if line.startswith("VmHWM:"))
        Path(peak_file).write_text(peak)
    return code if isinstance(code, int) else (0 if code is None else 1)


def _load() -> str:
    return " ".join(f"{x:.2f}" for x in os.getloadavg())


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] == ["--measure"] and len(argv) >= 3:  # a step, in its own process
        return _measure(argv[1], argv[2], argv[3:])
    parser = argparse.ArgumentParser(prog="python -m pisc_bench.bag_bench_cli",
                                     description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=600.0,
                        help="length of the bag to make (default 600)")
    parser.add_argument("--from", dest="source", type=Path, default=DEFAULT_SOURCE,
                        help="bag whose messages make the stream (default bags/default-swingup)")
    parser.add_argument("--dir", type=Path, help="where to make the bags (default: a "
                        "temporary directory, removed unless --keep)")
    parser.add_argument("--keep", action="store_true", help="keep the bags")
    parser.add_argument("--only", nargs="+", choices=STEPS, default=list(STEPS),
                        help="run these steps only (analyse and replay need finish)")
    parser.add_argument("--seed", type=int, default=16)
    parser.add_argument("--json", type=Path, metavar="FILE",
                        help="also write the figures to FILE (for pisc_bench)")
    parser.add_argument("--finish-step", help=argparse.SUPPRESS)  # the child of 'finish'
    args = parser.parse_args(argv)
    if args.finish_step:
        return _finish(args.finish_step)
    if not (args.seconds > 0 and np.isfinite(args.seconds)):
        print(f"bag_bench: --seconds {args.seconds}: expected a positive number of seconds",
              file=sys.stderr)
        return 2
    if not (args.source / "metadata.yaml").exists():
        print(f"bag_bench: --from {args.source}: not a bag directory (no metadata.yaml)",
              file=sys.stderr)
        return 2
    root = args.dir or Path(tempfile.mkdtemp(prefix="pisc-bag-bench-"))
    root.mkdir(parents=True, exist_ok=True)
    print(f"bag_bench {datetime.datetime.now(datetime.UTC):%Y-%m-%d %H:%M} UTC, load "
          f"average {_load()}, {os.cpu_count()} CPUs")
    try:
        return _bench(args, root)
    finally:
        if args.dir is None and not args.keep:
            shutil.rmtree(root, ignore_errors=True)
        print(f"load average at the end {_load()}")


def _bench(args: argparse.Namespace, root: Path) -> int:
    stream = root / "stream"
    if stream.exists():
        shutil.rmtree(stream)
    started = time.perf_counter()
    messages = make_stream(stream, args.source, args.seconds, args.seed)
    size = (stream / "stream_0.mcap").stat().st_size
    print(f"stream: {messages} messages, {size / 1e6:.1f} MB, {args.seconds:g} s from "
          f"{args.source} (made in {time.perf_counter() - started:.1f} s)")
    python = sys.executable
    results = []
    finished = root / "finished"
    if "finish" in args.only:
        if finished.exists():
            shutil.rmtree(finished)
        shutil.copytree(stream, finished)
        os.replace(finished / "stream_0.mcap", finished / "finished_0.mcap")
        results.append(_run_measured("finish", [python, "-m", "pisc_bench.bag_bench_cli",
                                                "--finish-step", str(finished)], messages))
    if "repair" in args.only:
        cut = root / "cut"
        if cut.exists():
            shutil.rmtree(cut)
        cut.mkdir()
        with (stream / "stream_0.mcap").open("rb") as src, (cut / "cut_0.mcap").open("wb") as dst:
            shutil.copyfileobj(src, dst)
            dst.truncate(size - 5)  # the last record cut: a recorder killed while writing
        results.append(_run_measured("repair", [python, "-m", "pisc_bringup.bag_cli",
                                                "repair", str(cut)], messages - 1))
    if "analyse" in args.only:
        results.append(_run_measured("analyse", [python, "-m", "pisc_bringup.bag_cli",
                                                 "analyse", str(finished), "--out",
                                                 str(root / "analysis")], messages))
    if "replay" in args.only:
        results.append(_run_measured("replay", [python, "-m", "pisc_bringup.bag_cli",
                                                "replay", str(finished)], messages))
    print(f"{'step':<9}{'wall s':>8}{'CPU s':>8}{'messages/s':>12}{'peak RSS MB':>13}  exit")
    failed = False
    for r in results:
        rate = r["messages"] / r["wall_s"] if r["wall_s"] > 0 else float("inf")
        print(f"{r['step']:<9}{r['wall_s']:>8.2f}{r['cpu_s']:>8.2f}{rate:>12,.0f}"
              f"{r['rss_mb']:>13.0f}  {r['rc']}")
        ok = r["rc"] == 0 or (r["step"] == "replay" and r["rc"] == 1)  # 1: a mismatch
        if not ok:
            failed = True
            print(f"  {r['step']} failed:\n{r['stderr'][-2000:]}", file=sys.stderr)
    if "replay" in args.only and results and results[-1]["step"] == "replay":
        lines = results[-1]["stdout"].splitlines()
        print("replay: " + (lines[0] if lines else "(no report)")
              + (f"; {lines[-1]}" if len(lines) > 1 else ""))
    if args.keep or args.dir is not None:
        print(f"bags kept in {root}")
    figures = json.dumps({r["step"]: {k: round(v, 3) if isinstance(v, float) else v
                                      for k, v in r.items() if k not in ("stdout", "stderr")}
                          for r in results})
    print(figures)
    if args.json is not None:
        args.json.write_text(figures + "\n")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
