"""Linear analysis: equilibria, Jacobians, poles, controllability, gain design.

What seeds 000 (sections 5-6) and 001 (section 4) did by hand: the equilibrium points
of ``z' = f(z, u)``, the Taylor linearisation ``A = df/dz``, ``B = df/du`` at any
equilibrium and input (seed 000 (16)-(23)), the controllability matrix with its rank
and determinant (seed 001 (20), thesis (3.45)), the open-loop characteristic
polynomial, and state feedback ``u = -K z`` by Bass-Gura's formula (seed 001
(22)-(25)) and by Ackermann's, cross-checked against python-control; LQR as an
alternative design.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import control
import numpy as np
import sympy as sp
from numpy.typing import ArrayLike

from pisc_analysis.symbolic import MechanicalSystem

__all__ = [
    "Controllability",
    "Equilibria",
    "ackermann_gain",
    "bass_gura_gain",
    "characteristic_coefficients",
    "closed_loop_poles",
    "controllability",
    "equilibria",
    "jacobians",
    "linearise",
    "lqr_gain",
    "place_gain",
]


@dataclass(frozen=True)
class Equilibria:
    """Equilibria of a mechanical system for a constant input.

    ``solutions`` are the values of the coordinates that gravity and the input fix
    (one dict per solution, principal values); ``free`` are the coordinates that any
    value leaves in equilibrium (the cart position). Velocities are zero.
    """

    solutions: list[dict[sp.Symbol, sp.Expr]]
    free: tuple[sp.Symbol, ...]


def equilibria(system: MechanicalSystem, values: Mapping[sp.Symbol, float],
               inputs: Mapping[sp.Symbol, float] | None = None) -> Equilibria:
    """Points with ``z' = 0`` for constant inputs (zero unless given); seed 000 (15),
    thesis (3.13)-(3.15).

    All velocities are zero there, so the accelerations must vanish together at
    zero velocity; solved jointly with sympy for the coordinates they contain.
    Solving each equation on its own, as seed 000 did with ``F = 0.1``, finds angles
    that zero one acceleration but not the other; jointly, a constant nonzero cart
    force leaves the cart-pole no equilibrium at all.
    """
    subs: dict[sp.Symbol, float | int] = {dq: 0 for dq in system.dq}
    subs.update({u: 0 for u in system.inputs})
    subs.update(values)
    if inputs:
        subs.update(inputs)
    acc = [sp.simplify(sp.sympify(a).subs(subs)) for a in system.accelerations()]
    acc = [a for a in acc if a != 0]
    unknowns = [q for q in system.q if any(a.has(q) for a in acc)]
    free = tuple(q for q in system.q if q not in unknowns)
    if not acc:
        return Equilibria([{}], free)
    if not unknowns:
        return Equilibria([], free)
    numerators = [sp.numer(sp.together(a)) for a in acc]
    solutions = sp.solve(numerators, unknowns, dict=True)
    real = [s for s in solutions if all(v.is_real is not False for v in s.values())]
    return Equilibria(real, free)


def jacobians(system: MechanicalSystem) -> tuple[sp.Matrix, sp.Matrix]:
    """Symbolic ``A(z, u) = df/dz`` and ``B(z, u) = df/du`` (seed 000 (20)-(21))."""
    f = sp.Matrix(system.state_space())
    a = f.jacobian(system.state())
    b = f.jacobian(system.inputs) if system.inputs else sp.zeros(len(f), 0)
    return a, b


def linearise(
    system: MechanicalSystem,
    values: Mapping[sp.Symbol, float],
    state: Sequence[float] | None = None,
    inputs: Sequence[float] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Numeric A and B at a state and input (default: the origin, zero input).

    Notes
    -----
    Seed 000 (18)-(23): the first-order Taylor expansion about ``(z_eq, F_eq)``. For
    the cart-pole about upright this is thesis (3.41)-(3.42).
    """
    a_sym, b_sym = jacobians(system)
    z = system.state()
    state = [0.0] * len(z) if state is None else list(state)
    inputs = [0.0] * len(system.inputs) if inputs is None else list(inputs)
    if len(state) != len(z) or len(inputs) != len(system.inputs):
        raise ValueError(f"linearise: expected {len(z)} states and {len(system.inputs)} "
                         f"inputs, got {len(state)} and {len(inputs)}")
    subs = dict(values)
    subs.update(zip(z, state, strict=True))
    subs.update(zip(system.inputs, inputs, strict=True))
    a = np.array(a_sym.subs(subs).evalf(), dtype=float)
    b = np.array(b_sym.subs(subs).evalf(), dtype=float).reshape(len(z), len(system.inputs))
    return a, b


@dataclass(frozen=True)
class Controllability:
    matrix: np.ndarray  # [B AB A^2B ...]
    rank: int
    determinant: float  # of the matrix when square (one input), else nan


def controllability(a: ArrayLike, b: ArrayLike) -> Controllability:
    """Controllability matrix, its rank and determinant (seed 001 (20), thesis (3.45))."""
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float).reshape(a.shape[0], -1)
    n = a.shape[0]
    blocks = [b]
    for _ in range(n - 1):
        blocks.append(a @ blocks[-1])
    matrix = np.hstack(blocks)
    det = float(np.linalg.det(matrix)) if matrix.shape[0] == matrix.shape[1] else float("nan")
    return Controllability(matrix, int(np.linalg.matrix_rank(matrix)), det)


