"""Compiled right-hand side and integrators of the plant (numba).

One kernel serves every scene: the state carries only the components a scene's
sub-models need (:class:`Layout`), the constants travel in one float array
(:func:`pisc_plant.plant.pack_constants`), and the same compiled step advances one rig
in a node or ten thousand in a batch (:func:`for_layout` gives a layout's entry points;
the batch one runs the single-rig one on each row, in parallel), so a rig gives
bit-identical results alone and in a batch.

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
from dataclasses import dataclass
from typing import NamedTuple

import numba
import numpy as np

__all__ = [
    "METHODS",
    "Kernels",
    "Layout",
    "armature_rate",
    "end_stops",
    "exp_coefficients",
    "for_layout",
    "phi",
    "rhs_one",
    "warm_up",
]

METHODS = ("rk4", "exprk4")
RK4, EXPRK4 = 0, 1

ARM_FULL, ARM_QUASI_STATIC, ARM_FORCE = 0, 1, 2

# Indices into the packed constants.
(P_A1, P_A2, P_ML, P_G, P_KF, P_BM, P_R, P_L, P_KER, P_BC, P_BP, P_FC, P_VC, P_WIR,
 P_WCUR, P_IRO, P_IRS, P_IRX, P_CUROFF, P_CURSCALE, P_XMIN, P_XMAX, P_JROT) = range(23)
N_CONSTANTS = 23


@dataclass(frozen=True)
class Layout:
    """Which components a scene's state has, and where."""

    armature: int  # ARM_FULL, ARM_QUASI_STATIC or ARM_FORCE
    filters: bool
    end_stops: bool

    @property
    def current_index(self) -> int:
        return 4 if self.armature == ARM_FULL else -1

    @property
    def ir_index(self) -> int:
        return (5 if self.armature == ARM_FULL else 4) if self.filters else -1

    @property
    def current_sensor_index(self) -> int:
        return self.ir_index + 1 if self.filters else -1

    @property
    def size(self) -> int:
        return 4 + (self.armature == ARM_FULL) + 2 * self.filters


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
    """
    h = step_s
    table = np.zeros((15, OP_WIDTH))
    phi_cur = np.array([[phi(k, -s * h * w_cur) for k in range(4)] for s in STAGE_FRACTIONS])
    for op, weights in enumerate(OP_WEIGHTS):
        scale = 1.0 if op < 2 else h
        for si, s in enumerate(STAGE_FRACTIONS):
            sh = s * h
            for k in range(4):
                alpha = scale * weights[si, k]
                if alpha == 0.0:
                    continue
                table[op, OP_D0] += alpha / math.factorial(k)
                table[op, OP_D1] += alpha * sh / math.factorial(k + 1)
                table[op, OP_DIR] += alpha * phi(k, -sh * w_ir)
                table[op, OP_DCUR] += alpha * phi_cur[si, k]
    table[ROW_PHI_CUR, 0:4] = phi_cur[0]
    table[ROW_PHI_CUR, 4:8] = phi_cur[1]
    table[ROW_CONST, 0:3] = (c_v, w_cur, h)
    if lam != 0.0:
        _armature_operators(lam, table, np.empty((2, 8)))
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


# The kernel's hot functions take the layout as arguments that are constants where they
# are inlined (``arm``; the indices ``ii`` of the current, ``vir``, ``vcur`` of the
# filters, -1 when absent; ``n`` the state's size): :func:`for_layout` compiles one set
# of entry points per layout, and the compiler removes the branches and index
# arithmetic of the others. Measured while building it (the generic version is not
# kept): the full-fidelity right-hand side took 41 ns per evaluation, against 164 ns with
# the layout read from an array (one core, 10 000 rigs).


@_inline
def _current(y, u, p, arm, ii):
    if arm == ARM_FULL:
        current = y[ii]
    elif arm == ARM_QUASI_STATIC:
        current = (u - p[P_KER] * y[1]) / p[P_R]
    else:
        current = u / p[P_KF]  # the current an ideal motor would need for force u
    return current


@_inline
def _accelerations(y, u, p, arm, current):
    """x_ddot, theta_ddot: (3.3), (3.5) with cart and pivot friction."""
    return _accelerations_at(y, u, p, arm, current, math.sin(y[2]), math.cos(y[2]))


@_inline
def _accelerations_at(y, u, p, arm, current, s, c):
    """:func:`_accelerations` with sin and cos of the angle given."""
    x_dot = y[1]
    theta_dot = y[3]
    if arm == ARM_FORCE:
        force = u
    else:
        # (4.2) and the rotor's viscous friction reflected to the cart
        force = p[P_KF] * current - p[P_BM] * x_dot
    force -= p[P_BC] * x_dot
    if p[P_FC] != 0.0:
        force -= p[P_FC] * math.tanh(x_dot / p[P_VC])
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
    return (distance / p[P_IRS]) ** p[P_IRX]


@_inline
def _current_sensor_voltage(p, current):
    return (current + p[P_CUROFF]) / p[P_CURSCALE]


@_inline
def _rhs(y, u, p, out, arm, ii, vir, vcur):
    current = _current(y, u, p, arm, ii)
    x_ddot, theta_ddot = _accelerations(y, u, p, arm, current)
    out[0] = y[1]
    out[1] = x_ddot
    out[2] = y[3]
    out[3] = theta_ddot
    if arm == ARM_FULL:
        # (2.81): L di/dt = u - R i - k_e phi_dot
        out[ii] = (u - p[P_R] * current - p[P_KER] * y[1]) / p[P_L]
    if vir >= 0:
        out[vir] = p[P_WIR] * (_ir_voltage(p, y[0]) - y[vir])
        out[vcur] = p[P_WCUR] * (_current_sensor_voltage(p, current) - y[vcur])


@_inline
def _couplings(z, y, u, p, c, arm, ii):
    """L's couplings at the step's start, into c: c_x, c_theta (0, 1), c_x1, c_theta1 (2,
    3), the rate of q (4), the current sensor's share of q (5), the accelerations (6, 7),
    c_x2, c_theta2 (8, 9), delta (10).

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
        for j in range(11):
            c[j] = 0.0
        return
    co = math.cos(z[2])
    si = math.sin(z[2])
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
    x_ddot, theta_ddot = _accelerations_at(y, u, p, arm, y[ii], si, co)
    c[6] = x_ddot
    c[7] = theta_ddot
    # the slow motion: without q's own share (q0 = q at the start, mostly the transient)
    q0 = z[ii]
    x_ddot_slow = x_ddot - cx * q0
    theta_ddot_slow = theta_ddot - cth * q0
    force = kf * (y[ii] - q0) - (p[P_BM] + p[P_BC]) * y[1]
    if p[P_FC] != 0.0:
        force -= p[P_FC] * math.tanh(y[1] / p[P_VC])
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
    c[0] = c0
    c[1] = c1
    c[2] = cx_1 * (theta_dot + shift)
    c[3] = cth_1 * (theta_dot + shift)
    # s = t^2 q / 2: the second-order change of c_x, c_theta during the step
    c[8] = cx_1 * theta_ddot_slow + cx_2 * theta_dot * theta_dot
    c[9] = cth_1 * theta_ddot_slow + cth_2 * theta_dot * theta_dot
    c[4] = armature_rate(p)
    c[5] = 1.0 - d * c[0] / c[4]
    # The state's own rate of q differs from L's by delta (about 0.005 1/s). The
    # current's departure is q + delta r in the scheme's variables (q e^(delta t) to first
    # order), so the velocities see delta c r besides c q.
    delta = -p[P_R] / p[P_L] + d * c[0] - c[4]
    c[10] = delta
    c[2] += delta * c[0]
    c[3] += delta * c[1]


