"""Fixed-step integrators for a plant held at constant input over a step.

The rig's plant is stiff only through linear, diagonal terms: the armature current
decays at R/L (about 7000 1/s) and the sensors' RC filters at 1/(RC). Writing the
right-hand side as ``y' = lam * y + N(y)`` with a constant diagonal ``lam`` lets an
exponential integrator treat those terms exactly and the rest with fourth-order
accuracy, stable at any step up to the control period.

Functions broadcast over a leading batch shape: ``y`` has shape (..., n).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

__all__ = ["Etdrk4", "phi_functions", "rk4_step"]

Rhs = Callable[[np.ndarray], np.ndarray]


def phi_functions(z: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """phi_1, phi_2 and phi_3 of exponential integrators, accurate for all real z.

    phi_k(z) = sum_j z^j / (j + k)!; the closed forms ((e^z - 1)/z, ...) lose digits
    to cancellation for small |z|, so the series is used for |z| < 1.
    """
    z = np.asarray(z, dtype=float)
    phi = []
    small = np.abs(z) < 1.0
    zs = np.where(small, z, 0.0)
    zl = np.where(small, 1.0, z)  # any nonzero value where the series is used
    expz = np.exp(zl)
    closed = [
        (expz - 1.0) / zl,
        (expz - 1.0 - zl) / zl**2,
        (expz - 1.0 - zl - 0.5 * zl**2) / zl**3,
    ]
    for k in (1, 2, 3):
        series = np.zeros_like(zs)
        term_power = np.ones_like(zs)
        for j in range(25):
            series = series + term_power / math.factorial(j + k)
            term_power = term_power * zs
        phi.append(np.where(small, series, closed[k - 1]))
    return phi[0], phi[1], phi[2]


@dataclass(frozen=True)
class Etdrk4:
    """Cox-Matthews fourth-order exponential time differencing for ``y' = lam y + N(y)``.

    ``lam`` is a constant diagonal (one rate per state, 0 for non-stiff states); with
    ``lam = 0`` the method is the classical Runge-Kutta scheme. The coefficients are
    precomputed for one step size.

    References
    ----------
    S. M. Cox and P. C. Matthews, "Exponential time differencing for stiff systems",
    J. Comput. Phys. 176 (2002) 430-455; coefficients in the phi-function form of
    A.-K. Kassam and L. N. Trefethen, SIAM J. Sci. Comput. 26 (2005) 1214-1233.
    """

    step_s: float
    e: np.ndarray
    e_half: np.ndarray
    q: np.ndarray
    f1: np.ndarray
    f2: np.ndarray
    f3: np.ndarray

    @classmethod
    def for_step(cls, lam: np.ndarray, step_s: float) -> Etdrk4:
        lam = np.asarray(lam, dtype=float)
        z = lam * step_s
        p1, p2, p3 = phi_functions(z)
        p1_half, _, _ = phi_functions(z / 2.0)
        h = step_s
        return cls(
            step_s=step_s,
            e=np.exp(z),
            e_half=np.exp(z / 2.0),
            q=0.5 * h * p1_half,
            f1=h * (p1 - 3.0 * p2 + 4.0 * p3),
            f2=h * (p2 - 2.0 * p3),
            f3=h * (4.0 * p3 - p2),
        )

    def step(self, nonlinear: Rhs, y: np.ndarray) -> np.ndarray:
        """One step of size ``step_s`` for an autonomous nonlinear part."""
        n_y = nonlinear(y)
        a = self.e_half * y + self.q * n_y
        n_a = nonlinear(a)
        b = self.e_half * y + self.q * n_a
        n_b = nonlinear(b)
        c = self.e_half * a + self.q * (2.0 * n_b - n_y)
        n_c = nonlinear(c)
        return self.e * y + self.f1 * n_y + 2.0 * self.f2 * (n_a + n_b) + self.f3 * n_c


def rk4_step(rhs: Rhs, y: np.ndarray, step_s: float) -> np.ndarray:
    """One classical Runge-Kutta step of an autonomous right-hand side."""
    h = step_s
    k1 = rhs(y)
    k2 = rhs(y + 0.5 * h * k1)
    k3 = rhs(y + 0.5 * h * k2)
    k4 = rhs(y + h * k3)
    return y + (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