def characteristic_coefficients(a: ArrayLike) -> np.ndarray:
    """``[a_1, ..., a_n]`` of ``det(sI - A) = s^n + a_1 s^(n-1) + ... + a_n`` (seed 001 (21))."""
    return np.real(np.poly(np.asarray(a, dtype=float)))[1:]


def _desired_coefficients(poles: ArrayLike) -> np.ndarray:
    poles = np.asarray(poles, dtype=complex)
    return np.real(np.poly(poles))[1:]


def _single_input(a: ArrayLike, b: ArrayLike, poles: ArrayLike) -> tuple[np.ndarray, np.ndarray,
                                                                         np.ndarray]:
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float).reshape(-1, 1)
    poles = np.asarray(poles, dtype=complex)
    n = a.shape[0]
    if a.shape != (n, n) or b.shape[0] != n:
        raise ValueError(f"A must be square and B have one column of {n} rows, "
                         f"got A {a.shape} and B {b.shape}")
    if poles.shape != (n,):
        raise ValueError(f"expected {n} poles, got {poles.size}")
    if not np.allclose(np.sort_complex(poles), np.sort_complex(poles.conj())):
        raise ValueError(f"poles {poles}: complex poles must come in conjugate pairs")
    c = controllability(a, b)
    if c.rank < n:
        raise ValueError(f"(A, B) is not controllable: the controllability matrix has rank "
                         f"{c.rank} < {n}")
    return a, b, poles


def bass_gura_gain(a: ArrayLike, b: ArrayLike, poles: ArrayLike) -> np.ndarray:
    """K with ``eig(A - B K) = poles`` by the formula of seed 001 (22)-(25).

    Notes
    -----
    ``K = [alpha_n - a_n, ..., alpha_1 - a_1] T^-1``, ``T = Mc W``, with ``a_i`` the
    open-loop characteristic coefficients (21), ``alpha_i`` the desired ones (22),
    ``Mc`` the controllability matrix and ``W`` the upper-left triangular Hankel
    matrix of ``a_(n-1), ..., a_1, 1`` (25). Single input only.
    """
    a, b, poles = _single_input(a, b, poles)
    n = a.shape[0]
    coeffs = characteristic_coefficients(a)
    alpha = _desired_coefficients(poles)
    hankel = np.concatenate([coeffs[: n - 1][::-1], [1.0], np.zeros(n - 1)])
    w = np.array([[hankel[i + j] for j in range(n)] for i in range(n)])
    t = controllability(a, b).matrix @ w
    diff = (alpha - coeffs)[::-1]
    return np.linalg.solve(t.T, diff)


def ackermann_gain(a: ArrayLike, b: ArrayLike, poles: ArrayLike) -> np.ndarray:
    """K by Ackermann's formula, ``K = [0 ... 0 1] Mc^-1 phi(A)``.

    Notes
    -----
    ``phi(s) = s^n + alpha_1 s^(n-1) + ... + alpha_n`` is the desired characteristic
    polynomial (seed 001 (22)); equivalent to (23)-(25) and computed independently.
    """
    a, b, poles = _single_input(a, b, poles)
    n = a.shape[0]
    alpha = np.concatenate([[1.0], _desired_coefficients(poles)])
    phi = np.zeros_like(a)
    for coefficient in alpha:
        phi = phi @ a + coefficient * np.eye(n)
    last = np.zeros(n)
    last[-1] = 1.0
    return np.linalg.solve(controllability(a, b).matrix.T, last) @ phi


def place_gain(a: ArrayLike, b: ArrayLike, poles: ArrayLike) -> np.ndarray:
    """K by python-control: ``place`` for distinct poles, ``acker`` for repeated ones."""
    a, b, poles = _single_input(a, b, poles)
    if len(np.unique(np.round(poles, 12))) < len(poles):
        k = control.acker(a, b, poles)
    else:
        k = control.place(a, b, poles)
    return np.asarray(k, dtype=float).reshape(-1)


def lqr_gain(a: ArrayLike, b: ArrayLike, q: ArrayLike, r: ArrayLike) -> np.ndarray:
    """K minimising ``integral(z' Q z + u' R u)`` (python-control ``lqr``)."""
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float).reshape(a.shape[0], -1)
    k, _, _ = control.lqr(a, b, np.atleast_2d(q), np.atleast_2d(r))
    return np.asarray(k, dtype=float).reshape(-1) if b.shape[1] == 1 else np.asarray(k)


def closed_loop_poles(a: ArrayLike, b: ArrayLike, k: ArrayLike) -> np.ndarray:
    """Eigenvalues of ``A - B K``, sorted by real part then imaginary part."""
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float).reshape(a.shape[0], -1)
    k = np.asarray(k, dtype=float).reshape(b.shape[1], a.shape[0])
    return np.sort_complex(np.linalg.eigvals(a - b @ k))
