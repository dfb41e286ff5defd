"""The rig's plant, composed of the sub-models a scene asks for.

State (last axis, any leading batch shape), only the components the models need::

    0 x           cart position, m
    1 x_dot       cart velocity, m/s
    2 theta       pendulum angle, rad (0 upright, pi hanging)
    3 theta_dot   pendulum rate, rad/s
    i             armature current, A            (models.armature = full)
    v_ir, v_cur   IR and current sensor voltages after their RC filters, V
                                                  (models.sensor_filters)

:attr:`Plant.index` says where each optional component is. Input, held constant over
each step (zero-order hold): the voltage command, applied through the H-bridge's
saturation and 7-bit quantisation, or, for an ideal force source
(``models.armature = ideal_force``), the cart force in newtons. Output: raw device
values (ADC codes, encoder count) and the same values decoded to SI, as the driver does,
or the true values for ideal sensors. The arithmetic is in :mod:`pisc_plant.kernel`.

The configuration is :class:`pisc_plant.plant_config.PlantConfig`. The plant of a plant
set (:func:`pisc_plant.plant_config.plant_set`) steps n rigs, state (n, size), each with
its own constants, and each rig gives the same bits as a plant built from its own
values. :meth:`Plant.advance` also takes one duration a rig.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from pisc_msgs_py.config import ConfigError
from pisc_model import sensors
from pisc_plant import layout
from pisc_plant.plant_config import PlantConfig, pack_constants, rigs_of

__all__ = ["Plant", "STATE_NAMES"]

STATE_NAMES = ("x", "x_dot", "theta", "theta_dot", "i", "v_ir", "v_cur")
X, X_DOT, THETA, THETA_DOT = range(4)

#: The kernel's modules, imported by the first :class:`Plant` (they import numba: a
#: configuration alone does not need it, :mod:`pisc_plant.plant_config`)
kernel: Any = None
kernel_batch: Any = None
kernel_operators: Any = None
kernel_rhs: Any = None
kernel_sets: Any = None


def _import_kernel() -> None:
    global kernel, kernel_batch, kernel_operators, kernel_rhs, kernel_sets
    if kernel is None:
        from pisc_plant import kernel as k, kernel_batch as b, kernel_operators as o
        from pisc_plant import kernel_rhs as r, kernel_sets as s
        kernel, kernel_batch, kernel_operators, kernel_rhs, kernel_sets = k, b, o, r, s


RK4_STABILITY = 2.785  # classical RK4 is stable on the negative real axis for h |lam| < 2.785
ARMATURE_CODES = {"full": layout.ARM_FULL, "quasi_static": layout.ARM_QUASI_STATIC,
                  "ideal_force": layout.ARM_FORCE}


class Plant:
    """Right-hand side, integration and measurement of a scene's rig.

    The object holds only constants derived from the configuration; the state is an
    array passed in and returned, so one ``Plant`` steps any number of rigs, with the
    same compiled arithmetic for one rig and for many. The plant of a plant set
    (:func:`pisc_plant.plant_config.plant_set`, :attr:`rigs` = n) steps states of shape
    (n, size), rig k with its own constants; its :attr:`lam` is (n, size).
    """

    #: The number of rigs of a plant set; None for a plant whose rigs share one
    #: configuration (any number of them)
    rigs: int | None

    def __init__(self, config: PlantConfig) -> None:
        _import_kernel()
        self.config = config
        c = config
        models = c.models
        self.layout = layout.Layout(ARMATURE_CODES[models.armature], models.sensor_filters,
                                    models.end_stops, models.friction == "coulomb")
        self._kernels = kernel.for_layout(self.layout)
        self.size = self.layout.size
        self.index = {"x": X, "x_dot": X_DOT, "theta": THETA, "theta_dot": THETA_DOT}
        if models.has_current_state:
            self.index["i"] = self.layout.current_index
        if models.sensor_filters:
            self.index["v_ir"] = self.layout.ir_index
            self.index["v_cur"] = self.layout.current_sensor_index
        self.state_names = tuple(sorted(self.index, key=self.index.__getitem__))
        self.rigs = rigs_of(c)
        self._p = pack_constants(c)
        # Linear, diagonal, stiff part of the right-hand side (in the exponential
        # scheme's variables): the armature's decay and the RC filters.
        self.lam = np.zeros((self.size,) if self.rigs is None else (self.rigs, self.size))
        if models.has_current_state:
            self.lam[..., self.layout.current_index] = (-c.motor.resistance_ohm
                                                        / c.motor.inductance_h)
        if models.sensor_filters:
            self.lam[..., self.layout.ir_index] = -self._p[layout.P_WIR]
            self.lam[..., self.layout.current_sensor_index] = -self._p[layout.P_WCUR]
        self._method = layout.METHODS.index(c.integrator.method)
        self._coefficients: dict[float, np.ndarray] = {}
        # per-rig steps: the operator tables (by the steps' bytes, the latest last), the
        # armature's rate of each rig, the constants in the kernel's blocks
        self._rig_tables: dict[bytes, np.ndarray] = {}
        self._rates: np.ndarray | None = None
        self._lanes: dict[int, np.ndarray] = {}
        if self.rigs is not None:
            self._p_rows = np.ascontiguousarray(self._p.T)  # rig k's constants, contiguous
            self._lanes[self.rigs] = kernel_sets.lanes(self._p)
        self._u1 = np.zeros(1)  # the one rig's input, for the kernel's rows
        # measurement_one: the IR sensor's decoded position by ADC code (a function of
        # the code alone, so the same bits; at most adc_levels entries)
        self._ir_position: dict[int, float] = {}
        self.nominal_substep_s = c.loop.period_s / c.integrator.substeps
        stiffest = float(np.max(-self.lam, initial=0.0))  # of the stiffest rig
        if c.integrator.method == "rk4" and self.nominal_substep_s * stiffest >= RK4_STABILITY:
            needed = math.ceil(c.loop.period_s * stiffest / RK4_STABILITY * 1.05)
            raise ConfigError(
                f"integrator.substeps = {c.integrator.substeps} is too few for rk4: the "
                f"fastest decay ({stiffest:.0f} 1/s) needs steps below "
                f"{RK4_STABILITY / stiffest * 1e3:.3f} ms; use at least {needed} substeps or "
                "integrator.method: exprk4")

    # -- model -------------------------------------------------------------------------

    @property
    def force_input(self) -> bool:
        """Whether the input is the cart force (ideal force source) rather than a voltage."""
        return self.config.models.force_input

    def applied(self, command: ArrayLike) -> np.ndarray:
        """What acts on the plant for a command: the bridge's voltage, or the force."""
        if self.force_input:
            return np.asarray(command, dtype=float)
        return self.config.actuator.apply(command)

    def initial_state(
        self,
        x: ArrayLike = 0.0,
        x_dot: ArrayLike = 0.0,
        theta: ArrayLike = math.pi,
        theta_dot: ArrayLike = 0.0,
        current_a: ArrayLike = 0.0,
    ) -> np.ndarray:
        """A state with the sensor filters settled on the given mechanical state."""
        values = [np.asarray(v, dtype=float) for v in (x, x_dot, theta, theta_dot, current_a)]
        if self.rigs is not None:
            shape = np.broadcast_shapes(*(v.shape for v in values))
            if shape not in ((), (self.rigs,)):
                raise ValueError(f"this plant is a set of {self.rigs} rigs: the initial values "
                                 f"must be numbers or of shape ({self.rigs},), not {shape}")
            values = [np.broadcast_to(v, (self.rigs,)) for v in values]
        x, x_dot, theta, theta_dot, current_a = np.broadcast_arrays(*values)
        parts = [x, x_dot, theta, theta_dot]
        if self.config.models.has_current_state:
            parts.append(current_a)
        if self.config.models.sensor_filters:
            s = self.config.sensors
            parts += [sensors.ir_voltage(s, x), sensors.current_sensor_voltage(s, current_a)]
        return np.stack(parts, axis=-1)

    def current(self, y: np.ndarray, command: ArrayLike = 0.0) -> np.ndarray:
        """Armature current: the state's, or the quasi-static one (2.81) with L di/dt = 0
        for the command held, or, for an ideal force source, the current a motor with
        the rig's constants would need for the force (4.2)."""
        models = self.config.models
        if models.has_current_state:
            return y[..., self.layout.current_index]
        applied = self.applied(command)
        if models.armature == "quasi_static":
            return (applied - self._p[layout.P_KER] * y[..., X_DOT]) / self._p[layout.P_R]
        return np.broadcast_to(applied / self._p[layout.P_KF], y.shape[:-1]).astype(float)

    def derivative(self, y: np.ndarray, command: ArrayLike) -> np.ndarray:
        """Full right-hand side y' for a command (for reference integrators and checks)."""
        ys, us = self._rows(y, command)
        out = np.empty_like(ys)
        arm, filters = self.layout.armature, self.layout.filters
        for row in range(ys.shape[0]):
            kernel_rhs.rhs_one(ys[row], us[row], self._constants_of(row), arm, filters, out[row])
        return out.reshape(np.shape(y))

    def applied_derivative(self, y: np.ndarray, applied: float,
                           rig: int | None = None) -> np.ndarray:
        """y' of one rig for an input already through the actuator (reference solvers);
        of a plant set, of the rig numbered ``rig``."""
        if self.rigs is not None and rig is None:
            raise ValueError(f"this plant is a set of {self.rigs} rigs: say which (rig=k)")
        out = np.empty(self.size)
        kernel_rhs.rhs_one(np.asarray(y, dtype=float), float(applied),
                           self._constants_of(0 if rig is None else rig),
                           self.layout.armature, self.layout.filters, out)
        return out

    def _constants_of(self, row: int) -> np.ndarray:
        """The constants of a state's row: the plant's, or of a plant set rig ``row``'s."""
        return self._p if self.rigs is None else self._p_rows[row]

    # -- integration ---------------------------------------------------------------------

    def coefficients(self, step_s: float) -> np.ndarray:
        """The exponential scheme's operator table for a step, (15, OP_WIDTH)
        (:func:`pisc_plant.kernel_operators.exp_coefficients`); of a plant set, every rig's, as
        :meth:`rig_coefficients`."""
        coef = self._coefficients.get(step_s)
        if coef is None:
            if self.rigs is not None:
                return self.rig_coefficients(np.full(self.rigs, float(step_s)))
            filters = self.config.models.sensor_filters
            full = self.config.models.has_current_state
            coef = kernel_operators.exp_coefficients(
                self._p[layout.P_WIR] if filters else 0.0,
                self._p[layout.P_WCUR] if filters else 0.0,
                self._p[layout.P_WCUR] / self._p[layout.P_CURSCALE],
                kernel_operators.armature_rate(self._p) if full else 0.0, step_s)
            if len(self._coefficients) < 64:
                self._coefficients[step_s] = coef
        return coef

    def rig_coefficients(self, steps_s: np.ndarray) -> np.ndarray:
        """Every rig's operator table for its own step ``steps_s[k]``, in the kernel's
        blocks: ``kernel_sets.lanes`` of (N_TABLE, rigs), rig k's table (rows 0-12 of
        :meth:`coefficients`, row-major) in column k; the same numbers, computed by
        :func:`pisc_plant.kernel_sets.exp_tables`. The last four sets of steps are kept (a
        rig's latency, the rest of its period and the period, say)."""
        steps_s = np.ascontiguousarray(steps_s, dtype=float)
        key = steps_s.tobytes()
        tables = self._rig_tables.pop(key, None)
        if tables is None:
            rigs = steps_s.shape[0]
            if self.rigs is not None and rigs != self.rigs:
                raise ValueError(f"{rigs} steps for a set of {self.rigs} rigs")
            p = self._p if self.rigs is None else self._p_rows[0]  # the sensors are common
            filters = self.config.models.sensor_filters
            block = kernel_sets.BLOCK
            tables = np.empty((-(-rigs // block), kernel_sets.N_TABLE * block))
            kernel_sets.exp_tables(p[layout.P_WIR] if filters else 0.0,
                                   p[layout.P_WCUR] if filters else 0.0,
                                   p[layout.P_WCUR] / p[layout.P_CURSCALE],
                                   self._armature_rates(rigs), steps_s, tables)
            while len(self._rig_tables) >= 4:
                del self._rig_tables[next(iter(self._rig_tables))]
        self._rig_tables[key] = tables
        return tables

    def _armature_rates(self, rigs: int) -> np.ndarray:
        """Each rig's :func:`pisc_plant.kernel_operators.armature_rate` (0 without the armature)."""
        if self._rates is None or self._rates.shape[0] != rigs:
            rates = np.zeros(rigs)
            if self.config.models.has_current_state:
                if self.rigs is None:
                    rates[:] = kernel_operators.armature_rate(self._p)
                else:
                    kernel_sets.armature_rates(self._p, rates)
            self._rates = rates
        return self._rates

    def _lane_constants(self, rigs: int) -> np.ndarray:
        """The constants of ``rigs`` rigs in the kernel's blocks
        (:func:`pisc_plant.kernel_sets.lanes`)."""
        p = self._lanes.get(rigs)
        if p is None:
            p = kernel_sets.lanes(np.repeat(self._p[:, None], rigs, axis=1))
            self._lanes = {rigs: p}
        return p

    def _rows(self, y: np.ndarray, command: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        y = np.asarray(y, dtype=float)
        if y.shape[-1] != self.size:
            raise ValueError(f"state has {y.shape[-1]} components, this scene's plant has "
                             f"{self.size} ({', '.join(self.state_names)})")
        if self.rigs is not None and y.shape[:-1] != (self.rigs,):
            raise ValueError(f"this plant is a set of {self.rigs} rigs: a state has shape "
                             f"({self.rigs}, {self.size}), not {y.shape}")
        ys = np.array(y.reshape(-1, self.size), dtype=float, order="C")
        us = np.ascontiguousarray(
            np.broadcast_to(self.applied(command), y.shape[:-1]).reshape(-1), dtype=float)
        return ys, us

    def advance(self, y: np.ndarray, command: ArrayLike,
                duration_s: float | np.ndarray) -> np.ndarray:
        """Integrate over ``duration_s`` with the command held constant; a new array.

        The interval is cut into equal substeps no longer than ``period / substeps``;
        after each substep the end stops act. ``duration_s`` may give one duration a
        rig (shape (n,) for states (n, size)): every rig then takes the substeps the
        longest needs, each of its own duration over their number; a rig with
        duration 0 keeps its state.
        """
        if type(duration_s) is not float or self.rigs is not None:
            return self._advance_rigs(y, command, duration_s)
        if not duration_s > 0.0:
            if duration_s == 0.0:
                return y
            raise ValueError(f"duration_s = {duration_s} must not be negative")
        n = max(1, math.ceil(duration_s / self.nominal_substep_s - 1e-9))
        h = duration_s / n
        coef = self.coefficients(h)
        stops = self.layout.end_stops
        if (np.ndim(y) == 1 and (type(command) is float or np.ndim(command) == 0)
                and len(y) == self.size):
            # one rig, one command: the same kernel call without the array bookkeeping
            # (np.ndim of a Python float, through numpy.asarray, took 1.1 us of it)
            out = np.array(y, dtype=float)
            self._u1[0] = (float(command) if self.force_input
                           else self.config.actuator.apply_scalar(command))
            self._kernels.advance(out.reshape(1, -1), self._u1, 0, 1, self._p, stops,
                                  self._method, n, h, coef)
            return out
        ys, us = self._rows(y, command)
        self._step_rows(ys, us, n, h, coef)
        return ys.reshape(np.shape(y))

    def _step_rows(self, ys: np.ndarray, us: np.ndarray, n: int, h: float,
                   coef: np.ndarray) -> None:
        stops = self.layout.end_stops
        if ys.shape[0] <= kernel_batch.CHUNK:
            self._kernels.advance(ys, us, 0, ys.shape[0], self._p, stops, self._method, n, h,
                                  coef)
        else:
            self._kernels.advance_many(ys, us, self._p, stops, self._method, n, h, coef)

    def advance_in_place(self, ys: np.ndarray, applied: np.ndarray, duration_s: float) -> None:
        """:meth:`advance` for a batch's loop (:func:`pisc_sim.closed_loop.simulate_batch`):
        the rows of ``ys`` (n, size), a C-contiguous float array, advanced in place, with
        ``applied`` (n,) already through the actuator (:meth:`applied`), one duration for
        all. The same bits as :meth:`advance` without its copy of the state and its pass
        through the actuator. Not for a plant set."""
        if self.rigs is not None:
            raise ValueError("advance_in_place is for one rig's constants; a plant set "
                             "takes advance")
        if not (type(ys) is np.ndarray and ys.dtype == np.float64 and ys.ndim == 2
                and ys.shape[1] == self.size and ys.flags.c_contiguous and ys.flags.writeable):
            raise ValueError(f"advance_in_place takes a writable C-contiguous float64 state "
                             f"of shape (n, {self.size}), not {getattr(ys, 'shape', ys)!r}")
        if not (type(applied) is np.ndarray and applied.dtype == np.float64
                and applied.shape == ys.shape[:1] and applied.flags.c_contiguous):
            raise ValueError(f"advance_in_place takes a C-contiguous float64 input of shape "
                             f"({ys.shape[0]},), not {getattr(applied, 'shape', applied)!r}")
        duration_s = float(duration_s)
        if not (math.isfinite(duration_s) and duration_s >= 0.0):
            raise ValueError(f"duration_s = {duration_s} must be finite and not negative")
        if duration_s == 0.0:
            return
        n = max(1, math.ceil(duration_s / self.nominal_substep_s - 1e-9))
        h = duration_s / n
        self._step_rows(ys, applied, n, h, self.coefficients(h))

    def _advance_rigs(self, y: np.ndarray, command: ArrayLike,
                      duration_s: float | np.ndarray) -> np.ndarray:
        """:meth:`advance` of a plant set or with one duration a rig: the kernel's entry
        points that give every rig its own constants and step."""
        durations = np.asarray(duration_s, dtype=float)
        if self.rigs is None and durations.ndim == 0:
            return self.advance(y, command, float(durations))
        ys, us = self._rows(y, command)
        rigs = ys.shape[0]
        if durations.ndim == 0:
            durations = np.full(rigs, float(durations))
        elif durations.shape != (rigs,) or np.ndim(y) != 2:
            raise ValueError(f"duration_s has shape {durations.shape}: one duration a rig "
                             f"takes states of shape (n, {self.size}) and durations (n,); "
                             f"the state has shape {np.shape(y)}")
        bad = ~(np.isfinite(durations) & (durations >= 0.0))
        if bad.any():
            k = int(np.argmax(bad))
            raise ValueError(f"duration_s = {durations[k]} (rig {k}) must be finite and not "
                             "negative")
        longest = float(durations.max(initial=0.0))
        if longest == 0.0:
            return ys.reshape(np.shape(y))
        n = max(1, math.ceil(longest / self.nominal_substep_s - 1e-9))
        steps = durations / n
        p = self._lane_constants(rigs)
        tables = (self.rig_coefficients(steps) if self._method == layout.EXPRK4
                  else np.empty((p.shape[0], 0)))
        stops = self.layout.end_stops
        if rigs <= kernel_batch.CHUNK:
            self._kernels.advance_set(ys, us, 0, rigs, p, stops, self._method, n, steps,
                                      tables)
        else:
            self._kernels.advance_set_many(ys, us, p, stops, self._method, n, steps, tables)
        return ys.reshape(np.shape(y))

    def end_stops(self, y: np.ndarray) -> np.ndarray:
        """Perfectly inelastic end stops of the track.

        A cart past a stop is put back on it; if it was moving outwards it stops, and
        the impulse that stops it changes the pendulum rate by
        ``-m l cos(theta) dx_dot / (I + m l^2)`` (second row of (2.26) integrated over
        the impact, with the impulse acting on the cart row only).
        """
        ys, _ = self._rows(y, 0.0)
        for k, row in enumerate(ys):
            kernel_rhs.end_stops(row, self._constants_of(k))
        return ys.reshape(np.shape(y))

    # -- measurement ---------------------------------------------------------------------

    def _sensor_voltages(self, y: np.ndarray, command: ArrayLike,
                         noise: np.ndarray | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        s = self.config.sensors
        x, theta, current = self._noisy(y, command, noise)
        if not self.config.models.sensor_filters:
            return sensors.ir_voltage(s, x), sensors.current_sensor_voltage(s, current), theta
        v_ir = y[..., self.layout.ir_index]
        v_cur = y[..., self.layout.current_sensor_index]
        if noise is not None:
            # behind the RC filters the noise is measurement noise at the ADC's input, of
            # the same size in x and i: through the IR curve's slope (4.8),
            # dv/dx = v / (exponent (origin - x)), and the current sensor's 1 / scale
            n = self.config.noise
            distance = np.maximum(s.ir_origin_m - y[..., X], 1e-3)
            v_ir = v_ir + v_ir / (s.ir_exponent * distance) * n.x_std_m * noise[..., 0]
            v_cur = v_cur + n.current_std_a * noise[..., 2] / s.current_scale_a_per_v
        return v_ir, v_cur, theta

    def _noisy(self, y: np.ndarray, command: ArrayLike, noise: np.ndarray | None
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """True x, theta, i plus the scaled noise draws (none without draws)."""
        x = y[..., X]
        theta = y[..., THETA]
        current = self.current(y, command)
        if noise is not None:
            n = self.config.noise
            x = x + n.x_std_m * noise[..., 0]
            theta = theta + n.theta_std_rad * noise[..., 1]
            current = current + n.current_std_a * noise[..., 2]
        return x, theta, current

    def raw_measurement(self, y: np.ndarray, command: ArrayLike = 0.0,
                        noise: np.ndarray | None = None
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(IR ADC code, current ADC code, encoder count) of a state."""
        s = self.config.sensors
        v_ir, v_cur, theta = self._sensor_voltages(y, command, noise)
        return (sensors.adc_code(s, v_ir), sensors.adc_code(s, v_cur),
                sensors.encoder_count(s, theta))

    def measurement_one(self, y: np.ndarray, command: float = 0.0,
                        noise: np.ndarray | None = None) -> tuple[float, float, float]:
        """:meth:`measurement` of one rig's state as floats, with the same bits.

        The sampled plant takes one measurement a period; numpy's per-call cost made it
        a tenth of a one-process lockstep cycle (py-spy, 2026-12-03). With quantised
        sensors behind their RC filters (every scene but the ideal ones) this does the
        same arithmetic on floats: the ADC codes (truncated, saturated), the encoder
        count, and the host's conversions, the IR curve's power through numpy (its
        float64 power is not the C library's). Other sensor models, a
        plant set and a non-finite state take :meth:`measurement`."""
        models = self.config.models
        if (models.sensors == "ideal" or not models.sensor_filters or self.rigs is not None
                or np.shape(y) != (self.size,)):
            x, theta, current = self.measurement(y, command, noise)
            return float(x), float(theta), float(current)
        s = self.config.sensors
        v_ir = float(y[self.layout.ir_index])
        v_cur = float(y[self.layout.current_sensor_index])
        theta = float(y[THETA])
        if not (math.isfinite(v_ir) and math.isfinite(v_cur) and math.isfinite(theta)):
            x, theta, current = self.measurement(y, command, noise)
            return float(x), float(theta), float(current)
        if noise is not None:  # as _noisy and _sensor_voltages add it
            n = self.config.noise
            theta = theta + n.theta_std_rad * float(noise[1])
            distance = max(s.ir_origin_m - float(y[X]), 1e-3)  # NaN stays, as np.maximum
            v_ir = v_ir + v_ir / (s.ir_exponent * distance) * n.x_std_m * float(noise[0])
            v_cur = v_cur + n.current_std_a * float(noise[2]) / s.current_scale_a_per_v
        lsb, low, top = s.adc_lsb_v, s.adc_ref_low_v, s.adc_levels - 1
        ir_code = min(max(math.floor((v_ir - low) / lsb), 0), top)  # sensors.adc_code
        cur_code = min(max(math.floor((v_cur - low) / lsb), 0), top)
        count = math.floor((theta - s.encoder_zero_rad) / s.encoder_rad_per_count + 0.5)
        # sensors.decode; the IR curve's power once per code
        x = self._ir_position.get(ir_code)
        if x is None:
            v = np.asarray(float(ir_code) * lsb + low) ** (-s.ir_exponent)
            x = self._ir_position[ir_code] = s.ir_origin_m - s.ir_scale_m * float(v)
        angle = float(count) * s.encoder_rad_per_count + s.encoder_zero_rad
        current = s.current_scale_a_per_v * (float(cur_code) * lsb + low) - s.current_offset_a
        return x, angle, current

    def measurement(self, y: np.ndarray, command: ArrayLike = 0.0,
                    noise: np.ndarray | None = None
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(x [m], theta [rad], i [A]) as the host program decodes the sensors' values.

        ``command`` is the command held at the sample (it sets the current when the
        armature is quasi-static or ideal); ``noise`` holds standard normal draws
        (..., 3) scaled by ``noise.*_std`` and added to x, theta and i before the sensors.
        With ideal sensors the (noisy) true values are returned.
        """
        if self.config.models.sensors == "ideal":
            x, theta, current = self._noisy(y, command, noise)
            return np.asarray(x, dtype=float), np.asarray(theta, dtype=float), np.asarray(
                current, dtype=float)
        return sensors.decode(self.config.sensors, *self.raw_measurement(y, command, noise))
