"""Compiled right-hand side and integrators of the plant (numba).

One kernel serves every scene: the state carries only the components a scene's
sub-models need (:class:`Layout`; the regularised Coulomb friction on the cart is
computed only in the layouts that model it), the constants travel in one float array
(:func:`pisc_plant.plant.pack_constants`), and the same compiled step advances one rig
in a node or ten thousand in a batch (:func:`for_layout` gives a layout's entry points:
one steps rows of a state array, the batch one hands chunks of rows to it in parallel).
Inside, the loop over rigs is vectorised, four rigs per AVX2 register, with sin, cos,
pow and tanh from glibc's vector library (:mod:`pisc_plant.vecmath`), and a rig gives
bit-identical results alone and in a batch. A plant set (every rig its own constants
and step, :func:`pisc_plant.plant.plant_set`) has entry points of its own that read each
rig's constants and operator table from blocks of :func:`lanes`; a rig of a set gives
the same bits as a plant of its own.

State order: ``x, x_dot, theta, theta_dot`` then, when modelled, the armature current
``i`` and the filtered sensor voltages ``v_ir, v_cur``. The input held over a step is
the applied armature voltage, or the cart force for an ideal force source.

Methods (:data:`METHODS`):

``rk4``
    Classical Runge-Kutta on the full right-hand side. Stable only while each substep
    resolves the fastest decay (h |lam| < 2.785); the plant refuses fewer substeps.
``exprk4``
    An exponential Runge-Kutta method of stiff order four (Hochbruck and Ostermann,
    "Explicit exponential Runge-Kutta methods for semilinear parabolic problems", SIAM
    J. Numer. Anal. 43 (2005) 1069-1090, the five-stage scheme (5.19)), stable at any
    step up to the period. Its order holds only if the nonlinear part N = f - L z is
    smooth along the solution; every term that carries the armature's fast transient
    must therefore be in the linear part L, or the transient that follows each voltage
    step reaches N, which the scheme samples as if it were smooth, and the error of
    each step stops falling with the step (measured: the first versions of this scheme
    converged at order 1 to 2 through voltage steps). So:

    * the current is replaced by its departure from the quasi-static current,
      ``q = i - (u - k_e x_dot / r) / R``; (2.81) becomes ``q' = -(R/L) q + d x_ddot``
      with ``d = k_e / (r R)`` (u is constant over the step);
    * L holds ``x' = x_dot``, ``theta' = theta_dot``, the current's weight in the
      accelerations ``c_x q``, ``c_theta q`` ((3.3), (3.5) with (4.2)), and the change
      of those weights during the step through the chain ``r' = lam r + q``,
      ``s' = lam s + r`` (r = t q and s = t^2 q / 2 for a decaying q): ``c_x1 r``,
      ``c_x2 s`` and the same for theta, from the angle's rate, acceleration and the
      transient's own push on the angle; r and s start at their slow values, so that
      they carry only the transient;
    * c_x and c_theta are those of the fast eigenvector: the transient also moves the
      velocities (by c q / lam) and the angle (c q / lam^2), which act back through the
      velocity and angle derivatives of the accelerations (back-EMF, centripetal and
      friction terms, gravity);
    * L's rate of q is a constant, :func:`armature_rate`, so that its phi-functions are
      computed once per step size; the state's own rate differs from it by delta
      (about 0.005 1/s on the thesis rig), carried as the current's departure
      ``q + delta r``;
    * the RC filters are linear in their own voltage and in q (with the back-EMF's
      share of the fast mode).

    L is block triangular, so each phi-function of it acts through a few divided
    differences of phi_k over its eigenvalues (0 double, lam triple, -w_ir, -w_cur), in
    closed form. README, "Scenes and integrators", gives the measured order.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import NamedTuple

import numba
import numpy as np

from pisc_plant.layout import (  # noqa: F401 (re-exported: the kernel's layout)
    METHODS, RK4, EXPRK4, ARM_FULL, ARM_QUASI_STATIC, ARM_FORCE, N_CONSTANTS, Layout, P_A1,
    P_A2, P_ML, P_G, P_KF, P_BM, P_R, P_L, P_KER, P_BC, P_BP, P_FC, P_VC, P_WIR, P_WCUR,
    P_IRO, P_IRS, P_IRX, P_CUROFF, P_CURSCALE, P_XMIN, P_XMAX, P_JROT,
)
from pisc_plant.vecmath import vcos, vpow, vsin, vtanh

__all__ = [
    "METHODS",
    "Kernels",
    "Layout",
    "armature_rate",
    "armature_rates",
    "end_stops",
    "exp_coefficients",
    "exp_tables",
    "for_layout",
    "from_lanes",
    "lanes",
    "phi",
    "rhs_one",
]


def phi(k: int, z: float) -> float:
    """phi_k(z) = sum_j z^j / (j + k)! (phi_0 = exp), accurate for every real z.

    The series for |z| < 2 (40 terms), else the recurrence
    phi_(k+1)(z) = (phi_k(z) - 1/k!) / z from the exponential, which loses nothing there.
    """
    if abs(z) < 2.0:
        total, term = 0.0, 1.0 / math.factorial(k)
        for j in range(40):
            total += term
            term *= z / (j + k + 1)
        return total
    value = math.exp(z)
    for j in range(k):
        value = (value - 1.0 / math.factorial(j)) / z
    return value


# The linear part L of the exponential scheme (see the module's docstring) acts on
# (x, x_dot, theta, theta_dot, q, v_ir, v_cur, r, s) as
#     x' = x_dot                      x_dot' = c_x q + c_x1 r + c_x2 s
#     theta' = theta_dot              theta_dot' = c_theta q + c_theta1 r + c_theta2 s
#     q' = lam q                      r' = lam r + q          s' = lam s + r
#     v_ir' = -w_ir v_ir              v_cur' = -w_cur v_cur + c_v q
# (r = t q and s = t^2 q / 2 for a decaying q). A function F(hL) = sum alpha
# phi_k(s h L) acts through these scalars, divided differences of F over the
# eigenvalues, times the couplings where they apply:
(OP_D0,     # F(0)                                    x, x_dot, theta, theta_dot
 OP_D1,     # F[0, 0]                                 x <- x_dot, theta <- theta_dot
 OP_DQ,     # F(lam)                                  q <- q, r <- r, s <- s
 OP_E1,     # F[0, lam]           (times c, c1, c2)   x_dot <- q, r, s
 OP_E2,     # F[0, 0, lam]        (times c, c1, c2)   x <- q, r, s
 OP_ER,     # F[lam, lam]                             r <- q, s <- r
 OP_E3,     # F[0, lam, lam]      (times c1, c2)      x_dot <- q through r, r through s
 OP_E4,     # F[0, 0, lam, lam]   (times c1, c2)      x <- q through r, r through s
 OP_DIR,    # F(-w_ir)                                v_ir
 OP_DCUR,   # F(-w_cur)                               v_cur
 OP_ECUR,   # F[-w_cur, lam]      (times c_v)         v_cur <- q
 OP_ES,     # F[lam, lam, lam]                        s <- q
 OP_E5,     # F[0, lam, lam, lam] (times c2)          x_dot <- q through s
 OP_E6,     # F[0, 0, lam, lam, lam] (times c2)       x <- q through s
 ) = range(14)
OP_WIDTH = 14
# Rows: e^(hL), e^(hL/2), then h times a21, a31, a32, a41, a42 (= a43), a51,
# a52 (= a53), a54, b1, b4, b5 of the scheme (5.19).
N_OPERATORS = 13
ROW_PHI_CUR = 13  # phi_0..phi_3 of -w_cur h/2, then of -w_cur h
ROW_CONST = 14  # c_v, w_cur, h


def _terms_to_weights(terms: list[tuple[float, int, float]]) -> np.ndarray:
    w = np.zeros((2, 4))
    for alpha, k, s in terms:
        w[0 if s == 0.5 else 1, k] += alpha
    return w


_A52 = [(0.5, 2, 0.5), (-1.0, 3, 1.0), (0.25, 2, 1.0), (-0.5, 3, 0.5)]
_A54 = [(0.25, 2, 0.5)] + [(-a, k, s) for a, k, s in _A52]
_A51 = ([(0.5, 1, 0.5)] + [(-2.0 * a, k, s) for a, k, s in _A52]
        + [(-a, k, s) for a, k, s in _A54])
# Each operator as weights of phi_k(s h L) for s in (1/2, 1) and k in 0..3.
OP_WEIGHTS = np.array([_terms_to_weights(t) for t in (
    [(1.0, 0, 1.0)],                                   # e^(hL)
    [(1.0, 0, 0.5)],                                   # e^(hL/2)
    [(0.5, 1, 0.5)],                                   # a21
    [(0.5, 1, 0.5), (-1.0, 2, 0.5)],                   # a31
    [(1.0, 2, 0.5)],                                   # a32
    [(1.0, 1, 1.0), (-2.0, 2, 1.0)],                   # a41
    [(1.0, 2, 1.0)],                                   # a42 = a43
    _A51, _A52, _A54,                                  # a51, a52 = a53, a54
    [(1.0, 1, 1.0), (-3.0, 2, 1.0), (4.0, 3, 1.0)],    # b1
    [(-1.0, 2, 1.0), (4.0, 3, 1.0)],                   # b4
    [(4.0, 2, 1.0), (-8.0, 3, 1.0)],                   # b5
)])
STAGE_FRACTIONS = np.array([0.5, 1.0])
INV_FACTORIAL = np.array([1.0 / math.factorial(k) for k in range(10)])


def exp_coefficients(w_ir: float, w_cur: float, c_v: float, lam: float,
                     step_s: float) -> np.ndarray:
    """The exponential scheme's operators for one step size, shape (15, OP_WIDTH).

    Rows 0-12 hold each operator's scalars (``OP_*``); row 13 phi_0..phi_3 of -w_cur h/2
    and of -w_cur h, row 14 ``c_v``, ``w_cur``, ``h``. ``w_ir``, ``w_cur`` are the
    filters' rates (0 without them), ``c_v`` the current filter's gain on q (w_cur over
    the sensor's A/V scale), ``lam`` the armature's rate in L (0 without an armature):
    the plant's constant :func:`armature_rate`, so that the table is computed once per
    step size, not at every step.

    Each scalar is a sum over s = 1/2, 1 and k = 0..3 of scale * OP_WEIGHTS[op, s, k]
    times the divided difference of phi_k(s h .) the column names, added in that order
    by the compiled :func:`_step_operators` and :func:`_armature_operators`: 2 us a
    table here. On the wall clock a plant needs two new tables every cycle (the voltage
    arrives at another time in each period); the same sums added one Python float at a
    time took 340 us a table, a fifth of the graph's CPU in a wall-clock run (py-spy,
    2026-12-03). test_kernel.py keeps that form as the reference, bit for bit.
    """
    table = np.empty((15, OP_WIDTH))
    _step_operators(float(w_ir), float(w_cur), float(c_v), float(step_s), table,
                    np.empty((2, 4)))
    if lam != 0.0:
        _armature_operators(float(lam), table, np.empty((2, 8)))
    return table


_jit = numba.njit(cache=True, error_model="numpy")
# Small helpers are inlined at numba's IR level: as calls, passing their arrays cost
# more than their arithmetic (measured: 250 ns per operator application).
_inline = numba.njit(cache=True, error_model="numpy", inline="always")


@_inline
def armature_rate(p):
    """The armature's rate lam in L: -R/L plus the back-EMF's share d k_f / den, with den
    at cos^2(theta) = 1/2, the middle of its range.

    The rate the state implies, -R/L + d c_x(theta, theta_dot), differs from it by about
    d k_f a1 / (2 den^2) at most (0.0049 1/s on the thesis rig, 7e-7 of R/L), which the
    scheme carries as delta (:func:`_couplings`). A constant rate makes the operators
    constants of the step size (:func:`exp_coefficients`).
    """
    d = p[P_KER] / p[P_R]
    return -p[P_R] / p[P_L] + d * p[P_KF] / (p[P_A2] - 0.5 * p[P_A1])


@_jit
def _phis(z, out):
    """phi_0 .. phi_7 of z into ``out`` (see :func:`phi`)."""
    if abs(z) < 4.0:
        term = INV_FACTORIAL[7]
        total = 0.0
        for j in range(60):
            total += term
            term *= z / (j + 8)
        out[7] = total
        for k in range(6, -1, -1):
            out[k] = INV_FACTORIAL[k] + z * out[k + 1]
    else:
        out[0] = math.exp(z)
        for k in range(7):
            out[k + 1] = (out[k] - INV_FACTORIAL[k]) / z


@_jit
def _armature_operators(lam, coef, ph):
    """The scalars that depend on the armature's rate ``lam``, from phi_k(s h lam).

    With F = phi_k(s h .) and phi_k' = phi_k - k phi_(k+1): F(lam) = phi_k,
    F[0, lam] = s h phi_(k+1), F[0, 0, lam] = (s h)^2 phi_(k+2), F[lam, lam] = s h phi_k',
    F[0, lam, lam] = (s h)^2 phi_(k+1)', F[0, 0, lam, lam] = (s h)^3 phi_(k+2)',
    and with phi_k'' = phi_k - 2 k phi_(k+1) + k (k+1) phi_(k+2) (the same rule twice):
    F[lam, lam, lam] = (s h)^2 phi_k'' / 2, F[0, lam, lam, lam] = (s h)^3 phi_(k+1)'' / 2,
    F[0, 0, lam, lam, lam] = (s h)^4 phi_(k+2)'' / 2 (repeated nodes: derivatives over
    the factorial); F[-w_cur, lam] = (F(-w_cur) - F(lam)) / (-w_cur - lam).
    """
    c_v = coef[ROW_CONST, 0]
    w_cur = coef[ROW_CONST, 1]
    h = coef[ROW_CONST, 2]
    for si in range(2):
        _phis(STAGE_FRACTIONS[si] * h * lam, ph[si])
    gap = -w_cur - lam
    for op in range(N_OPERATORS):
        scale = 1.0 if op < 2 else h
        dq = 0.0
        e1 = 0.0
        e2 = 0.0
        er = 0.0
        e3 = 0.0
        e4 = 0.0
        es = 0.0
        e5 = 0.0
        e6 = 0.0
        ecur = 0.0
        for si in range(2):
            sh = STAGE_FRACTIONS[si] * h
            f = ph[si]
            for k in range(4):
                alpha = OP_WEIGHTS[op, si, k]
                if alpha != 0.0:
                    dq += alpha * f[k]
                    e1 += alpha * sh * f[k + 1]
                    e2 += alpha * sh * sh * f[k + 2]
                    er += alpha * sh * (f[k] - k * f[k + 1])
                    e3 += alpha * sh * sh * (f[k + 1] - (k + 1) * f[k + 2])
                    e4 += alpha * sh * sh * sh * (f[k + 2] - (k + 2) * f[k + 3])
                    # phi_j'' = phi_j - 2 j phi_(j+1) + j (j + 1) phi_(j+2)
                    es += alpha * 0.5 * sh ** 2 * (f[k] - 2 * k * f[k + 1]
                                                   + k * (k + 1) * f[k + 2])
                    e5 += alpha * 0.5 * sh ** 3 * (f[k + 1] - 2 * (k + 1) * f[k + 2]
                                                   + (k + 1) * (k + 2) * f[k + 3])
                    e6 += alpha * 0.5 * sh ** 4 * (f[k + 2] - 2 * (k + 2) * f[k + 3]
                                                   + (k + 2) * (k + 3) * f[k + 4])
                    if gap != 0.0:
                        ecur += alpha * (coef[ROW_PHI_CUR, 4 * si + k] - f[k]) / gap
        coef[op, OP_DQ] = scale * dq
        coef[op, OP_E1] = scale * e1
        coef[op, OP_E2] = scale * e2
        coef[op, OP_ER] = scale * er
        coef[op, OP_E3] = scale * e3
        coef[op, OP_E4] = scale * e4
        coef[op, OP_ES] = scale * es
        coef[op, OP_E5] = scale * e5
        coef[op, OP_E6] = scale * e6
        coef[op, OP_ECUR] = scale * c_v * ecur


# The hot path works on one rig's state as a tuple of numbers, never on arrays, so that
# LLVM can keep every intermediate in registers and vectorise the loop over rigs (four
# rigs per AVX2 register, sin, cos, pow and tanh from the vector library: see
# :mod:`pisc_plant.vecmath`). A rig's state is ``(x, x_dot, theta, theta_dot, i, v_ir,
# v_cur)`` whatever the layout (absent components are 0 and stay 0); the exponential
# scheme's variables are ``(x, x_dot, theta, theta_dot, q, v_ir, v_cur, r, s)``. The
# layout enters as constants (``arm``, ``filt``) where the functions are inlined, so the
# compiler removes the branches of the others. The constants ``p`` and the operator
# table ``ops`` are tuples unpacked once per call, so the loop over rigs reads no memory
# besides the rigs' states and inputs. Measured while building it: README, "Batch".

_ZERO9 = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)


@_inline
def _constants(a, stops):
    """The packed constants as a tuple (see ``P_*``); without ``stops`` the track's ends
    are at -inf and +inf, so that the end stops never act and the loop needs no flag."""
    return (a[0], a[1], a[2], a[3], a[4], a[5], a[6], a[7], a[8], a[9], a[10], a[11],
            a[12], a[13], a[14], a[15], a[16], a[17], a[18], a[19],
            a[P_XMIN] if stops else -np.inf, a[P_XMAX] if stops else np.inf, a[22])


@_inline
def _operator(coef, k):
    return (coef[k, 0], coef[k, 1], coef[k, 2], coef[k, 3], coef[k, 4], coef[k, 5],
            coef[k, 6], coef[k, 7], coef[k, 8], coef[k, 9], coef[k, 10], coef[k, 11],
            coef[k, 12], coef[k, 13])


@_inline
def _operators(coef):
    """Rows 0-12 of :func:`exp_coefficients`' table as a tuple of tuples."""
    return (_operator(coef, 0), _operator(coef, 1), _operator(coef, 2), _operator(coef, 3),
            _operator(coef, 4), _operator(coef, 5), _operator(coef, 6), _operator(coef, 7),
            _operator(coef, 8), _operator(coef, 9), _operator(coef, 10),
            _operator(coef, 11), _operator(coef, 12))


