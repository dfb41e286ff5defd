"""The shooting searches of the feasibility study: direct shooting (:func:`shoot`) and
multiple shooting with the catch deadline brought down by continuation
(:func:`transcribe`), both ``scipy.optimize.least_squares`` on the compiled plant.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from pisc_analysis.feasibility import (CURRENT, THETA, THETA_DOT, X, X_DOT, Limits, Rig,
                                       Verdict, rollout, samples, verify, wrap)
from pisc_analysis.feasibility_feedback import Pool, hold_from, hold_gain

__all__ = ["Transcribed", "Transcription", "expand", "shoot", "transcribe"]


def expand(knots: np.ndarray, per_knot: int) -> np.ndarray:
    return np.repeat(knots, per_knot, axis=-1)


def shoot(rig: Rig, limits: Limits, guess: np.ndarray, per_knot: int,
          margin_m: float = 0.003, max_nfev: int = 60) -> np.ndarray:
    """Direct shooting: knot voltages (piecewise constant over ``per_knot`` periods)
    from ``guess`` (K,) that bring the rig upright at rest at the horizon's end.

    ``scipy.optimize.least_squares`` (trust region reflective, the bridge's voltage as
    bounds) on the residuals: the terminal theta (from the nearest upright), theta_dot /
    omega_0, x_dot and x (weighted), and penalties for every sample's distance past the
    safe range less ``margin_m`` and past the current limit. The Jacobian by forward
    differences, all K + 1 rollouts in one batch on the compiled plant.
    """
    from scipy.optimize import least_squares

    limit_i = limits.current_a
    hi, lo = limits.x_max_m - margin_m, limits.x_min_m + margin_m
    w0 = rig.omega0

    def residuals(states: np.ndarray) -> np.ndarray:
        end = states[:, -1]
        terminal = np.stack([2.0 * wrap(end[:, THETA]), 2.0 * end[:, THETA_DOT] / w0,
                             1.0 * end[:, X_DOT], 0.5 * end[:, X]], axis=-1)
        x = states[:, 1:, X]
        track = 30.0 * (np.maximum(x - hi, 0.0) + np.maximum(lo - x, 0.0))
        parts = [terminal, track]
        if limit_i is not None:
            parts.append(3.0 * np.maximum(np.abs(states[:, 1:, CURRENT]) - limit_i, 0.0))
        return np.concatenate(parts, axis=-1)

    step = 1e-3  # V

    def fun(v: np.ndarray) -> np.ndarray:
        return residuals(rollout(rig, expand(v[None, :], per_knot)))[0]

    def jac(v: np.ndarray) -> np.ndarray:
        # forward differences inward from the bounds
        signs = np.where(v + step > limits.voltage_v, -1.0, 1.0)
        batch = np.vstack([v, v + step * np.diag(signs)])
        r = residuals(rollout(rig, expand(batch, per_knot)))
        return ((r[1:] - r[0]) / (step * signs[:, None])).T

    v0 = np.clip(np.asarray(guess, dtype=float), -limits.voltage_v + 1e-6,
                 limits.voltage_v - 1e-6)
    result = least_squares(fun, v0, jac=jac,
                           bounds=(-limits.voltage_v, limits.voltage_v), method="trf",
                           x_scale=1.0, max_nfev=max_nfev, xtol=1e-10, ftol=1e-10)
    return np.asarray(result.x)


# -- multiple shooting -------------------------------------------------------------------

@dataclass(frozen=True)
class Transcription:
    """The settings of :func:`transcribe` (multiple shooting, the catch deadline by
    continuation)."""

    knot_periods: int = 1  # the voltage piecewise constant over knots of 1 period (5 ms)
    segment_periods: int = 40  # a shooting segment: 0.2 s
    tail_s: float = 0.6  # the catch region kept this long past the deadline, then the hold
    deadline_step_s: float = 0.04  # the continuation's first step of the catch deadline
    first_deadline_after_s: float = 0.5  # the latest deadline it starts from, past catch_by_s
    guesses: int = 2  # the best feedback rollouts it starts from
    max_nfev: int = 40  # least-squares evaluations per deadline
    track_margin_m: float = 0.0005
    region_margin: float = 0.002  # below delta_s of (4.1)
    current_margin: float = 0.99  # of the current limit
    tolerance: float = 1e-3  # the largest residual (scaled) that counts as met


@dataclass(frozen=True)
class Transcribed:
    """What :func:`transcribe` found: a witness (or None), its check, the earliest
    deadline met with a zero residual (inf if none), candidates checked."""

    voltages: np.ndarray | None
    verdict: Verdict | None
    earliest_s: float
    tried: int


# scales of the shooting nodes' states x, x_dot, theta, theta_dot, i (the unknowns are
# the states over these)
_NODE_SCALE = np.array([0.01, 0.1, 0.02, 0.2, 0.05])


class _Shooting:
    """Residuals and their Jacobian of one multiple-shooting problem: the voltage
    piecewise constant over knots of ``knot_periods``, the horizon cut into segments of
    ``segment_periods``, the unknowns the knot voltages and the state at the start of
    every segment but the first (scaled by :data:`_NODE_SCALE`). A residual block per
    segment: three hinges per sample (the safe range less a margin; the current limit;
    from the deadline sample on, the catch region (4.1) less a margin), then the
    continuity defect to the next node (5), or, for the last segment, the hand-over
    hinges (4): near upright, slow, the cart near the middle, where the LQR hold takes
    over. A zero residual is a voltage sequence meeting every rule up to the horizon."""

    def __init__(self, rig: Rig, limits: Limits, settings: Transcription, horizon: int,
                 deadline: int) -> None:
        self.rig, self.limits, self.s = rig, limits, settings
        self.kp, self.seg = settings.knot_periods, settings.segment_periods
        self.nseg = horizon // self.seg
        self.kps = self.seg // self.kp
        self.nknots = self.nseg * self.kps
        self.horizon, self.deadline = horizon, deadline
        self.hi = limits.x_max_m - settings.track_margin_m
        self.lo = limits.x_min_m + settings.track_margin_m
        self.i_max = (math.inf if limits.current_a is None
                      else settings.current_margin * limits.current_a)
        self.region = limits.delta_s - settings.region_margin
        self.block = 3 * self.seg + 5

    def split(self, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        knots = z[: self.nknots].reshape(self.nseg, self.kps)
        nodes = z[self.nknots:].reshape(self.nseg - 1, 5) * _NODE_SCALE
        return knots, np.vstack([self.rig.y0[None, :], nodes])

    def segments(self, starts: np.ndarray, knots: np.ndarray) -> np.ndarray:
        # batches of at most 256 rigs: the kernel's single-thread path (kernel_batch.CHUNK),
        # several times faster per rig than its threaded one on a shared 2-core machine
        volts = expand(knots, self.kp)
        return np.concatenate([rollout(self.rig, volts[a: a + 256], y0=starts[a: a + 256])
                               for a in range(0, len(starts), 256)])

    def _blocks(self, traj: np.ndarray, seg_index: np.ndarray, following: np.ndarray
                ) -> np.ndarray:
        """Residual blocks (B, block) of segment trajectories (B, seg + 1, 5) that are
        segments ``seg_index`` (B,), the next node ``following`` (B, 5)."""
        y = traj[:, 1:]
        k = seg_index[:, None] * self.seg + np.arange(1, self.seg + 1)[None, :]
        x = y[..., X]
        track = (np.maximum(x - self.hi, 0.0) + np.maximum(self.lo - x, 0.0)) / 0.005
        current = np.maximum(np.abs(y[..., CURRENT]) - self.i_max, 0.0) / 0.02
        reach = wrap(y[..., THETA]) ** 2 + self.limits.k_va * y[..., THETA_DOT] ** 2
        region = np.where(k >= self.deadline, np.maximum(reach - self.region, 0.0) / 0.02, 0.0)
        end = traj[:, -1]
        defect = (end - following) / _NODE_SCALE
        last = seg_index == self.nseg - 1
        handover = np.stack([
            np.maximum(np.abs(wrap(end[:, THETA])) - 0.05, 0.0) / 0.01,
            np.maximum(np.abs(end[:, THETA_DOT]) - 0.3, 0.0) / 0.1,
            np.maximum(np.abs(end[:, X_DOT]) - 0.15, 0.0) / 0.05,
            np.maximum(np.abs(end[:, X]) - 0.06, 0.0) / 0.01,
            np.zeros(len(end))], axis=-1)
        tail = np.where(last[:, None], handover, defect)
        return np.concatenate([track, current, region, tail], axis=-1)

    def residuals(self, z: np.ndarray) -> np.ndarray:
        knots, starts = self.split(z)
        traj = self.segments(starts, knots)
        index = np.arange(self.nseg)
        following = np.vstack([starts[1:], np.zeros((1, 5))])
        return self._blocks(traj, index, following).ravel()

    def jacobian(self, z: np.ndarray) -> np.ndarray:
        """Forward differences, every segment's perturbations in one batch: a segment's
        residuals depend on its knots and its start only (and its defect on the next
        node, with derivative -1 in the scaled unknowns)."""
        knots, starts = self.split(z)
        u_max = self.limits.voltage_v
        step_u, step_s = 1e-4, 1e-6
        per = 1 + self.kps + 5
        b_knots = np.repeat(knots, per, axis=0).reshape(self.nseg, per, self.kps)
        b_starts = np.repeat(starts, per, axis=0).reshape(self.nseg, per, 5)
        signs = np.where(knots + step_u > u_max, -1.0, 1.0)  # inward from the bound
        for a in range(self.kps):
            b_knots[:, 1 + a, a] += step_u * signs[:, a]
        for a in range(5):
            b_starts[:, 1 + self.kps + a, a] += step_s * _NODE_SCALE[a]
        index = np.repeat(np.arange(self.nseg), per)
        following = np.repeat(np.vstack([starts[1:], np.zeros((1, 5))]), per, axis=0)
        traj = self.segments(b_starts.reshape(-1, 5), b_knots.reshape(-1, self.kps))
        r = self._blocks(traj, index, following).reshape(self.nseg, per, self.block)
        base = r[:, 0]
        jac = np.zeros((self.nseg, self.block, len(z)))
        for j in range(self.nseg):
            cols = slice(j * self.kps, (j + 1) * self.kps)
            jac[j, :, cols] = ((r[j, 1: 1 + self.kps] - base[j]) / (step_u * signs[j][:, None])).T
            if j > 0:
                c0 = self.nknots + 5 * (j - 1)
                jac[j, :, c0: c0 + 5] = ((r[j, 1 + self.kps:] - base[j]) / step_s).T
            if j < self.nseg - 1:
                c1 = self.nknots + 5 * j
                jac[j, 3 * self.seg + np.arange(5), c1 + np.arange(5)] = -1.0
        from scipy.sparse import csr_matrix

        return csr_matrix(jac.reshape(self.nseg * self.block, len(z)))

    def unknowns(self, voltages: np.ndarray, states: np.ndarray) -> np.ndarray:
        """The unknowns of a trajectory: knot means of ``voltages`` (>= horizon values)
        and ``states`` (>= horizon + 1 samples) at the segments' starts."""
        knots = voltages[: self.horizon].reshape(-1, self.kp).mean(axis=1)
        nodes = states[self.seg: self.horizon: self.seg] / _NODE_SCALE
        return np.concatenate([knots, nodes.ravel()])

    def solve(self, z0: np.ndarray, max_nfev: int) -> tuple[np.ndarray, float]:
        from scipy.optimize import least_squares

        u_max = self.limits.voltage_v
        lower = np.full(len(z0), -np.inf)
        upper = np.full(len(z0), np.inf)
        lower[: self.nknots], upper[: self.nknots] = -u_max, u_max
        z0 = np.clip(z0, lower + 1e-9, upper - 1e-9)
        result = least_squares(self.residuals, z0, jac=self.jacobian, bounds=(lower, upper),
                               method="trf", tr_solver="lsmr", max_nfev=max_nfev,
                               tr_options={"atol": 1e-10, "btol": 1e-10}, x_scale="jac",
                               xtol=1e-12, ftol=1e-12, gtol=1e-12)
        return np.asarray(result.x), float(np.max(np.abs(result.fun), initial=0.0))


