"""Benchmark of pisc_identify: rigs drawn from a distribution, an excitation recorded on
each, identified, and the estimates and their 95 % intervals compared with the truth.

    python -m pisc_bench.identify_bench_cli [--via driver|lockstep] [--draws 20] [--seed 1]
                                              [--duration S] [--set NAME=VALUE ...]
                                              [--truth NAME=VALUE ...] [--keep DIR]

``--via driver`` (default) records each run as on the rig: ``pisc_virtual_rig`` on a
pseudo-terminal with the drawn plant as its parameter file, ``pisc_graph --scene
excitation --driver PORT`` (both under SCHED_FIFO, as ``test/test_driver.py`` runs them),
in real time, on a ROS domain it claims (unless ROS_DOMAIN_ID is set); ``--via
lockstep`` simulates the same experiment in this process (the pure closed loop, the
graph's cores), with the distribution's command latency. Both run
the ``excitation`` scene's experiment (its ``experiment.*`` parameters and, unless
``--duration`` says otherwise, its length). The hidden plant of each draw: the motor's
R, L, J_m and b_m, the cart's Coulomb and viscous friction, the pivot's friction and the
sensors' measurement noise from the distribution (default ``thesis-rig``; through the
driver the virtual rig has read its sensors with that noise since 2026-12-03, and had
none before), the rig's masses and lengths the thesis's
(thesis Table 6.1: measured, and J_m cannot be told from the cart's mass otherwise).
b_m / r^2 acts as cart viscous friction, so the truth the cart viscous estimate is
compared with is b_c + (b_m - b_m,base) / r^2.

Prints, per draw, each parameter's truth, estimate, error and whether the 95 % interval
covers the truth, then the coverage per parameter, how many estimates are within the
tolerances (:data:`TOLERANCE`: R, J_m 5 %; friction 10 % or 0.005 whichever is larger;
L 20 % or reported not identifiable), and the identification's wall time for the recording. Each
draw's line gives its recording's sample-to-voltage latency (median, p99) as the bag has
it: a run that the machine did not keep in time identifies worse.
"""

from __future__ import annotations

import math
import os
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from pisc_robust.identify import Result, identify
from pisc_robust.identify_data import Recording, UNKNOWNS, parse_fit, recording_from_arrays
from pisc_robust.identify_report import load_base
from pisc_sim.configuration import config_path, load_run_config, params_file_text
from pisc_msgs_py.config import load_params_file

#: The parameters each draw hides (from the distribution), and the rest kept nominal.
DRAWN = ("motor.resistance_ohm", "motor.inductance_h", "motor.rotor_inertia_kgm2",
         "motor.viscous_friction_nms", "friction.cart_coulomb_n",
         "friction.cart_viscous_ns_per_m", "friction.pivot_viscous_nms")
#: The sensors' measurement noise, drawn too (the virtual rig reads its sensors with it)
NOISE = ("noise.x_std_m", "noise.theta_std_rad", "noise.current_std_a")
#: Drawn for lockstep runs only: through the driver the latency is the machine's own
LOCKSTEP_ALSO = ("actuator.command_delay_s",)
FIT = "R,L,J_m,cart_coulomb,cart_viscous,pivot_viscous,delay,current_offset"
#: What an estimate must come within of its truth to count as identified: relative, and
#: an absolute floor (the larger wins)
TOLERANCE = {"R": (0.05, 0.0), "J_m": (0.05, 0.0), "cart_coulomb": (0.10, 0.005),
             "cart_viscous": (0.10, 0.005), "L": (0.20, 0.0)}
RT_RIG, RT_GRAPH = "50", "40"
SCENE = "excitation"  # the experiment each draw records (its length unless --duration)
#: The parameters whose intervals' coverage the summary counts (the physical ones)
COVERAGE = ("R", "L", "J_m", "cart_coulomb", "cart_viscous", "pivot_viscous")


@dataclass
class Outcome:
    draw: int
    truth: dict[str, float]
    result: Result | None
    error: str = ""
    wall_s: float = 0.0
    checks: dict[str, tuple[float, float, float, float, bool, bool]] = field(
        default_factory=dict)  # key -> (truth, estimate, low, high, covered, within)
    not_identifiable: list[str] = field(default_factory=list)