@_inline
def _current(y, u, p, arm):
    if arm == ARM_FULL:
        current = y[4]
    elif arm == ARM_QUASI_STATIC:
        current = (u - p[P_KER] * y[1]) / p[P_R]
    else:
        current = u / p[P_KF]  # the current an ideal motor would need for force u
    return current


@_inline
def _accelerations(y, u, p, arm, current, fric):
    """x_ddot, theta_ddot: (3.3), (3.5) with cart and pivot friction."""
    return _accelerations_at(y[1], y[3], u, p, arm, current, vsin(y[2]), vcos(y[2]), fric)


@_inline
def _accelerations_at(x_dot, theta_dot, u, p, arm, current, s, c, fric):
    """:func:`_accelerations` with sin and cos of the angle given; ``fric`` (a constant of
    the compilation): the layout models Coulomb friction on the cart."""
    if arm == ARM_FORCE:
        force = u
    else:
        # (4.2) and the rotor's viscous friction reflected to the cart
        force = p[P_KF] * current - p[P_BM] * x_dot
    force -= p[P_BC] * x_dot
    # Coulomb friction, regularised. In a layout without it (fric, a constant of the
    # compilation, so no branch in the vectorised loop) F_c = 0 and the term is an exact
    # 0, and its tanh is not taken (docs/scenes-and-numerics.md: what that saves)
    if fric:
        force -= p[P_FC] * vtanh(x_dot / p[P_VC])
    torque = -p[P_BP] * theta_dot
    a1 = p[P_A1]
    a2 = p[P_A2]
    ml = p[P_ML]
    g = p[P_G]
    den = a2 - a1 * c * c
    centripetal = ml * theta_dot * theta_dot * s
    # A pivot torque enters the pendulum row of (2.26); solved for the accelerations it
    # adds -a1 c tau / ml to the cart numerator and a1 a2 tau / ml to the pendulum's.
    x_ddot = (-a1 * g * s * c + centripetal + force - a1 * c * torque / ml) / den
    theta_ddot = (a1 * a2 * g * s - a1 * centripetal * c - a1 * force * c
                  + a1 * a2 * torque / ml) / (ml * den)
    return x_ddot, theta_ddot