@_inline
def _apply_add(op, v, c, out, ii, ri, vir, vcur):
    """out += F(hL) v for one operator's scalars (see ``OP_*``); r at ``ri``, s after it."""
    d0 = op[OP_D0]
    d1 = op[OP_D1]
    out[0] += d0 * v[0] + d1 * v[1]
    out[1] += d0 * v[1]
    out[2] += d0 * v[2] + d1 * v[3]
    out[3] += d0 * v[3]
    q = 0.0
    if ii >= 0:
        q = v[ii]
        r = v[ri]
        s = v[ri + 1]
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
        out[0] += c[0] * p_q + c[2] * p_r + c[8] * p_s
        out[1] += c[0] * v_q + c[2] * v_r + c[8] * v_s
        out[2] += c[1] * p_q + c[3] * p_r + c[9] * p_s
        out[3] += c[1] * v_q + c[3] * v_r + c[9] * v_s
        dq = op[OP_DQ]
        er = op[OP_ER]
        out[ii] += dq * q
        out[ri] += dq * r + er * q
        out[ri + 1] += dq * s + er * r + op[OP_ES] * q
    if vir >= 0:
        out[vir] += op[OP_DIR] * v[vir]
        out[vcur] += op[OP_DCUR] * v[vcur] + op[OP_ECUR] * c[5] * q