def draw_truths(draws: int, seed: int, distribution: str = "thesis-rig",
                lockstep: bool = False, noise: bool = False) -> list[dict[str, float]]:
    """The hidden plants: ``DRAWN`` of each draw, with ``noise`` the sensors' noise
    (``NOISE``, and ``noise.seed`` = seed + draw) and for lockstep ``LOCKSTEP_ALSO``."""
    from pisc_robust.uncertainty import load_distribution

    config, _, _ = load_run_config("default")
    dist = load_distribution(distribution, config)
    sample = dist.draw(draws, seed)
    keep = DRAWN + (NOISE if noise else ()) + (LOCKSTEP_ALSO if lockstep else ())
    return [{**{k: float(v) for k, v in sample.one(k).items() if k in keep},
             **({"noise.seed": seed + k} if noise else {})}
            for k in range(draws)]


def expected(truth: dict[str, float], base: Any) -> dict[str, float]:
    """The values the estimates should find (cart viscous with b_m's share)."""
    r2 = base.motor.wheel_radius_m ** 2
    out = {u.key: truth[u.name] for u in UNKNOWNS if u.name in truth}
    if "cart_viscous" in out:
        out["cart_viscous"] += (truth.get("motor.viscous_friction_nms",
                                          base.motor.viscous_friction_nms)
                                - base.motor.viscous_friction_nms) / r2
    return out


def judge(outcome: Outcome, base: Any) -> None:
    want = expected(outcome.truth, base)
    res = outcome.result
    for e in res.estimates:
        key = e.unknown.key
        if key not in want:
            continue
        t = want[key]
        rel, floor = TOLERANCE.get(key, (math.inf, 0.0))
        within = abs(e.value - t) <= max(rel * abs(t), floor)
        outcome.checks[key] = (t, e.value, e.low, e.high, e.low <= t <= e.high, within)
    outcome.not_identifiable = [e.unknown.key for e in res.not_identifiable]


def scene_experiment() -> tuple[dict[str, Any], float]:
    """The ``excitation`` scene's experiment parameters (flat) and its length, s."""
    from pisc_sim.scene import load_scene

    scene = load_scene(SCENE)
    return ({k: v for k, v in scene.overrides.items() if k.startswith("experiment.")},
            scene.duration_s)


def record_lockstep(truth: dict[str, float], duration_s: float, overrides: dict[str, Any],
                    seed: int) -> Recording:
    from pisc_sim.closed_loop import simulate

    plant = {"models.friction": "coulomb", "noise.seed": seed, **truth}
    experiment, _ = scene_experiment()
    config, _, _ = load_run_config("default", {**experiment, **overrides},
                                   plant_overrides=plant)
    log = simulate(config, duration_s)
    return recording_from_arrays("lockstep", config.loop.period_s, log["x"], log["theta"],
                                 log["i"], log["u"], experiment="excitation")


def truth_file(truth: dict[str, float], path: Path) -> None:
    """The virtual rig's parameter file: the default configuration with the truth."""
    flat = load_params_file(config_path("default"))
    flat.update({"models.friction": "coulomb", **truth})
    path.write_text(params_file_text(flat))


def record_driver(truth: dict[str, float], duration_s: float, overrides: dict[str, Any],
                  bag: Path, env: dict[str, str] | None = None, attempts: int = 3) -> Path:
    """Run the excitation through the driver against a virtual rig with ``truth``; the bag.

    A run that the machine could not keep in time (the graph did not finish) is tried
    again, up to ``attempts`` times."""
    from pisc_plant.rig_process import RigProcess

    params = bag.parent / f"{bag.name}-truth.yaml"
    truth_file(truth, params)
    sets = [a for k, v in overrides.items() for a in ("--set", f"{k}={v}")]
    last = ""
    for attempt in range(attempts):
        target = bag if attempt == 0 else bag.parent / f"{bag.name}-{attempt}"
        rig = RigProcess(["--realtime", RT_RIG, "--params-file", str(params)], env=env)
        try:
            graph = subprocess.run(
                [sys.executable, "-m", "pisc_bringup.graph_cli", "--scene", SCENE,
                 "--driver", rig.device, "--duration", str(duration_s), "--bag", str(target),
                 "--realtime", RT_GRAPH, *sets],
                env=env, capture_output=True, text=True, timeout=120 + 3 * duration_s)
        finally:
            rig.stop()
        if graph.returncode in (0, 1) and (target / "metadata.yaml").exists():
            return target
        last = (graph.stdout + graph.stderr)[-2000:]
    raise RuntimeError(f"the excitation run through the driver failed {attempts} times:\n{last}")


