"""Supervisor: switching rule (4.1) with hysteresis, start-up target, safety faults."""

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
    assert switching_criterion(0.015, 2 * math.pi + 0.3, 2.0) == pytest.approx(0.09 + 0.06)
    assert switching_criterion(0.015, -0.3, -2.0) == pytest.approx(0.15)


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
