"""Compiled right-hand side and integrators of the plant (numba).

One kernel serves every scene: the state carries only the components a scene's
sub-models need (:class:`Layout`), the constants travel in one float array
(:func:`pisc_plant.plant.pack_constants`), and the same compiled step advances one rig
in a node or ten thousand in a batch (:func:`advance_many` runs :func:`advance_one` on
each row, in parallel), so a rig gives bit-identical results alone and in a batch.

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
    step up to the period. It needs the stiff part of the right-hand side linear, with
    everything the fast armature drives inside that linear part; otherwise the fast
    transient that follows each voltage step reaches the explicitly treated terms and
    the order collapses (seen in an earlier version that made only the current's decay
    linear; not kept). So:

    * the current is replaced by its departure from the quasi-static current,
      ``q = i - (u - k_e x_dot / r) / R``; (2.81) becomes ``q' = -(R/L) q + d x_ddot``
      with ``d = k_e / (r R)`` (u is constant over the step);
    * L, frozen at the start of each step, holds ``x' = x_dot``, ``theta' = theta_dot``,
      the current's weight in the accelerations ``c_x q``, ``c_theta q`` ((3.3), (3.5)
      with (4.2)), their first change with the angle ``c_x1 r``, ``c_theta1 r`` with
      ``r = (t - t_n) q`` carried as an extra state (``r' = lam r + q``, r = 0 at each
      step), the decay ``lam = -R/L + d c_x``, and the RC filters, which are linear
      in their own voltage and in q;
    * c_x and c_theta include the back-EMF's share (``1 - c_x d / lam``): x_dot follows
      q's decay by c_x q / lam and feeds it back through the quasi-static current.

    L is block triangular, so each phi-function of it acts through a few divided
    differences of phi_k over its eigenvalues (0 double, lam double, -w_ir, -w_cur), in
    closed form. On the stated test (README, "Integration") the error then falls at
    fourth order from one step per period.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

__all__ = [
    "METHODS",
    "Layout",
    "advance_many",
    "advance_one",
    "end_stops",
    "exp_coefficients",
    "phi",
    "rhs_many",
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
# Indices into the integer layout.
L_ARM, L_I, L_VIR, L_VCUR, L_STOPS, L_N = range(6)


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

    def array(self) -> np.ndarray:
        return np.array([self.armature, self.current_index, self.ir_index,
                         self.current_sensor_index, int(self.end_stops), self.size],
                        dtype=np.int64)


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
# (x, x_dot, theta, theta_dot, q, v_ir, v_cur, r) as
#     x' = x_dot                      x_dot' = c_x q + c_x1 r
#     theta' = theta_dot              theta_dot' = c_theta q + c_theta1 r
#     q' = lam q                      r' = lam r + q
#     v_ir' = -w_ir v_ir              v_cur' = -w_cur v_cur + c_v q
# A function F(hL) = sum alpha phi_k(s h L) acts through these scalars, divided
# differences of F over the eigenvalues, times the couplings where they apply:
(OP_D0,     # F(0)                                    x, x_dot, theta, theta_dot
 OP_D1,     # F[0, 0]                                 x <- x_dot, theta <- theta_dot
 OP_DQ,     # F(lam)                                  q <- q, r <- r
 OP_E1,     # F[0, lam]           (times c)           x_dot <- q, x_dot <- r
 OP_E2,     # F[0, 0, lam]        (times c)           x <- q, x <- r
 OP_ER,     # F[lam, lam]                             r <- q
 OP_E3,     # F[0, lam, lam]      (times c1)          x_dot <- q through r
 OP_E4,     # F[0, 0, lam, lam]   (times c1)          x <- q through r
 OP_DIR,    # F(-w_ir)                                v_ir
 OP_DCUR,   # F(-w_cur)                               v_cur
 OP_ECUR,   # F[-w_cur, lam]      (times c_v)         v_cur <- q
 ) = range(11)
OP_WIDTH = 12
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


def exp_coefficients(w_ir: float, w_cur: float, c_v: float, step_s: float) -> np.ndarray:
    """The exponential scheme's operators for one step size, shape (15, OP_WIDTH).

    Rows 0-12 hold the scalars that do not depend on the armature's rate (D0, D1, DIR,
    DCUR); the kernel fills in the others at every step, because the rate in L depends
    on the state (:func:`_armature_operators`). Row 13 holds phi_0..phi_3 of -w_cur h/2
    and of -w_cur h, row 14 ``c_v``, ``w_cur``, ``h``. ``w_ir``, ``w_cur`` are the
    filters' rates (0 without them), ``c_v`` the current filter's gain on q (w_cur over
    the sensor's A/V scale).
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
    return table


_jit = numba.njit(cache=True, error_model="numpy")
# Small helpers are inlined at numba's IR level: as calls, passing their arrays cost
# more than their arithmetic (measured: 250 ns per operator application).
_inline = numba.njit(cache=True, error_model="numpy", inline="always")


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
    F[-w_cur, lam] = (F(-w_cur) - F(lam)) / (-w_cur - lam).
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
                    if gap != 0.0:
                        ecur += alpha * (coef[ROW_PHI_CUR, 4 * si + k] - f[k]) / gap
        coef[op, OP_DQ] = scale * dq
        coef[op, OP_E1] = scale * e1
        coef[op, OP_E2] = scale * e2
        coef[op, OP_ER] = scale * er
        coef[op, OP_E3] = scale * e3
        coef[op, OP_E4] = scale * e4
        coef[op, OP_ECUR] = scale * c_v * ecur


@_inline
def _current(y, u, p, lay):
    arm = lay[L_ARM]
    if arm == ARM_FULL:
        return y[lay[L_I]]
    if arm == ARM_QUASI_STATIC:
        return (u - p[P_KER] * y[1]) / p[P_R]
    return u / p[P_KF]  # the current an ideal motor would need for force u


@_inline
def _accelerations(y, u, p, lay, current):
    """x_ddot, theta_ddot: (3.3), (3.5) with cart and pivot friction."""
    x_dot = y[1]
    theta_dot = y[3]
    if lay[L_ARM] == ARM_FORCE:
        force = u
    else:
        # (4.2) and the rotor's viscous friction reflected to the cart
        force = p[P_KF] * current - p[P_BM] * x_dot
    force -= p[P_BC] * x_dot
    if p[P_FC] != 0.0:
        force -= p[P_FC] * math.tanh(x_dot / p[P_VC])
    torque = -p[P_BP] * theta_dot
    s = math.sin(y[2])
    c = math.cos(y[2])
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


@_jit
def rhs_one(y, u, p, lay, out):
    """Full right-hand side y' into ``out``."""
    current = _current(y, u, p, lay)
    x_ddot, theta_ddot = _accelerations(y, u, p, lay, current)
    out[0] = y[1]
    out[1] = x_ddot
    out[2] = y[3]
    out[3] = theta_ddot
    if lay[L_ARM] == ARM_FULL:
        # (2.81): L di/dt = u - R i - k_e phi_dot
        out[lay[L_I]] = (u - p[P_R] * current - p[P_KER] * y[1]) / p[P_L]
    if lay[L_VIR] >= 0:
        out[lay[L_VIR]] = p[P_WIR] * (_ir_voltage(p, y[0]) - y[lay[L_VIR]])
        out[lay[L_VCUR]] = p[P_WCUR] * (_current_sensor_voltage(p, current) - y[lay[L_VCUR]])


@_inline
def _couplings(z, p, lay, c):
    """c_x, c_theta, c_x1, c_theta1 and lam of L at the state's angle and rates, into c.

    The current's weights in (3.3) and (3.5) with f = k_f i (4.2) are
    c_x = k_f / den and c_theta = -a1 cos(theta) k_f / (m l den), den = a2 - a1 cos^2.
    The fast mode also moves the velocities, by (c_x, c_theta) q / lam, and through the
    velocity Jacobian J of the accelerations (back-EMF via the quasi-static current,
    centripetal terms, viscous friction) that motion acts back in proportion to q: the
    couplings L holds are (I + J / lam) (c_x, c_theta). c_x1, c_theta1 are the rates of
    change of c_x, c_theta along theta_dot.
    """
    if lay[L_ARM] != ARM_FULL:
        for j in range(5):
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
    c[0] = cx + (j11 * cx + j12 * cth) / lam
    c[1] = cth + (j21 * cx + j22 * cth) / lam
    c[2] = -kf * 2.0 * a1 * co * si / (den * den) * theta_dot
    c[3] = a1 * kf * si * (den + 2.0 * a1 * co * co) / (ml * den * den) * theta_dot
    c[4] = lam


@_inline
def _apply_add(op, v, c, lay, out):
    """out += F(hL) v for one operator's scalars (see ``OP_*``)."""
    d0 = op[OP_D0]
    d1 = op[OP_D1]
    out[0] += d0 * v[0] + d1 * v[1]
    out[1] += d0 * v[1]
    out[2] += d0 * v[2] + d1 * v[3]
    out[3] += d0 * v[3]
    ii = lay[L_I]
    q = 0.0
    if ii >= 0:
        q = v[ii]
        ri = lay[L_N]
        r = v[ri]
        cx = c[0]
        cth = c[1]
        cx1 = c[2]
        cth1 = c[3]
        e1 = op[OP_E1]
        e2 = op[OP_E2]
        e3q = op[OP_E3] * q
        e4q = op[OP_E4] * q
        out[0] += cx * e2 * q + cx1 * (e2 * r + e4q)
        out[1] += cx * e1 * q + cx1 * (e1 * r + e3q)
        out[2] += cth * e2 * q + cth1 * (e2 * r + e4q)
        out[3] += cth * e1 * q + cth1 * (e1 * r + e3q)
        out[ii] += op[OP_DQ] * q
        out[ri] += op[OP_DQ] * r + op[OP_ER] * q
    vir = lay[L_VIR]
    if vir >= 0:
        vcur = lay[L_VCUR]
        out[vir] += op[OP_DIR] * v[vir]
        out[vcur] += op[OP_DCUR] * v[vcur] + op[OP_ECUR] * q


@_inline
def _nonlinear(z, u, p, lay, c, y, out):
    """N(z) = f(z) - L z in the exponential scheme's variables (q for i, plus r).

    ``y`` is scratch for the state in the original variables.
    """
    n = lay[L_N]
    for j in range(n):
        y[j] = z[j]
    arm = lay[L_ARM]
    ii = lay[L_I]
    q = 0.0
    r = 0.0
    if arm == ARM_FULL:
        q = z[ii]
        r = z[n]
        y[ii] = q + (u - p[P_KER] * z[1]) / p[P_R]
    current = _current(y, u, p, lay)
    x_ddot, theta_ddot = _accelerations(y, u, p, lay, current)
    out[0] = 0.0
    out[1] = x_ddot - c[0] * q - c[2] * r
    out[2] = 0.0
    out[3] = theta_ddot - c[1] * q - c[3] * r
    if arm == ARM_FULL:
        # q' = -(R/L) q + d x_ddot = lam q + d (x_ddot - c_x q), d = k_e / (r R)
        d = p[P_KER] / p[P_R]
        out[ii] = d * (x_ddot - c[0] * q) + (-p[P_R] / p[P_L] + d * c[0] - c[4]) * q
        out[n] = 0.0
    if lay[L_VIR] >= 0:
        out[lay[L_VIR]] = p[P_WIR] * _ir_voltage(p, y[0])
        # v_cur' = w_cur ((i + offset) / scale - v_cur); L holds c_v q
        out[lay[L_VCUR]] = p[P_WCUR] * _current_sensor_voltage(p, current - q)


@_inline
def end_stops(y, p, lay):
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
# the step's start, the new state; 9, 10 phi values; 11 the couplings.
TMP_ROW, SCRATCH_ROW, Z_ROW, NEW_ROW = 5, 6, 7, 8
# The scheme's stages as (operator row, work row) terms:
# U2 = e^(hL/2) z + a21 N1; U3 = e^(hL/2) z + a31 N1 + a32 N2;
# U4 = e^(hL) z + a41 N1 + a42 (N2 + N3); U5 = e^(hL/2) z + a51 N1 + a52 (N2 + N3) + a54 N4;
# z_new = e^(hL) z + b1 N1 + b4 N4 + b5 N5.
STAGE_TERMS = np.full((5, 5, 2), -1, dtype=np.int64)
for _stage, _terms in enumerate((
        [(1, Z_ROW), (2, 0)],
        [(1, Z_ROW), (3, 0), (4, 1)],
        [(0, Z_ROW), (5, 0), (6, 1), (6, 2)],
        [(1, Z_ROW), (7, 0), (8, 1), (8, 2), (9, 3)],
        [(0, Z_ROW), (10, 0), (11, 3), (12, 4)])):
    STAGE_TERMS[_stage, :len(_terms)] = _terms


@_jit
def advance_one(y, u, p, lay, method, substeps, h, coef, work, table):
    """``substeps`` steps of size ``h`` with the input ``u`` held; updates ``y`` in place.

    ``coef`` holds the exponential scheme's operators (:func:`exp_coefficients`) for
    step ``h`` (ignored by rk4); ``work`` (WORK_ROWS, WORK_WIDTH) and ``table`` (shaped
    like ``coef``) are scratch.
    """
    n = lay[L_N]
    stops = lay[L_STOPS] != 0
    k1 = work[0]
    k2 = work[1]
    k3 = work[2]
    k4 = work[3]
    tmp = work[TMP_ROW]
    if method == RK4:
        for _ in range(substeps):
            rhs_one(y, u, p, lay, k1)
            for j in range(n):
                tmp[j] = y[j] + 0.5 * h * k1[j]
            rhs_one(tmp, u, p, lay, k2)
            for j in range(n):
                tmp[j] = y[j] + 0.5 * h * k2[j]
            rhs_one(tmp, u, p, lay, k3)
            for j in range(n):
                tmp[j] = y[j] + h * k3[j]
            rhs_one(tmp, u, p, lay, k4)
            for j in range(n):
                y[j] = y[j] + (h / 6.0) * (k1[j] + 2.0 * k2[j] + 2.0 * k3[j] + k4[j])
            if stops:
                end_stops(y, p, lay)
        return
    arm = lay[L_ARM]
    ii = lay[L_I]
    m = n + 1 if arm == ARM_FULL else n  # r joins the state
    z = work[Z_ROW]
    table[:] = coef
    ph = work[9:11, :8]
    c = work[11, :5]
    for _ in range(substeps):
        for j in range(n):
            z[j] = y[j]
        if arm == ARM_FULL:
            z[ii] -= (u - p[P_KER] * y[1]) / p[P_R]
            z[n] = 0.0
        _couplings(z, p, lay, c)
        if arm == ARM_FULL:
            _armature_operators(c[4], table, ph)
        # N1 at z; then each stage sums operators on z and the N's so far (STAGE_TERMS)
        # and evaluates N there; the last sum is the new state
        _nonlinear(z, u, p, lay, c, work[SCRATCH_ROW], work[0])
        for stage in range(5):
            out = work[TMP_ROW] if stage < 4 else work[NEW_ROW]
            for j in range(m):
                out[j] = 0.0
            for t in range(STAGE_TERMS.shape[1]):
                op = STAGE_TERMS[stage, t, 0]
                if op < 0:
                    break
                _apply_add(table[op], work[STAGE_TERMS[stage, t, 1]], c, lay, out)
            if stage < 4:
                _nonlinear(out, u, p, lay, c, work[SCRATCH_ROW], work[stage + 1])
        out = work[NEW_ROW]
        for j in range(n):
            y[j] = out[j]
        if arm == ARM_FULL:
            y[ii] += (u - p[P_KER] * y[1]) / p[P_R]
        if stops:
            end_stops(y, p, lay)


WORK_ROWS = 12
WORK_WIDTH = 8


@numba.njit(cache=True, parallel=True, error_model="numpy")
def advance_many(ys, us, p, lay, method, substeps, h, coef):
    """:func:`advance_one` on every row of ``ys`` (in place), in parallel chunks."""
    rows = ys.shape[0]
    chunk = 64
    for c in numba.prange((rows + chunk - 1) // chunk):
        work = np.empty((WORK_ROWS, WORK_WIDTH))
        table = np.empty_like(coef)
        for row in range(c * chunk, min(rows, (c + 1) * chunk)):
            advance_one(ys[row], us[row], p, lay, method, substeps, h, coef, work, table)


@numba.njit(cache=True, error_model="numpy")
def rhs_many(ys, us, p, lay, out):
    """:func:`rhs_one` on every row."""
    for row in range(ys.shape[0]):
        rhs_one(ys[row], us[row], p, lay, out[row])


def warm_up() -> float:
    """Compile (or load from numba's cache) every kernel entry point; seconds taken.

    The first compilation takes tens of seconds; ``./pisc`` runs this once at set-up so
    that nodes and tests started later load the cache instead of compiling in parallel.
    """
    import time

    from pisc_plant.params import ModelParams
    from pisc_plant.plant import IntegratorParams, Plant, PlantConfig

    start = time.perf_counter()
    for models in (ModelParams(), ModelParams(armature="ideal_force", current_loop="ideal",
                                              sensors="ideal", sensor_filters=False)):
        for method in METHODS:
            plant = Plant(PlantConfig(models=models, integrator=IntegratorParams(method, 20)))
            one = plant.initial_state(0.0)
            plant.advance(one, 1.0, 0.005)
            plant.advance(plant.initial_state(np.zeros(2)), np.zeros(2), 0.005)
            plant.derivative(one, 0.0)
            plant.end_stops(one)
    return time.perf_counter() - start


if __name__ == "__main__":
    print(f"pisc_plant.kernel: compiled or loaded in {warm_up():.1f} s")
