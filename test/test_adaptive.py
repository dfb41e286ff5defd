"""The default controller on the rigs it must serve, in the pure closed loop (which a
lockstep run of the graph reproduces bit for bit: test_graph): its online estimates of
the pendulum converge by the catch, the nominal rig is caught from every start, and a rig
that cannot be swung up is kept inside the track."""

from __future__ import annotations

import numpy as np
import pytest

from pisc_robust.robustness import load_benchmark
from pisc_runs.verdict import Criteria
from pisc_plant.plant import Plant
from pisc_plant.sampled import SampledPlant
from pisc_plant.command import plant_command
from pisc_sim.closed_loop import Controllers, simulate_batch
from pisc_sim.configuration import load_run_config
from pisc_msgs_py.types import Mode

CRITERIA = Criteria()


def _truth(plant) -> tuple[float, float]:
    """omega_0^2 = m g l / J and beta = b / J of a plant's pendulum."""
    rig = plant.rig
    inertia = rig.pendulum_inertia_kgm2 + rig.ml * rig.pendulum_com_m
    pivot = plant.friction.pivot_viscous_nms if plant.models.friction != "none" else 0.0
    return rig.mgl / inertia, pivot / inertia


def _estimates_at_the_catch(config) -> tuple[tuple[float, float], float]:
    """Run the controllers on the configuration's plant until the first catch; the
    supervisor's estimates (omega_0^2, beta) then, and the time."""
    plant = Plant(config.simulated_plant)
    i0 = config.initial
    sampled = SampledPlant(plant, plant.initial_state(i0.x_m, i0.x_dot_mps, i0.theta_rad,
                                                      i0.theta_dot_radps))
    controllers = Controllers(config)
    for k in range(int(round(8.0 / config.loop.period_s))):
        sample = sampled.sample()
        out = controllers.step(sample.position_m, sample.angle_rad, sample.current_a)
        if out.mode is Mode.CATCH:
            return controllers._supervisor.estimates, k * config.loop.period_s
        sampled.command(plant_command(plant.config, setpoint_a=out.i_d, voltage_v=out.voltage))
        sampled.advance()
    raise AssertionError("not caught within 8 s")


def _drawn(index: int) -> dict[str, float]:
    """Draw ``index`` of thesis-rig's 300 draws of seed 1, as --plant-set values."""
    _, distribution, draws, _ = load_benchmark("default", [], "thesis-rig", 300, 1)
    return {**distribution.plant, **draws.one(index)}


@pytest.mark.parametrize("draw", [None, 1, 2, 3])
def test_the_estimates_converge_by_the_catch(draw):
    """omega_0^2 within 5 % of the plant's; the pivot's loss b / J within 0.05 1/s (5 % of
    its span over thesis-rig, 0 .. 0.95 1/s: its true value may be 0), on the nominal rig
    and on three drawn rigs with the sensors' noise, the latency and friction."""
    plant_overrides = {} if draw is None else _drawn(draw)
    config, _, _ = load_run_config("default", plant_overrides=plant_overrides)
    (w2, beta), at = _estimates_at_the_catch(config)
    true_w2, true_beta = _truth(config.simulated_plant)
    assert at <= 6.0
    assert w2 == pytest.approx(true_w2, rel=0.05), (w2, true_w2, at)
    assert beta == pytest.approx(true_beta, abs=0.05), (beta, true_beta, at)


def test_the_nominal_rig_from_41_starts():
    """From rest, hanging, x0 = -0.10 .. +0.10 m: caught by 3.0 s, held from 6 s to 12 s,
    the hold's set-point RMS at most 0.05 A, never outside the safe range."""
    config, _, _ = load_run_config("default")
    x0 = np.linspace(-0.1, 0.1, 41)
    out = simulate_batch(config, x0, CRITERIA.run_s, CRITERIA.fast_hold_from_s,
                         hold_box=(CRITERIA.theta_rad, CRITERIA.x_m))
    safety = config.supervisor.safety
    assert not out.faulted.any()
    assert out.x_min_m.min() >= safety.x_min_m and out.x_max_m.max() <= safety.x_max_m
    late = x0[out.caught_at_s > CRITERIA.fast_by_s]
    assert late.size == 0, f"caught after 3 s from x0 = {late}"
    assert np.all(out.unheld_at_s < CRITERIA.fast_hold_from_s)
    assert np.all(out.hold_setpoint_rms_a <= 0.05), out.hold_setpoint_rms_a.max()
