"""Where the chunks of a robustness evaluation run: in this process, on a local Dask
cluster embedded in the command, or on an existing Dask cluster.

:func:`chunk_runner` is a context manager that yields a ``map_chunks(fn, tasks)``
function for :func:`pisc_robust.robustness.evaluate`: it calls ``fn(*task)`` for every
task and returns the results in the order of ``tasks``. Every chunk is a pure function
of its arguments (its noise generator is seeded by the chunk's index), so the three
ways give the same numbers bit for bit.

- ``workers=0``: one chunk after another in this process, no Dask at all. The plant's
  compiled kernel spreads each chunk's rigs over the cores (numba threads); the
  controllers' compiled pass runs on them too.
- ``workers=N`` (N >= 1): a Dask ``LocalCluster`` of N worker processes with one thread
  each, started with the command and closed with it. Each worker's numba runs on one
  thread (``NUMBA_NUM_THREADS=1``), so N workers keep N cores busy without
  oversubscribing them, and the controllers' numpy work runs on every core too.
- ``scheduler=ADDRESS``: the chunks go to an existing cluster (``dask scheduler`` and
  ``dask worker`` started elsewhere, with PISC installed on every worker); nothing is
  started or stopped here. An address Dask cannot parse is refused before a client is
  made (:func:`check_scheduler`: a client made from one hung for a minute on its way
  out), and each worker whose numba would start more threads than the worker has
  (``NUMBA_NUM_THREADS`` not set to 1: such workers ran 6-8 times slower) is named in a
  warning.

The commands' default (:func:`default_workers`) was chosen by measurement on the
project's 2-core machine (``pisc_robustness default --seed 1``, docs/robustness.md,
"Scaling"): for 10,000 draws (10 chunks) a local cluster of two workers took 15.6-16.1 s
when no other job competed for the cores, against 19.8-20.9 s in this process (24-28 s
against 22-23 s while other jobs shared the cores); for 3000 draws 7.6-9.2 s against 6.5-6.8 s,
for 1000 draws 5.8-6.0 s against 2.4-2.5 s. The cluster's start-up (about 2.5 s, and the
first chunk of each worker loads the compiled kernel) pays off from about five chunks.

The commands let idle OpenMP threads sleep (``OMP_WAIT_POLICY=PASSIVE``, here and in the
local workers): with OpenMP's default active wait, spinning threads made a chunk of 1000
draws take 5 to 12 times longer whenever other processes shared the cores.

Why Dask and not Ray: Dask's wheels are pure Python and a few MB, a ``LocalCluster``
starts inside the command in seconds with nothing to install or run beforehand, and it
is what Optuna and numpy users already know; Ray's wheels are hundreds of MB and start
a runtime of services (GCS, raylet, dashboard) before the first task.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from typing import Any

__all__ = ["CLUSTER_FROM_CHUNKS", "check_scheduler", "chunk_runner", "core_count",
           "default_workers", "describe_runner", "worker_warnings", "workers_for"]

#: Chunks from which a command's default is a local cluster (one worker per core).
CLUSTER_FROM_CHUNKS = 5

#: Environment of every local worker process: one numba thread (and one BLAS thread) per
#: worker, which has one core, and OpenMP threads that sleep when idle. With OpenMP's
#: default active wait a worker's chunk of 1000 draws took 20-26 s of wall time and twice
#: that in CPU time (two threads spinning at every period's barrier) instead of 2.3 s.
WORKER_ENV = {"NUMBA_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "OMP_WAIT_POLICY": "PASSIVE",
              "OPENBLAS_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}

MapChunks = Callable[[Callable[..., Any], Sequence[tuple[Any, ...]]], list[Any]]
Progress = Callable[[int], None]


def core_count() -> int:
    """The cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


def default_workers(chunks: int) -> int:
    """``--workers`` when a command is given neither it nor ``--scheduler``: in this
    process below :data:`CLUSTER_FROM_CHUNKS` chunks or on one core, else a local cluster
    of one worker per core (at most one per chunk)."""
    cores = core_count()
    return 0 if chunks < CLUSTER_FROM_CHUNKS or cores < 2 else min(cores, chunks)


def workers_for(chunks: int, workers: int | None, scheduler: str | None) -> int | None:
    """The workers a command runs ``chunks`` chunks on: ``workers`` as given (``--workers``),
    else, without ``--scheduler``, :func:`default_workers`."""
    return default_workers(chunks) if workers is None and not scheduler else workers


def describe_runner(workers: int | None, scheduler: str | None) -> str:
    """In words, where the chunks run."""
    if scheduler:
        return f"Dask cluster at {scheduler}"
    if workers == 0:
        return "in this process (no Dask)"
    n = core_count() if workers is None else workers
    return f"local Dask cluster, {n} worker process{'es' if n != 1 else ''} x 1 thread"