@_inline
def _ir_voltage(p, x):
    distance = max(p[P_IRO] - x, 1e-3)
    return vpow(distance / p[P_IRS], p[P_IRX])


@_inline
def _current_sensor_voltage(p, current):
    return (current + p[P_CUROFF]) / p[P_CURSCALE]


@_inline
def _rhs(y, u, p, arm, filt, fric):
    """The full right-hand side y' (state order of the tuple, see above)."""
    current = _current(y, u, p, arm)
    x_ddot, theta_ddot = _accelerations(y, u, p, arm, current, fric)
    di = 0.0
    if arm == ARM_FULL:
        # (2.81): L di/dt = u - R i - k_e phi_dot
        di = (u - p[P_R] * current - p[P_KER] * y[1]) / p[P_L]
    dir_ = 0.0
    dcur = 0.0
    if filt:
        dir_ = p[P_WIR] * (_ir_voltage(p, y[0]) - y[5])
        dcur = p[P_WCUR] * (_current_sensor_voltage(p, current) - y[6])
    return (y[1], x_ddot, y[3], theta_ddot, di, dir_, dcur)


@_inline
def _couplings(z, y, u, p, arm, fric):
    """L's couplings at the step's start: c_x, c_theta (0, 1), c_x1, c_theta1 (2, 3), the
    rate of q (4), the current sensor's share of q (5), the accelerations (6, 7), c_x2,
    c_theta2 (8, 9), delta (10).

    The current's weights in (3.3) and (3.5) with f = k_f i (4.2) are
    c_x = k_f / den and c_theta = -a1 cos(theta) k_f / (m l den), den = a2 - a1 cos^2.
    The fast mode also moves the velocities, by (c_x, c_theta) q / lam, and the angle by
    c_theta q / lam^2; through the velocity Jacobian J of the accelerations (back-EMF
    via the quasi-static current, centripetal terms, viscous friction) and their angle
    derivatives K that motion acts back in proportion to q. The couplings L holds are
    those of the fast eigenvector, (I + J / lam + (J^2 + K) / lam^2) (c_x, c_theta).
    c_x1, c_theta1 are the change of c_x, c_theta with the angle times its rate during
    the transient, c_x2, c_theta2 their second-order change (below). The
    quasi-static current moves with x_dot's share of the fast mode, so the current the
    sensor's filter sees is q (1 - d c_x / lam) besides the quasi-static part: c[5].
    L's own rate is the constant of :func:`armature_rate`, c[4].
    """
    if arm != ARM_FULL:
        return (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    co = vcos(z[2])
    si = vsin(z[2])
    theta_dot = z[3]
    a1 = p[P_A1]
    a2 = p[P_A2]
    ml = p[P_ML]
    kf = p[P_KF]
    den = a2 - a1 * co * co
    d = p[P_KER] / p[P_R]
    cx = kf / den
    cth = -a1 * co * kf / (ml * den)
    lam = -p[P_R] / p[P_L] + d * cx
    # velocity Jacobian of (x_ddot, theta_ddot): damping of x_dot (back-EMF, b_m, b_c),
    # of theta_dot (pivot b_p), centripetal terms
    damp_x = kf * d + p[P_BM] + p[P_BC]
    j11 = -damp_x / den
    j12 = (2.0 * ml * theta_dot * si + a1 * co * p[P_BP] / ml) / den
    j21 = a1 * co * damp_x / (ml * den)
    j22 = (-2.0 * a1 * theta_dot * si * co - a1 * a2 * p[P_BP] / (ml * ml)) / den
    x_ddot, theta_ddot = _accelerations_at(y[1], y[3], u, p, arm, y[4], si, co, fric)
    # the slow motion: without q's own share (q0 = q at the start, mostly the transient)
    q0 = z[4]
    x_ddot_slow = x_ddot - cx * q0
    theta_ddot_slow = theta_ddot - cth * q0
    force = kf * (y[4] - q0) - (p[P_BM] + p[P_BC]) * y[1]
    if fric:
        force -= p[P_FC] * vtanh(y[1] / p[P_VC])
    torque = -p[P_BP] * theta_dot
    # angle derivatives K of the slow accelerations (3.3), (3.5): numerators over den
    dden = 2.0 * a1 * co * si
    cos2 = co * co - si * si
    k12 = (-a1 * p[P_G] * cos2 + ml * theta_dot * theta_dot * co + a1 * si * torque / ml
           - x_ddot_slow * dden) / den
    k22 = ((a1 * a2 * p[P_G] * co - a1 * ml * theta_dot * theta_dot * cos2
            + a1 * force * si) / ml - theta_ddot_slow * dden) / den
    v0 = cx + (j11 * cx + j12 * cth) / lam
    v1 = cth + (j21 * cx + j22 * cth) / lam
    c0 = v0 + (j11 * (v0 - cx) + j12 * (v1 - cth) + k12 * cth / lam) / lam
    c1 = v1 + (j21 * (v0 - cx) + j22 * (v1 - cth) + k22 * cth / lam) / lam
    # the angle's derivatives of c_x = k_f / den and c_theta = -(a1 k_f / ml) cos / den
    dden2 = 2.0 * a1 * cos2
    cx_1 = -kf * dden / (den * den)
    cx_2 = -kf * (dden2 * den - 2.0 * dden * dden) / (den * den * den)
    g_num = -si * den - co * dden  # (cos / den)' = g_num / den^2
    g_num1 = -co * den - co * dden2
    cth_1 = -(a1 * kf / ml) * g_num / (den * den)
    cth_2 = -(a1 * kf / ml) * (g_num1 * den - 2.0 * g_num * dden) / (den * den * den)
    # The transient moves the angle by c1 q0 ((e^(lam t) - 1) / lam^2 - t / lam) while
    # q = q0 e^(lam t) flows, which changes c_x, c_theta by their angle derivative times
    # that: q0 times -e^(lam t) / lam^2 and -t e^(lam t) / lam (the slow angle's shift)
    # and e^(2 lam t) / lam^2 (the fast angle). e^(2 lam t) has no place in L; matched in
    # its value at the start and its integral by e^(lam t) + (lam t / 2) e^(lam t), it
    # cancels the first term and halves the second: r's couplings see theta_dot + shift.
    shift = -0.5 * c1 * q0 / lam
    rate = armature_rate(p)
    # The state's own rate of q differs from L's by delta (about 0.005 1/s). The
    # current's departure is q + delta r in the scheme's variables (q e^(delta t) to first
    # order), so the velocities see delta c r besides c q.
    delta = -p[P_R] / p[P_L] + d * c0 - rate
    return (c0, c1,
            cx_1 * (theta_dot + shift) + delta * c0,
            cth_1 * (theta_dot + shift) + delta * c1,
            rate,
            1.0 - d * c0 / rate,
            x_ddot, theta_ddot,
            # s = t^2 q / 2: the second-order change of c_x, c_theta during the step
            cx_1 * theta_ddot_slow + cx_2 * theta_dot * theta_dot,
            cth_1 * theta_ddot_slow + cth_2 * theta_dot * theta_dot,
            delta)


@_inline
def _apply_add(op, v, c, out, full, filt):
    """out + F(hL) v for one operator's scalars (see ``OP_*``)."""
    d0 = op[OP_D0]
    d1 = op[OP_D1]
    o0 = out[0] + (d0 * v[0] + d1 * v[1])
    o1 = out[1] + d0 * v[1]
    o2 = out[2] + (d0 * v[2] + d1 * v[3])
    o3 = out[3] + d0 * v[3]
    o4 = out[4]
    o5 = out[5]
    o6 = out[6]
    o7 = out[7]
    o8 = out[8]
    q = 0.0
    if full:
        q = v[4]
        r = v[7]
        s = v[8]
        e1 = op[OP_E1]
        e2 = op[OP_E2]
        e3 = op[OP_E3]
        e4 = op[OP_E4]
        # what q, r, s add to the velocities (1) and positions (0), per coupling
        v_q = e1 * q
        v_r = e1 * r + e3 * q
        v_s = e1 * s + e3 * r + op[OP_E5] * q
        p_q = e2 * q
        p_r = e2 * r + e4 * q
        p_s = e2 * s + e4 * r + op[OP_E6] * q
        o0 = o0 + (c[0] * p_q + c[2] * p_r + c[8] * p_s)
        o1 = o1 + (c[0] * v_q + c[2] * v_r + c[8] * v_s)
        o2 = o2 + (c[1] * p_q + c[3] * p_r + c[9] * p_s)
        o3 = o3 + (c[1] * v_q + c[3] * v_r + c[9] * v_s)
        dq = op[OP_DQ]
        er = op[OP_ER]
        o4 = o4 + dq * q
        o7 = o7 + (dq * r + er * q)
        o8 = o8 + (dq * s + er * r + op[OP_ES] * q)
    if filt:
        o5 = o5 + op[OP_DIR] * v[5]
        o6 = o6 + (op[OP_DCUR] * v[6] + op[OP_ECUR] * c[5] * q)
    return (o0, o1, o2, o3, o4, o5, o6, o7, o8)


@_inline
def _apply_add_n(op, v, c, out, full, filt):
    """:func:`_apply_add` for a vector N of the nonlinear part, whose x, theta, r and s
    components are zero (the positions' derivatives and the chain's are all in L)."""
    d1 = op[OP_D1]
    o0 = out[0] + d1 * v[1]
    o1 = out[1] + op[OP_D0] * v[1]
    o2 = out[2] + d1 * v[3]
    o3 = out[3] + op[OP_D0] * v[3]
    o4 = out[4]
    o5 = out[5]
    o6 = out[6]
    o7 = out[7]
    o8 = out[8]
    q = 0.0
    if full:
        q = v[4]
        v_q = c[0] * op[OP_E1] + c[2] * op[OP_E3] + c[8] * op[OP_E5]
        p_q = c[0] * op[OP_E2] + c[2] * op[OP_E4] + c[8] * op[OP_E6]
        vth_q = c[1] * op[OP_E1] + c[3] * op[OP_E3] + c[9] * op[OP_E5]
        pth_q = c[1] * op[OP_E2] + c[3] * op[OP_E4] + c[9] * op[OP_E6]
        o0 = o0 + p_q * q
        o1 = o1 + v_q * q
        o2 = o2 + pth_q * q
        o3 = o3 + vth_q * q
        o4 = o4 + op[OP_DQ] * q
        o7 = o7 + op[OP_ER] * q
        o8 = o8 + op[OP_ES] * q
    if filt:
        o5 = o5 + op[OP_DIR] * v[5]
        o6 = o6 + (op[OP_DCUR] * v[6] + op[OP_ECUR] * c[5] * q)
    return (o0, o1, o2, o3, o4, o5, o6, o7, o8)


@_inline
def _nonlinear(z, u, p, c, arm, filt, at_start, fric):
    """N(z) = f(z) - L z in the exponential scheme's variables (q for i, plus r, s).

    ``at_start``: z is the step's start, whose accelerations :func:`_couplings` left in
    c[6], c[7].
    """
    q = 0.0
    r = 0.0
    s = 0.0
    i = z[4]
    if arm == ARM_FULL:
        q = z[4]
        r = z[7]
        s = z[8]
        i = q + c[10] * r + (u - p[P_KER] * z[1]) / p[P_R]
    y = (z[0], z[1], z[2], z[3], i, z[5], z[6])
    current = _current(y, u, p, arm)
    if at_start and arm == ARM_FULL:
        x_ddot = c[6]
        theta_ddot = c[7]
    else:
        x_ddot, theta_ddot = _accelerations(y, u, p, arm, current, fric)
    n4 = 0.0
    if arm == ARM_FULL:
        # with Q = q + delta r the current's departure, Q' = -(R/L) Q + d x_ddot; L gives
        # lam Q + delta q, so N's share is d (x_ddot - c_x Q) + delta^2 r
        d = p[P_KER] / p[P_R]
        delta = c[10]
        n4 = d * (x_ddot - c[0] * (q + delta * r)) + delta * delta * r
    n5 = 0.0
    n6 = 0.0
    if filt:
        n5 = p[P_WIR] * _ir_voltage(p, y[0])
        # v_cur' = w_cur ((i + offset) / scale - v_cur); L holds c_v c[5] q
        n6 = p[P_WCUR] * _current_sensor_voltage(p, current - c[5] * q)
    return (0.0, x_ddot - c[0] * q - c[2] * r - c[8] * s, 0.0,
            theta_ddot - c[1] * q - c[3] * r - c[9] * s, n4, n5, n6, 0.0, 0.0)


@_inline
def _end_stops(y, p):
    """Perfectly inelastic end stops (see :meth:`pisc_plant.plant.Plant.end_stops`) at
    p[P_XMIN], p[P_XMAX]; the cosine is taken whether they act or not, so that the loop
    has no branch."""
    cos_theta = vcos(y[2])
    x = y[0]
    x_dot = y[1]
    lo = p[P_XMIN]
    hi = p[P_XMAX]
    out = (x < lo and x_dot < 0.0) or (x > hi and x_dot > 0.0)
    theta_dot = y[3] + p[P_ML] * cos_theta * x_dot / p[P_JROT] if out else y[3]
    x_new = lo if x < lo else (hi if x > hi else x)
    return (x_new, 0.0 if out else x_dot, y[2], theta_dot, y[4], y[5], y[6])


@_inline
def _rk4(y, u, p, h, arm, filt, fric):
    """One classical Runge-Kutta step."""
    k1 = _rhs(y, u, p, arm, filt, fric)
    t = 0.5 * h
    k2 = _rhs((y[0] + t * k1[0], y[1] + t * k1[1], y[2] + t * k1[2], y[3] + t * k1[3],
               y[4] + t * k1[4], y[5] + t * k1[5], y[6] + t * k1[6]), u, p, arm, filt, fric)
    k3 = _rhs((y[0] + t * k2[0], y[1] + t * k2[1], y[2] + t * k2[2], y[3] + t * k2[3],
               y[4] + t * k2[4], y[5] + t * k2[5], y[6] + t * k2[6]), u, p, arm, filt, fric)
    k4 = _rhs((y[0] + h * k3[0], y[1] + h * k3[1], y[2] + h * k3[2], y[3] + h * k3[3],
               y[4] + h * k3[4], y[5] + h * k3[5], y[6] + h * k3[6]), u, p, arm, filt, fric)
    w = h / 6.0
    return (y[0] + w * (k1[0] + 2.0 * k2[0] + 2.0 * k3[0] + k4[0]),
            y[1] + w * (k1[1] + 2.0 * k2[1] + 2.0 * k3[1] + k4[1]),
            y[2] + w * (k1[2] + 2.0 * k2[2] + 2.0 * k3[2] + k4[2]),
            y[3] + w * (k1[3] + 2.0 * k2[3] + 2.0 * k3[3] + k4[3]),
            y[4] + w * (k1[4] + 2.0 * k2[4] + 2.0 * k3[4] + k4[4]),
            y[5] + w * (k1[5] + 2.0 * k2[5] + 2.0 * k3[5] + k4[5]),
            y[6] + w * (k1[6] + 2.0 * k2[6] + 2.0 * k3[6] + k4[6]))


@_inline
def _sum9(a, b):
    return (a[0] + b[0], a[1] + b[1], a[2] + b[2], a[3] + b[3], a[4] + b[4], a[5] + b[5],
            a[6] + b[6], a[7] + b[7], a[8] + b[8])


# Rows of the operator table (see OP_WEIGHTS)
(T_E, T_E2, T_A21, T_A31, T_A32, T_A41, T_A42, T_A51, T_A52, T_A54, T_B1, T_B4,
 T_B5) = range(N_OPERATORS)


@_inline
def _exprk4(y, u, p, ops, arm, filt, fric):
    """One step of the exponential scheme (5.19) (see the module's docstring)."""
    full = arm == ARM_FULL
    slow = 0.0
    if full:
        slow = (u - p[P_KER] * y[1]) / p[P_R]
    z = (y[0], y[1], y[2], y[3], y[4] - slow, y[5], y[6], 0.0, 0.0)
    c = _couplings(z, y, u, p, arm, fric)
    n1 = _nonlinear(z, u, p, c, arm, filt, True, fric)
    if full:
        # r starts at its slow value N_q / lam^2, so that r carries t q only for the
        # transient: from r = 0 the slow part of q would start a fast transient in r
        # that the explicit terms (c_x1 r in N) cannot follow
        lam = c[4]
        r0 = n1[4] / (lam * lam)
        s0 = -r0 / lam
        # the current's departure q + delta r stays
        z = (z[0], z[1], z[2], z[3], z[4] - c[10] * r0, z[5], z[6], r0, s0)
        n1 = (n1[0], n1[1] - (c[2] * r0 + c[8] * s0), n1[2], n1[3] - (c[3] * r0 + c[9] * s0),
              n1[4], n1[5], n1[6], n1[7], n1[8])
    # the scheme (5.19): U2 = e^(hL/2) z + a21 N1; U3 = e^(hL/2) z + a31 N1 + a32 N2;
    # U4 = e^(hL) z + a41 N1 + a42 (N2 + N3);
    # U5 = e^(hL/2) z + a51 N1 + a52 (N2 + N3) + a54 N4;
    # z_new = e^(hL) z + b1 N1 + b4 N4 + b5 N5
    ez2 = _apply_add(ops[T_E2], z, c, _ZERO9, full, filt)
    ez = _apply_add(ops[T_E], z, c, _ZERO9, full, filt)
    n2 = _nonlinear(_apply_add_n(ops[T_A21], n1, c, ez2, full, filt), u, p, c, arm, filt,
                    False, fric)
    u3 = _apply_add_n(ops[T_A31], n1, c, ez2, full, filt)
    n3 = _nonlinear(_apply_add_n(ops[T_A32], n2, c, u3, full, filt), u, p, c, arm, filt,
                    False, fric)
    sum23 = _sum9(n2, n3)
    u4 = _apply_add_n(ops[T_A41], n1, c, ez, full, filt)
    n4 = _nonlinear(_apply_add_n(ops[T_A42], sum23, c, u4, full, filt), u, p, c, arm, filt,
                    False, fric)
    u5 = _apply_add_n(ops[T_A51], n1, c, ez2, full, filt)
    u5 = _apply_add_n(ops[T_A52], sum23, c, u5, full, filt)
    n5 = _nonlinear(_apply_add_n(ops[T_A54], n4, c, u5, full, filt), u, p, c, arm, filt,
                    False, fric)
    new = _apply_add_n(ops[T_B1], n1, c, ez, full, filt)
    new = _apply_add_n(ops[T_B4], n4, c, new, full, filt)
    new = _apply_add_n(ops[T_B5], n5, c, new, full, filt)
    i = new[4]
    if full:
        i = new[4] + (c[10] * new[7] + (u - p[P_KER] * new[1]) / p[P_R])
    return (new[0], new[1], new[2], new[3], i, new[5], new[6])


@_inline
def _put(y, k, b0, b1, b2, b3, b4, b5, b6):
    b0[k] = y[0]
    b1[k] = y[1]
    b2[k] = y[2]
    b3[k] = y[3]
    b4[k] = y[4]
    b5[k] = y[5]
    b6[k] = y[6]


@_jit
def _lanes(b0, b1, b2, b3, b4, b5, b6, us, p, ops, method, substeps, h, arm, filt, fric):
    """Advance the rigs whose states are the columns of the rows b0..b6 (one row per
    state component, one column per rig): the loop over rigs is the vectorised one.

    Compiled once per layout: ``literally`` makes ``arm``, ``filt`` and ``fric`` (the
    Coulomb term) constants of each compilation. (Inlined into the entry points instead,
    as the helpers below it are, numba copied the whole step's intermediate code at every
    level of inlining: the kernel took 14 minutes to compile.)
    """
    numba.literally(arm)
    numba.literally(filt)
    numba.literally(fric)
    rigs = us.shape[0]
    if method == RK4:
        for _ in range(substeps):
            for k in range(rigs):
                y = _rk4((b0[k], b1[k], b2[k], b3[k], b4[k], b5[k], b6[k]), us[k], p, h,
                         arm, filt, fric)
                y = _end_stops(y, p)
                _put(y, k, b0, b1, b2, b3, b4, b5, b6)
    else:
        for _ in range(substeps):
            for k in range(rigs):
                y = _exprk4((b0[k], b1[k], b2[k], b3[k], b4[k], b5[k], b6[k]), us[k], p,
                            ops, arm, filt, fric)
                y = _end_stops(y, p)
                _put(y, k, b0, b1, b2, b3, b4, b5, b6)


@_inline
def _advance_rows(ys, us, lo, hi, p, stops, method, substeps, h, coef, arm, filt, ii, vir,
                  vcur, fric):
    """Advance rows lo..hi of ys (one rig per row, the layout's order) in place."""
    rigs = hi - lo
    cols = np.zeros((7, rigs))
    for k in range(rigs):
        cols[0, k] = ys[lo + k, 0]
        cols[1, k] = ys[lo + k, 1]
        cols[2, k] = ys[lo + k, 2]
        cols[3, k] = ys[lo + k, 3]
        if ii >= 0:
            cols[4, k] = ys[lo + k, ii]
        if vir >= 0:
            cols[5, k] = ys[lo + k, vir]
            cols[6, k] = ys[lo + k, vcur]
    _lanes(cols[0], cols[1], cols[2], cols[3], cols[4], cols[5], cols[6], us[lo:hi],
           _constants(p, stops), _operators(coef), method, substeps, h, arm, filt, fric)
    for k in range(rigs):
        ys[lo + k, 0] = cols[0, k]
        ys[lo + k, 1] = cols[1, k]
        ys[lo + k, 2] = cols[2, k]
        ys[lo + k, 3] = cols[3, k]
        if ii >= 0:
            ys[lo + k, ii] = cols[4, k]
        if vir >= 0:
            ys[lo + k, vir] = cols[5, k]
            ys[lo + k, vcur] = cols[6, k]


class Kernels(NamedTuple):
    """The compiled functions of one layout (:func:`for_layout`)."""

    advance: Callable  # (ys, us, lo, hi, p, stops, method, substeps, h, coef): rows lo..hi
    advance_many: Callable  # (ys, us, p, stops, method, substeps, h, coef): all, in parallel
    # each rig its own constants p and operators (lanes layout) and step hs[k]:
    advance_set: Callable  # (ys, us, lo, hi, p, stops, method, substeps, hs, tables)
    advance_set_many: Callable  # (ys, us, p, stops, method, substeps, hs, tables)


# One set of entry points per layout, and one more with the Coulomb term
# (models.friction = coulomb), written out: the layout's numbers must be
# constants where _advance_rows is inlined. (Closures over the numbers would say this in
# fewer lines, but numba's cache gives closures of one function the same symbol names,
# and two of them loaded into one process corrupted each other: a segfault.)
@_jit
def _advance_full_filters(ys, us, lo, hi, p, stops, method, substeps, h, coef):
    _advance_rows(ys, us, lo, hi, p, stops, method, substeps, h, coef,
                  ARM_FULL, True, 4, 5, 6, False)


@_jit
def _advance_full_filters_coulomb(ys, us, lo, hi, p, stops, method, substeps, h, coef):
    _advance_rows(ys, us, lo, hi, p, stops, method, substeps, h, coef,
                  ARM_FULL, True, 4, 5, 6, True)


@_jit
def _advance_full(ys, us, lo, hi, p, stops, method, substeps, h, coef):
    _advance_rows(ys, us, lo, hi, p, stops, method, substeps, h, coef,
                  ARM_FULL, False, 4, -1, -1, False)


@_jit
def _advance_full_coulomb(ys, us, lo, hi, p, stops, method, substeps, h, coef):
    _advance_rows(ys, us, lo, hi, p, stops, method, substeps, h, coef,
                  ARM_FULL, False, 4, -1, -1, True)


@_jit
def _advance_quasi_static_filters(ys, us, lo, hi, p, stops, method, substeps, h, coef):
    _advance_rows(ys, us, lo, hi, p, stops, method, substeps, h, coef,
                  ARM_QUASI_STATIC, True, -1, 4, 5, False)


@_jit
def _advance_quasi_static_filters_coulomb(ys, us, lo, hi, p, stops, method, substeps, h, coef):
    _advance_rows(ys, us, lo, hi, p, stops, method, substeps, h, coef,
                  ARM_QUASI_STATIC, True, -1, 4, 5, True)


@_jit
def _advance_quasi_static(ys, us, lo, hi, p, stops, method, substeps, h, coef):
    _advance_rows(ys, us, lo, hi, p, stops, method, substeps, h, coef,
                  ARM_QUASI_STATIC, False, -1, -1, -1, False)


@_jit
def _advance_quasi_static_coulomb(ys, us, lo, hi, p, stops, method, substeps, h, coef):
    _advance_rows(ys, us, lo, hi, p, stops, method, substeps, h, coef,
                  ARM_QUASI_STATIC, False, -1, -1, -1, True)


@_jit
def _advance_force_filters(ys, us, lo, hi, p, stops, method, substeps, h, coef):
    _advance_rows(ys, us, lo, hi, p, stops, method, substeps, h, coef,
                  ARM_FORCE, True, -1, 4, 5, False)


@_jit
def _advance_force_filters_coulomb(ys, us, lo, hi, p, stops, method, substeps, h, coef):
    _advance_rows(ys, us, lo, hi, p, stops, method, substeps, h, coef,
                  ARM_FORCE, True, -1, 4, 5, True)


@_jit
def _advance_force(ys, us, lo, hi, p, stops, method, substeps, h, coef):
    _advance_rows(ys, us, lo, hi, p, stops, method, substeps, h, coef,
                  ARM_FORCE, False, -1, -1, -1, False)


@_jit
def _advance_force_coulomb(ys, us, lo, hi, p, stops, method, substeps, h, coef):
    _advance_rows(ys, us, lo, hi, p, stops, method, substeps, h, coef,
                  ARM_FORCE, False, -1, -1, -1, True)


# Rigs per task of the parallel loop: the columns of a task (7 x 256 doubles, 14 KiB)
# stay in the core's first-level cache through the substeps.
CHUNK = 256


@_inline
def _chunks(advance, ys, us, p, stops, method, substeps, h, coef):
    rows = ys.shape[0]
    for c in numba.prange((rows + CHUNK - 1) // CHUNK):
        advance(ys, us, c * CHUNK, min(rows, (c + 1) * CHUNK), p, stops, method, substeps,
                h, coef)


_parallel = numba.njit(cache=True, parallel=True, error_model="numpy")


@_parallel
def _many_full_filters(ys, us, p, stops, method, substeps, h, coef):
    _chunks(_advance_full_filters, ys, us, p, stops, method, substeps, h, coef)


@_parallel
def _many_full_filters_coulomb(ys, us, p, stops, method, substeps, h, coef):
    _chunks(_advance_full_filters_coulomb, ys, us, p, stops, method, substeps, h, coef)


@_parallel
def _many_full(ys, us, p, stops, method, substeps, h, coef):
    _chunks(_advance_full, ys, us, p, stops, method, substeps, h, coef)


@_parallel
def _many_full_coulomb(ys, us, p, stops, method, substeps, h, coef):
    _chunks(_advance_full_coulomb, ys, us, p, stops, method, substeps, h, coef)


@_parallel
def _many_quasi_static_filters(ys, us, p, stops, method, substeps, h, coef):
    _chunks(_advance_quasi_static_filters, ys, us, p, stops, method, substeps, h, coef)


@_parallel
def _many_quasi_static_filters_coulomb(ys, us, p, stops, method, substeps, h, coef):
    _chunks(_advance_quasi_static_filters_coulomb, ys, us, p, stops, method, substeps, h, coef)


@_parallel
def _many_quasi_static(ys, us, p, stops, method, substeps, h, coef):
    _chunks(_advance_quasi_static, ys, us, p, stops, method, substeps, h, coef)


@_parallel
def _many_quasi_static_coulomb(ys, us, p, stops, method, substeps, h, coef):
    _chunks(_advance_quasi_static_coulomb, ys, us, p, stops, method, substeps, h, coef)


@_parallel
def _many_force_filters(ys, us, p, stops, method, substeps, h, coef):
    _chunks(_advance_force_filters, ys, us, p, stops, method, substeps, h, coef)


@_parallel
def _many_force_filters_coulomb(ys, us, p, stops, method, substeps, h, coef):
    _chunks(_advance_force_filters_coulomb, ys, us, p, stops, method, substeps, h, coef)


@_parallel
def _many_force(ys, us, p, stops, method, substeps, h, coef):
    _chunks(_advance_force, ys, us, p, stops, method, substeps, h, coef)


@_parallel
def _many_force_coulomb(ys, us, p, stops, method, substeps, h, coef):
    _chunks(_advance_force_coulomb, ys, us, p, stops, method, substeps, h, coef)


@_inline
def _rhs_into(y, u, p, out, arm, filt, ii, vir, vcur):
    s = (y[0], y[1], y[2], y[3], y[ii] if ii >= 0 else 0.0, y[vir] if vir >= 0 else 0.0,
         y[vcur] if vir >= 0 else 0.0)
    f = _rhs(s, u, _constants(p, True), arm, filt, True)
    out[0] = f[0]
    out[1] = f[1]
    out[2] = f[2]
    out[3] = f[3]
    if ii >= 0:
        out[ii] = f[4]
    if vir >= 0:
        out[vir] = f[5]
        out[vcur] = f[6]


@_jit
def rhs_one(y, u, p, arm, filters, out):
    """Full right-hand side y' into ``out`` for the layout (arm, filters)."""
    if filters:
        if arm == ARM_FULL:
            _rhs_into(y, u, p, out, ARM_FULL, True, 4, 5, 6)
        elif arm == ARM_QUASI_STATIC:
            _rhs_into(y, u, p, out, ARM_QUASI_STATIC, True, -1, 4, 5)
        else:
            _rhs_into(y, u, p, out, ARM_FORCE, True, -1, 4, 5)
    elif arm == ARM_FULL:
        _rhs_into(y, u, p, out, ARM_FULL, False, 4, -1, -1)
    elif arm == ARM_QUASI_STATIC:
        _rhs_into(y, u, p, out, ARM_QUASI_STATIC, False, -1, -1, -1)
    else:
        _rhs_into(y, u, p, out, ARM_FORCE, False, -1, -1, -1)


@_jit
def end_stops(y, p):
    """The end stops on one rig's state array, in place (any layout: they touch x,
    x_dot and theta_dot only)."""
    s = _end_stops((y[0], y[1], y[2], y[3], 0.0, 0.0, 0.0), _constants(p, True))
    y[0] = s[0]
    y[1] = s[1]
    y[3] = s[3]


@_jit
def apply_add(op, v, c, out):
    """:func:`_apply_add` on arrays, full armature and filters (for tests)."""
    o = _apply_add((op[0], op[1], op[2], op[3], op[4], op[5], op[6], op[7], op[8], op[9],
                    op[10], op[11], op[12], op[13]),
                   (v[0], v[1], v[2], v[3], v[4], v[5], v[6], v[7], v[8]),
                   (c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7], c[8], c[9], c[10]),
                   (out[0], out[1], out[2], out[3], out[4], out[5], out[6], out[7], out[8]),
                   True, True)
    for j in range(9):
        out[j] = o[j]


@_jit
def apply_add_n(op, v, c, out):
    """:func:`_apply_add_n` on arrays, full armature and filters (for tests)."""
    o = _apply_add_n((op[0], op[1], op[2], op[3], op[4], op[5], op[6], op[7], op[8], op[9],
                      op[10], op[11], op[12], op[13]),
                     (v[0], v[1], v[2], v[3], v[4], v[5], v[6], v[7], v[8]),
                     (c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7], c[8], c[9], c[10]),
                     (out[0], out[1], out[2], out[3], out[4], out[5], out[6], out[7],
                      out[8]),
                     True, True)
    for j in range(9):
        out[j] = o[j]


