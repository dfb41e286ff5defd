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
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike

from pisc_msgs_py.config import ConfigError, in_range, one_of, param
from pisc_plant import kernel, sensors
from pisc_plant.params import (
    ActuatorParams,
    FrictionParams,
    LoopParams,
    ModelParams,
    MotorParams,
    NoiseParams,
    RigParams,
    SensorParams,
    TrackParams,
)

__all__ = ["PLANT_SECTIONS", "IntegratorParams", "Plant", "PlantConfig", "STATE_NAMES"]

STATE_NAMES = ("x", "x_dot", "theta", "theta_dot", "i", "v_ir", "v_cur")
X, X_DOT, THETA, THETA_DOT = range(4)

RK4_STABILITY = 2.785  # classical RK4 is stable on the negative real axis for h |lam| < 2.785
ARMATURE_CODES = {"full": kernel.ARM_FULL, "quasi_static": kernel.ARM_QUASI_STATIC,
                  "ideal_force": kernel.ARM_FORCE}


@dataclass(frozen=True)
class IntegratorParams:
    """Numerical integration of the plant between control samples.

    ``exprk4`` (the default, 2 steps per period) is an exponential Runge-Kutta method of
    stiff order four that treats the armature's transient and the sensor filters in
    closed form and is stable at any step up to the period (:mod:`pisc_plant.kernel`).
    ``rk4`` is the classical Runge-Kutta method; it is stable only while each step
    resolves the armature (h R / L < 2.785), which the plant checks. README, "Scenes and
    integrators", measures both against SciPy.
    """

    method: str = param("exprk4", "'exprk4' (exponential, stable at any step) or 'rk4' "
                        "(classical Runge-Kutta)", "", one_of(*kernel.METHODS))
    substeps: int = param(2, "integration steps per control period", "", in_range(1, 100000))


@dataclass(frozen=True)
class PlantConfig:
    rig: RigParams = field(default_factory=RigParams)
    motor: MotorParams = field(default_factory=MotorParams)
    sensors: SensorParams = field(default_factory=SensorParams)
    actuator: ActuatorParams = field(default_factory=ActuatorParams)
    track: TrackParams = field(default_factory=TrackParams)
    loop: LoopParams = field(default_factory=LoopParams)
    integrator: IntegratorParams = field(default_factory=IntegratorParams)
    models: ModelParams = field(default_factory=ModelParams)
    friction: FrictionParams = field(default_factory=FrictionParams)
    noise: NoiseParams = field(default_factory=NoiseParams)


#: The parameter sections a plant is built from, as :class:`PlantConfig`'s fields.
PLANT_SECTIONS: dict[str, type] = {
    "rig": RigParams, "motor": MotorParams, "sensors": SensorParams, "actuator": ActuatorParams,
    "track": TrackParams, "loop": LoopParams, "integrator": IntegratorParams,
    "models": ModelParams, "friction": FrictionParams, "noise": NoiseParams,
}


def pack_constants(c: PlantConfig) -> np.ndarray:
    """The configuration as the kernel's constant vector."""
    p = np.zeros(kernel.N_CONSTANTS)
    rig, m, s, t, f = c.rig, c.motor, c.sensors, c.track, c.friction
    friction = c.models.friction
    p[kernel.P_A1] = rig.a1
    # the rotor's inertia reflected to the cart, J_m / r^2, joins the cart row only
    p[kernel.P_A2] = rig.a2 + (m.reflected_mass_kg if c.models.has_current else 0.0)
    p[kernel.P_ML] = rig.ml
    p[kernel.P_G] = rig.gravity_mps2
    p[kernel.P_KF] = m.force_per_amp
    p[kernel.P_BM] = m.reflected_damping_ns_per_m
    p[kernel.P_R] = m.resistance_ohm
    p[kernel.P_L] = m.inductance_h
    p[kernel.P_KER] = m.back_emf_v_s_per_rad / m.wheel_radius_m
    if friction != "none":
        p[kernel.P_BC] = f.cart_viscous_ns_per_m
        p[kernel.P_BP] = f.pivot_viscous_nms
    if friction == "coulomb":
        p[kernel.P_FC] = f.cart_coulomb_n
    p[kernel.P_VC] = f.coulomb_velocity_mps
    p[kernel.P_WIR] = 2.0 * math.pi * s.ir_filter_hz
    p[kernel.P_WCUR] = 2.0 * math.pi * s.current_filter_hz
    p[kernel.P_IRO] = s.ir_origin_m
    p[kernel.P_IRS] = s.ir_scale_m
    p[kernel.P_IRX] = -1.0 / s.ir_exponent
    p[kernel.P_CUROFF] = s.current_offset_a
    p[kernel.P_CURSCALE] = s.current_scale_a_per_v
    p[kernel.P_XMIN] = t.min_m
    p[kernel.P_XMAX] = t.max_m
    p[kernel.P_JROT] = rig.pendulum_inertia_kgm2 + rig.ml * rig.pendulum_com_m
    return p


