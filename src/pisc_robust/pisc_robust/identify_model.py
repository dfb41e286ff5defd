"""The model the fit simulates and the least-squares problem over the parameters
(:class:`Problem`: the segments' initial states eliminated, the Jacobian one batched call
of the compiled kernel, forward differences).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import numpy as np

from pisc_model.params import ModelParams, NoiseParams
from pisc_msgs_py.config import ConfigError
from pisc_plant import kernel_batch
from pisc_plant.plant import Plant
from pisc_plant.plant_config import PlantConfig, plant_set
from pisc_robust.identify_data import (
    BY_KEY,
    NOT_PLANT,
    QUANTISATION_RMS,
    FitError,
    Unknown,
)
from pisc_robust.identify_segments import Segments

__all__ = ["HELD_SAMPLES", "STATE_NAMES", "STATE_SCALE", "Problem", "config_value",
           "model_plant"]

STATE_SCALE = np.array([0.002, 0.02, 0.002, 0.05, 0.005, 0.005])  # x, x', th, th', v_ir, v_cur
STATE_NAMES = ("x", "x_dot", "theta", "theta_dot", "v_ir", "v_cur")
STEP = 1e-6  # forward-difference step, in units of each unknown's scale
#: A channel reading one code for at least this many samples in a row holds a level (50 ms:
#: the excitation's bit), whose quantisation error every such sample shares
HELD_SAMPLES = 10


def model_plant(base: PlantConfig) -> PlantConfig:
    """The model the fit simulates: ``base``'s values in the rig's full layout (armature
    current, quantised sensors and their filters, Coulomb and viscous friction), without
    noise and without end stops (segments at a stop are left out)."""
    from dataclasses import replace

    return replace(base, models=ModelParams(armature="full", current_loop="sampled_pi",
                                            sensors="quantised", sensor_filters=True,
                                            friction="coulomb", end_stops=False),
                   noise=NoiseParams())


def _with_values(config: PlantConfig, values: dict[str, float]) -> PlantConfig:
    """``config`` with the dotted parameters ``values`` set (one rig)."""
    sections: dict[str, dict[str, float]] = {}
    for name, value in values.items():
        section, _, leaf = name.partition(".")
        sections.setdefault(section, {})[leaf] = float(value)
    return dataclasses.replace(config, **{
        section: dataclasses.replace(getattr(config, section), **changes)
        for section, changes in sections.items()})


def config_value(config: PlantConfig, name: str) -> float:
    """The value of the dotted parameter ``name`` in ``config``."""
    section, _, leaf = name.partition(".")
    return float(getattr(getattr(config, section), leaf))


class Problem:
    """The least-squares problem over the parameters, the segments' initial states
    eliminated (variable projection).

    For parameters theta, each segment's initial state is fitted on its own (a damped
    Gauss-Newton iteration on six unknowns, every segment and perturbation a rig of one
    batched simulation); :meth:`residuals` is the weighted residual at those states, and
    :meth:`jacobian` its derivative with the states' response taken into account
    (Kaufman's projection: each segment's parameter columns minus their part along its
    own state columns). ``least_squares`` then works on the few parameters only.
    """

    def __init__(self, segments: Segments, base: PlantConfig, fit: Sequence[Unknown],
                 start: dict[str, float]) -> None:
        self.seg = segments
        self.base_config = base
        self.base = model_plant(base)
        self.fit = list(fit)
        self.period = base.loop.period_s
        self.sensors = base.sensors
        self.p = len(self.fit)
        self.start = start
        self.weights = np.full(3, 1.0 / QUANTISATION_RMS)  # 1 / (sigma in steps)
        s = self.sensors
        self.steps = np.array([s.adc_lsb_v, s.encoder_rad_per_count, s.adc_lsb_v])
        self.flat_mask = segments.mask.reshape(segments.count, -1)
        self.rows = np.flatnonzero(segments.mask.reshape(-1))
        per_segment = self.flat_mask.sum(axis=1)
        self.row_edges = np.concatenate([[0], np.cumsum(per_segment)])
        self.scale = np.array([u.scale for u in self.fit])
        self.offsets = np.zeros((segments.count, 6))  # the states, scaled, from the guess
        self._solved: tuple[bytes, np.ndarray] | None = None
        self.simulations = 0

    # unknowns <-> values
    def initial(self) -> np.ndarray:
        return np.array([self.start[u.key] / u.scale for u in self.fit])

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        low = np.array([u.low / u.scale for u in self.fit])
        high = np.array([(min(u.high, 0.95 * self.period) if u.key == "delay" else u.high)
                         / u.scale for u in self.fit])
        return low, high

    def values(self, z: np.ndarray) -> dict[str, float]:
        out = dict(self.start)
        for k, u in enumerate(self.fit):
            out[u.key] = float(z[k] * u.scale)
        return out

    def states(self, offsets: np.ndarray | None = None) -> np.ndarray:
        """Initial states (n, 6): x, x_dot, theta, theta_dot, v_ir, v_cur."""
        return self.seg.guess + (self.offsets if offsets is None else offsets) * STATE_SCALE

    # simulation
    def simulate(self, values: dict[str, np.ndarray], y0: np.ndarray,
                 rows: np.ndarray) -> np.ndarray:
        """Predicted (IR voltage, angle, current sensor voltage) (rigs, length, 3) of the
        segments ``rows`` (one per rig), rig k with ``values[key][k]`` and state ``y0[k]``.

        Groups of at most ``kernel_batch.CHUNK`` rigs, which the kernel steps on one thread:
        its threads gain nothing at this size and, spinning, cost milliseconds a call."""
        out = np.empty((len(rows), self.seg.length, 3))
        for lo in range(0, len(rows), kernel_batch.CHUNK):
            group = slice(lo, lo + kernel_batch.CHUNK)
            out[group] = self._simulate({k: np.asarray(v)[group] for k, v in values.items()},
                                        y0[group], rows[group])
        return out

    def _simulate(self, values: dict[str, np.ndarray], y0: np.ndarray,
                  rows: np.ndarray, states: np.ndarray | None = None) -> np.ndarray:
        self.simulations += 1
        seg = self.seg
        rigs = len(rows)
        plant = self._plant(values)
        idx = plant.index
        delay = np.broadcast_to(values["delay"], (rigs,))
        # the current sensor's zero error, as the voltage it adds at the ADC
        offset = np.broadcast_to(values["current_offset"], (rigs,)) / (
            self.sensors.current_scale_a_per_v)
        u = seg.u[rows]
        latency = seg.latency[rows]
        acting, pending, pending_u = self._acting_at_start(rows, delay)
        y = self._start_state(plant, y0, acting)
        length = seg.length
        out = np.empty((rigs, length, 3))
        for j in range(length):
            out[:, j, 0] = y[:, idx["v_ir"]]
            out[:, j, 1] = y[:, idx["theta"]]
            out[:, j, 2] = y[:, idx["v_cur"]] + offset
            if states is not None:
                states[:, j] = y
            if j == length - 1:
                break
            y, acting, pending, pending_u = self._period(
                plant, y, acting, pending, pending_u, u[:, j], latency[:, j] + delay)
        if not np.all(np.isfinite(out)):
            raise FitError("the model diverged (a value that is not finite) at " + ", ".join(
                f"{k} = {np.asarray(v).ravel()[0]:.4g}" for k, v in values.items()
                if BY_KEY[k] in self.fit))
        return out

    def _plant(self, values: dict[str, np.ndarray]) -> Plant:
        """The plant set of one rig per value (the plant's parameters among ``values``)."""
        plant_values = {BY_KEY[key].name: v for key, v in values.items()
                        if key not in NOT_PLANT}
        try:
            return Plant(plant_set(self.base, plant_values))
        except ConfigError as exc:
            raise FitError(f"the fit reached an invalid model: {exc}") from None

    def _acting_at_start(self, rows: np.ndarray, delay: np.ndarray
                         ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(the voltage acting at each segment's first sample, the arrival in the first
        period of a voltage that came late (NaN: none), that voltage)."""
        seg = self.seg
        period = self.period
        acting = seg.u_before[rows]
        pending = np.full(len(rows), np.nan)  # arrival of a late voltage in this period, s
        pending_u = acting.copy()
        if seg.latency_before is not None:
            d = seg.latency_before[rows] + delay
            late = d >= period
            acting = np.where(late, seg.u_before2[rows], acting)
            pending = np.where(late, np.minimum(d - period, 0.999 * period), np.nan)
        return acting, pending, pending_u

    @staticmethod
    def _start_state(plant: Plant, y0: np.ndarray, acting: np.ndarray) -> np.ndarray:
        """The plant's state from a segment's six (x, x_dot, theta, theta_dot, v_ir, v_cur),
        the armature current at its quasi-static value under ``acting``."""
        idx = plant.index
        motor = plant.config.motor
        resistance = np.broadcast_to(np.asarray(motor.resistance_ohm, dtype=float),
                                     (len(y0),))
        ker = (np.asarray(motor.back_emf_v_s_per_rad, dtype=float)
               / np.asarray(motor.wheel_radius_m, dtype=float))
        y = np.empty((len(y0), plant.size))
        y[:, idx["x"]] = y0[:, 0]
        y[:, idx["x_dot"]] = y0[:, 1]
        y[:, idx["theta"]] = y0[:, 2]
        y[:, idx["theta_dot"]] = y0[:, 3]
        y[:, idx["i"]] = (plant.applied(acting) - ker * y0[:, 1]) / resistance
        y[:, idx["v_ir"]] = y0[:, 4]
        y[:, idx["v_cur"]] = y0[:, 5]
        return y

    def _period(self, plant: Plant, y: np.ndarray, acting: np.ndarray, pending: np.ndarray,
                pending_u: np.ndarray, u: np.ndarray, arrival: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """One period from a sample: the late voltage of the sample before arrives at
        ``pending`` (if any), then this sample's ``u`` at ``arrival`` (its latency plus
        the delay), unless it is late too (>= a period); bytes reach the rig in the order
        they were written. Returns ``(y, acting, pending, pending_u)`` at the next sample."""
        period = self.period
        t = np.zeros(len(y))
        if not np.all(np.isnan(pending)):
            has = ~np.isnan(pending)
            t = np.where(has, pending, 0.0)
            if np.any(t > 0.0):
                y = plant.advance(y, acting, t)
            acting = np.where(has, pending_u, acting)
        arrival = np.clip(arrival, 0.0, 1.999 * period)
        late = arrival >= period
        d = np.where(late, period, np.maximum(arrival, t))
        if np.any(d > t):
            y = plant.advance(y, acting, d - t)
        acting = np.where(late, acting, u)
        if np.any(d < period):
            y = plant.advance(y, acting, period - d)
        return y, acting, np.where(late, arrival - period, np.nan), u

    def _weighted(self, predicted: np.ndarray, rows: np.ndarray) -> np.ndarray:
        """(rigs, length * 3) weighted residuals in sensor steps, 0 where masked."""
        r = (predicted - self.seg.measured[rows]) / self.steps * self.weights
        return np.where(self.seg.mask[rows], r, 0.0).reshape(len(rows), -1)

    def _batch(self, z: np.ndarray, offsets: np.ndarray, parameters: bool
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """Residuals (n, length*3) at the states, their derivatives by the states
        (6, n, length*3) and, with ``parameters``, by the parameters (p, n, length*3):
        one batched simulation, forward differences."""
        n_seg, p = self.seg.count, self.p
        extra = p if parameters else 0
        blocks = 1 + extra + 6
        # segment-major: a segment's rigs side by side share their steps (its latencies),
        # and the kernel computes the exponential scheme's tables once for such a run
        rows = np.repeat(np.arange(n_seg), blocks)
        which = np.tile(np.arange(blocks), n_seg)  # 0 base, then parameters, then states
        values = {k: np.full(len(rows), v) for k, v in self.values(z).items()}
        for k in range(extra):
            u = self.fit[k]
            values[u.key][which == 1 + k] += STEP * u.scale
        y0 = np.repeat(self.states(offsets), blocks, axis=0)
        for c in range(6):
            y0[which == 1 + extra + c, c] += STEP * STATE_SCALE[c]
        r = self._weighted(self.simulate(values, y0, rows), rows).reshape(n_seg, blocks, -1)
        r = r.transpose(1, 0, 2)
        diff = (r[1:] - r[0]) / STEP  # per unit of the scaled unknowns
        return r[0], diff[extra:], (diff[:extra] if parameters else None)

    def solve_states(self, z: np.ndarray, iterations: int = 8) -> np.ndarray:
        """Fit every segment's initial state for parameters ``z``; the residuals (n, L*3).

        Damped Gauss-Newton on each segment's six unknowns, the derivatives by forward
        differences in the same batched simulation as the residuals (the calls cost
        about what a simulation of the segments alone costs); a segment whose cost a
        step raised goes back and is damped more."""
        key = np.asarray(z, dtype=float).tobytes()
        if self._solved is not None and self._solved[0] == key:
            return self._solved[1]
        offsets = self.offsets.copy()
        damping = np.full(self.seg.count, 1e-6)
        kept: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None  # r, ds, cost
        step = np.zeros_like(offsets)
        for _ in range(iterations):
            r, ds, _ = self._batch(z, offsets, parameters=False)
            cost = np.einsum("ij,ij->i", r, r)
            if kept is not None:
                worse = cost > kept[2]
                if worse.any():
                    offsets[worse] -= step[worse]
                    r[worse], ds[:, worse], cost[worse] = (kept[0][worse], kept[1][:, worse],
                                                          kept[2][worse])
                damping = np.where(worse, damping * 100.0, np.maximum(damping * 0.1, 1e-9))
            kept = (r, ds, cost)
            a = np.einsum("cnk,dnk->ncd", ds, ds)
            diagonal = np.maximum(np.einsum("ncc->nc", a), 1e-12)
            a += damping[:, None, None] * np.eye(6) * diagonal[:, :, None]
            g = np.einsum("cnk,nk->nc", ds, r)
            step = -np.linalg.solve(a, g[:, :, None])[:, :, 0]
            promised = -np.einsum("nc,nc->n", g, step)
            if promised.sum() < 1e-10 * max(cost.sum(), 1.0):
                break
            offsets = offsets + step
        else:
            r, _, _ = self._batch(z, offsets, parameters=False)
            worse = np.einsum("ij,ij->i", r, r) > kept[2]
            offsets[worse] -= step[worse]
            r[worse] = kept[0][worse]
        self.offsets = offsets
        self._solved = (key, r)
        return r

    def residuals(self, z: np.ndarray) -> np.ndarray:
        r = self.solve_states(z)
        return r.reshape(-1)[self.rows]

    def jacobian(self, z: np.ndarray) -> np.ndarray:
        """d residuals / d parameters with the states following (Kaufman's projection)."""
        self.solve_states(z)
        _, ds, dp = self._batch(z, self.offsets, parameters=True)
        # per segment: J_p - J_s (J_s^T J_s)^-1 J_s^T J_p
        a = np.einsum("cnk,dnk->ncd", ds, ds)
        b = np.einsum("cnk,pnk->ncp", ds, dp)
        solved = np.linalg.solve(a + 1e-12 * np.eye(6), b)  # (n, 6, p)
        projected = dp - np.einsum("cnk,ncp->pnk", ds, solved)
        return projected.reshape(self.p, -1)[:, self.rows].T

    def timing(self, z: np.ndarray) -> tuple[np.ndarray, float]:
        """Each cycle's voltage timing as the current sensor tells it: (the change of
        each cycle's delay, (n, length), 0 where the data say nothing; the spread of
        the delays about the recorded latency plus ``delay``, s).

        The voltage answering sample k reaches the rig some time after the latency the
        bag records (the way from the controllers' publication to the rig is not
        recorded), and a current step a fraction of a millisecond early or late moves
        the filtered current at sample k + 1 by several ADC codes (and the cart's
        impulse with it). From the model's state at each sample, one period is
        simulated at the current delay and a little later: the slope s of the
        predicted current sensor voltage against the delay and the residual r at
        k + 1 give the correction -s r / (s^2 + sigma_q^2 / sigma_e^2), the mean of the
        delay given r when the delays scatter by sigma_e about their mean and the sensor
        reads with sigma_q (both by moments: r^2 = sigma_q^2 + s^2 sigma_e^2 over the
        cycles). A cycle whose current barely changes keeps its delay.
        """
        seg = self.seg
        n_seg, length = seg.count, seg.length
        values = self.values(z)
        rows = np.arange(n_seg)
        states = np.empty((n_seg, length, Plant(self.base).size))
        predicted = self._simulate({k: np.full(n_seg, v) for k, v in values.items()},
                                   self.states(), rows, states)
        single = Plant(_with_values(self.base, {BY_KEY[k].name: v for k, v in values.items()
                                                if k not in NOT_PLANT}))
        index = single.index["v_cur"]
        period = self.period
        # cycles whose voltage and the one before came on time (the late ones keep theirs)
        before = (np.zeros(n_seg) if seg.latency_before is None else seg.latency_before)
        previous = np.concatenate([before[:, None], seg.latency[:, :-2]], axis=1)
        on_time = ((seg.latency[:, :-1] + values["delay"] < 0.999 * period)
                   & (previous + values["delay"] < period))
        cycle = (np.arange(length - 1)[None, :] < (seg.size - 1)[:, None]) & on_time
        y = states[:, :-1][cycle]
        acting = np.concatenate([seg.u_before[:, None], seg.u[:, :-1]], axis=1)[:, :-1][cycle]
        new = seg.u[:, :-1][cycle]
        d0 = np.clip(seg.latency[:, :-1][cycle] + values["delay"], 0.0, 0.999 * period)
        shift = np.where(d0 + 1e-4 < 0.999 * period, 1e-4, -1e-4)

        def current_after(d: np.ndarray) -> np.ndarray:
            out = np.empty(len(d))
            for lo in range(0, len(d), 4096):
                g = slice(lo, lo + 4096)
                y1 = single.advance(y[g], acting[g], d[g])
                out[g] = single.advance(y1, new[g], period - d[g])[:, index]
            return out

        at = current_after(d0)
        slope = (current_after(d0 + shift) - at) / shift
        r = (predicted[:, 1:, 2][cycle] - seg.measured[:, 1:, 2][cycle])
        r = np.where(seg.mask[:, 1:, 2][cycle], r, 0.0)
        # moments: r^2 = sigma_q^2 + sigma_e^2 s^2
        design = np.column_stack([np.ones_like(slope), slope * slope])
        (q2, e2), *_ = np.linalg.lstsq(design, r * r, rcond=None)
        q2 = max(q2, (QUANTISATION_RMS * self.steps[2]) ** 2)
        if not e2 > 0.0:
            return np.zeros((n_seg, length)), 0.0
        change = -slope * r / (slope * slope + q2 / e2)
        change = np.clip(d0 + change, 0.0, 0.999 * period) - d0
        out = np.zeros((n_seg, length))
        out[:, :-1][cycle] = change
        return out, math.sqrt(e2)

    def row_codes(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(the measured code, the channel, whether it is held) of every residual row:
        ADC codes of the IR and current readings, encoder counts of the angle (each
        rounded: noisy or off-grid readings are taken at their nearest code); a row is
        held when its channel reads the same code for at least :data:`HELD_SAMPLES`
        samples in a row (a level, not a signal passing through the code). Counting
        every current reading as held (the PI loop (3.47) acts on the code it reads)
        made R's intervals cover through the driver but widened J_m's past
        :data:`pisc_robust.identify.IDENTIFIABLE` (docs/identification.md, "The quantisation floor")."""
        s = self.sensors
        m = self.seg.measured
        codes = np.rint(np.stack([(m[..., 0] - s.adc_ref_low_v) / s.adc_lsb_v - 0.5,
                                  (m[..., 1] - s.encoder_zero_rad) / s.encoder_rad_per_count,
                                  (m[..., 2] - s.adc_ref_low_v) / s.adc_lsb_v - 0.5],
                                 axis=-1)).astype(np.int64)
        mask = self.seg.mask
        # runs of one code along each segment's samples, per channel: (n, 3, length)
        c, v = codes.transpose(0, 2, 1), mask.transpose(0, 2, 1)
        start = np.ones(c.shape, dtype=bool)
        start[..., 1:] = (c[..., 1:] != c[..., :-1]) | (v[..., 1:] != v[..., :-1])
        run = np.cumsum(start.reshape(-1)) - 1
        held = (np.bincount(run)[run] >= HELD_SAMPLES).reshape(c.shape).transpose(0, 2, 1)
        channel = np.broadcast_to(np.arange(3), m.shape)
        return (codes.reshape(-1)[self.rows], channel.reshape(-1)[self.rows],
                held.reshape(-1)[self.rows])

    def segment_rows(self, s: int) -> slice:
        return slice(self.row_edges[s], self.row_edges[s + 1])

    def channel_rms(self, z: np.ndarray) -> np.ndarray:
        """RMS residual of each channel, in the sensor's steps (unweighted)."""
        r = self.residuals(z)
        channel = np.tile(np.arange(3), self.seg.count * self.seg.length)[self.rows]
        return np.array([math.sqrt(np.mean((r[channel == c] / self.weights[c]) ** 2))
                         for c in range(3)])

    def reweight(self, z: np.ndarray) -> None:
        """Weight each channel by its residual RMS at ``z`` (at least quantisation's)."""
        self.weights = 1.0 / np.maximum(self.channel_rms(z), QUANTISATION_RMS)
        self._solved = None

    def forget(self) -> None:
        """Solve the states anew at the next evaluation (the segments' data changed)."""
        self._solved = None

    def predictions(self, z: np.ndarray) -> np.ndarray:
        """Predicted (IR voltage, angle, current sensor voltage) of every segment."""
        self.solve_states(z)
        rows = np.arange(self.seg.count)
        values = {k: np.full(len(rows), v) for k, v in self.values(z).items()}
        return self.simulate(values, self.states(), rows)