@_inline
def _apply_add_n(op, v, c, out, ii, ri, vir, vcur):
    """:func:`_apply_add` for a vector N of the nonlinear part, whose x, theta, r and s
    components are zero (the positions' derivatives and the chain's are all in L)."""
    d1 = op[OP_D1]
    out[0] += d1 * v[1]
    out[1] += op[OP_D0] * v[1]
    out[2] += d1 * v[3]
    out[3] += op[OP_D0] * v[3]
    q = 0.0
    if ii >= 0:
        q = v[ii]
        v_q = c[0] * op[OP_E1] + c[2] * op[OP_E3] + c[8] * op[OP_E5]
        p_q = c[0] * op[OP_E2] + c[2] * op[OP_E4] + c[8] * op[OP_E6]
        vth_q = c[1] * op[OP_E1] + c[3] * op[OP_E3] + c[9] * op[OP_E5]
        pth_q = c[1] * op[OP_E2] + c[3] * op[OP_E4] + c[9] * op[OP_E6]
        out[0] += p_q * q
        out[1] += v_q * q
        out[2] += pth_q * q
        out[3] += vth_q * q
        out[ii] += op[OP_DQ] * q
        out[ri] += op[OP_ER] * q
        out[ri + 1] += op[OP_ES] * q
    if vir >= 0:
        out[vir] += op[OP_DIR] * v[vir]
        out[vcur] += op[OP_DCUR] * v[vcur] + op[OP_ECUR] * c[5] * q


@_jit
def apply_add(op, v, c, out, ii, ri, vir, vcur):
    """:func:`_apply_add` with the layout's indices as arguments (for tests)."""
    _apply_add(op, v, c, out, ii, ri, vir, vcur)


@_jit
def apply_add_n(op, v, c, out, ii, ri, vir, vcur):
    """:func:`_apply_add_n` with the layout's indices as arguments (for tests)."""
    _apply_add_n(op, v, c, out, ii, ri, vir, vcur)


@_inline
def _nonlinear(z, u, p, c, y, out, arm, ii, vir, vcur, n, at_start):
    """N(z) = f(z) - L z in the exponential scheme's variables (q for i, plus r).

    ``y`` is scratch for the state in the original variables. ``at_start``: z is the
    step's start, whose accelerations :func:`_couplings` left in c[6], c[7].
    """
    for j in range(n):
        y[j] = z[j]
    q = 0.0
    r = 0.0
    s = 0.0
    if arm == ARM_FULL:
        q = z[ii]
        r = z[n]
        s = z[n + 1]
        y[ii] = q + c[10] * r + (u - p[P_KER] * z[1]) / p[P_R]
    current = _current(y, u, p, arm, ii)
    if at_start and arm == ARM_FULL:
        x_ddot = c[6]
        theta_ddot = c[7]
    else:
        x_ddot, theta_ddot = _accelerations(y, u, p, arm, current)
    out[0] = 0.0
    out[1] = x_ddot - c[0] * q - c[2] * r - c[8] * s
    out[2] = 0.0
    out[3] = theta_ddot - c[1] * q - c[3] * r - c[9] * s
    if arm == ARM_FULL:
        # with Q = q + delta r the current's departure, Q' = -(R/L) Q + d x_ddot; L gives
        # lam Q + delta q, so N's share is d (x_ddot - c_x Q) + delta^2 r
        d = p[P_KER] / p[P_R]
        delta = c[10]
        out[ii] = d * (x_ddot - c[0] * (q + delta * r)) + delta * delta * r
        out[n] = 0.0
        out[n + 1] = 0.0
    if vir >= 0:
        out[vir] = p[P_WIR] * _ir_voltage(p, y[0])
        # v_cur' = w_cur ((i + offset) / scale - v_cur); L holds c_v c[5] q
        out[vcur] = p[P_WCUR] * _current_sensor_voltage(p, current - c[5] * q)


