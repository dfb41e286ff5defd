"""Region of attraction of the catch in the loop as it runs: sampled, quantised, saturated.

For a grid of initial angles and rates (and a cart position) near upright, the whole
closed loop of the graph runs in one batch (:func:`pisc_sim.closed_loop.
simulate_batch`: the plant with its armature, sensor filters, ADC and encoder
quantisation, 7-bit bridge and end stops; the estimator's differences; the supervisor
with the switching rule (4.1); the PI current loop with its saturations). The rig
starts moving at the given rates (the estimator is primed with the previous sample), and
each start is classified:

* ``CAUGHT_AT_ONCE``: in catch from the first sample to the end, and held (|theta|
  below the tolerance over the last ``hold_window_s``, no fault): the catch controller
  itself recovered it;
* ``CAUGHT_LATER``: not caught at once (the switching rule (4.1) chose the swing-up,
  or the catch let go), but caught and held by the end;
* ``NOT_RECOVERED``: anything else (fell, faulted on the track's safe range, or still
  not held).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pisc_sim.closed_loop import simulate_batch
from pisc_sim.configuration import GraphConfig
from pisc_control.supervisor import switching_criterion
from pisc_model.dynamics import wrap_to_upright

__all__ = [
    "CAUGHT_AT_ONCE",
    "CAUGHT_LATER",
    "NOT_RECOVERED",
    "RoaMap",
    "plot_roa",
    "region_of_attraction",
]

NOT_RECOVERED = 0
CAUGHT_AT_ONCE = 1
CAUGHT_LATER = 2


@dataclass(frozen=True)
class RoaMap:
    """Outcome per start; arrays indexed [rate, angle]."""

    label: str
    theta_rad: np.ndarray
    theta_dot_radps: np.ndarray
    x0_m: float
    outcome: np.ndarray
    caught_at_s: np.ndarray
    faulted: np.ndarray  # the cart left the safe range (or the state was not finite)
    inside_criterion: np.ndarray  # theta^2 + k_va theta_dot^2 < delta_s (4.1)
    k_va: float
    delta_s: float
    duration_s: float
    elapsed_s: float

    def fraction(self, code: int, mask: np.ndarray | None = None) -> float:
        sel = self.outcome if mask is None else self.outcome[mask]
        return float(np.mean(sel == code)) if sel.size else float("nan")

    def summary(self) -> str:
        n = self.outcome.size
        inside = self.inside_criterion
        return (f"{self.label}: {len(self.theta_dot_radps)} x {len(self.theta_rad)} starts at "
                f"x0 = {self.x0_m:+.3f} m, {self.duration_s:.2f} s each, in "
                f"{self.elapsed_s:.1f} s; caught at once {np.sum(self.outcome == CAUGHT_AT_ONCE)}"
                f", caught later {np.sum(self.outcome == CAUGHT_LATER)}, not recovered "
                f"{np.sum(self.outcome == NOT_RECOVERED)} of {n}; inside (4.1) "
                f"({np.sum(inside)} starts) caught at once "
                f"{100 * self.fraction(CAUGHT_AT_ONCE, inside):.1f} %, not recovered "
                f"{np.sum(inside & (self.outcome == NOT_RECOVERED))} of which "
                f"{np.sum(inside & (self.outcome == NOT_RECOVERED) & self.faulted)} faulted "
                "(cart out of the safe range)")


def region_of_attraction(
    config: GraphConfig,
    theta_rad: Sequence[float] | np.ndarray,
    theta_dot_radps: Sequence[float] | np.ndarray,
    *,
    x0_m: float = 0.0,
    duration_s: float = 1.5,
    hold_window_s: float = 0.5,
    hold_tolerance_rad: float = 0.05,
    label: str = "",
    progress: Callable[[int, int], None] | None = None,
) -> RoaMap:
    """Classify every (theta, theta_dot) start of the grid (see the module docstring).

    Angles are from upright (0 = upright); the cart starts at rest at ``x0_m``.
    The whole grid is one batch; the plant's compiled kernel spreads it over the cores.
    """
    theta = np.asarray(theta_rad, dtype=float)
    rate = np.asarray(theta_dot_radps, dtype=float)
    if theta.ndim != 1 or rate.ndim != 1 or theta.size == 0 or rate.size == 0:
        raise ValueError("region_of_attraction: theta_rad and theta_dot_radps must be "
                         "non-empty 1-D grids")
    if not 0.0 < hold_window_s <= duration_s:
        raise ValueError(f"hold_window_s = {hold_window_s} must be in (0, duration_s = "
                         f"{duration_s}]")
    grid_theta, grid_rate = np.meshgrid(theta, rate)
    started = time.perf_counter()
    job = _Job(config, float(x0_m), duration_s, duration_s - hold_window_s)
    caught_at, faulted, hold_theta = job.run(grid_theta, grid_rate, progress)
    elapsed = time.perf_counter() - started
    held = np.isfinite(caught_at) & ~faulted & (hold_theta < hold_tolerance_rad)
    codes = np.where(held & (caught_at == 0.0), CAUGHT_AT_ONCE,
                     np.where(held, CAUGHT_LATER, NOT_RECOVERED))
    sw = config.supervisor.switching
    inside = switching_criterion(sw.k_va, wrap_to_upright(grid_theta), grid_rate) < sw.delta_s
    return RoaMap(label, theta, rate, float(x0_m), codes, caught_at, faulted, inside,
                  sw.k_va, sw.delta_s, duration_s, elapsed)


@dataclass(frozen=True)
class _Job:
    config: GraphConfig
    x0_m: float
    duration_s: float
    hold_start_s: float

    def run(self, theta: np.ndarray, rate: np.ndarray,
            progress: Callable[[int, int], None] | None
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        outcome = simulate_batch(
            self.config, np.full(theta.shape, self.x0_m), self.duration_s,
            hold_start_s=self.hold_start_s, x_dot0_mps=0.0, theta0_rad=theta,
            theta_dot0_radps=rate, prime_estimator=True, progress=progress)
        return outcome.caught_at_s, np.asarray(outcome.faulted), outcome.hold_theta_rad


def plot_roa(maps: Sequence[RoaMap], path: Path, columns: int | None = None) -> Path:
    """The maps in rows of ``columns`` (all in one row by default), with the catch
    criterion (4.1) drawn on each (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import ListedColormap
    from matplotlib.patches import Patch

    colours = ListedColormap(["#d9d9d9", "#2c7fb8", "#a1dab4"])
    columns = len(maps) if columns is None else columns
    rows = -(-len(maps) // columns)
    fig, axes = plt.subplots(rows, columns, figsize=(5.5 * columns, 4.4 * rows + 0.4),
                             squeeze=False)
    for ax in axes.flat[len(maps):]:
        ax.set_visible(False)
    for ax, m in zip(axes.flat, maps, strict=False):
        ax.pcolormesh(m.theta_rad, m.theta_dot_radps, m.outcome, cmap=colours, vmin=-0.5,
                      vmax=2.5, shading="nearest")
        th = np.linspace(-np.sqrt(m.delta_s), np.sqrt(m.delta_s), 400)
        rate = np.sqrt(np.maximum(m.delta_s - th**2, 0.0) / m.k_va) if m.k_va > 0 else th * 0
        ax.plot(th, rate, "k--", lw=1.2)
        ax.plot(th, -rate, "k--", lw=1.2)
        ax.set_xlim(m.theta_rad[0], m.theta_rad[-1])
        ax.set_ylim(m.theta_dot_radps[0], m.theta_dot_radps[-1])
        ax.set_xlabel("theta(0) from upright [rad]")
        ax.set_ylabel("theta_dot(0) [rad/s]")
        ax.set_title(f"{m.label}: x0 = {m.x0_m:+.2f} m, {m.duration_s:.1f} s", fontsize=10)
    handles = [Patch(color="#2c7fb8", label="caught at once and held"),
               Patch(color="#a1dab4", label="caught later (after swing-up) and held"),
               Patch(color="#d9d9d9", label="not recovered"),
               plt.Line2D([], [], color="k", ls="--", label="catch criterion (4.1) = delta_s")]
    fig.legend(handles=handles, loc="lower center", ncol=4, fontsize=8)
    fig.tight_layout(rect=(0, 0.4 / (4.4 * rows + 0.4) + 0.03, 1, 1))
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path
