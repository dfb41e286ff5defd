"""Necessary conditions of the feasibility study: what no input can do.

:func:`energy_bound` compares the energy the pendulum must gain to enter the catch
region (:func:`region_energy`) with the most any input can add in the horizon (the cart
acceleration bounded by :func:`accel_bound`), and the comparison lemma's
:func:`climb_time` to that energy; :attr:`EnergyBound.infeasible` proves a rig
infeasible.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from pisc_analysis.feasibility import (Limits, Rig, cart_friction, pendulum_energy,
                                       pivot_friction)

__all__ = ["EnergyBound", "accel_bound", "climb_time", "energy_bound", "region_energy"]


@dataclass(frozen=True)
class EnergyBound:
    """A necessary condition for entering the catch region by ``horizon_s`` (see
    :func:`energy_bound`); ``infeasible`` proves that no input can."""

    needed_j: float  # E* - E_p(0): what the pendulum must gain to enter the region
    largest_gain_j: float  # the most any input can add in the horizon, pivot loss paid
    accel_bound_mps2: float  # the largest cart acceleration any input can give
    horizon_s: float
    least_time_s: float = 0.0  # :func:`climb_time`: no input enters the region sooner

    @property
    def infeasible(self) -> bool:
        return self.largest_gain_j < self.needed_j or self.least_time_s > self.horizon_s


def region_energy(rig: Rig, limits: Limits) -> float:
    """E*: the least pendulum energy E_p inside the catch region (4.1), theta^2 + k_va
    theta_dot^2 < delta_s; at theta_dot = 0, |theta| = sqrt(delta_s): m g l (cos
    sqrt(delta_s) - 1). The pendulum enters the region with E_p > E*."""
    return rig.mgl * (math.cos(min(math.sqrt(limits.delta_s), math.pi)) - 1.0)


def accel_bound(rig: Rig, limits: Limits) -> float:
    """a_b: the largest |x_ddot| any input can give while |theta_dot| <= 2 omega_0 (3.3):
    (f_max + cart friction at the no-load speed + m l (2 omega_0)^2 + a1 g / 2
    + a1 b_p 2 omega_0 / (m l)) / (a2 - a1), f_max = k_m i_max / r (4.2) with i_max the
    current limit and the check's 2 % tolerance (or the stall current u_max / R without
    a limit)."""
    m = rig.config.motor
    i_max = (1.02 * limits.current_a if limits.current_a is not None
             else limits.voltage_v / m.resistance_ohm)
    no_load = limits.voltage_v * m.wheel_radius_m / m.back_emf_v_s_per_rad
    friction = float(abs(cart_friction(rig, np.array(no_load))))
    w = 2.0 * rig.omega0
    f_bound = (m.force_per_amp * i_max + friction + rig.ml * w * w
               + rig.a1 * rig.mgl / rig.ml / 2.0 + rig.a1 * pivot_friction(rig) * w / rig.ml)
    return f_bound / (rig.a2 - rig.a1)


def energy_bound(rig: Rig, limits: Limits, horizon_s: float | None = None) -> EnergyBound:
    """An energy budget that no input can beat.

    The pendulum's energy in the cart's frame E_p (:func:`pendulum_energy`) obeys
    dE_p/dt = -m l x_ddot theta_dot cos(theta) - b_p theta_dot^2. To be in the catch
    region the pendulum needs E_p > E* (:func:`region_energy`, < 0); until E_p first
    reaches E*, |theta_dot| <= 2 omega_0, so |x_ddot| <= a_b (:func:`accel_bound`).
    With S = int theta_dot^2 dt and Cauchy-Schwarz, int |theta_dot| dt <= sqrt(T S), so
    the gain is at most max_S (m l a_b sqrt(T S) - b_p S) = (m l a_b)^2 T / (4 b_p)
    (unbounded without pivot friction). If that is below E* - E_p(0), no input enters
    the catch region by T. The comparison lemma (:func:`climb_time`, ``least_time_s``)
    is a second, sharper test: no input enters it sooner than that.
    """
    horizon = limits.catch_by_s if horizon_s is None else horizon_s
    bp = pivot_friction(rig)
    accel = accel_bound(rig, limits)
    needed = float(region_energy(rig, limits) - pendulum_energy(rig, rig.y0))
    gain = math.inf if bp == 0.0 else (rig.ml * accel) ** 2 * horizon / (4.0 * bp)
    return EnergyBound(needed, gain, accel, horizon, climb_time(rig, limits))


def climb_time(rig: Rig, limits: Limits, cells: int = 400, phases: int = 2000) -> float:
    """A lower bound on the time any input needs to bring E_p from E_p(0) to E*
    (:func:`region_energy`): the comparison lemma on dE_p/dt <= G(E_p).

    With c = cos(theta) and theta_dot^2 = w^2(E, c) = 2 (E + m g l (1 - c)) / J at
    energy E (the pendulum terms of (2.54)), dE_p/dt = -m l x_ddot theta_dot c - b_p
    theta_dot^2 <= G(E) = max_c (m l a_b w |c| - b_p w^2) over the phases c with
    w^2 >= 0, a_b of :func:`accel_bound` (valid while E_p < E*). E* - E_p(0) is cut into
    ``cells`` equal cells of energy; the phase range [-1, 1] into ``phases`` cells, on
    each of which w is largest at the lower c and at the cell's upper energy, w^2
    smallest at the upper c and the lower energy: that upper-bounds G over the energy
    cell (G_k), every step an inequality. Crossing energy cell k upward takes at least
    dE / G_k (E_p rises at most at G_k while in it, and must rise by dE there), so the
    sum over the cells bounds the time. Returns 0 if E_p(0) >= E*.
    """
    start = float(pendulum_energy(rig, rig.y0))
    target = region_energy(rig, limits)
    if start >= target:
        return 0.0
    a_b, bp = accel_bound(rig, limits), pivot_friction(rig)
    ml, mgl, j = rig.ml, rig.mgl, rig.inertia
    edges = np.linspace(start, target, cells + 1)
    c = np.linspace(-1.0, 1.0, phases + 1)
    c_lo, c_hi = c[:-1], c[1:]
    c_abs = np.maximum(np.abs(c_lo), np.abs(c_hi))
    e_lo, e_hi = edges[:-1, None], edges[1:, None]
    w_top = np.sqrt(np.maximum(2.0 * (e_hi + mgl * (1.0 - c_lo)) / j, 0.0))
    w2_low = np.maximum(2.0 * (e_lo + mgl * (1.0 - c_hi)) / j, 0.0)
    reachable = 2.0 * (e_hi + mgl * (1.0 - c_lo)) >= 0.0
    g = np.max(np.where(reachable, ml * a_b * w_top * c_abs - bp * w2_low, -np.inf), axis=1)
    return float(np.sum(np.diff(edges) / np.maximum(g, 1e-300)))
