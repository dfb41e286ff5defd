"""Supervisor: switching rule (4.1) with hysteresis and an energy band, start-up target,
the catch's settling reference, safety faults."""

import math

import numpy as np
import pytest

from pisc_control.supervisor import (
    FAULT_NOT_FINITE,
    FAULT_OUT_OF_RANGE,
    SafetyParams,
    StartupParams,
    Supervisor,
    SupervisorConfig,
    SupervisorState,
    SwitchingParams,
    switching_criterion,
)
from pisc_control.swing_up import SwingUpParams, swing_up_force
from pisc_msgs_py.config import ConfigError
from pisc_msgs_py.types import Mode

CATCH, SWING, FAULT = Mode.CATCH.code, Mode.SWING_UP.code, Mode.FAULT.code


def test_criterion_measures_from_the_nearest_upright():
    from pisc_control.floatmath import wrap

    assert switching_criterion(0.015, wrap(2 * math.pi + 0.3), 2.0) == pytest.approx(0.15)
    assert switching_criterion(0.015, -0.3, -2.0) == pytest.approx(0.09 + 0.06)
    # hanging: pi from upright whichever way round
    assert switching_criterion(0.0, wrap(-math.pi), 0.0) == pytest.approx(math.pi ** 2)


def test_enter_catch_below_delta_s_and_leave_at_delta_exit():
    sup = Supervisor(SupervisorConfig(switching=SwitchingParams(k_va=0.0, delta_s=0.04,
                                                                delta_exit=0.09)))
    s = SupervisorState()
    s, _, mode = sup.update(s, 0.0, 0.0, 0.25, 0.0)  # 0.0625 > 0.04
    assert mode == SWING
    s, _, mode = sup.update(s, 0.0, 0.0, 0.19, 0.0)  # 0.0361 < 0.04
    assert mode == CATCH
    s, _, mode = sup.update(s, 0.0, 0.0, 0.29, 0.0)  # 0.0841 < 0.09: still catching
    assert mode == CATCH
    s, _, mode = sup.update(s, 0.0, 0.0, 0.31, 0.0)  # 0.0961 >= 0.09
    assert mode == SWING


def test_delta_exit_below_delta_s_is_refused():
    with pytest.raises(ConfigError, match="switching.delta_exit"):
        SwitchingParams(delta_s=0.6, delta_exit=0.5)


def test_thesis_gains_refused_if_3_29_breaks():
    with pytest.raises(ConfigError, match=r"\(3.29\)"):
        Supervisor(SupervisorConfig(swing_up=SwingUpParams(k_e=20.0)))


@pytest.mark.parametrize("x0,expected_target", [(0.0, -0.05), (0.1, 0.05), (-0.06, -0.01)])
def test_startup_target_points_to_the_middle_of_the_safe_range(x0, expected_target):
    cfg = SupervisorConfig(startup=StartupParams(distance_m=0.05))
    sup = Supervisor(cfg)
    s, force, _ = sup.update(SupervisorState(), x0, 0.0, math.pi, 0.0)
    assert float(s.startup_target_m) == pytest.approx(expected_target)
    assert force == pytest.approx(swing_up_force(cfg.rig, cfg.swing_up, x0, 0.0, math.pi, 0.0,
                                                 expected_target))
    assert force != 0.0


def test_without_startup_a_resting_rig_at_the_target_gets_no_force():
    _, force, mode = Supervisor(SupervisorConfig()).update(SupervisorState(), 0.0, 0.0,
                                                           math.pi, 0.0)
    assert int(mode) == SWING
    assert abs(float(force)) < 1e-15  # sin(pi) = 1.2e-16 in floating point


def test_leaving_the_safe_range_faults_with_zero_force_and_latches():
    sup = Supervisor(SupervisorConfig(safety=SafetyParams(x_min_m=-0.1, x_max_m=0.1)))
    s, _, mode = sup.update(SupervisorState(), 0.05, 0.0, 0.1, 0.0)
    assert mode == CATCH
    s, force, mode = sup.update(s, 0.11, 1.0, 0.1, 0.0)
    assert (float(force), int(mode), int(s.fault)) == (0.0, FAULT, FAULT_OUT_OF_RANGE)
    s, force, mode = sup.update(s, 0.0, 0.0, 0.0, 0.0)  # back in range: still faulted
    assert (float(force), int(mode)) == (0.0, FAULT)
    assert "outside the safe range" in sup.fault_reason(int(s.fault), 0.11)


def test_non_finite_state_faults_and_never_yields_a_non_finite_force():
    sup = Supervisor(SupervisorConfig())
    s, force, mode = sup.update(SupervisorState(), 0.0, float("nan"), math.pi, 0.0)
    assert (float(force), int(mode), int(s.fault)) == (0.0, FAULT, FAULT_NOT_FINITE)


def test_batch_of_rigs_in_one_call():
    sup = Supervisor(SupervisorConfig())
    x = np.array([0.0, 0.0, 0.3])
    theta = np.array([math.pi, 0.1, 0.0])
    s, force, mode = sup.update(SupervisorState(), x, np.zeros(3), theta, np.zeros(3))
    assert list(mode) == [SWING, CATCH, FAULT]
    assert force[2] == 0.0