@_inline
def end_stops(y, p):
    """Perfectly inelastic end stops (see :meth:`pisc_plant.plant.Plant.end_stops`)."""
    x = y[0]
    if x >= p[P_XMIN] and x <= p[P_XMAX]:
        return
    x_dot = y[1]
    if (x < p[P_XMIN] and x_dot < 0.0) or (x > p[P_XMAX] and x_dot > 0.0):
        y[3] = y[3] + p[P_ML] * math.cos(y[2]) * x_dot / p[P_JROT]
        y[1] = 0.0
    y[0] = min(max(x, p[P_XMIN]), p[P_XMAX])


# Work rows: 0..4 the N's of the stages, then a stage's state, scratch, the state z at
# the step's start, the new state, e^(hL/2) z, e^(hL) z, the couplings, N2 + N3.
TMP_ROW, SCRATCH_ROW, Z_ROW, NEW_ROW, EZ2_ROW, EZ_ROW, C_ROW, SUM_ROW = range(5, 13)
WORK_ROWS = 13
WORK_WIDTH = 12
# Rows of the operator table (see OP_WEIGHTS)
(T_E, T_E2, T_A21, T_A31, T_A32, T_A41, T_A42, T_A51, T_A52, T_A54, T_B1, T_B4,
 T_B5) = range(N_OPERATORS)


@_inline
def _advance(y, u, p, stops, method, substeps, h, coef, work, arm, ii, vir, vcur, n):
    k1 = work[0]
    k2 = work[1]
    k3 = work[2]
    k4 = work[3]
    tmp = work[TMP_ROW]
    if method == RK4:
        for _ in range(substeps):
            _rhs(y, u, p, k1, arm, ii, vir, vcur)
            for j in range(n):
                tmp[j] = y[j] + 0.5 * h * k1[j]
            _rhs(tmp, u, p, k2, arm, ii, vir, vcur)
            for j in range(n):
                tmp[j] = y[j] + 0.5 * h * k2[j]
            _rhs(tmp, u, p, k3, arm, ii, vir, vcur)
            for j in range(n):
                tmp[j] = y[j] + h * k3[j]
            _rhs(tmp, u, p, k4, arm, ii, vir, vcur)
            for j in range(n):
                y[j] = y[j] + (h / 6.0) * (k1[j] + 2.0 * k2[j] + 2.0 * k3[j] + k4[j])
            if stops:
                end_stops(y, p)
        return
    full = arm == ARM_FULL
    ri = n if full else -1
    m = n + 2 if full else n  # r and s join the state
    z = work[Z_ROW]
    c = work[C_ROW]
    scratch = work[SCRATCH_ROW]
    n1 = work[0]
    n2 = work[1]
    n3 = work[2]
    n4 = work[3]
    n5 = work[4]
    ez2 = work[EZ2_ROW]
    ez = work[EZ_ROW]
    sum23 = work[SUM_ROW]
    new = work[NEW_ROW]
    for _ in range(substeps):
        for j in range(n):
            z[j] = y[j]
        if full:
            z[ii] -= (u - p[P_KER] * y[1]) / p[P_R]
            z[n] = 0.0
            z[n + 1] = 0.0
        _couplings(z, y, u, p, c, arm, ii)
        _nonlinear(z, u, p, c, scratch, n1, arm, ii, vir, vcur, n, True)
        if full:
            # r starts at its slow value N_q / lam^2, so that r carries t q only for the
            # transient: from r = 0 the slow part of q would start a fast transient in r
            # that the explicit terms (c_x1 r in N) cannot follow
            lam = c[4]
            r0 = n1[ii] / (lam * lam)
            s0 = -r0 / lam
            z[n] = r0
            z[n + 1] = s0
            z[ii] -= c[10] * r0  # the current's departure q + delta r stays
            n1[1] -= c[2] * r0 + c[8] * s0
            n1[3] -= c[3] * r0 + c[9] * s0
        # the scheme (5.19): U2 = e^(hL/2) z + a21 N1; U3 = e^(hL/2) z + a31 N1 + a32 N2;
        # U4 = e^(hL) z + a41 N1 + a42 (N2 + N3);
        # U5 = e^(hL/2) z + a51 N1 + a52 (N2 + N3) + a54 N4;
        # z_new = e^(hL) z + b1 N1 + b4 N4 + b5 N5
        for j in range(m):
            ez2[j] = 0.0
            ez[j] = 0.0
        _apply_add(coef[T_E2], z, c, ez2, ii, ri, vir, vcur)
        _apply_add(coef[T_E], z, c, ez, ii, ri, vir, vcur)
        for j in range(m):
            tmp[j] = ez2[j]
        _apply_add_n(coef[T_A21], n1, c, tmp, ii, ri, vir, vcur)
        _nonlinear(tmp, u, p, c, scratch, n2, arm, ii, vir, vcur, n, False)
        for j in range(m):
            tmp[j] = ez2[j]
        _apply_add_n(coef[T_A31], n1, c, tmp, ii, ri, vir, vcur)
        _apply_add_n(coef[T_A32], n2, c, tmp, ii, ri, vir, vcur)
        _nonlinear(tmp, u, p, c, scratch, n3, arm, ii, vir, vcur, n, False)
        for j in range(m):
            sum23[j] = n2[j] + n3[j]
            tmp[j] = ez[j]
        _apply_add_n(coef[T_A41], n1, c, tmp, ii, ri, vir, vcur)
        _apply_add_n(coef[T_A42], sum23, c, tmp, ii, ri, vir, vcur)
        _nonlinear(tmp, u, p, c, scratch, n4, arm, ii, vir, vcur, n, False)
        for j in range(m):
            tmp[j] = ez2[j]
        _apply_add_n(coef[T_A51], n1, c, tmp, ii, ri, vir, vcur)
        _apply_add_n(coef[T_A52], sum23, c, tmp, ii, ri, vir, vcur)
        _apply_add_n(coef[T_A54], n4, c, tmp, ii, ri, vir, vcur)
        _nonlinear(tmp, u, p, c, scratch, n5, arm, ii, vir, vcur, n, False)
        for j in range(m):
            new[j] = ez[j]
        _apply_add_n(coef[T_B1], n1, c, new, ii, ri, vir, vcur)
        _apply_add_n(coef[T_B4], n4, c, new, ii, ri, vir, vcur)
        _apply_add_n(coef[T_B5], n5, c, new, ii, ri, vir, vcur)
        for j in range(n):
            y[j] = new[j]
        if full:
            y[ii] += c[10] * new[n] + (u - p[P_KER] * y[1]) / p[P_R]
        if stops:
            end_stops(y, p)