# -- plant sets: every rig its own constants and step (pisc_plant.plant.plant_set) --------
#
# The uniform entry points above hold one set of constants and one operator table as
# tuples, in registers. A plant set gives each rig its own: 23 constants, the exponential
# scheme's 13 x 14 operator scalars and a step. They are laid out in blocks of BLOCK
# rigs, each block's quantities row after row (``lanes``: block b holds quantity j of
# its rig l at [b, j * BLOCK + l]), so that the loop over a block's rigs reads each
# quantity from consecutive addresses (vector loads, four rigs at once) at distances the
# compiler knows. Measured while building it (10 000 rigs of the full-fidelity layout,
# one core, on a machine shared with other work: figures varied by +-15 % between runs):
# quantity-major columns over all rigs, (182, rigs), did not vectorise at all (LLVM:
# "too many memory checks needed": every row was a pointer of its own); in blocks of
# 256 rigs, 373 KiB of operators a block, the step took 1.6 to 1.9 times the uniform
# one; in blocks of 16 (23 KiB, in the first-level cache for the later substeps) 1.2 to
# 1.5 times: reading each rig's 1.5 KiB of operators at every call is what a plant set
# costs. (Reading a block through once before stepping it did not help.)

#: Rigs per block of the per-rig constants and operators (``lanes``); a divisor of
#: CHUNK, so that the parallel entry points' chunks start at a block.
BLOCK = 16
N_TABLE = N_OPERATORS * OP_WIDTH  # operator scalars a rig
FACTORIAL = np.array([float(math.factorial(k)) for k in range(10)])