class Plant:
    """Right-hand side, integration and measurement of a scene's rig.

    The object holds only constants derived from the configuration; the state is an
    array passed in and returned, so one ``Plant`` steps any number of rigs, with the
    same compiled arithmetic for one rig and for many.
    """

    def __init__(self, config: PlantConfig) -> None:
        self.config = config
        c = config
        models = c.models
        self.layout = kernel.Layout(ARMATURE_CODES[models.armature], models.sensor_filters,
                                    models.end_stops)
        self._kernels = kernel.for_layout(self.layout)
        self.size = self.layout.size
        self.index = {"x": X, "x_dot": X_DOT, "theta": THETA, "theta_dot": THETA_DOT}
        if models.has_current_state:
            self.index["i"] = self.layout.current_index
        if models.sensor_filters:
            self.index["v_ir"] = self.layout.ir_index
            self.index["v_cur"] = self.layout.current_sensor_index
        self.state_names = tuple(sorted(self.index, key=self.index.__getitem__))
        self._p = pack_constants(c)
        # Linear, diagonal, stiff part of the right-hand side (in the exponential
        # scheme's variables): the armature's decay and the RC filters.
        self.lam = np.zeros(self.size)
        if models.has_current_state:
            self.lam[self.layout.current_index] = -c.motor.resistance_ohm / c.motor.inductance_h
        if models.sensor_filters:
            self.lam[self.layout.ir_index] = -self._p[kernel.P_WIR]
            self.lam[self.layout.current_sensor_index] = -self._p[kernel.P_WCUR]
        self._method = kernel.METHODS.index(c.integrator.method)
        self._coefficients: dict[float, np.ndarray] = {}
        self._u1 = np.zeros(1)  # the one rig's input, for the kernel's rows
        self.nominal_substep_s = c.loop.period_s / c.integrator.substeps
        stiffest = float(np.max(-self.lam, initial=0.0))
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
        x, x_dot, theta, theta_dot, current_a = np.broadcast_arrays(
            *(np.asarray(v, dtype=float) for v in (x, x_dot, theta, theta_dot, current_a))
        )
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
            return (applied - self._p[kernel.P_KER] * y[..., X_DOT]) / self._p[kernel.P_R]
        return np.broadcast_to(applied / self._p[kernel.P_KF], y.shape[:-1]).astype(float)

    def derivative(self, y: np.ndarray, command: ArrayLike) -> np.ndarray:
        """Full right-hand side y' for a command (for reference integrators and checks)."""
        ys, us = self._rows(y, command)
        out = np.empty_like(ys)
        arm, filters = self.layout.armature, self.layout.filters
        for row in range(ys.shape[0]):
            kernel.rhs_one(ys[row], us[row], self._p, arm, filters, out[row])
        return out.reshape(np.shape(y))

    def applied_derivative(self, y: np.ndarray, applied: float) -> np.ndarray:
        """y' of one rig for an input already through the actuator (reference solvers)."""
        out = np.empty(self.size)
        kernel.rhs_one(np.asarray(y, dtype=float), float(applied), self._p,
                       self.layout.armature, self.layout.filters, out)
        return out

    # -- integration ---------------------------------------------------------------------

    def coefficients(self, step_s: float) -> np.ndarray:
        coef = self._coefficients.get(step_s)
        if coef is None:
            filters = self.config.models.sensor_filters
            full = self.config.models.has_current_state
            coef = kernel.exp_coefficients(
                self._p[kernel.P_WIR] if filters else 0.0,
                self._p[kernel.P_WCUR] if filters else 0.0,
                self._p[kernel.P_WCUR] / self._p[kernel.P_CURSCALE],
                kernel.armature_rate(self._p) if full else 0.0, step_s)
            if len(self._coefficients) < 64:
                self._coefficients[step_s] = coef
        return coef

    def _rows(self, y: np.ndarray, command: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
        y = np.asarray(y, dtype=float)
        if y.shape[-1] != self.size:
            raise ValueError(f"state has {y.shape[-1]} components, this scene's plant has "
                             f"{self.size} ({', '.join(self.state_names)})")
        ys = np.array(y.reshape(-1, self.size), dtype=float, order="C")
        us = np.ascontiguousarray(
            np.broadcast_to(self.applied(command), y.shape[:-1]).reshape(-1), dtype=float)
        return ys, us

    def advance(self, y: np.ndarray, command: ArrayLike, duration_s: float) -> np.ndarray:
        """Integrate over ``duration_s`` with the command held constant; a new array.

        The interval is cut into equal substeps no longer than ``period / substeps``;
        after each substep the end stops act.
        """
        if not duration_s > 0.0:
            if duration_s == 0.0:
                return y
            raise ValueError(f"duration_s = {duration_s} must not be negative")
        n = max(1, math.ceil(duration_s / self.nominal_substep_s - 1e-9))
        h = duration_s / n
        coef = self.coefficients(h)
        stops = self.layout.end_stops
        if np.ndim(y) == 1 and np.ndim(command) == 0 and len(y) == self.size:
            # one rig, one command: the same kernel call without the array bookkeeping
            out = np.array(y, dtype=float)
            self._u1[0] = (float(command) if self.force_input
                           else self.config.actuator.apply_scalar(command))
            self._kernels.advance(out.reshape(1, -1), self._u1, 0, 1, self._p, stops,
                                  self._method, n, h, coef)
            return out
        ys, us = self._rows(y, command)
        if ys.shape[0] <= kernel.CHUNK:
            self._kernels.advance(ys, us, 0, ys.shape[0], self._p, stops, self._method, n, h,
                                  coef)
        else:
            self._kernels.advance_many(ys, us, self._p, stops, self._method, n, h, coef)
        return ys.reshape(np.shape(y))

    def end_stops(self, y: np.ndarray) -> np.ndarray:
        """Perfectly inelastic end stops of the track.

        A cart past a stop is put back on it; if it was moving outwards it stops, and
        the impulse that stops it changes the pendulum rate by
        ``-m l cos(theta) dx_dot / (I + m l^2)`` (second row of (2.26) integrated over
        the impact, with the impulse acting on the cart row only).
        """
        ys, _ = self._rows(y, 0.0)
        for row in ys:
            kernel.end_stops(row, self._p)
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