class Kernels(NamedTuple):
    """The compiled functions of one layout (:func:`for_layout`)."""

    advance: Callable  # (y, u, p, stops, method, substeps, h, coef, work)
    advance_many: Callable  # (ys, us, p, stops, method, substeps, h, coef)


# One set of entry points per layout, written out: the layout's numbers must be
# constants where _advance and _rhs are inlined. (Closures over the numbers would say
# this in fewer lines, but numba's cache gives closures of one function the same symbol
# names, and two of them loaded into one process corrupted each other: a segfault.)
@_jit
def _advance_full_filters(y, u, p, stops, method, substeps, h, coef, work):
    _advance(y, u, p, stops, method, substeps, h, coef, work, ARM_FULL, 4, 5, 6, 7)


@_jit
def _advance_full(y, u, p, stops, method, substeps, h, coef, work):
    _advance(y, u, p, stops, method, substeps, h, coef, work, ARM_FULL, 4, -1, -1, 5)


@_jit
def _advance_quasi_static_filters(y, u, p, stops, method, substeps, h, coef, work):
    _advance(y, u, p, stops, method, substeps, h, coef, work, ARM_QUASI_STATIC, -1, 4, 5, 6)


@_jit
def _advance_quasi_static(y, u, p, stops, method, substeps, h, coef, work):
    _advance(y, u, p, stops, method, substeps, h, coef, work, ARM_QUASI_STATIC, -1, -1, -1, 4)


@_jit
def _advance_force_filters(y, u, p, stops, method, substeps, h, coef, work):
    _advance(y, u, p, stops, method, substeps, h, coef, work, ARM_FORCE, -1, 4, 5, 6)


@_jit
def _advance_force(y, u, p, stops, method, substeps, h, coef, work):
    _advance(y, u, p, stops, method, substeps, h, coef, work, ARM_FORCE, -1, -1, -1, 4)


