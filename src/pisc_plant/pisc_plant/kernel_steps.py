"""One integration step of one rig: classical Runge-Kutta and the exponential scheme.

Methods (:data:`pisc_plant.layout.METHODS`):

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
    * L's rate of q is a constant, :func:`pisc_plant.kernel_operators.armature_rate`, so
      that its phi-functions are computed once per step size; the state's own rate
      differs from it by delta (about 0.005 1/s on the thesis rig), carried as the
      current's departure ``q + delta r``;
    * the RC filters are linear in their own voltage and in q (with the back-EMF's
      share of the fast mode).

    L is block triangular, so each phi-function of it acts through a few divided
    differences of phi_k over its eigenvalues (0 double, lam triple, -w_ir, -w_cur), in
    closed form. README, "Scenes and integrators", gives the measured order.

A step works on a rig's state as a tuple (:mod:`pisc_plant.kernel_rhs`); the operators
are rows of :func:`pisc_plant.kernel_operators.exp_coefficients`' table as tuples
(:func:`as_operators`). :func:`apply_add` and :func:`apply_add_n` are the operator
applications on arrays, for tests.
"""

from __future__ import annotations

from pisc_plant.kernel_jit import compiled, inlined
from pisc_plant.kernel_operators import (
    N_OPERATORS, OP_D0, OP_D1, OP_DCUR, OP_DIR, OP_DQ, OP_E1, OP_E2, OP_E3, OP_E4, OP_E5,
    OP_E6, OP_ECUR, OP_ER, OP_ES, armature_rate,
)
from pisc_plant.kernel_rhs import (
    accelerations, accelerations_at, armature_current, current_sensor_voltage, ir_voltage, rhs,
)
from pisc_plant.layout import (
    ARM_FULL, P_A1, P_A2, P_BC, P_BM, P_BP, P_FC, P_G, P_KER, P_KF, P_L, P_ML, P_R, P_VC,
    P_WCUR, P_WIR,
)
from pisc_plant.vecmath import vcos, vsin, vtanh

__all__ = ["apply_add", "apply_add_n", "as_operators", "exprk4_step", "rk4_step"]

_ZERO9 = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)


@inlined
def _operator(coef, k):
    return (coef[k, 0], coef[k, 1], coef[k, 2], coef[k, 3], coef[k, 4], coef[k, 5],
            coef[k, 6], coef[k, 7], coef[k, 8], coef[k, 9], coef[k, 10], coef[k, 11],
            coef[k, 12], coef[k, 13])


@inlined
def as_operators(coef):
    """Rows 0-12 of :func:`exp_coefficients`' table as a tuple of tuples."""
    return (_operator(coef, 0), _operator(coef, 1), _operator(coef, 2), _operator(coef, 3),
            _operator(coef, 4), _operator(coef, 5), _operator(coef, 6), _operator(coef, 7),
            _operator(coef, 8), _operator(coef, 9), _operator(coef, 10),
            _operator(coef, 11), _operator(coef, 12))


@inlined
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
    x_ddot, theta_ddot = accelerations_at(y[1], y[3], u, p, arm, y[4], si, co, fric)
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


@inlined
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


@inlined
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


@inlined
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
    current = armature_current(y, u, p, arm)
    if at_start and arm == ARM_FULL:
        x_ddot = c[6]
        theta_ddot = c[7]
    else:
        x_ddot, theta_ddot = accelerations(y, u, p, arm, current, fric)
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
        n5 = p[P_WIR] * ir_voltage(p, y[0])
        # v_cur' = w_cur ((i + offset) / scale - v_cur); L holds c_v c[5] q
        n6 = p[P_WCUR] * current_sensor_voltage(p, current - c[5] * q)
    return (0.0, x_ddot - c[0] * q - c[2] * r - c[8] * s, 0.0,
            theta_ddot - c[1] * q - c[3] * r - c[9] * s, n4, n5, n6, 0.0, 0.0)


@inlined
def rk4_step(y, u, p, h, arm, filt, fric):
    """One classical Runge-Kutta step."""
    k1 = rhs(y, u, p, arm, filt, fric)
    t = 0.5 * h
    k2 = rhs((y[0] + t * k1[0], y[1] + t * k1[1], y[2] + t * k1[2], y[3] + t * k1[3],
              y[4] + t * k1[4], y[5] + t * k1[5], y[6] + t * k1[6]), u, p, arm, filt, fric)
    k3 = rhs((y[0] + t * k2[0], y[1] + t * k2[1], y[2] + t * k2[2], y[3] + t * k2[3],
              y[4] + t * k2[4], y[5] + t * k2[5], y[6] + t * k2[6]), u, p, arm, filt, fric)
    k4 = rhs((y[0] + h * k3[0], y[1] + h * k3[1], y[2] + h * k3[2], y[3] + h * k3[3],
              y[4] + h * k3[4], y[5] + h * k3[5], y[6] + h * k3[6]), u, p, arm, filt, fric)
    w = h / 6.0
    return (y[0] + w * (k1[0] + 2.0 * k2[0] + 2.0 * k3[0] + k4[0]),
            y[1] + w * (k1[1] + 2.0 * k2[1] + 2.0 * k3[1] + k4[1]),
            y[2] + w * (k1[2] + 2.0 * k2[2] + 2.0 * k3[2] + k4[2]),
            y[3] + w * (k1[3] + 2.0 * k2[3] + 2.0 * k3[3] + k4[3]),
            y[4] + w * (k1[4] + 2.0 * k2[4] + 2.0 * k3[4] + k4[4]),
            y[5] + w * (k1[5] + 2.0 * k2[5] + 2.0 * k3[5] + k4[5]),
            y[6] + w * (k1[6] + 2.0 * k2[6] + 2.0 * k3[6] + k4[6]))


@inlined
def _sum9(a, b):
    return (a[0] + b[0], a[1] + b[1], a[2] + b[2], a[3] + b[3], a[4] + b[4], a[5] + b[5],
            a[6] + b[6], a[7] + b[7], a[8] + b[8])


# Rows of the operator table (see OP_WEIGHTS)
(T_E, T_E2, T_A21, T_A31, T_A32, T_A41, T_A42, T_A51, T_A52, T_A54, T_B1, T_B4,
 T_B5) = range(N_OPERATORS)


@inlined
def exprk4_step(y, u, p, ops, arm, filt, fric):
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


@compiled
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


@compiled
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
