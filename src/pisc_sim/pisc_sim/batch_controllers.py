"""The controllers of a batch, compiled: one pass over the rigs per cycle (numba), with
the measurement before them and the bookkeeping after them.

:func:`pisc_sim.closed_loop.simulate_batch` runs the estimator, the supervisor and the
current loop of every rig each cycle. Here one compiled loop over the rigs, split
between the cores (``prange``), runs for each rig the laws the nodes run, compiled from
their Python source as they are (:func:`pisc_control.estimator.estimator_step`,
:func:`pisc_control.adaptation.adaptation_step`,
:func:`pisc_control.supervisor.supervisor_step` with the swing-up's and the catch's laws
it calls, :func:`pisc_control.current_loop.current_loop_step`). The compiled form gives
the bits the nodes give: numba compiles without ``fastmath``, so no multiply-add is fused
and nothing is reassociated, and ``math.sin`` and ``math.cos`` are the C library's in
both (``test_batch_controllers`` compares the compiled pass with the nodes' one-rig
controllers over closed-loop runs and hostile inputs).

For :func:`~pisc_sim.closed_loop.simulate_batch` (:meth:`BatchControllers.track`,
:meth:`BatchControllers.cycle`) the same pass also does what surrounds the controllers
in a cycle, which numpy did in a few dozen more passes over the rigs: the sensors'
measurement from the plant's state (:meth:`pisc_plant.plant.Plant.measurement` with
quantised sensors behind their filters, noise included; numpy measures for it otherwise
and where a reading is not finite), the outcomes' bookkeeping, and the actuator's
saturation and quantisation of the voltage, so that the plant steps the rows in place
(:meth:`pisc_plant.plant.Plant.advance_in_place`). The outcomes equal the numpy path's
(``test_batch_controllers``).

numba's cache keys an entry on its own file's time stamp only; the compiled pass holds
the code of the laws' modules (:data:`LAW_MODULES`), so when one of them is newer than
the cache's index, the index is removed here before numba reads it
(:func:`drop_stale_cache`) and the pass compiles anew.
Experiments (``experiment.kind``) are not compiled: :func:`supported` says so and the
batch then runs them over arrays (:meth:`pisc_control.supervisor.Supervisor.update`).
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import numba
import numpy as np
from numba.extending import register_jitable

from pisc_control import (
    adaptation,
    catch,
    current_loop,
    estimator,
    floatmath,
    supervisor,
    swing_up,
)
from pisc_control.estimator import EstimatorState, estimator_constants
from pisc_control.supervisor import CATCH, FAULT, FAULT_NONE, SWING_UP, Supervisor
from pisc_model import sensors
from pisc_plant.plant import Plant
from pisc_sim.configuration import GraphConfig

__all__ = ["LAW_MODULES", "BatchControllers", "drop_stale_cache", "supported", "warm_up"]

#: the modules whose laws the compiled pass holds
LAW_MODULES = (floatmath, estimator, adaptation, swing_up, catch, supervisor, current_loop)


def drop_stale_cache(module_file: str, pattern: str, sources) -> None:
    """Remove the numba cache indexes ``pattern`` of ``module_file`` that are older than
    one of ``sources`` (modules or paths), whose code the compiled functions of
    ``module_file`` hold (numba compares the time stamp of ``module_file`` alone)."""
    newest = max(Path(getattr(m, "__file__", m)).stat().st_mtime for m in sources)
    cache = Path(module_file).parent / "__pycache__"
    try:
        for index in cache.glob(f"{Path(module_file).stem}.{pattern}.nbi"):
            if index.stat().st_mtime < newest:
                index.unlink(missing_ok=True)
    except OSError:  # a read-only install: numba then keeps its cache elsewhere
        pass


drop_stale_cache(__file__, "_pass-*", LAW_MODULES)
# the laws the pass calls, callable from compiled code (and unchanged as Python functions)
for _function in (floatmath.clip, floatmath.floor, floatmath.sin, floatmath.cos,
                  floatmath.wrap, swing_up.lyapunov_force, swing_up.pendulum_energy,
                  swing_up.energy_pump_force, catch.catch_force, catch.held_catch_force,
                  catch.hold_blend, catch.guard_lets_go, catch.narrow_interval,
                  catch.governor_interval, catch.catch_reference,
                  supervisor.switching_criterion, supervisor.startup_target,
                  supervisor.fault_code, current_loop.current_setpoint_step,
                  current_loop.pi_step):
    register_jitable(error_model="numpy")(_function)
# inlined into the pass (numba's own inlining), which calls them for every rig
_estimator_step = numba.njit(estimator.estimator_step, error_model="numpy", inline="always")
_supervisor_step = numba.njit(supervisor.supervisor_step, error_model="numpy",
                              inline="always")
_current_loop_step = numba.njit(current_loop.current_loop_step, error_model="numpy",
                                inline="always")
_wrap = numba.njit(floatmath.wrap, error_model="numpy", inline="always")
_adaptation_step = numba.njit(adaptation.adaptation_step, error_model="numpy",
                              inline="always")


@numba.njit(error_model="numpy", inline="always")
def _maximum(a, b):
    """np.maximum of two floats (a NaN in either gives NaN)."""
    return a if (a >= b or a != a) else b


@numba.njit(error_model="numpy", inline="always")
def _minimum(a, b):
    """np.minimum of two floats (a NaN in either gives NaN)."""
    return a if (a <= b or a != a) else b


@numba.njit(error_model="numpy", inline="always")
def _actuator(full_scale, levels, step, v):
    """ActuatorParams.apply of one voltage: saturated, then quantised (NaN stays)."""
    v = _minimum(_maximum(v, -full_scale), full_scale)  # np.clip
    if levels == 0.0 or v != v:
        return v
    magnitude = min(np.floor(abs(v) / step + 0.5), levels)
    sign = 1.0 if v > 0.0 else (-1.0 if v < 0.0 else 0.0)  # np.sign
    return sign * magnitude * step


@numba.njit(cache=True, error_model="numpy", parallel=True)
def _pass(s, w, k, rows, ac, adapt, c, est_a, est_b, first, est_first, span, oldest,
          write, x_hist, theta_hist, v_x, v_theta, mode, fault, caught, startup_target, reference, integral, measure, y,
          ir_index, cur_index, draws, m, ir_table, x, theta, current, book, t, hold,
          track_range, force_per_amp, faulted, previous_mode, caught_at, first_catch,
          hold_theta, hold_x, hold_i2, x_min, x_max, unheld_at, box_theta, box_x, force_out,
          setpoint_out, voltage_out, command_out, applied_out):
    """One cycle of every rig; state in place. Returns the number of rigs whose
    measurement the pass does not take (then nothing else has been done).

    ``measure``: take the measurements from the plant's state ``y`` (rigs, size) first,
    into x, theta, current, as :meth:`pisc_plant.plant.Plant.measurement` does with
    quantised sensors behind their filters: ``draws`` (rigs, 3) of noise when it has
    rows, the constants ``m`` (:func:`_plant_constants`), the IR curve of every
    ADC code from numpy (``ir_table``); a reading that is not finite, or an angle too
    large for the count's integer, is not taken here (the caller measures with numpy
    and calls again with ``measure`` false). Otherwise x, theta, current are given.

    ``book``: keep simulate_batch's outcomes (at time t; ``hold``: inside the hold
    window; ``track_range``: y is a state after an advance, whose x the range takes;
    ``unheld_at``: the last sample time the true state was outside the hold box
    |theta| < ``box_theta``, |x| < ``box_x``, so that a run is held from T when it is
    below T)
    and write the plant's command (the voltage, or ``force_per_amp`` i_d when that is
    positive: an ideal force source) and what acts on the plant (the voltage through
    the actuator, :meth:`pisc_model.params.ActuatorParams.apply`, or the force).
    """
    rigs = x.shape[0]
    if measure:
        lsb, low, top = m[M_LSB], m[M_LOW], m[M_TOP]
        noisy = draws.shape[0] > 0
        bad = 0
        for r in numba.prange(rigs):
            v_ir = y[r, ir_index]
            v_cur = y[r, cur_index]
            th = y[r, 2]
            if noisy:  # Plant._sensor_voltages and _noisy
                th = th + m[M_THETA_STD] * draws[r, 1]
                distance = _maximum(m[M_IR_ORIGIN] - y[r, 0], 1e-3)
                v_ir = v_ir + v_ir / (m[M_IR_EXPONENT] * distance) * m[M_X_STD] * draws[r, 0]
                v_cur = v_cur + m[M_CURRENT_STD] * draws[r, 2] / m[M_CURRENT_SCALE]
            turns = (th - m[M_ENCODER_ZERO]) / m[M_RAD_PER_COUNT] + 0.5
            if not (math.isfinite(v_ir) and math.isfinite(v_cur) and abs(turns) < 2.0 ** 62):
                bad += 1
                continue
            # sensors.adc_code (truncated, saturated), encoder_count, decode
            ir_code = min(max(np.floor((v_ir - low) / lsb), 0.0), top)
            cur_code = min(max(np.floor((v_cur - low) / lsb), 0.0), top)
            x[r] = ir_table[int(ir_code)]
            theta[r] = np.floor(turns) * m[M_RAD_PER_COUNT] + m[M_ENCODER_ZERO]
            current[r] = (m[M_CURRENT_SCALE] * (cur_code * lsb + low)) - m[M_CURRENT_OFFSET]
        if bad:
            return bad
    for r in numba.prange(rigs):
        xr, thr = x[r], theta[r]
        if est_first:
            x_dot = 0.0
            theta_dot = 0.0
        else:
            x_dot, theta_dot = _estimator_step(est_a, est_b, span, xr, thr, x_hist[r, oldest],
                                               theta_hist[r, oldest], v_x[r], v_theta[r])
        x_hist[r, write] = xr
        theta_hist[r, write] = thr
        v_x[r] = x_dot
        v_theta[r] = theta_dot
        pendulum = _adaptation_step(ac, adapt[r], xr, thr, first or mode[r] != CATCH)
        force, md, f, ck, tg, ref = _supervisor_step(
            s, w, k, rows, pendulum, first, xr, x_dot, thr, theta_dot, mode[r], fault[r],
            caught[r], startup_target[r], reference[r])
        mode[r], fault[r], caught[r], startup_target[r], reference[r] = md, f, ck, tg, ref
        i_d, voltage, integral[r] = _current_loop_step(c, md == FAULT, force,
                                                       current[r], integral[r])
        force_out[r] = force
        setpoint_out[r] = i_d
        voltage_out[r] = voltage
        if book:  # simulate_batch's bookkeeping, element by element
            if track_range:
                x_min[r] = _minimum(x_min[r], y[r, 0])
                x_max[r] = _maximum(x_max[r], y[r, 0])
            faulted[r] = faulted[r] or md == FAULT
            catching = md == CATCH
            if catching and previous_mode[r] != CATCH:
                caught_at[r] = t
            elif not catching:
                caught_at[r] = np.inf
            if catching and not math.isfinite(first_catch[r]):
                first_catch[r] = t
            previous_mode[r] = md
            off_upright = abs(_wrap(y[r, 2]))
            if not (off_upright < box_theta and abs(y[r, 0]) < box_x):
                unheld_at[r] = t
            if hold:
                hold_theta[r] = _maximum(hold_theta[r], off_upright)
                hold_x[r] = _maximum(hold_x[r], abs(y[r, 0]))
                hold_i2[r] += i_d * i_d
            if force_per_amp > 0.0:
                command_out[r] = applied_out[r] = force_per_amp * i_d
            else:
                command_out[r] = voltage
                applied_out[r] = _actuator(m[M_FULL_SCALE], m[M_LEVELS], m[M_STEP], voltage)
    return 0


# places in the pass's constants of the plant (its sensors, its noise, its actuator)
(M_LSB, M_LOW, M_TOP, M_IR_ORIGIN, M_IR_EXPONENT, M_CURRENT_SCALE, M_CURRENT_OFFSET,
 M_ENCODER_ZERO, M_RAD_PER_COUNT, M_X_STD, M_THETA_STD, M_CURRENT_STD, M_FULL_SCALE,
 M_LEVELS, M_STEP, N_M) = range(16)


def _plant_constants(plant: Plant) -> tuple[np.ndarray, np.ndarray, bool]:
    """The pass's constants of ``plant`` (its actuator, its sensors) with the IR table,
    and whether the pass measures it (not with ideal sensors, without sensor filters or
    for a plant set: numpy does)."""
    config = plant.config
    a, s, n = config.actuator, config.sensors, config.noise
    m = np.zeros(N_M)
    m[M_FULL_SCALE], m[M_LEVELS], m[M_STEP] = a.full_scale_v, a.command_levels, a.step_v
    if (config.models.sensors == "ideal" or not config.models.sensor_filters
            or plant.rigs is not None):
        return m, np.zeros(1), False
    m[M_LSB], m[M_LOW], m[M_TOP] = s.adc_lsb_v, s.adc_ref_low_v, s.adc_levels - 1
    m[M_IR_ORIGIN], m[M_IR_EXPONENT] = s.ir_origin_m, s.ir_exponent
    m[M_CURRENT_SCALE], m[M_CURRENT_OFFSET] = s.current_scale_a_per_v, s.current_offset_a
    m[M_ENCODER_ZERO], m[M_RAD_PER_COUNT] = s.encoder_zero_rad, s.encoder_rad_per_count
    m[M_X_STD], m[M_THETA_STD], m[M_CURRENT_STD] = n.x_std_m, n.theta_std_rad, n.current_std_a
    # the host's IR curve (4.8) of every code, by numpy's power as sensors.decode takes it
    table = sensors.ir_position(s, sensors.adc_voltage(s, np.arange(s.adc_levels)))
    return m, np.ascontiguousarray(table, dtype=float), True


def supported(config: GraphConfig) -> bool:
    """Whether the compiled cores cover this configuration (all but experiments)."""
    return config.supervisor.experiment.kind == "none"


class BatchControllers:
    """The controllers of ``rigs`` rigs, stepped a cycle at a time by the compiled pass.

    ``estimator`` is the estimator's state before the first cycle (a primed previous
    sample, :func:`pisc_sim.closed_loop.simulate_batch`), flat arrays of ``rigs``
    values; the default is none (the first sample gives zero velocity).
    """

    def __init__(self, config: GraphConfig, supervisor: Supervisor, rigs: int,
                 estimator: EstimatorState | None = None) -> None:
        if not supported(config):
            raise ValueError(f"experiment.kind = {config.supervisor.experiment.kind!r}: "
                             "experiments run over arrays (Supervisor.update), not in the "
                             "compiled pass")
        period = config.loop.period_s
        self._s, self._w, self._k = supervisor.constants
        self._rows = np.ascontiguousarray(supervisor.governor_rows, dtype=float).reshape(-1, 8)
        sc = supervisor.config
        self._ac = supervisor.adaptation
        self._adapt = np.zeros((rigs, adaptation.adaptation_size(sc.adaptation)))
        for row in self._adapt:
            adaptation.adaptation_init(sc.adaptation, sc.rig, row)
        self._c = current_loop.current_loop_constants(config.plant.motor, config.current_loop,
                                                      period)
        self._est_a, self._est_b = estimator_constants(config.estimator, period)
        self._period = period
        self._n = config.estimator.difference_periods
        self._x_hist = np.zeros((rigs, self._n))
        self._theta_hist = np.zeros((rigs, self._n))
        self._v_x = np.zeros(rigs)
        self._v_theta = np.zeros(rigs)
        self._seen = 0  # samples the estimator holds (the same for every rig)
        if estimator is not None and estimator.x_m is not None:
            if estimator.x_past:
                raise ValueError("a primed estimator holds one previous sample")
            self._x_hist[:, 0] = np.broadcast_to(estimator.x_m, (rigs,))
            self._theta_hist[:, 0] = np.broadcast_to(estimator.theta_rad, (rigs,))
            self._v_x[:] = np.broadcast_to(estimator.x_dot_mps, (rigs,))
            self._v_theta[:] = np.broadcast_to(estimator.theta_dot_radps, (rigs,))
            self._seen = 1
        self._cycles = 0
        self._mode = np.full(rigs, SWING_UP, dtype=np.int64)
        self._fault = np.full(rigs, FAULT_NONE, dtype=np.int64)
        self._caught = np.zeros(rigs, dtype=np.bool_)
        self._startup_target = np.zeros(rigs)
        self._reference = np.zeros(rigs)
        self._integral = np.zeros(rigs)
        self._force, self._setpoint = np.empty(rigs), np.empty(rigs)
        self._voltage, self._command = np.empty(rigs), np.empty(rigs)
        self._applied = np.empty(rigs)
        self._x, self._theta, self._current = np.empty(rigs), np.empty(rigs), np.empty(rigs)
        # the outcomes (track); unused arrays until then
        self._constants, self._measures = _NO_CONSTANTS, False
        self._ir_index = self._cur_index = 0
        self._force_per_amp = 0.0
        self._plant: Plant | None = None
        self._book = {name: np.zeros(rigs, dtype=dtype) for name, dtype in (
            ("faulted", np.bool_), ("previous_mode", np.int64), ("caught_at", float),
            ("first_catch", float), ("hold_theta", float), ("hold_x", float),
            ("hold_i2", float), ("x_min", float), ("x_max", float), ("unheld_at", float))}
        self._box = (0.0, 0.0)

    def _window(self) -> tuple[float, int, int]:
        """(span, oldest, write) of the estimator's window at this cycle."""
        n = min(self._seen, self._n)  # samples in the difference's window
        span = self._period if n <= 1 else n * self._period
        return span, (self._seen - n) % self._n, self._seen % self._n

    def _run(self, measure: bool, y: np.ndarray, draws: np.ndarray,
             measured: tuple[np.ndarray, np.ndarray, np.ndarray], book: bool, t: float,
             hold: bool, track_range: bool) -> int:
        span, oldest, write = self._window()
        m, table = self._constants
        k = self._book
        bad = _pass(self._s, self._w, self._k, self._rows, self._ac, self._adapt, self._c,
                    self._est_a, self._est_b, self._cycles == 0, self._seen == 0, span, oldest, write, self._x_hist, self._theta_hist,
                    self._v_x, self._v_theta, self._mode, self._fault, self._caught,
                    self._startup_target, self._reference, self._integral, measure, y,
                    self._ir_index, self._cur_index, draws, m, table, *measured, book, t,
                    hold, track_range, self._force_per_amp, k["faulted"], k["previous_mode"],
                    k["caught_at"], k["first_catch"], k["hold_theta"], k["hold_x"],
                    k["hold_i2"], k["x_min"], k["x_max"], k["unheld_at"], *self._box,
                    self._force, self._setpoint,
                    self._voltage, self._command, self._applied)
        if not bad:
            self._seen += 1
            self._cycles += 1
        return bad

    def step(self, x: np.ndarray, theta: np.ndarray, current: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """One cycle for flat arrays of measurements: (force, mode code, i_d, voltage)."""
        # contiguous and writable (a read-only view would compile a second entry point)
        x, theta, current = (np.require(v, float, ("C", "W")) for v in (x, theta, current))
        rigs = self._v_x.shape[0]
        if not x.shape == theta.shape == current.shape == (rigs,):
            raise ValueError(f"measurements of shape {x.shape}, {theta.shape}, "
                             f"{current.shape}: want ({rigs},) each")
        self._run(False, _NO_STATE, _NO_DRAWS, (x, theta, current), False, 0.0, False, False)
        return (self._force.copy(), self._mode.copy(), self._setpoint.copy(),
                self._voltage.copy())

    def track(self, plant: Plant, x0: np.ndarray, box: tuple[float, float] = (0.05, 0.02)
              ) -> None:
        """Keep simulate_batch's outcomes from here on (:meth:`cycle`), for rigs that start
        at the flat positions ``x0`` on ``plant``; ``box``: the hold's |theta| and |x|
        bounds, outside which a sample's time is the rig's ``unheld_at``."""
        rigs = self._v_x.shape[0]
        m, table, self._measures = _plant_constants(plant)
        self._constants = m, table
        self._plant = plant
        self._ir_index = plant.layout.ir_index
        self._cur_index = plant.layout.current_sensor_index
        config = plant.config
        self._force_per_amp = config.motor.force_per_amp if config.models.force_input else 0.0
        self._book = {"faulted": np.zeros(rigs, dtype=np.bool_),
                      "previous_mode": np.full(rigs, SWING_UP, dtype=np.int64),
                      "caught_at": np.full(rigs, np.inf), "first_catch": np.full(rigs, np.inf),
                      "hold_theta": np.zeros(rigs), "hold_x": np.zeros(rigs),
                      "hold_i2": np.zeros(rigs), "x_min": np.array(x0, dtype=float),
                      "x_max": np.array(x0, dtype=float), "unheld_at": np.full(rigs, -np.inf)}
        self._box = (float(box[0]), float(box[1]))

    def cycle(self, y: np.ndarray, applied: np.ndarray, draws: np.ndarray | None, t: float,
              hold: bool) -> tuple[np.ndarray, np.ndarray]:
        """One cycle of simulate_batch from the plant's state ``y`` (rigs, size) at time
        ``t``: the measurement, the controllers, the outcomes (``hold``: inside the hold
        window; the range takes y's x from the second cycle on, the states after an
        advance). Returns the plant's command (:func:`pisc_plant.command.plant_command`)
        and what acts on the plant for it (:meth:`pisc_plant.plant.Plant.applied`), flat.
        ``applied`` is the command held at the sample, ``draws`` the noise (rigs, 3)."""
        if self._plant is None:
            raise ValueError("cycle needs the plant: call track(plant, x0) first")
        rigs, size = self._v_x.shape[0], self._plant.size
        # the pass reads by index without bounds checks: the shapes are checked here
        if np.shape(y) != (rigs, size) or np.shape(applied) != (rigs,) or (
                draws is not None and np.shape(draws) != (rigs, 3)):
            raise ValueError(f"state {np.shape(y)}, applied {np.shape(applied)}, draws "
                             f"{None if draws is None else np.shape(draws)}: want "
                             f"({rigs}, {size}), ({rigs},) and None or ({rigs}, 3)")
        y = np.require(y, float, ("C", "W"))
        draws = _NO_DRAWS if draws is None else np.require(draws, float, ("C", "W"))
        track_range = self._cycles > 0
        mine = (self._x, self._theta, self._current)
        if not self._measures or self._run(True, y, draws, mine, True, t, hold, track_range):
            measured = self._plant.measurement(y, applied, None if not draws.size else draws)
            measured = tuple(np.require(np.broadcast_to(v, (y.shape[0],)), float, ("C", "W"))
                             for v in measured)
            self._run(False, y, draws, measured, True, t, hold, track_range)
        return self._command.copy(), self._applied.copy()

    def outcomes(self, y: np.ndarray) -> dict[str, np.ndarray]:
        """The outcomes kept so far, the range including the state ``y`` (rigs, size)
        after the last advance."""
        k = self._book
        k["x_min"] = np.minimum(k["x_min"], y[:, 0])
        k["x_max"] = np.maximum(k["x_max"], y[:, 0])
        return k


_NO_STATE = np.zeros((0, 1))
_NO_DRAWS = np.zeros((0, 3))
_NO_CONSTANTS = (np.zeros(N_M), np.zeros(1))


def warm_up() -> float:
    """Compile (or load from numba's cache) the compiled pass; seconds taken."""
    from pisc_sim.scene import load_scene

    start = time.perf_counter()
    config = load_scene("thesis-rig").config
    controllers = BatchControllers(config, Supervisor(config.supervisor), 2)
    controllers.step(np.zeros(2), np.zeros(2), np.zeros(2))
    return time.perf_counter() - start


if __name__ == "__main__":  # python -m pisc_sim.batch_controllers: ./pisc test warms it
    print(f"pisc_sim.batch_controllers: the compiled batch controllers ready in "
          f"{warm_up():.1f} s", flush=True)