def test_the_catch_reference_settles_from_where_the_catch_began():
    """settle_rate 0.05 m/s at Ts = 5 ms: a catch that begins at x = -0.05 m balances about
    -0.05 + 0.00025 k after k more samples, then about x* = 0."""
    from pisc_control.catch import CatchParams, catch_force

    cfg = SupervisorConfig(catch=CatchParams(settle_rate_mps=0.05))
    sup = Supervisor(cfg)
    s = SupervisorState()
    for k in range(250):
        s, force, mode = sup.update(s, -0.05, 0.0, 0.01, 0.0)
        expected_ref = min(-0.05 + 0.00025 * (k + 1), 0.0)
        assert int(mode) == CATCH
        assert float(s.catch_reference_m) == pytest.approx(expected_ref, abs=1e-12)
        assert float(force) == pytest.approx(
            catch_force(*sup.gain, -0.05, 0.0, 0.01, 0.0, expected_ref), rel=1e-12)
    # without the rate, the thesis's law: x* at once
    plain = Supervisor(SupervisorConfig())
    _, force, _ = plain.update(SupervisorState(), -0.05, 0.0, 0.01, 0.0)
    assert float(force) == pytest.approx(catch_force(*plain.gain, -0.05, 0.0, 0.01, 0.0, 0.0))


def test_the_energy_band_catches_only_a_pendulum_that_can_coast_up():
    """Both states lie inside (4.1) (theta = 0.3 rad, delta_s 0.6); at rest 0.3 rad from
    upright the pendulum's energy is m g l (cos 0.3 - 1) = -0.40 mJ, moving at 3 rad/s
    towards upright it is +0.07 mJ. A 0.2 mJ band catches the second only; once
    catching, only (4.1)'s exit threshold lets go."""
    from pisc_control.swing_up import rig_pendulum_energy
    from pisc_model.params import RigParams

    rig = RigParams()
    assert float(rig_pendulum_energy(rig, 0.3, 0.0)) == pytest.approx(-4.0e-4, rel=0.01)
    assert abs(float(rig_pendulum_energy(rig, 0.3, -3.0))) < 2e-4
    sup = Supervisor(SupervisorConfig(switching=SwitchingParams(energy_band_j=2e-4)))
    _, _, mode = sup.update(SupervisorState(), np.zeros(2), np.zeros(2), np.array([0.3, 0.3]),
                            np.array([0.0, -3.0]))
    assert list(mode) == [SWING, CATCH]
    catching = SupervisorState(np.array([CATCH]), np.array([0]), np.array([0.0]),
                               np.array([True]))
    _, _, mode = sup.update(catching, 0.0, 0.0, 0.3, 0.0)
    assert list(mode) == [CATCH]


def _governed(**catch):
    from pisc_control.catch import CatchParams as Catch

    # the default configuration's catch poles
    poles = (-14.0443, -4.8126, -4.0131, -3.5227)
    return Supervisor(SupervisorConfig(
        swing_up=SwingUpParams(law="energy_pump", guard_accel_mps2=2.0),
        catch=Catch(governor=True, poles=poles, **catch)))


def test_governor_interval_holds_its_prediction():
    """Every reference inside the governor's interval keeps the linear prediction inside
    the track less the margin and the set-point within its bound; just outside it, some
    row breaks one of them."""
    from pisc_control.catch import governor_interval

    sup = _governed()
    rows = sup.governor_rows
    state = (0.05, 0.05, 0.03, -0.1)  # x, x_dot, theta from upright, theta_dot
    lo, hi = governor_interval(sup.constants[2], sup.rows, *state)
    assert lo < hi
    c = sup.config

    def worst(r: float) -> tuple[float, float, float]:
        w = np.array([state[0] - r, *state[1:]])
        x = r + rows[:, :4] @ w
        i = rows[:, 4:] @ w
        return x.min(), x.max(), np.abs(i).max()

    low, high = c.safety.x_min_m + 0.02, c.safety.x_max_m - 0.02
    for r in np.linspace(lo, hi, 7):
        x_min, x_max, i_max = worst(r)
        assert x_min >= low - 1e-12 and x_max <= high + 1e-12 and i_max <= 0.8 + 1e-12
    for r in (lo - 1e-3, hi + 1e-3):
        x_min, x_max, i_max = worst(r)
        assert x_min < low or x_max > high or i_max > 0.8


def test_governor_refuses_a_catch_that_would_leave_the_track():
    """The same pendulum, coasting into the catch region: caught with the cart in the
    middle of the track, not with the cart near the end and running towards it (the
    current's bound set out of the way: the track refuses it)."""
    from pisc_control.supervisor import OneRigSupervisor

    theta, theta_dot = 0.03, -0.1
    middle = OneRigSupervisor(_governed(governor_current_a=5.0))
    _, code = middle.step(0.0, 0.0, theta, theta_dot)
    assert code == Mode.CATCH.code
    end = OneRigSupervisor(_governed(governor_current_a=5.0))
    _, code = end.step(0.10, 0.4, theta, theta_dot)
    assert code == Mode.SWING_UP.code


def test_catch_guard_needs_the_pump_guard():
    from pisc_control.catch import CatchParams as Catch

    with pytest.raises(ConfigError, match="catch.guard"):
        Supervisor(SupervisorConfig(catch=Catch(guard=True)))
