"""Equations of motion from a Lagrangian, by the general procedures of seed 001.

Seed 001 (Camusso and Cardona) wrote four Maple procedures for any mechanical system
with n degrees of freedom, given only its Lagrangian and the non-conservative forces:
``dyn2`` forms Lagrange's equations (4), ``dyn3`` the mass, stiffness and damping
matrices by differentiating the internal forces with respect to the accelerations,
coordinates and velocities ((7)-(10)), ``dyn4`` solves for the accelerations. This
module does the same with sympy, and writes the result as a first-order state-space
model ``z' = f(z, u)`` with ``z = [q1, q1', q2, q2', ...]`` (for the cart-pole
``[x, x_dot, theta, theta_dot]``, SPEC section 1).

Time derivatives are taken by the chain rule, ``d/dt e = sum_j de/dq_j q_j' +
de/dq_j' q_j''``, which is what Maple's substitution of ``q_j = u_j(t)`` amounts to.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import sympy as sp

__all__ = [
    "CartPoleSymbols",
    "MechanicalSystem",
    "cart_pole",
    "cart_pole_hand_accelerations",
    "numeric_state_space",
]


@dataclass(frozen=True)
class MechanicalSystem:
    """A mechanical system given by its Lagrangian, as seed 001's ``dyn1`` defines it.

    Parameters
    ----------
    q, dq, ddq
        Generalised coordinates, velocities and accelerations (plain symbols).
    lagrangian
        L = K - V in terms of ``q`` and ``dq`` and parameters.
    forces
        Generalised non-conservative forces Q_k, one per coordinate (the right-hand
        side of Lagrange's equation (4) of seed 001); may contain inputs, feedback
        gains and the state.
    inputs
        Input symbols (e.g. the cart force f); the state space is ``f(z, u)``.
    """

    q: tuple[sp.Symbol, ...]
    dq: tuple[sp.Symbol, ...]
    ddq: tuple[sp.Symbol, ...]
    lagrangian: sp.Expr
    forces: tuple[sp.Expr, ...]
    inputs: tuple[sp.Symbol, ...] = ()

    def __post_init__(self) -> None:
        n = len(self.q)
        if not (len(self.dq) == len(self.ddq) == len(self.forces) == n) or n == 0:
            raise ValueError(
                f"MechanicalSystem: q, dq, ddq and forces must have the same nonzero length, "
                f"got {len(self.q)}, {len(self.dq)}, {len(self.ddq)}, {len(self.forces)}")

    @property
    def n(self) -> int:
        """Number of degrees of freedom."""
        return len(self.q)

    def time_derivative(self, expr: sp.Expr) -> sp.Expr:
        """d/dt of an expression in q and dq, by the chain rule."""
        return sum(
            (sp.diff(expr, qj) * dqj + sp.diff(expr, dqj) * ddqj
             for qj, dqj, ddqj in zip(self.q, self.dq, self.ddq, strict=True)),
            sp.Integer(0))

    def residuals(self) -> list[sp.Expr]:
        """Lagrange's equations (4) as ``r_k = d/dt dL/dq_k' - dL/dq_k - Q_k = 0``.

        Notes
        -----
        Seed 001's ``dyn2`` and its vector of inertial forces ``finer`` (10) in ``dyn3``.
        """
        out = []
        for qk, dqk, qf in zip(self.q, self.dq, self.forces, strict=True):
            momentum = sp.diff(self.lagrangian, dqk)
            out.append(sp.expand(self.time_derivative(momentum) - sp.diff(self.lagrangian, qk)
                                 - qf))
        return out

    def mass_matrix(self) -> sp.Matrix:
        """M[i, j] = d r_i / d q_j'' (seed 001 ``dyn3``, (9))."""
        r = self.residuals()
        return sp.Matrix(self.n, self.n, lambda i, j: sp.simplify(sp.diff(r[i], self.ddq[j])))

    def stiffness_matrix(self) -> sp.Matrix:
        """K[i, j] = d r_i / d q_j (seed 001 ``dyn3``, (7))."""
        r = self.residuals()
        return sp.Matrix(self.n, self.n, lambda i, j: sp.simplify(sp.diff(r[i], self.q[j])))

    def damping_matrix(self) -> sp.Matrix:
        """C[i, j] = d r_i / d q_j' (seed 001 ``dyn3``, (8))."""
        r = self.residuals()
        return sp.Matrix(self.n, self.n, lambda i, j: sp.simplify(sp.diff(r[i], self.dq[j])))

    def accelerations(self) -> list[sp.Expr]:
        """q'' solving r(q, q', q'') = 0 (seed 001 ``dyn4``).

        Notes
        -----
        The residual is affine in q'': ``r = M q'' + h(q, q')``, so
        ``q'' = M^-1 (M q'' - r)``, which no longer contains q''. Seed 001's ``dyn4``
        prints ``M^-1 (r - M q'')``, the opposite sign; it is corrected here.
        """
        return list(_solved_accelerations(self))

    def state(self) -> tuple[sp.Symbol, ...]:
        """State vector ``z = [q1, q1', q2, q2', ...]``."""
        return tuple(s for pair in zip(self.q, self.dq, strict=True) for s in pair)

    def state_space(self) -> list[sp.Expr]:
        """``f(z, u)`` of ``z' = f(z, u)``, z as in :meth:`state`."""
        acc = self.accelerations()
        return [e for dqk, ak in zip(self.dq, acc, strict=True) for e in (dqk, ak)]


@functools.lru_cache(maxsize=32)
def _solved_accelerations(system: MechanicalSystem) -> tuple[sp.Expr, ...]:
    """:meth:`MechanicalSystem.accelerations`, kept for each system (equal systems, such as
    two calls of :func:`cart_pole`, share one entry): sympy's ``simplify`` of the solved
    accelerations takes seconds, and the report asks for them ten times (the symbols and
    expressions are immutable, so a kept result is the same as a new one)."""
    r = sp.Matrix(system.residuals())
    mass = r.jacobian(system.ddq)  # unsimplified, so that M q'' cancels term by term
    h = sp.expand(r - mass * sp.Matrix(system.ddq))
    if any(h_i.has(*system.ddq) for h_i in h):
        raise ValueError("the equations of motion are not affine in the accelerations")
    solved = sp.simplify(mass).LUsolve(-h)
    return tuple(sp.simplify(e) for e in solved)


@dataclass(frozen=True)
class CartPoleSymbols:
    """Symbols of the cart-pole (SPEC section 2 names)."""

    M: sp.Symbol
    m: sp.Symbol
    l: sp.Symbol  # noqa: E741 - the thesis's symbol
    I: sp.Symbol  # noqa: E741 - the thesis's symbol
    g: sp.Symbol
    f: sp.Symbol


def _cart_pole_symbols() -> CartPoleSymbols:
    M, m, l, g = sp.symbols("M m l g", positive=True)
    I_ = sp.Symbol("I", nonnegative=True)
    f = sp.Symbol("f", real=True)
    return CartPoleSymbols(M, m, l, I_, g, f)


def cart_pole(with_inertia: bool = True,
              feedback: Sequence[sp.Expr] | None = None) -> tuple[MechanicalSystem,
                                                                   CartPoleSymbols]:
    """The cart-pole's Lagrangian (thesis (2.12)-(2.14); seed 001 (1)-(3)).

    ``K = 1/2 M x'^2 + 1/2 m (x_G'^2 + y_G'^2) + 1/2 I theta'^2``, ``V = m g l cos(theta)``
    with ``x_G = x + l sin(theta)``, ``y_G = l cos(theta)`` (theta = 0 upright, SPEC
    section 1). The cart force f is the generalised force on x; ``feedback``, if
    given, replaces f by an expression in the state (seed 001's ``Fnc``).
    ``with_inertia=False`` is the point mass of seeds 000 and 001 (I = 0).
    """
    s = _cart_pole_symbols()
    x, theta = sp.symbols("x theta", real=True)
    x_dot, theta_dot = sp.symbols("x_dot theta_dot", real=True)
    x_ddot, theta_ddot = sp.symbols("x_ddot theta_ddot", real=True)
    xg_dot = x_dot + s.l * sp.cos(theta) * theta_dot
    yg_dot = -s.l * sp.sin(theta) * theta_dot
    inertia = s.I if with_inertia else sp.Integer(0)
    kinetic = (sp.Rational(1, 2) * s.M * x_dot**2
               + sp.Rational(1, 2) * s.m * (xg_dot**2 + yg_dot**2)
               + sp.Rational(1, 2) * inertia * theta_dot**2)
    potential = s.m * s.g * s.l * sp.cos(theta)
    force = s.f if feedback is None else sp.sympify(feedback[0])
    inputs = (s.f,) if feedback is None else ()
    system = MechanicalSystem(
        q=(x, theta), dq=(x_dot, theta_dot), ddq=(x_ddot, theta_ddot),
        lagrangian=kinetic - potential, forces=(force, sp.Integer(0)), inputs=inputs)
    return system, s


def cart_pole_hand_accelerations(s: CartPoleSymbols, theta: sp.Symbol, theta_dot: sp.Symbol,
                                 with_inertia: bool = True) -> tuple[sp.Expr, sp.Expr]:
    """The hand-derived model of SPEC section 2, thesis (3.1)-(3.6), as sympy expressions.

    ``a1 = m^2 l^2 / (m l^2 + I)``, ``a2 = M + m``, ``den = a2 - a1 cos^2``;
    ``x'' = (-a1 g sin cos + m l theta'^2 sin + f) / den``,
    ``theta'' = (a1 a2 g sin - a1 m l theta'^2 sin cos - a1 f cos) / (m l den)``.
    """
    inertia = s.I if with_inertia else sp.Integer(0)
    a1 = s.m**2 * s.l**2 / (s.m * s.l**2 + inertia)
    a2 = s.M + s.m
    sn, cs = sp.sin(theta), sp.cos(theta)
    den = a2 - a1 * cs**2
    x_ddot = (-a1 * s.g * sn * cs + s.m * s.l * theta_dot**2 * sn + s.f) / den
    theta_ddot = (a1 * a2 * s.g * sn - a1 * s.m * s.l * theta_dot**2 * sn * cs
                  - a1 * s.f * cs) / (s.m * s.l * den)
    return x_ddot, theta_ddot


def numeric_state_space(
    system: MechanicalSystem, values: Mapping[sp.Symbol, float]
) -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
    """``f(z, u)`` as a numpy function, parameters substituted from ``values``.

    The returned function takes ``z`` with the state on the last axis (any leading
    shape) and ``u`` with the inputs on the last axis, and returns ``z'``.
    """
    f = [sp.sympify(e).subs(values) for e in system.state_space()]
    z = system.state()
    free = set().union(*(e.free_symbols for e in f)) - set(z) - set(system.inputs)
    if free:
        names = ", ".join(sorted(str(s) for s in free))
        raise ValueError(f"numeric_state_space: no value given for {names}")
    fn = sp.lambdify([*z, *system.inputs], f, modules="numpy")
    nz = len(z)

    def rhs(state: np.ndarray, inputs: np.ndarray) -> np.ndarray:
        state = np.asarray(state, dtype=float)
        inputs = np.asarray(inputs, dtype=float)
        args = [state[..., i] for i in range(nz)]
        args += [inputs[..., i] for i in range(len(system.inputs))]
        out = fn(*args)
        return np.stack(np.broadcast_arrays(*[np.asarray(o, dtype=float) for o in out]),
                        axis=-1)

    return rhs
