"""Stability tests: Krasovskii's, Routh's, and the sampled PI current loop.

* Krasovskii's test (seed 001 section 3): the equilibrium of ``z' = f(z)`` is
  asymptotically stable if ``F = A(z) + A(z)^T`` is negative definite near it,
  ``A = df/dz``. As seed 001 states it (P = I) the test can never pass for a
  mechanical system written as ``[q, q']``: ``f_1 = q_1'`` makes ``F[0, 0] = 0``.
  The generalised form (Slotine and Li, seed 001's reference [5], "generalised
  Krasovskii theorem") asks ``P A(z) + A(z)^T P < 0`` for some P > 0; with P from
  the Lyapunov equation of the linearisation it passes in a neighbourhood whose size
  :func:`krasovskii_radius` estimates.
* Routh's table of the continuous PI current loop (3.51), Table 3.1 of the thesis.
* The PI loop as it runs: sampled every Ts, the voltage held for a period, the current
  measured through the sensor's RC filter. Its poles in z decide stability; unlike
  the continuous loop it is not stable for every positive gain (SPEC section 3).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np
import scipy.linalg
import sympy as sp
from numpy.typing import ArrayLike

from pisc_analysis.symbolic import MechanicalSystem
from pisc_control.current_loop import CurrentLoopParams
from pisc_model.params import MotorParams

__all__ = [
    "KrasovskiiResult",
    "closed_loop_jacobian",
    "SampledPiCheck",
    "krasovskii",
    "krasovskii_radius",
    "lyapunov_matrix",
    "pi_characteristic_polynomial",
    "quasi_static_pi_poles",
    "routh_table",
    "sampled_pi_check",
    "sampled_pi_poles",
    "sampled_pi_resistance_limit",
]


# -- Krasovskii ------------------------------------------------------------------------


@dataclass(frozen=True)
class KrasovskiiResult:
    """Largest eigenvalue of ``P A(z) + A(z)^T P`` over the states tried, and where."""

    max_eigenvalue: float
    worst_state: np.ndarray
    negative_definite: bool


def lyapunov_matrix(a_closed: ArrayLike, q: ArrayLike | None = None) -> np.ndarray:
    """P > 0 solving ``A^T P + P A = -Q`` (Q = I by default) for a Hurwitz A."""
    a = np.asarray(a_closed, dtype=float)
    q = np.eye(a.shape[0]) if q is None else np.asarray(q, dtype=float)
    if np.max(np.linalg.eigvals(a).real) >= 0.0:
        raise ValueError("lyapunov_matrix: the closed loop is not Hurwitz (an eigenvalue has "
                         "a nonnegative real part)")
    return scipy.linalg.solve_continuous_lyapunov(a.T, -q)


def closed_loop_jacobian(
    system: MechanicalSystem, values: dict[sp.Symbol, float], gain: ArrayLike
) -> Callable[[np.ndarray], np.ndarray]:
    """``A(z) = df/dz`` of the closed loop ``z' = f(z, -K z)``, as a batch function.

    Differentiated symbolically (seed 001 (13)-(14)), then evaluated with numpy for
    states of shape (N, n), returning (N, n, n). Single-input systems.
    """
    z = system.state()
    k = np.asarray(gain, dtype=float).reshape(-1)
    if len(system.inputs) != 1 or len(k) != len(z):
        raise ValueError(f"closed_loop_jacobian: need one input and {len(z)} gains, got "
                         f"{len(system.inputs)} inputs and {len(k)} gains")
    law = -sum((float(ki) * zi for ki, zi in zip(k, z, strict=True)), sp.Integer(0))
    f = sp.Matrix(system.state_space()).subs(values).subs(system.inputs[0], law)
    jac = f.jacobian(z)
    fn = sp.lambdify(z, list(jac), modules="numpy")  # a flat list: entries may be constants
    n = len(z)

    def jacobian(states: np.ndarray) -> np.ndarray:
        states = np.atleast_2d(np.asarray(states, dtype=float))
        out = np.empty((states.shape[0], n, n))
        cols = [states[:, i] for i in range(n)]
        raw = fn(*cols)
        for index, entry in enumerate(raw):
            out[:, index // n, index % n] = np.broadcast_to(np.asarray(entry, dtype=float),
                                                            states.shape[0])
        return out

    return jacobian


def krasovskii(
    jacobian: Callable[[np.ndarray], np.ndarray],
    states: ArrayLike,
    p: ArrayLike | None = None,
) -> KrasovskiiResult:
    """Krasovskii's test at the given states (seed 001 section 3).

    Parameters
    ----------
    jacobian
        ``A(z)`` for states ``z`` of shape (N, n), returning (N, n, n).
    states
        The states to test, shape (N, n).
    p
        The weighting P (identity, seed 001's form, if omitted).
    """
    z = np.atleast_2d(np.asarray(states, dtype=float))
    a = jacobian(z)
    p = np.eye(z.shape[1]) if p is None else np.asarray(p, dtype=float)
    pa = p @ a
    f = pa + np.swapaxes(pa, -1, -2)
    top = np.linalg.eigvalsh(f)[:, -1]
    worst = int(np.argmax(top))
    return KrasovskiiResult(float(top[worst]), z[worst], bool(np.all(top < 0.0)))


def krasovskii_radius(
    jacobian: Callable[[np.ndarray], np.ndarray],
    p: ArrayLike,
    scale: Sequence[float],
    samples: int = 4000,
    seed: int = 0,
    max_radius: float = 4.0,
    tolerance: float = 1e-3,
) -> float:
    """Largest r such that ``P A + A^T P < 0`` at every sampled z with ``|z / scale| <= r``.

    States are drawn uniformly in the unit ball (fixed seed), scaled per component by
    ``scale`` and by r; r is found by bisection. A sampled estimate, not a proof.
    """
    rng = np.random.default_rng(seed)
    n = len(scale)
    directions = rng.normal(size=(samples, n))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    radii = rng.uniform(size=(samples, 1)) ** (1.0 / n)
    unit = directions * radii * np.asarray(scale, dtype=float)

    def ok(r: float) -> bool:
        return krasovskii(jacobian, unit * r, p).negative_definite

    if not krasovskii(jacobian, np.zeros((1, n)), p).negative_definite:
        return 0.0
    lo, hi = 0.0, max_radius
    if ok(hi):
        return hi
    while hi - lo > tolerance:
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if ok(mid) else (lo, mid)
    return lo


# -- Routh ----------------------------------------------------------------------------


def routh_table(coefficients: ArrayLike) -> tuple[np.ndarray, int]:
    """Routh's table of ``c_n s^n + ... + c_0`` (highest power first) and its sign changes.

    The number of sign changes in the first column is the number of roots in the
    right half-plane. A zero in the first column is replaced by a small epsilon (the
    classical device); a zero row (symmetric roots) raises ValueError.
    """
    c = np.asarray(coefficients, dtype=float)
    n = len(c)
    if n < 2:
        raise ValueError("routh_table: need a polynomial of degree >= 1")
    width = (n + 1) // 2
    table = np.zeros((n, width))
    table[0, : len(c[0::2])] = c[0::2]
    table[1, : len(c[1::2])] = c[1::2]
    eps = 1e-12 * max(1.0, float(np.max(np.abs(c))))
    for row in range(2, n):
        if np.all(table[row - 1] == 0.0):
            raise ValueError("routh_table: a row of zeros (roots symmetric about the origin)")
        pivot = table[row - 1, 0] if table[row - 1, 0] != 0.0 else eps
        for col in range(width - 1):
            table[row, col] = (pivot * table[row - 2, col + 1]
                               - table[row - 2, 0] * table[row - 1, col + 1]) / pivot
    first = table[:, 0].copy()
    first[first == 0.0] = eps
    changes = int(np.sum(np.sign(first[:-1]) != np.sign(first[1:])))
    return table, changes


def pi_characteristic_polynomial(motor: MotorParams, loop: CurrentLoopParams,
                                 inertia_kgm2: float | None = None) -> np.ndarray:
    """``[c_3, c_2, c_1, c_0]`` of the denominator of (3.51), thesis (3.52)-(3.55).

    ``L J s^3 + (J (R + k_pi) + b L) s^2 + (b (R + k_pi) + k_e k_m + k_ii J) s + k_ii b``
    with J the shaft's inertia: the rotor's J_m by default, as in the thesis.
    """
    j = motor.rotor_inertia_kgm2 if inertia_kgm2 is None else inertia_kgm2
    b = motor.viscous_friction_nms
    r, ell = motor.resistance_ohm, motor.inductance_h
    ke, km = motor.back_emf_v_s_per_rad, motor.torque_constant_nm_per_a
    return np.array([ell * j, j * (r + loop.k_pi) + b * ell,
                     b * (r + loop.k_pi) + ke * km + loop.k_ii * j, loop.k_ii * b])


# -- the sampled PI loop ---------------------------------------------------------------


def quasi_static_pi_poles(resistance_ohm: float, k_pi: float, k_ii: float,
                          period_s: float) -> np.ndarray:
    """Roots of ``R z^2 + (k_pi + k_ii Ts - R) z - k_pi`` (SPEC section 3).

    The sampled PI loop (3.47) as the C++ program runs it, with an armature so fast
    that the current is ``u / R`` within the period (L / R << Ts) and the measured
    current lagging the voltage by one sample.
    """
    return np.roots([resistance_ohm, k_pi + k_ii * period_s - resistance_ohm, -k_pi])


def _continuous_plant(motor: MotorParams, sensor_filter_hz: float | None,
                      load_inertia_kgm2: float | None) -> tuple[np.ndarray, np.ndarray,
                                                                np.ndarray]:
    """Armature (2.81), optional shaft (2.82) with back-EMF, optional RC sensor filter."""
    r, ell = motor.resistance_ohm, motor.inductance_h
    ke, km = motor.back_emf_v_s_per_rad, motor.torque_constant_nm_per_a
    names = ["i"] + (["omega"] if load_inertia_kgm2 is not None else []) + (
        ["v"] if sensor_filter_hz is not None else [])
    n = len(names)
    a = np.zeros((n, n))
    b = np.zeros((n, 1))
    c = np.zeros((1, n))
    a[0, 0] = -r / ell
    b[0, 0] = 1.0 / ell
    if load_inertia_kgm2 is not None:
        w = names.index("omega")
        a[0, w] = -ke / ell
        a[w, 0] = km / load_inertia_kgm2
        a[w, w] = -motor.viscous_friction_nms / load_inertia_kgm2
    if sensor_filter_hz is not None:
        v = names.index("v")
        rate = 2.0 * math.pi * sensor_filter_hz
        a[v, 0] = rate
        a[v, v] = -rate
        c[0, v] = 1.0
    else:
        c[0, 0] = 1.0
    return a, b, c


def sampled_pi_poles(
    motor: MotorParams,
    loop: CurrentLoopParams,
    period_s: float,
    *,
    sensor_filter_hz: float | None = None,
    load_inertia_kgm2: float | None = None,
) -> np.ndarray:
    """Poles in z of the PI current loop sampled at ``period_s``, from the ZOH model.

    Parameters
    ----------
    motor, loop
        Armature R, L, k_e, k_m, b_m and the PI gains k_pi, k_ii.
    sensor_filter_hz
        Corner of the current sensor's RC low-pass (72 Hz on the rig); None measures
        the armature current itself.
    load_inertia_kgm2
        Inertia on the shaft, for the back-EMF (e.g. J_m + (M + m) r^2 with the cart on
        the wheels); None holds the rotor still (no back-EMF).

    Notes
    -----
    The loop as the C++ program and :mod:`pisc_control.current_loop` run it: at sample
    k the measured current y(k) gives e(k) = i_d - y(k), the integral is updated,
    ``u(k) = k_pi e(k) + integral(k)`` (3.47) and held until k+1 (zero-order hold), so
    the plant ``x' = A x + B u`` is discretised exactly, ``[Ad Bd] = expm([[A, B],
    [0, 0]] Ts)``. With s(k) the integral before the update, the closed loop is
    ``x(k+1) = (Ad - Bd (k_pi + k_ii Ts) C) x(k) + Bd s(k)``,
    ``s(k+1) = s(k) - k_ii Ts C x(k)``. Saturation and quantisation are left out
    (small signals).
    """
    a, b, c = _continuous_plant(motor, sensor_filter_hz, load_inertia_kgm2)
    n = a.shape[0]
    block = np.zeros((n + 1, n + 1))
    block[:n, :n] = a
    block[:n, n:] = b
    phi = scipy.linalg.expm(block * period_s)
    ad, bd = phi[:n, :n], phi[:n, n:]
    gain = loop.k_pi + loop.k_ii * period_s
    closed = np.zeros((n + 1, n + 1))
    closed[:n, :n] = ad - gain * bd @ c
    closed[:n, n:] = bd
    closed[n:, :n] = -loop.k_ii * period_s * c
    closed[n, n] = 1.0
    return np.linalg.eigvals(closed)


@dataclass(frozen=True)
class SampledPiCheck:
    """Outcome of the sampled PI loop test for one motor and one model."""

    resistance_ohm: float
    model: str
    poles: np.ndarray
    spectral_radius: float
    stable: bool

    @property
    def worst_pole(self) -> complex:
        return complex(self.poles[int(np.argmax(np.abs(self.poles)))])


def sampled_pi_check(
    motor: MotorParams,
    loop: CurrentLoopParams,
    period_s: float,
    *,
    model: str = "filter",
    sensor_filter_hz: float = 72.0,
    load_inertia_kgm2: float | None = None,
) -> SampledPiCheck:
    """Is the PI current loop stable as it runs, sampled at ``period_s``?

    This is the test that matters on the rig (SPEC section 3): Routh's test of
    the continuous loop (3.51) passes for every positive gain; the sampled loop does
    not. ``model``:

    * ``"quasi-static"``: ``R z^2 + (k_pi + k_ii Ts - R) z - k_pi`` (SPEC section 3),
      current = u / R, measured directly;
    * ``"armature"``: the exact ZOH model of the armature (R, L), current measured
      directly;
    * ``"filter"``: the armature measured through the sensor's RC filter at
      ``sensor_filter_hz`` (the rig: 72 Hz), the model the simulated plant runs.

    Stable when every pole lies strictly inside the unit circle.
    """
    if model == "quasi-static":
        poles = quasi_static_pi_poles(motor.resistance_ohm, loop.k_pi, loop.k_ii, period_s)
    elif model == "armature":
        poles = sampled_pi_poles(motor, loop, period_s, load_inertia_kgm2=load_inertia_kgm2)
    elif model == "filter":
        poles = sampled_pi_poles(motor, loop, period_s, sensor_filter_hz=sensor_filter_hz,
                                 load_inertia_kgm2=load_inertia_kgm2)
    else:
        raise ValueError(f"model = {model!r}: expected 'quasi-static', 'armature' or 'filter'")
    poles = np.sort_complex(np.asarray(poles, dtype=complex))
    radius = float(np.max(np.abs(poles)))
    return SampledPiCheck(motor.resistance_ohm, model, poles, radius, radius < 1.0)


def sampled_pi_resistance_limit(
    motor: MotorParams,
    loop: CurrentLoopParams,
    period_s: float,
    *,
    model: str = "filter",
    sensor_filter_hz: float = 72.0,
    low_ohm: float = 0.01,
    high_ohm: float = 1000.0,
    tolerance_ohm: float = 1e-4,
) -> float:
    """The armature resistance below which the sampled PI loop is unstable.

    Bisection on R between ``low_ohm`` (must be unstable) and ``high_ohm`` (must be
    stable), the rest of ``motor`` kept (L fixed). For the quasi-static model the
    answer is ``k_pi + k_ii Ts / 2`` (the pole at z = -1).
    """
    def stable(r: float) -> bool:
        return sampled_pi_check(replace(motor, resistance_ohm=r), loop, period_s, model=model,
                                sensor_filter_hz=sensor_filter_hz).stable

    if stable(low_ohm) or not stable(high_ohm):
        raise ValueError(f"sampled_pi_resistance_limit: no stability boundary between "
                         f"{low_ohm} and {high_ohm} ohm for model {model!r}")
    lo, hi = low_ohm, high_ohm
    while hi - lo > tolerance_ohm:
        mid = 0.5 * (lo + hi)
        lo, hi = (lo, mid) if stable(mid) else (mid, hi)
    return hi
