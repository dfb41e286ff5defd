"""The chunks of an evaluation give the same numbers, bit for bit, wherever they run."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from pisc_robust import robustness
from pisc_robust.cluster import WORKER_ENV, chunk_runner, core_count, default_workers
from pisc_sim.configuration import load_graph_config
from pisc_robust.robustness import evaluate, prepare
from pisc_runs.verdict import Criteria
from pisc_robust.uncertainty import load_distribution

# caught by 3 s held from 6 s (fast), by 5 s held from 6 s (caught), in a 6.5 s run
SHORT = Criteria(run_s=6.5, catch_by_s=5.0, hold_from_s=6.0)


@pytest.fixture(scope="module")
def setup():
    config = load_graph_config("default")[0]
    distribution = load_distribution("thesis-rig", config)
    config, plant = prepare(config, distribution)
    return config, plant, distribution.draw(160, seed=5)


def assert_same_bits(a, b) -> None:
    for field in dataclasses.fields(a):
        x, y = getattr(a, field.name), getattr(b, field.name)
        assert x.dtype == y.dtype and x.shape == y.shape, field.name
        assert x.tobytes() == y.tobytes(), field.name


def test_a_local_cluster_of_two_workers_gives_the_in_process_outcomes_bit_for_bit(
        setup, monkeypatch):
    config, plant, draws = setup
    monkeypatch.setattr(robustness, "CHUNK_DRAWS", 80)  # two chunks, one per worker
    with chunk_runner(workers=0) as here:
        expected = evaluate(config, plant, draws, SHORT, seed=5, map_chunks=here)
    seen = []
    with chunk_runner(workers=2, progress=seen.append) as on_cluster:
        got = evaluate(config, plant, draws, SHORT, seed=5, map_chunks=on_cluster)
    assert seen == [1, 1]
    assert len(got) == 160
    assert_same_bits(expected, got)
    # and the default, sequential runner is the in-process one
    assert_same_bits(expected, evaluate(config, plant, draws, SHORT, seed=5))


def test_an_existing_scheduler_runs_the_chunks_it_is_given(setup, monkeypatch):
    from distributed import LocalCluster

    config, plant, draws = setup
    draws = draws[:40]
    monkeypatch.setattr(robustness, "CHUNK_DRAWS", 20)
    expected = evaluate(config, plant, draws, SHORT, seed=2)
    with LocalCluster(n_workers=1, processes=False, dashboard_address=None) as cluster, \
            chunk_runner(scheduler=cluster.scheduler_address) as on_cluster:
        got = evaluate(config, plant, draws, SHORT, seed=2, map_chunks=on_cluster)
    assert_same_bits(expected, got)


def test_chunks_with_another_seed_draw_other_noise(setup, monkeypatch):
    config, plant, draws = setup
    draws = draws[:20]
    a = evaluate(config, plant, draws, SHORT, seed=1)
    b = evaluate(config, plant, draws, SHORT, seed=2)
    assert not np.array_equal(a.hold_setpoint_rms_a, b.hold_setpoint_rms_a)


def test_the_default_runs_few_chunks_here_and_many_on_a_worker_per_core():
    assert default_workers(1) == default_workers(4) == 0  # measured: docs/robustness.md
    many = default_workers(10)
    assert many == (min(core_count(), 10) if core_count() > 1 else 0)
    assert WORKER_ENV["NUMBA_NUM_THREADS"] == "1"
    assert WORKER_ENV["OMP_WAIT_POLICY"] == "PASSIVE"


@pytest.mark.parametrize("workers, scheduler", [(-1, None), (2, "tcp://localhost:1")])
def test_a_bad_runner_is_refused(workers, scheduler):
    with pytest.raises(ValueError), chunk_runner(workers, scheduler):
        pass


def test_a_scheduler_address_that_is_none_is_refused_before_a_client_is_made(monkeypatch):
    import distributed

    from pisc_robust.cluster import check_scheduler

    def no_client(*args, **kwargs):  # a client made from it hung for a minute on exit
        raise AssertionError("a Dask client was made")

    monkeypatch.setattr(distributed, "Client", no_client)
    for address in ("notanaddress", "tcp://host", "tcp://host:port"):
        with pytest.raises(ValueError, match=f"^{address}: not a Dask scheduler's address"):
            with chunk_runner(scheduler=address):
                pass
    check_scheduler("tcp://127.0.0.1:8786")  # a well-formed one is not judged further


@pytest.mark.skipif(core_count() < 2, reason="a one-core machine: numba defaults to one "
                    "thread there, so no worker can oversubscribe its core")
def test_workers_whose_numba_would_oversubscribe_them_are_named(setup, monkeypatch):
    """A cluster's workers started without NUMBA_NUM_THREADS=1 (each would run one numba
    thread per core beside its one Dask thread: 6-8 times slower): each is named in a
    warning; started as the local cluster starts them, none is."""
    from distributed import LocalCluster

    config, plant, draws = setup
    monkeypatch.setattr(robustness, "CHUNK_DRAWS", 20)
    monkeypatch.delenv("NUMBA_NUM_THREADS", raising=False)
    for env, expected in (({}, 1), (dict(WORKER_ENV), 0)):
        said: list[str] = []
        with LocalCluster(n_workers=1, threads_per_worker=1, processes=True,
                          dashboard_address=None, env=env) as cluster, \
                chunk_runner(scheduler=cluster.scheduler_address, warn=said.append) as run:
            evaluate(config, plant, draws[:20], SHORT, seed=2, map_chunks=run)
        assert len(said) == expected, said
        if expected:
            assert said[0].startswith("Dask worker tcp://") and (
                f"numba would run {core_count()} threads beside its 1 (NUMBA_NUM_THREADS is "
                "not 1") in said[0]
            assert "start them with NUMBA_NUM_THREADS=1 OMP_WAIT_POLICY=PASSIVE" in said[0]