def transcribe(rig: Rig, limits: Limits, pool: Pool, settings: Transcription | None = None,
               k_gain: np.ndarray | None = None) -> Transcribed:
    """Multiple shooting with the catch deadline as the continuation parameter.

    The rule "in the catch region (4.1) for good from some t <= catch_by_s" is the same
    as "in it at every sample from catch_by_s on": the deadline. From each of the
    ``guesses`` best rollouts of the feedback search (``pool``), whose stay in the region
    begins late (at t_c), the deadline starts at min(t_c, ``catch_by_s`` +
    ``first_deadline_after_s``; a budget: a local method seldom moves a catch by
    seconds) and comes down by ``deadline_step_s`` to ``catch_by_s``; at each deadline
    d, ``scipy.optimize.least_squares`` (trust region reflective, the bridge's voltage
    as bounds) drives the residuals of :class:`_Shooting` over the horizon d +
    ``tail_s`` to zero (at most ``tolerance``), warm-started from the last deadline met
    (nodes included). A deadline not met is tried again half as far below the last one
    met, down to one period; then it stops. Met at ``catch_by_s``, the knots are
    re-simulated alone from the start, handed to the LQR hold (:func:`hold_from`) and
    checked (:func:`verify`)."""
    s = settings or Transcription()
    if s.segment_periods % s.knot_periods:
        raise ValueError(f"segment_periods ({s.segment_periods}) must be a multiple of "
                         f"knot_periods ({s.knot_periods})")
    period = rig.period_s
    steps = int(round(limits.duration_s / period))
    k_gain = hold_gain(rig) if k_gain is None else k_gain
    target = samples(limits.catch_by_s, period)
    step = max(1, int(round(s.deadline_step_s / period)))
    outside = (wrap(pool.states[..., THETA]) ** 2
               + limits.k_va * pool.states[..., THETA_DOT] ** 2 >= limits.delta_s)
    start = np.where(outside.any(axis=-1), steps + 1 - np.argmax(outside[..., ::-1], axis=-1), 0)
    earliest, tried = math.inf, 0
    best_verdict = None
    for j in np.argsort(pool.badness)[: s.guesses]:
        d = min(int(start[j]), target + int(round(s.first_deadline_after_s / period)))
        d = target + step * math.ceil(max(d - target, 0) / step)
        voltages, states = pool.voltages[j], pool.states[j]
        met, stride = math.inf, step
        while d >= target:
            horizon = s.segment_periods * math.ceil((d + s.tail_s / period)
                                                    / s.segment_periods)
            if horizon >= steps:
                break
            problem = _Shooting(rig, limits, s, horizon, d)
            z, worst = problem.solve(problem.unknowns(voltages, states), s.max_nfev)
            if worst > s.tolerance:
                # not met: a smaller step from the last deadline met, down to one period
                if stride == 1 or math.isinf(met):
                    break
                d += stride
                stride = max(1, stride // 2)
                d -= stride
                continue
            met = d * period
            # the next deadline starts from this solution: its voltages and the states of
            # its segments re-simulated from its nodes
            knots, starts = problem.split(z)
            seg_states = problem.segments(starts, knots)
            states = np.concatenate([seg_states[:, :-1].reshape(-1, 5), seg_states[-1:, -1]])
            voltages = expand(knots.ravel(), problem.kp)
            if d == target:
                break
            d = max(target, d - stride)
        earliest = min(earliest, met)
        if not met <= limits.catch_by_s + period / 2:
            continue
        y = rollout(rig, voltages)
        tail, _ = hold_from(rig, limits, y[-1][None, :], steps - len(voltages), k_gain)
        candidate = np.concatenate([voltages, tail[0]])
        verdict = verify(rig, limits, candidate)
        tried += 1
        if verdict.ok:
            return Transcribed(candidate, verdict, met, tried)
        best_verdict = verdict
    return Transcribed(None, best_verdict, earliest, tried)