def lanes(a: np.ndarray) -> np.ndarray:
    """Per-rig quantities ``a`` (m, rigs) in the kernel's block layout, (blocks, m * BLOCK):
    quantity j of rig k at ``[k // BLOCK, j * BLOCK + k % BLOCK]`` (the last block padded
    with zeros)."""
    m, rigs = a.shape
    blocks = -(-rigs // BLOCK)
    out = np.zeros((blocks, m, BLOCK))
    full = rigs // BLOCK
    out[:full] = a[:, :full * BLOCK].reshape(m, full, BLOCK).transpose(1, 0, 2)
    if full < blocks:
        out[full, :, :rigs - full * BLOCK] = a[:, full * BLOCK:]
    return out.reshape(blocks, m * BLOCK)


def from_lanes(a: np.ndarray, rigs: int) -> np.ndarray:
    """The inverse of :func:`lanes`: (blocks, m * BLOCK) -> (m, rigs)."""
    blocks = a.shape[0]
    m = a.shape[1] // BLOCK
    return a.reshape(blocks, m, BLOCK).transpose(1, 0, 2).reshape(m, blocks * BLOCK)[:, :rigs]


@_jit
def _phi(k, z):
    """:func:`phi` compiled, with the same arithmetic (the same bits)."""
    if abs(z) < 2.0:
        total = 0.0
        term = INV_FACTORIAL[k]
        for j in range(40):
            total += term
            term *= z / (j + k + 1)
        return total
    value = math.exp(z)
    for j in range(k):
        value = (value - INV_FACTORIAL[j]) / z
    return value


@_jit
def _step_operators(w_ir, w_cur, c_v, step_s, table, phi_ir):
    """The part of :func:`exp_coefficients`' table that does not depend on the armature's
    rate (rows 0-12 of OP_D0, OP_D1, OP_DIR, OP_DCUR and rows 13, 14), into ``table``,
    with the same arithmetic in the same order (the same bits)."""
    h = step_s
    table[:, :] = 0.0
    for si in range(2):
        s = STAGE_FRACTIONS[si]
        for k in range(4):
            table[ROW_PHI_CUR, 4 * si + k] = _phi(k, -s * h * w_cur)
            phi_ir[si, k] = _phi(k, -(s * h) * w_ir)
    for op in range(N_OPERATORS):
        scale = 1.0 if op < 2 else h
        for si in range(2):
            sh = STAGE_FRACTIONS[si] * h
            for k in range(4):
                alpha = scale * OP_WEIGHTS[op, si, k]
                if alpha == 0.0:
                    continue
                table[op, OP_D0] += alpha / FACTORIAL[k]
                table[op, OP_D1] += alpha * sh / FACTORIAL[k + 1]
                table[op, OP_DIR] += alpha * phi_ir[si, k]
                table[op, OP_DCUR] += alpha * table[ROW_PHI_CUR, 4 * si + k]
    table[ROW_CONST, 0] = c_v
    table[ROW_CONST, 1] = w_cur
    table[ROW_CONST, 2] = h


@_parallel
def exp_tables(w_ir, w_cur, c_v, lam, steps, out):
    """:func:`exp_coefficients` of every rig k (rates ``lam[k]``, step ``steps[k]``;
    ``w_ir``, ``w_cur``, ``c_v`` are common), rows 0-12 into ``out`` in the layout of
    :func:`lanes` ((blocks, N_TABLE * BLOCK), operator scalar ``op * OP_WIDTH + j``):
    the same numbers, bit for bit. A rig whose step (and rate) equals the previous rig's
    reuses its work."""
    rigs = lam.shape[0]
    for b in numba.prange(out.shape[0]):
        table = np.zeros((15, OP_WIDTH))
        phi_ir = np.empty((2, 4))
        ph = np.empty((2, 8))
        for lane in range(min(BLOCK, rigs - b * BLOCK)):
            k = b * BLOCK + lane
            same_step = lane > 0 and steps[k] == steps[k - 1]
            if not (same_step and lam[k] == lam[k - 1]):
                if not same_step or lam[k] == 0.0:
                    _step_operators(w_ir, w_cur, c_v, steps[k], table, phi_ir)  # zeroes
                if lam[k] != 0.0:
                    _armature_operators(lam[k], table, ph)
            for op in range(N_OPERATORS):
                for j in range(OP_WIDTH):
                    out[b, (op * OP_WIDTH + j) * BLOCK + lane] = table[op, j]


@_jit
def armature_rates(p, out):
    """:func:`armature_rate` of each column of the constants ``p`` (N_CONSTANTS, rigs)."""
    for k in range(out.shape[0]):
        out[k] = armature_rate(p[:, k])


@_inline
def _constants_at(a, k, stops):
    """Rig k's constants in a block of :func:`lanes` (see :func:`_constants`)."""
    return (a[k], a[BLOCK + k], a[2 * BLOCK + k], a[3 * BLOCK + k], a[4 * BLOCK + k],
            a[5 * BLOCK + k], a[6 * BLOCK + k], a[7 * BLOCK + k], a[8 * BLOCK + k],
            a[9 * BLOCK + k], a[10 * BLOCK + k], a[11 * BLOCK + k], a[12 * BLOCK + k],
            a[13 * BLOCK + k], a[14 * BLOCK + k], a[15 * BLOCK + k], a[16 * BLOCK + k],
            a[17 * BLOCK + k], a[18 * BLOCK + k], a[19 * BLOCK + k],
            a[P_XMIN * BLOCK + k] if stops else -np.inf,
            a[P_XMAX * BLOCK + k] if stops else np.inf, a[22 * BLOCK + k])


@_inline
def _operator_at(t, op, k):
    b = op * OP_WIDTH * BLOCK + k
    return (t[b], t[b + BLOCK], t[b + 2 * BLOCK], t[b + 3 * BLOCK], t[b + 4 * BLOCK],
            t[b + 5 * BLOCK], t[b + 6 * BLOCK], t[b + 7 * BLOCK], t[b + 8 * BLOCK],
            t[b + 9 * BLOCK], t[b + 10 * BLOCK], t[b + 11 * BLOCK], t[b + 12 * BLOCK],
            t[b + 13 * BLOCK])


@_inline
def _operators_at(t, k):
    """Rig k's operator table in a block of :func:`lanes` (see :func:`_operators`)."""
    return (_operator_at(t, 0, k), _operator_at(t, 1, k), _operator_at(t, 2, k),
            _operator_at(t, 3, k), _operator_at(t, 4, k), _operator_at(t, 5, k),
            _operator_at(t, 6, k), _operator_at(t, 7, k), _operator_at(t, 8, k),
            _operator_at(t, 9, k), _operator_at(t, 10, k), _operator_at(t, 11, k),
            _operator_at(t, 12, k))


@_inline
def _state_at(b, k):
    return (b[k], b[BLOCK + k], b[2 * BLOCK + k], b[3 * BLOCK + k], b[4 * BLOCK + k],
            b[5 * BLOCK + k], b[6 * BLOCK + k])


@_inline
def _put_at(y, old, moved, b, k):
    """Rig k's new state into the block's columns, or its old one if it did not move (a
    select, not a branch)."""
    b[k] = y[0] if moved else old[0]
    b[BLOCK + k] = y[1] if moved else old[1]
    b[2 * BLOCK + k] = y[2] if moved else old[2]
    b[3 * BLOCK + k] = y[3] if moved else old[3]
    b[4 * BLOCK + k] = y[4] if moved else old[4]
    b[5 * BLOCK + k] = y[5] if moved else old[5]
    b[6 * BLOCK + k] = y[6] if moved else old[6]


@_jit
def _lanes_set(b, us, hs, p, stops, ops, method, substeps, arm, filt, fric):
    """:func:`_lanes` for one block of a plant set: the rigs' states are the columns of
    ``b`` (component j of rig k at ``b[j * BLOCK + k]``), their constants ``p`` and
    operators ``ops`` blocks of :func:`lanes`, their steps ``hs`` (rk4 steps by them;
    exprk4's steps are in its operators). A rig whose step is 0 keeps its state.

    Every index is a multiple of BLOCK plus the rig, so the compiler sees each array as
    one object read at known distances, and the run-time checks of overlap it needs
    before it vectorises are few (one array per quantity were too many).
    """
    numba.literally(arm)
    numba.literally(filt)
    numba.literally(fric)
    rigs = us.shape[0]
    if method == RK4:
        for _ in range(substeps):
            for k in range(rigs):
                h = hs[k]
                y0 = _state_at(b, k)
                pk = _constants_at(p, k, stops)
                y = _end_stops(_rk4(y0, us[k], pk, h, arm, filt, fric), pk)
                _put_at(y, y0, h > 0.0, b, k)
    else:
        for _ in range(substeps):
            for k in range(rigs):
                y0 = _state_at(b, k)
                pk = _constants_at(p, k, stops)
                y = _end_stops(_exprk4(y0, us[k], pk, _operators_at(ops, k), arm, filt,
                                       fric), pk)
                _put_at(y, y0, hs[k] > 0.0, b, k)


@_inline
def _advance_set_rows(ys, us, lo, hi, p, stops, method, substeps, hs, tables, arm, filt, ii,
                      vir, vcur):
    """Advance rows lo..hi of ys (lo a multiple of BLOCK) in place, block by block, each
    rig with its own constants (``p``) and step (``hs``, and ``tables`` for exprk4), both
    in the layout of :func:`lanes`."""
    cols = np.zeros(7 * BLOCK)
    for start in range(lo, hi, BLOCK):
        rigs = min(hi - start, BLOCK)
        block = start // BLOCK
        for k in range(rigs):
            cols[k] = ys[start + k, 0]
            cols[BLOCK + k] = ys[start + k, 1]
            cols[2 * BLOCK + k] = ys[start + k, 2]
            cols[3 * BLOCK + k] = ys[start + k, 3]
            if ii >= 0:
                cols[4 * BLOCK + k] = ys[start + k, ii]
            if vir >= 0:
                cols[5 * BLOCK + k] = ys[start + k, vir]
                cols[6 * BLOCK + k] = ys[start + k, vcur]
        _lanes_set(cols, us[start:start + rigs], hs[start:start + rigs], p[block], stops,
                   tables[block], method, substeps, arm, filt, True)
        for k in range(rigs):
            ys[start + k, 0] = cols[k]
            ys[start + k, 1] = cols[BLOCK + k]
            ys[start + k, 2] = cols[2 * BLOCK + k]
            ys[start + k, 3] = cols[3 * BLOCK + k]
            if ii >= 0:
                ys[start + k, ii] = cols[4 * BLOCK + k]
            if vir >= 0:
                ys[start + k, vir] = cols[5 * BLOCK + k]
                ys[start + k, vcur] = cols[6 * BLOCK + k]


# One row-range and one parallel entry point per layout, as above.
@_jit
def _set_full_filters(ys, us, lo, hi, p, stops, method, substeps, hs, tables):
    _advance_set_rows(ys, us, lo, hi, p, stops, method, substeps, hs, tables, ARM_FULL, True,
                      4, 5, 6)


@_jit
def _set_full(ys, us, lo, hi, p, stops, method, substeps, hs, tables):
    _advance_set_rows(ys, us, lo, hi, p, stops, method, substeps, hs, tables, ARM_FULL, False,
                      4, -1, -1)


@_jit
def _set_quasi_static_filters(ys, us, lo, hi, p, stops, method, substeps, hs, tables):
    _advance_set_rows(ys, us, lo, hi, p, stops, method, substeps, hs, tables,
                      ARM_QUASI_STATIC, True, -1, 4, 5)


@_jit
def _set_quasi_static(ys, us, lo, hi, p, stops, method, substeps, hs, tables):
    _advance_set_rows(ys, us, lo, hi, p, stops, method, substeps, hs, tables,
                      ARM_QUASI_STATIC, False, -1, -1, -1)


@_jit
def _set_force_filters(ys, us, lo, hi, p, stops, method, substeps, hs, tables):
    _advance_set_rows(ys, us, lo, hi, p, stops, method, substeps, hs, tables, ARM_FORCE, True,
                      -1, 4, 5)


@_jit
def _set_force(ys, us, lo, hi, p, stops, method, substeps, hs, tables):
    _advance_set_rows(ys, us, lo, hi, p, stops, method, substeps, hs, tables, ARM_FORCE, False,
                      -1, -1, -1)


@_inline
def _set_chunks(advance, ys, us, p, stops, method, substeps, hs, tables):
    rows = ys.shape[0]
    for c in numba.prange((rows + CHUNK - 1) // CHUNK):
        advance(ys, us, c * CHUNK, min(rows, (c + 1) * CHUNK), p, stops, method, substeps,
                hs, tables)


@_parallel
def _many_set_full_filters(ys, us, p, stops, method, substeps, hs, tables):
    _set_chunks(_set_full_filters, ys, us, p, stops, method, substeps, hs, tables)


@_parallel
def _many_set_full(ys, us, p, stops, method, substeps, hs, tables):
    _set_chunks(_set_full, ys, us, p, stops, method, substeps, hs, tables)


@_parallel
def _many_set_quasi_static_filters(ys, us, p, stops, method, substeps, hs, tables):
    _set_chunks(_set_quasi_static_filters, ys, us, p, stops, method, substeps, hs, tables)


@_parallel
def _many_set_quasi_static(ys, us, p, stops, method, substeps, hs, tables):
    _set_chunks(_set_quasi_static, ys, us, p, stops, method, substeps, hs, tables)


@_parallel
def _many_set_force_filters(ys, us, p, stops, method, substeps, hs, tables):
    _set_chunks(_set_force_filters, ys, us, p, stops, method, substeps, hs, tables)


@_parallel
def _many_set_force(ys, us, p, stops, method, substeps, hs, tables):
    _set_chunks(_set_force, ys, us, p, stops, method, substeps, hs, tables)


_SET_POINTS = {
    (ARM_FULL, True): (_set_full_filters, _many_set_full_filters),
    (ARM_FULL, False): (_set_full, _many_set_full),
    (ARM_QUASI_STATIC, True): (_set_quasi_static_filters, _many_set_quasi_static_filters),
    (ARM_QUASI_STATIC, False): (_set_quasi_static, _many_set_quasi_static),
    (ARM_FORCE, True): (_set_force_filters, _many_set_force_filters),
    (ARM_FORCE, False): (_set_force, _many_set_force),
}
# (armature, filters, Coulomb friction): the uniform entry points; a plant set's above
# take the Coulomb term always (each rig has its own F_c)
_ENTRY_POINTS = {
    (ARM_FULL, True, False): (_advance_full_filters, _many_full_filters),
    (ARM_FULL, True, True): (_advance_full_filters_coulomb, _many_full_filters_coulomb),
    (ARM_FULL, False, False): (_advance_full, _many_full),
    (ARM_FULL, False, True): (_advance_full_coulomb, _many_full_coulomb),
    (ARM_QUASI_STATIC, True, False): (_advance_quasi_static_filters,
                                      _many_quasi_static_filters),
    (ARM_QUASI_STATIC, True, True): (_advance_quasi_static_filters_coulomb,
                                     _many_quasi_static_filters_coulomb),
    (ARM_QUASI_STATIC, False, False): (_advance_quasi_static, _many_quasi_static),
    (ARM_QUASI_STATIC, False, True): (_advance_quasi_static_coulomb,
                                      _many_quasi_static_coulomb),
    (ARM_FORCE, True, False): (_advance_force_filters, _many_force_filters),
    (ARM_FORCE, True, True): (_advance_force_filters_coulomb, _many_force_filters_coulomb),
    (ARM_FORCE, False, False): (_advance_force, _many_force),
    (ARM_FORCE, False, True): (_advance_force_coulomb, _many_force_coulomb),
}


def for_layout(layout: Layout) -> Kernels:
    """The kernels of a layout (each compiled on its first use, or loaded from cache;
    :func:`pisc_plant.warm.warm_up` compiles the uniform ones, not those of plant sets)."""
    return Kernels(*_ENTRY_POINTS[(layout.armature, layout.filters, layout.coulomb)],
                   *_SET_POINTS[(layout.armature, layout.filters)])