def identify_one(recording: Recording, fit: str = FIT) -> tuple[Result, float]:
    base, _, _ = load_base("default", [recording])
    started = time.perf_counter()
    result = identify([recording], parse_fit(fit), base)
    return result, time.perf_counter() - started


def format_outcome(o: Outcome) -> str:
    if o.result is None:
        return f"draw {o.draw}: FAILED: {o.error}"
    lines = [f"draw {o.draw}: identified in {o.wall_s:.1f} s ({o.result.cycles} samples); "
             f"residual {' / '.join(f'{v:.3f}' for v in o.result.residual_rms)} steps"
             + _timing(o.result)]
    for key, (t, v, lo, hi, covered, within) in o.checks.items():
        tol = TOLERANCE.get(key)
        lines.append(f"  {key:<14} truth {t:<12.5g} estimate {v:<12.5g} "
                     f"error {100 * (v - t) / t if t else math.nan:+7.2f} %  "
                     f"[{lo:.5g} .. {hi:.5g}] {'covers' if covered else 'MISSES'}"
                     + ("" if tol is None else f"  {'within' if within else 'OUTSIDE'} "
                        "tolerance"))
    for key in o.not_identifiable:
        lines.append(f"  {key:<14} reported not identifiable")
    return "\n".join(lines)


def _timing(result: Result) -> str:
    """How well the recording kept time: its sample-to-voltage latency as the bag has it
    (a run on a loaded machine answers late, and the fit's timing suffers)."""
    latency = np.concatenate([r.latency_s for r in result.recordings]) * 1e3
    if not latency.size or not np.any(latency):
        return ""  # (lockstep: none recorded)
    return (f"; latency median {np.median(latency):.2f} ms, p99 "
            f"{np.percentile(latency, 99):.2f} ms")


def summary(outcomes: list[Outcome]) -> str:
    done = [o for o in outcomes if o.result is not None]
    lines = [f"{len(done)} of {len(outcomes)} draws identified"]
    keys = sorted({k for o in done for k in o.checks})
    covered_all = 0
    total = 0
    for key in keys:
        rows = [o.checks[key] for o in done if key in o.checks]
        cov = sum(r[4] for r in rows)
        if key in COVERAGE:
            covered_all += cov
            total += len(rows)
        within = sum(r[5] for r in rows)
        errors = [abs(r[1] - r[0]) / abs(r[0]) for r in rows if r[0]]
        tol = f", within tolerance {within} of {len(rows)}" if key in TOLERANCE else ""
        lines.append(f"  {key:<14} interval covers the truth {cov} of {len(rows)} "
                     f"({100 * cov / len(rows):.0f} %){tol}; median |error| "
                     f"{100 * float(np.median(errors)) if errors else math.nan:.2f} %, largest "
                     f"{100 * max(errors) if errors else math.nan:.2f} %")
    for key in ("L",):
        n = sum(key in o.not_identifiable for o in done)
        if n:
            lines.append(f"  {key:<14} reported not identifiable in {n} of {len(done)}")
    if total:
        lines.append(f"intervals of {', '.join(COVERAGE)}: {covered_all} of {total} cover "
                     f"the truth ({100 * covered_all / total:.1f} %; delay, a nuisance that "
                     "takes up L / R and the unrecorded part of the latency, is not counted)")
    walls = [o.wall_s for o in done]
    if walls:
        lines.append(f"identification wall time: median {np.median(walls):.1f} s, largest "
                     f"{max(walls):.1f} s (per recording of the run's length; "
                     f"{os.cpu_count()} cores)")
    return "\n".join(lines)
