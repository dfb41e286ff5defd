"""The closed-loop comparisons of seeds 000 and 001: linear model against nonlinear plant.

* Seed 000 section 7: the cart-pole M1 = M2 = 1 kg, l = 1 m, g = 9.8 under state
  feedback with integral action on the cart position,
  ``F = -KR [theta, theta_dot, x, x_dot] + KI x5``, ``x5' = -x``,
  KR = [-158.6130, -48.3707, -25.2051, -26.7648], KI = -10, from theta(0) = x(0) = 0.5,
  over 2 pi seconds (SPEC section 5).
* Seed 001 section 5: M = 2 kg, m = 0.1 kg, l = 0.5 m, g = 9.81 with the gain placed
  at -1 +- sqrt(3) j, -5, -5, from x(0) = 0.2 m, theta(0) = 0.1 rad.

Both integrate the nonlinear model (SPEC section 2, :func:`pisc_model.dynamics.
accelerations`, equal to the symbolic model) and its linearisation about upright
(3.41)-(3.42) with SciPy's DOP853 at tight tolerances, and report the largest
difference per state and when it occurs.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.integrate import solve_ivp

from pisc_analysis.linear import bass_gura_gain
from pisc_model.dynamics import accelerations, linearise_upright
from pisc_model.params import RigParams

__all__ = [
    "Comparison",
    "SEED000_KI",
    "SEED000_KR",
    "SEED000_RIG",
    "SEED001_POLES",
    "SEED001_RIG",
    "plot_comparison",
    "seed000_comparison",
    "seed001_comparison",
]

SEED000_RIG = RigParams(cart_mass_kg=1.0, pendulum_mass_kg=1.0, pendulum_com_m=1.0,
                        pendulum_inertia_kgm2=0.0, gravity_mps2=9.8)
SEED000_KR = (-158.6130, -48.3707, -25.2051, -26.7648)  # on [theta, theta_dot, x, x_dot]
SEED000_KI = -10.0
SEED001_RIG = RigParams(cart_mass_kg=2.0, pendulum_mass_kg=0.1, pendulum_com_m=0.5,
                        pendulum_inertia_kgm2=0.0, gravity_mps2=9.81)
SEED001_POLES = (complex(-1.0, math.sqrt(3.0)), complex(-1.0, -math.sqrt(3.0)), -5.0, -5.0)

STATE_NAMES = ("x", "x_dot", "theta", "theta_dot")
UNITS = {"x": "m", "x_dot": "m/s", "theta": "rad", "theta_dot": "rad/s", "x5": "m s",
         "f": "N"}


@dataclass(frozen=True)
class Comparison:
    """Linear and nonlinear responses on a common time grid."""

    title: str
    names: tuple[str, ...]
    t: np.ndarray
    linear: np.ndarray  # (N, len(names))
    nonlinear: np.ndarray
    force_linear: np.ndarray
    force_nonlinear: np.ndarray

    def max_difference(self, name: str) -> tuple[float, float]:
        """(largest |nonlinear - linear| of a state, the time at which it occurs)."""
        i = self.names.index(name)
        d = np.abs(self.nonlinear[:, i] - self.linear[:, i])
        k = int(np.argmax(d))
        return float(d[k]), float(self.t[k])

    def difference_after(self, name: str, t_s: float) -> float:
        """Largest |nonlinear - linear| of a state from ``t_s`` on."""
        i = self.names.index(name)
        keep = self.t >= t_s
        return float(np.max(np.abs(self.nonlinear[keep, i] - self.linear[keep, i])))

    def summary_lines(self) -> list[str]:
        lines = []
        half = self.t[-1] / 2
        for name in self.names:
            d, t = self.max_difference(name)
            peak = float(np.max(np.abs(self.nonlinear[:, self.names.index(name)])))
            lines.append(f"{name:<10} largest |nonlinear - linear| {d:.4g} {UNITS[name]} at "
                         f"t = {t:.3f} s (peak |value| {peak:.4g}); after t = "
                         f"{half:.2f} s: {self.difference_after(name, half):.2g}")
        return lines


def _simulate(rhs, y0: np.ndarray, duration_s: float, points: int) -> tuple[np.ndarray,
                                                                            np.ndarray]:
    t = np.linspace(0.0, duration_s, points)
    sol = solve_ivp(rhs, (0.0, duration_s), y0, method="DOP853", t_eval=t, rtol=1e-11,
                    atol=1e-12)
    if not sol.success:
        raise RuntimeError(f"integration failed: {sol.message}")
    return t, sol.y.T


def _closed_loop(rig: RigParams, gain: np.ndarray, integral_gain: float | None,
                 y0: np.ndarray, duration_s: float, points: int
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Both models under ``f = -K z (+ KI x5)``; z = [x, x_dot, theta, theta_dot(, x5)]."""
    a, b = linearise_upright(rig)
    bv = b[:, 0]

    def force(y: np.ndarray) -> float:
        f = -float(gain @ y[:4])
        if integral_gain is not None:
            f += integral_gain * y[4]
        return f

    def nonlinear(_t: float, y: np.ndarray) -> np.ndarray:
        f = force(y)
        x_ddot, theta_ddot = accelerations(rig, y[2], y[3], f)
        out = [y[1], float(x_ddot), y[3], float(theta_ddot)]
        return np.array(out + ([-y[0]] if integral_gain is not None else []))

    def linear(_t: float, y: np.ndarray) -> np.ndarray:
        dz = a @ y[:4] + bv * force(y)
        return np.concatenate([dz, [-y[0]] if integral_gain is not None else []])

    t, yn = _simulate(nonlinear, y0, duration_s, points)
    _, yl = _simulate(linear, y0, duration_s, points)
    fn = np.array([force(y) for y in yn])
    fl = np.array([force(y) for y in yl])
    return t, yl, yn, fl, fn