@_inline
def _rows(advance, ys, us, p, stops, method, substeps, h, coef):
    rows = ys.shape[0]
    chunk = 64
    for c in numba.prange((rows + chunk - 1) // chunk):
        work = np.empty((WORK_ROWS, WORK_WIDTH))
        for row in range(c * chunk, min(rows, (c + 1) * chunk)):
            advance(ys[row], us[row], p, stops, method, substeps, h, coef, work)


_parallel = numba.njit(cache=True, parallel=True, error_model="numpy")


@_parallel
def _many_full_filters(ys, us, p, stops, method, substeps, h, coef):
    _rows(_advance_full_filters, ys, us, p, stops, method, substeps, h, coef)


@_parallel
def _many_full(ys, us, p, stops, method, substeps, h, coef):
    _rows(_advance_full, ys, us, p, stops, method, substeps, h, coef)


@_parallel
def _many_quasi_static_filters(ys, us, p, stops, method, substeps, h, coef):
    _rows(_advance_quasi_static_filters, ys, us, p, stops, method, substeps, h, coef)


@_parallel
def _many_quasi_static(ys, us, p, stops, method, substeps, h, coef):
    _rows(_advance_quasi_static, ys, us, p, stops, method, substeps, h, coef)


@_parallel
def _many_force_filters(ys, us, p, stops, method, substeps, h, coef):
    _rows(_advance_force_filters, ys, us, p, stops, method, substeps, h, coef)


@_parallel
def _many_force(ys, us, p, stops, method, substeps, h, coef):
    _rows(_advance_force, ys, us, p, stops, method, substeps, h, coef)


@_jit
def rhs_one(y, u, p, arm, filters, out):
    """Full right-hand side y' into ``out`` for the layout (arm, filters)."""
    if filters:
        if arm == ARM_FULL:
            _rhs(y, u, p, out, ARM_FULL, 4, 5, 6)
        elif arm == ARM_QUASI_STATIC:
            _rhs(y, u, p, out, ARM_QUASI_STATIC, -1, 4, 5)
        else:
            _rhs(y, u, p, out, ARM_FORCE, -1, 4, 5)
    elif arm == ARM_FULL:
        _rhs(y, u, p, out, ARM_FULL, 4, -1, -1)
    elif arm == ARM_QUASI_STATIC:
        _rhs(y, u, p, out, ARM_QUASI_STATIC, -1, -1, -1)
    else:
        _rhs(y, u, p, out, ARM_FORCE, -1, -1, -1)


_ENTRY_POINTS = {
    (ARM_FULL, True): (_advance_full_filters, _many_full_filters),
    (ARM_FULL, False): (_advance_full, _many_full),
    (ARM_QUASI_STATIC, True): (_advance_quasi_static_filters, _many_quasi_static_filters),
    (ARM_QUASI_STATIC, False): (_advance_quasi_static, _many_quasi_static),
    (ARM_FORCE, True): (_advance_force_filters, _many_force_filters),
    (ARM_FORCE, False): (_advance_force, _many_force),
}


def for_layout(layout: Layout) -> Kernels:
    """The kernels of a layout (each compiled on its first use, or loaded from cache)."""
    return Kernels(*_ENTRY_POINTS[(layout.armature, layout.filters)])


def warm_up() -> float:
    """Compile (or load from numba's cache) the entry points of every layout; seconds.

    The first compilation takes minutes; ``./pisc`` runs this once at set-up so that
    nodes and tests started later load the cache instead of compiling in parallel.
    """
    import time

    from pisc_plant.params import ModelParams
    from pisc_plant.plant import IntegratorParams, Plant, PlantConfig

    start = time.perf_counter()
    for armature in ("full", "quasi_static", "ideal_force"):
        for filters in (True, False):
            models = ModelParams(armature=armature,
                                 current_loop="ideal" if armature == "ideal_force"
                                 else "sampled_pi",
                                 sensors="quantised" if filters else "ideal",
                                 sensor_filters=filters)
            plant = Plant(PlantConfig(models=models, integrator=IntegratorParams("exprk4", 2)))
            one = plant.initial_state(0.0)
            plant.advance(one, 1.0, 0.005)
            plant.advance(plant.initial_state(np.zeros(2)), np.zeros(2), 0.005)
            plant.derivative(one, 0.0)
            plant.end_stops(one)
    return time.perf_counter() - start


if __name__ == "__main__":
    print(f"pisc_plant.kernel: compiled or loaded in {warm_up():.1f} s")
