"""Force to current (4.2) and the sampled PI loop (3.47) exactly as the C++ program."""

import numpy as np
import pytest

from pisc_control.current_loop import (
    CurrentLoopParams,
    CurrentLoopState,
    current_loop_cycle,
    current_loop_update,
    current_setpoint,
)
from pisc_model.params import MotorParams

P = CurrentLoopParams()
TS = 0.005


def cpp_reference(forces, currents):
    """Appendix A.2, transcribed line by line (float arithmetic in double)."""
    VM, IM, radioR, km, kpi, kii = 11.47, 0.9, 0.032, 0.0637, 2.9, 1800.0
    intei = 0.0
    out = []
    for f, curr in zip(forces, currents, strict=True):
        i_d = f * (radioR / km)
        i_d = min(max(i_d, -IM), IM)
        ei = i_d - curr
        propi = kpi * ei
        if intei < VM and intei > -VM:
            intei = intei + kii * TS * ei
        else:
            if intei >= VM:
                intei = 0.95 * VM
            if intei <= -VM:
                intei = -0.95 * VM
        uf = propi + intei
        uf = min(max(uf, -VM), VM)
        out.append((i_d, uf))
    return out


def test_matches_the_cpp_program_including_anti_windup():
    rng = np.random.default_rng(5)
    forces = np.concatenate([np.full(50, 3.0), rng.uniform(-3, 3, 200), np.full(50, -3.0)])
    currents = np.concatenate([np.zeros(50), rng.uniform(-1, 1, 200), np.zeros(50)])
    state = CurrentLoopState()
    motor = MotorParams()
    reset_seen = False
    for (f, i), (i_d_ref, u_ref) in zip(zip(forces, currents, strict=True),
                                        cpp_reference(forces, currents), strict=True):
        i_d = current_setpoint(motor, P, f)
        before = float(state.integral_v)
        state, u = current_loop_update(P, TS, state, i_d, i)
        reset_seen |= before >= 11.47 and float(state.integral_v) == 0.95 * 11.47
        assert float(i_d) == pytest.approx(i_d_ref, rel=1e-12, abs=1e-15)
        assert float(u) == pytest.approx(u_ref, rel=1e-12, abs=1e-12)
    assert reset_seen  # the test exercised the reset branch


def test_setpoint_is_f_r_over_km_saturated():
    motor = MotorParams()
    assert current_setpoint(motor, P, 1.0) == pytest.approx(0.032 / 0.0637)
    assert current_setpoint(motor, P, 10.0) == 0.9
    assert current_setpoint(motor, P, -10.0) == -0.9


# -- one cycle as the graph runs it (the node, the pure closed loop, the batch) -----------

def test_a_cycle_without_fault_is_the_setpoint_then_the_pi_loop_bit_for_bit():
    motor = MotorParams()
    state = CurrentLoopState()
    ref_state = CurrentLoopState()
    for force, current in ((1.2, 0.0), (-0.4, 0.31), (7.0, -0.2), (0.0, 0.05)):
        state, i_d, u = current_loop_cycle(motor, P, TS, state, force, current)
        ref_i_d = float(current_setpoint(motor, P, force))
        ref_state, ref_u = current_loop_update(P, TS, ref_state, ref_i_d, current)
        assert float(i_d) == ref_i_d
        assert float(u) == float(ref_u)
        assert float(state.integral_v) == float(ref_state.integral_v)
    assert float(i_d) == 0.0 and float(state.integral_v) != 0.0  # the integral is carried


def test_a_faulted_cycle_answers_zero_and_clears_the_integral():
    motor = MotorParams()
    state, _, _ = current_loop_cycle(motor, P, TS, CurrentLoopState(), 1.5, 0.0)
    assert float(state.integral_v) == pytest.approx(1800.0 * TS * 1.5 * 0.032 / 0.0637)
    state, i_d, u = current_loop_cycle(motor, P, TS, state, 1.5, 0.0, fault=True)
    assert (float(i_d), float(u), float(state.integral_v)) == (0.0, 0.0, 0.0)
    # when the fault clears, the loop starts as a fresh one: no integral left to kick
    after, i_d, u = current_loop_cycle(motor, P, TS, state, 1.5, 0.0)
    fresh, i_d0, u0 = current_loop_cycle(motor, P, TS, CurrentLoopState(), 1.5, 0.0)
    assert (float(i_d), float(u), float(after.integral_v)) == (
        float(i_d0), float(u0), float(fresh.integral_v))


def test_a_cycle_of_many_rigs_zeroes_only_the_faulted_ones():
    motor = MotorParams()
    state = CurrentLoopState(np.array([0.5, -0.5, 2.0]))
    force = np.array([1.0, -2.0, 0.3])
    current = np.array([0.1, 0.0, -0.1])
    fault = np.array([False, True, False])
    new, i_d, u = current_loop_cycle(motor, P, TS, state, force, current, fault)
    ref_i_d = current_setpoint(motor, P, force)
    ref_state, ref_u = current_loop_update(P, TS, state, ref_i_d, current)
    np.testing.assert_array_equal(i_d, [ref_i_d[0], 0.0, ref_i_d[2]])
    np.testing.assert_array_equal(u, [ref_u[0], 0.0, ref_u[2]])
    np.testing.assert_array_equal(new.integral_v,
                                  [ref_state.integral_v[0], 0.0, ref_state.integral_v[2]])