def check_scheduler(address: str) -> None:
    """Refuse an address that is not a Dask scheduler's (``tcp://host:8786``) with a
    :class:`ValueError` saying why, before any client is made."""
    from distributed.comm.addressing import parse_address, parse_host_port

    try:
        scheme, location = parse_address(address)
        if scheme in ("tcp", "tls", "ws", "wss"):
            parse_host_port(location)
    except ValueError as exc:
        raise ValueError(f"{address}: not a Dask scheduler's address ({exc}); expected "
                         "e.g. tcp://host:8786") from None


def _worker_threads() -> dict[str, Any]:
    """On a worker: how many threads its numba would use, and OpenMP's wait policy."""
    import numba

    return {"numba": int(numba.config.NUMBA_NUM_THREADS),
            "omp_wait": os.environ.get("OMP_WAIT_POLICY", "")}


def worker_warnings(client: Any) -> list[str]:
    """A sentence for each worker of ``client``'s cluster whose numba would use more
    threads than the worker has (workers started without ``NUMBA_NUM_THREADS=1``)."""
    threads = {address: info.get("nthreads", 1)
               for address, info in client.scheduler_info()["workers"].items()}
    out = []
    for address, got in sorted(client.run(_worker_threads).items()):
        have = threads.get(address, 1)
        if got["numba"] > have:
            out.append(
                f"Dask worker {address}: numba would run {got['numba']} threads beside its "
                f"{have} (NUMBA_NUM_THREADS is not {have}"
                + ("" if got["omp_wait"].upper() == "PASSIVE" else
                   ", OMP_WAIT_POLICY not PASSIVE") + "); such workers ran 6-8 times "
                f"slower: start them with NUMBA_NUM_THREADS={have} OMP_WAIT_POLICY=PASSIVE "
                f"dask worker ... --nthreads {have}")
    return out


def _map_here(progress: Progress | None) -> MapChunks:
    def map_chunks(fn: Callable[..., Any], tasks: Sequence[tuple[Any, ...]]) -> list[Any]:
        out = []
        for task in tasks:
            out.append(fn(*task))
            if progress is not None:
                progress(1)
        return out

    return map_chunks


def _map_on(client: Any, progress: Progress | None) -> MapChunks:
    from distributed import as_completed

    def map_chunks(fn: Callable[..., Any], tasks: Sequence[tuple[Any, ...]]) -> list[Any]:
        # pure=False: no hashing of the arguments for keys; each task runs once
        futures = [client.submit(fn, *task, pure=False) for task in tasks]
        try:
            for _ in as_completed(futures, loop=client.loop):
                if progress is not None:
                    progress(1)
            return client.gather(futures)
        finally:
            client.cancel(futures)

    return map_chunks


def _warn(text: str) -> None:
    import sys

    print(f"warning: {text}", file=sys.stderr, flush=True)


@contextmanager
def chunk_runner(workers: int | None = None, scheduler: str | None = None,
                 progress: Progress | None = None,
                 warn: Callable[[str], None] | None = None) -> Iterator[MapChunks]:
    """A ``map_chunks(fn, tasks)`` that runs chunks as the module's docstring says.

    Parameters
    ----------
    workers
        0: in this process, without Dask; N >= 1: a local Dask cluster of N worker
        processes with one thread each; None: one worker per core.
    scheduler
        The address of an existing Dask scheduler (``tcp://host:8786``); excludes
        ``workers``.
    progress
        Called with 1 after each chunk finishes (in any order).
    warn
        Called with each of :func:`worker_warnings` of a scheduler's cluster (default:
        printed on standard error).

    Raises
    ------
    ValueError
        For a negative ``workers``, both ``workers`` and ``scheduler``, or an address
        that is not a scheduler's (:func:`check_scheduler`).
    OSError
        When the scheduler cannot be reached (Dask's own error).
    """
    if workers is not None and workers < 0:
        raise ValueError(f"workers = {workers}: 0 (in this process) or more")
    if scheduler and workers is not None:
        raise ValueError("a scheduler address and a number of local workers exclude "
                         "each other")
    if not scheduler and workers == 0:
        yield _map_here(progress)
        return
    from distributed import Client, LocalCluster

    if scheduler:
        check_scheduler(scheduler)
        with Client(scheduler, set_as_default=False) as client:
            for text in worker_warnings(client):
                (warn or _warn)(text)
            yield _map_on(client, progress)
        return
    n = core_count() if workers is None else workers
    with LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                      dashboard_address=None, env=dict(WORKER_ENV),
                      silence_logs=logging.ERROR) as cluster, \
            Client(cluster, set_as_default=False) as client:
        yield _map_on(client, progress)
