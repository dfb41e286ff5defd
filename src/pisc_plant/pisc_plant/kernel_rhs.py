"""The scene's right-hand side on one rig: the accelerations (3.3), (3.5) with cart and
pivot friction, the armature (2.81), the sensors' RC filters, and the track's end stops.

The hot path works on one rig's state as a tuple of numbers, never on arrays, so that
LLVM can keep every intermediate in registers and vectorise the loop over rigs (four
rigs per AVX2 register, sin, cos, pow and tanh from the vector library: see
:mod:`pisc_plant.vecmath`). A rig's state is ``(x, x_dot, theta, theta_dot, i, v_ir,
v_cur)`` whatever the layout (absent components are 0 and stay 0); the exponential
scheme's variables are ``(x, x_dot, theta, theta_dot, q, v_ir, v_cur, r, s)``. The
layout enters as constants (``arm``, ``filt``) where the functions are inlined, so the
compiler removes the branches of the others. The constants ``p`` and the operator
table ``ops`` are tuples unpacked once per call, so the loop over rigs reads no memory
besides the rigs' states and inputs. Measured while building it: README, "Batch".

:func:`rhs_one` and :func:`end_stops` are the entry points on a state array (reference
integrators, checks); the inlined helpers are what the integrators of
:mod:`pisc_plant.kernel_steps` build on.
"""

from __future__ import annotations

import numpy as np

from pisc_plant.kernel_jit import compiled, inlined
from pisc_plant.layout import (
    ARM_FORCE, ARM_FULL, ARM_QUASI_STATIC, P_A1, P_A2, P_BC, P_BM, P_BP, P_CUROFF, P_CURSCALE,
    P_FC, P_G, P_IRO, P_IRS, P_IRX, P_JROT, P_KER, P_KF, P_L, P_ML, P_R, P_VC, P_WCUR, P_WIR,
    P_XMAX, P_XMIN,
)
from pisc_plant.vecmath import vcos, vpow, vsin, vtanh

__all__ = ["accelerations", "accelerations_at", "armature_current", "as_constants",
           "current_sensor_voltage", "end_stops", "ir_voltage", "rhs", "rhs_one",
           "stop_at_ends"]


@inlined
def as_constants(a, stops):
    """The packed constants as a tuple (see ``P_*``); without ``stops`` the track's ends
    are at -inf and +inf, so that the end stops never act and the loop needs no flag."""
    return (a[0], a[1], a[2], a[3], a[4], a[5], a[6], a[7], a[8], a[9], a[10], a[11],
            a[12], a[13], a[14], a[15], a[16], a[17], a[18], a[19],
            a[P_XMIN] if stops else -np.inf, a[P_XMAX] if stops else np.inf, a[22])


@inlined
def armature_current(y, u, p, arm):
    if arm == ARM_FULL:
        current = y[4]
    elif arm == ARM_QUASI_STATIC:
        current = (u - p[P_KER] * y[1]) / p[P_R]
    else:
        current = u / p[P_KF]  # the current an ideal motor would need for force u
    return current


@inlined
def accelerations(y, u, p, arm, current, fric):
    """x_ddot, theta_ddot: (3.3), (3.5) with cart and pivot friction."""
    return accelerations_at(y[1], y[3], u, p, arm, current, vsin(y[2]), vcos(y[2]), fric)


@inlined
def accelerations_at(x_dot, theta_dot, u, p, arm, current, s, c, fric):
    """:func:`accelerations` with sin and cos of the angle given; ``fric`` (a constant of
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


@inlined
def ir_voltage(p, x):
    distance = max(p[P_IRO] - x, 1e-3)
    return vpow(distance / p[P_IRS], p[P_IRX])


@inlined
def current_sensor_voltage(p, current):
    return (current + p[P_CUROFF]) / p[P_CURSCALE]


@inlined
def rhs(y, u, p, arm, filt, fric):
    """The full right-hand side y' (state order of the tuple, see above)."""
    current = armature_current(y, u, p, arm)
    x_ddot, theta_ddot = accelerations(y, u, p, arm, current, fric)
    di = 0.0
    if arm == ARM_FULL:
        # (2.81): L di/dt = u - R i - k_e phi_dot
        di = (u - p[P_R] * current - p[P_KER] * y[1]) / p[P_L]
    dir_ = 0.0
    dcur = 0.0
    if filt:
        dir_ = p[P_WIR] * (ir_voltage(p, y[0]) - y[5])
        dcur = p[P_WCUR] * (current_sensor_voltage(p, current) - y[6])
    return (y[1], x_ddot, y[3], theta_ddot, di, dir_, dcur)


@inlined
def stop_at_ends(y, p):
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


@inlined
def _rhs_into(y, u, p, out, arm, filt, ii, vir, vcur):
    s = (y[0], y[1], y[2], y[3], y[ii] if ii >= 0 else 0.0, y[vir] if vir >= 0 else 0.0,
         y[vcur] if vir >= 0 else 0.0)
    f = rhs(s, u, as_constants(p, True), arm, filt, True)
    out[0] = f[0]
    out[1] = f[1]
    out[2] = f[2]
    out[3] = f[3]
    if ii >= 0:
        out[ii] = f[4]
    if vir >= 0:
        out[vir] = f[5]
        out[vcur] = f[6]


@compiled
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


@compiled
def end_stops(y, p):
    """The end stops on one rig's state array, in place (any layout: they touch x,
    x_dot and theta_dot only)."""
    s = stop_at_ends((y[0], y[1], y[2], y[3], 0.0, 0.0, 0.0), as_constants(p, True))
    y[0] = s[0]
    y[1] = s[1]
    y[3] = s[3]
