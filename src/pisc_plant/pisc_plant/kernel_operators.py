"""The exponential scheme's operators: the phi-functions of its linear part L and the
table of each operator's scalars for one step size.

The exponential Runge-Kutta scheme (5.19) of :mod:`pisc_plant.kernel_steps` applies
functions of L, sums of phi_k(s h L), to vectors. L is block triangular, so each acts
through a few divided differences of phi_k over L's eigenvalues (0 double, the
armature's rate lam triple, -w_ir, -w_cur), in closed form: :func:`exp_coefficients`
computes them once per step size (:func:`step_operators` the part without the armature,
:func:`armature_operators` the part that depends on its rate), :func:`armature_rate` is
the constant rate L holds; :func:`phi` and :func:`_phis` are the phi-functions.
"""

from __future__ import annotations

import math

import numpy as np

from pisc_plant.kernel_jit import compiled, inlined
from pisc_plant.layout import P_A1, P_A2, P_KER, P_KF, P_L, P_R

__all__ = ["FACTORIAL", "INV_FACTORIAL", "N_OPERATORS", "OP_WEIGHTS", "OP_WIDTH", "ROW_CONST",
           "ROW_PHI_CUR", "STAGE_FRACTIONS", "armature_operators", "armature_rate",
           "exp_coefficients", "phi", "step_operators"]


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
FACTORIAL = np.array([float(math.factorial(k)) for k in range(10)])


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
    by the compiled :func:`step_operators` and :func:`armature_operators`: 2 us a
    table here. On the wall clock a plant needs two new tables every cycle (the voltage
    arrives at another time in each period); the same sums added one Python float at a
    time took 340 us a table, a fifth of the graph's CPU in a wall-clock run (py-spy,
    2026-12-03). test_kernel.py keeps that form as the reference, bit for bit.
    """
    table = np.empty((15, OP_WIDTH))
    step_operators(float(w_ir), float(w_cur), float(c_v), float(step_s), table,
                   np.empty((2, 4)))
    if lam != 0.0:
        armature_operators(float(lam), table, np.empty((2, 8)))
    return table


@inlined
def armature_rate(p):
    """The armature's rate lam in L: -R/L plus the back-EMF's share d k_f / den, with den
    at cos^2(theta) = 1/2, the middle of its range.

    The rate the state implies, -R/L + d c_x(theta, theta_dot), differs from it by about
    d k_f a1 / (2 den^2) at most (0.0049 1/s on the thesis rig, 7e-7 of R/L), which the
    scheme carries as delta (:func:`couplings`). A constant rate makes the operators
    constants of the step size (:func:`exp_coefficients`).
    """
    d = p[P_KER] / p[P_R]
    return -p[P_R] / p[P_L] + d * p[P_KF] / (p[P_A2] - 0.5 * p[P_A1])


@compiled
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


@compiled
def armature_operators(lam, coef, ph):
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


@compiled
def phi(k, z):
    """phi_k(z) = sum_j z^j / (j + k)! (phi_0 = exp), accurate for every real z.

    The series for |z| < 2 (40 terms), else the recurrence
    phi_(k+1)(z) = (phi_k(z) - 1/k!) / z from the exponential, which loses nothing there.
    """
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


@compiled
def step_operators(w_ir, w_cur, c_v, step_s, table, phi_ir):
    """The part of :func:`exp_coefficients`' table that does not depend on the armature's
    rate (rows 0-12 of OP_D0, OP_D1, OP_DIR, OP_DCUR and rows 13, 14), into ``table``,
    with the same arithmetic in the same order (the same bits)."""
    h = step_s
    table[:, :] = 0.0
    for si in range(2):
        s = STAGE_FRACTIONS[si]
        for k in range(4):
            table[ROW_PHI_CUR, 4 * si + k] = phi(k, -s * h * w_cur)
            phi_ir[si, k] = phi(k, -(s * h) * w_ir)
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