def seed000_comparison(duration_s: float = 2.0 * math.pi, points: int = 4001) -> Comparison:
    """Seed 000 section 7: linear vs nonlinear with integral action, from 0.5, 0.5.

    Notes
    -----
    Seed 000 orders the state ``[theta, theta_dot, x, x_dot, x5]``; here
    ``[x, x_dot, theta, theta_dot, x5]`` with the gains reordered to match.
    ``control = -KR . z + KI x5`` as in its listing, so ``f = -K z + KI x5`` with
    ``K = [KR3, KR4, KR1, KR2]``.
    """
    kr = SEED000_KR
    gain = np.array([kr[2], kr[3], kr[0], kr[1]])
    y0 = np.array([0.5, 0.0, 0.5, 0.0, 0.0])
    t, yl, yn, fl, fn = _closed_loop(SEED000_RIG, gain, SEED000_KI, y0, duration_s, points)
    return Comparison("Seed 000: linear vs nonlinear, integral action on x (x0 = theta0 = 0.5)",
                      (*STATE_NAMES, "x5"), t, yl, yn, fl, fn)


def seed001_comparison(duration_s: float = 8.0, points: int = 4001) -> Comparison:
    """Seed 001 section 5: the placed gain from x(0) = 0.2 m, theta(0) = 0.1 rad."""
    a, b = linearise_upright(SEED001_RIG)
    gain = bass_gura_gain(a, b, SEED001_POLES)
    y0 = np.array([0.2, 0.0, 0.1, 0.0])
    t, yl, yn, fl, fn = _closed_loop(SEED001_RIG, gain, None, y0, duration_s, points)
    return Comparison("Seed 001: closed loop from x = 0.2 m, theta = 0.1 rad",
                      STATE_NAMES, t, yl, yn, fl, fn)


def plot_comparison(comparison: Comparison, path: Path) -> Path:
    """One panel per state and one for the force, both models overlaid (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = [*comparison.names, "f"]
    fig, axes = plt.subplots(len(names), 1, figsize=(8, 2.0 * len(names)), sharex=True)
    for ax, name in zip(axes, names, strict=True):
        if name == "f":
            lin, non = comparison.force_linear, comparison.force_nonlinear
        else:
            i = comparison.names.index(name)
            lin, non = comparison.linear[:, i], comparison.nonlinear[:, i]
        ax.plot(comparison.t, lin, "-", label="linear")
        ax.plot(comparison.t, non, "--", label="nonlinear")
        ax.set_ylabel(f"{name} [{UNITS[name]}]")
        ax.grid(True, alpha=0.3)
    axes[0].legend(loc="upper right")
    axes[0].set_title(comparison.title)
    axes[-1].set_xlabel("t [s]")
    fig.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path
