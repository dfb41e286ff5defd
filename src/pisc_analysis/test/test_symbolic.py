"""Equations of motion from the Lagrangian against the hand-derived model (SPEC section 2)."""

import numpy as np
import pytest
import sympy as sp

from pisc_analysis.symbolic import (
    MechanicalSystem,
    cart_pole,
    cart_pole_hand_accelerations,
    numeric_state_space,
)
from pisc_model.dynamics import accelerations
from pisc_model.params import RigParams


@pytest.fixture(scope="module", params=[True, False], ids=["with_I", "point_mass"])
def derived(request):
    system, s = cart_pole(with_inertia=request.param)
    return request.param, system, s, system.accelerations()


def test_symbolic_model_equals_hand_model_of_spec_section_2(derived):
    with_inertia, system, s, acc = derived
    hand = cart_pole_hand_accelerations(s, system.q[1], system.dq[1], with_inertia)
    assert sp.simplify(acc[0] - hand[0]) == 0
    assert sp.simplify(acc[1] - hand[1]) == 0
    # and the two models really are different expressions when I matters
    assert acc[1].has(s.I) == with_inertia


def test_symbolic_model_matches_the_plant_at_random_states(derived):
    with_inertia, system, s, _ = derived
    rig = RigParams(pendulum_inertia_kgm2=2.631524e-5 if with_inertia else 0.0)
    values = {s.M: rig.cart_mass_kg, s.m: rig.pendulum_mass_kg, s.l: rig.pendulum_com_m,
              s.I: rig.pendulum_inertia_kgm2, s.g: rig.gravity_mps2}
    rhs = numeric_state_space(system, values)
    rng = np.random.default_rng(6)
    z = rng.uniform([-0.2, -2.0, -np.pi, -20.0], [0.2, 2.0, np.pi, 20.0], size=(1000, 4))
    f = rng.uniform(-5.0, 5.0, size=(1000, 1))
    out = rhs(z, f)
    x_ddot, theta_ddot = accelerations(rig, z[:, 2], z[:, 3], f[:, 0])
    np.testing.assert_array_equal(out[:, 0], z[:, 1])
    np.testing.assert_array_equal(out[:, 2], z[:, 3])
    np.testing.assert_allclose(out[:, 1], x_ddot, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(out[:, 3], theta_ddot, rtol=1e-12, atol=1e-10)


def test_matrices_by_differentiation_are_seed_001s_7_to_9():
    k1, k2, k3, k4 = sp.symbols("k1:5", real=True)
    system, s = cart_pole(with_inertia=False)
    x, theta = system.q
    x_dot, theta_dot = system.dq
    fnc = k1 * theta + k2 * theta_dot + k3 * x + k4 * x_dot
    closed, s = cart_pole(with_inertia=False, feedback=[fnc])
    mass = closed.mass_matrix()
    stiffness = closed.stiffness_matrix()
    damping = closed.damping_matrix()
    ml = s.m * s.l
    x_ddot, theta_ddot = closed.ddq
    assert sp.simplify(mass - sp.Matrix([[s.M + s.m, ml * sp.cos(theta)],
                                         [ml * sp.cos(theta), ml * s.l]])) == sp.zeros(2, 2)
    # (8): C = [[-k4, -2 m l sin(q2) q2' - k2], [0, 0]]
    assert sp.simplify(damping - sp.Matrix([[-k4, -2 * ml * sp.sin(theta) * theta_dot - k2],
                                            [0, 0]])) == sp.zeros(2, 2)
    # (7) as it should read (the seed's typesetting lost the dots):
    # K = [[-k3, -m l cos(q2) q2'^2 - m l sin(q2) q2'' - k1],
    #      [0, -m l sin(q2) q1'' - m g l cos(q2)]]
    expected = sp.Matrix([
        [-k3, -ml * sp.cos(theta) * theta_dot**2 - ml * sp.sin(theta) * theta_ddot - k1],
        [0, -ml * sp.sin(theta) * x_ddot - s.m * s.g * s.l * sp.cos(theta)]])
    assert sp.simplify(stiffness - expected) == sp.zeros(2, 2)


def test_a_one_degree_of_freedom_pendulum_gives_seed_000s_equation_8():
    theta, theta_dot, theta_ddot = sp.symbols("theta theta_dot theta_ddot", real=True)
    m, g, l = sp.symbols("m g l", positive=True)
    # seed 000 measures theta from hanging: x = l sin, y = -l cos
    lagrangian = sp.Rational(1, 2) * m * l**2 * theta_dot**2 + m * g * l * sp.cos(theta)
    system = MechanicalSystem((theta,), (theta_dot,), (theta_ddot,), lagrangian, (0,))
    assert system.state_space() == [theta_dot, -g * sp.sin(theta) / l]


def test_refusals_name_what_is_wrong():
    t = sp.Symbol("t")
    with pytest.raises(ValueError, match="same nonzero length"):
        MechanicalSystem((t,), (), (), t, (0,))
    system, s = cart_pole()
    with pytest.raises(ValueError, match="no value given for I, M"):
        numeric_state_space(system, {s.m: 1.0, s.l: 1.0, s.g: 9.81})


def test_equal_systems_share_their_solved_accelerations():
    """The solved accelerations are kept per system: a second cart-pole built anew gets the
    same expressions without solving again; a different system is solved for itself."""
    from pisc_analysis import symbolic

    first = cart_pole()[0].accelerations()
    before = symbolic._solved_accelerations.cache_info()
    again = cart_pole()[0].accelerations()
    after = symbolic._solved_accelerations.cache_info()
    assert again == first and after.hits == before.hits + 1 and after.misses == before.misses
    point_mass = cart_pole(with_inertia=False)[0].accelerations()
    assert point_mass != first
