"""The thesis rig at full fidelity: cart-pole, DC motor armature, sensor filters, end stops.

State (last axis, any leading batch shape)::

    0 x           cart position, m
    1 x_dot       cart velocity, m/s
    2 theta       pendulum angle, rad (0 upright, pi hanging)
    3 theta_dot   pendulum rate, rad/s
    4 i           armature current, A
    5 v_ir        IR sensor voltage after its 10 Hz RC filter, V
    6 v_cur       current sensor voltage after its 72 Hz RC filter, V

Input: the voltage command, held constant over each step (zero-order hold) and applied
through the H-bridge's saturation and 7-bit quantisation. Output: raw device values
(ADC codes, encoder count) and the same values decoded to SI, as the driver does.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike

from pisc_msgs_py.config import ConfigError, in_range, one_of, param
from pisc_plant import motor as motor_model
from pisc_plant import sensors
from pisc_plant.dynamics import accelerations
from pisc_plant.integrators import Etdrk4, rk4_step
from pisc_plant.params import (
    ActuatorParams,
    LoopParams,
    MotorParams,
    RigParams,
    SensorParams,
    TrackParams,
)

__all__ = ["IntegratorParams", "Plant", "PlantConfig", "STATE_NAMES"]

STATE_NAMES = ("x", "x_dot", "theta", "theta_dot", "i", "v_ir", "v_cur")
X, X_DOT, THETA, THETA_DOT, CURRENT, V_IR, V_CUR = range(7)


RK4_STABILITY = 2.785  # classical RK4 is stable on the negative real axis for h |lam| < 2.785


@dataclass(frozen=True)
class IntegratorParams:
    """Numerical integration of the plant between control samples.

    ``rk4`` (the default) is the classical Runge-Kutta method; it is stable only while
    the step resolves the armature (h R / L < 2.785), which the plant checks. ``etdrk4``
    (Cox-Matthews exponential time differencing) treats the armature and sensor filters
    exactly and is stable at any step, but loses order on this coupled problem: on a
    recorded 1 s swing-up it left 5.5e-4 rad at 1 ms steps where RK4 at 0.25 ms left
    2.2e-9 rad for the same cost (README, "Integration").
    """

    method: str = param("rk4", "'rk4' or 'etdrk4'", "", one_of("rk4", "etdrk4"))
    substeps: int = param(20, "integration steps per control period", "", in_range(1, 100000))


@dataclass(frozen=True)
class PlantConfig:
    rig: RigParams = field(default_factory=RigParams)
    motor: MotorParams = field(default_factory=MotorParams)
    sensors: SensorParams = field(default_factory=SensorParams)
    actuator: ActuatorParams = field(default_factory=ActuatorParams)
    track: TrackParams = field(default_factory=TrackParams)
    loop: LoopParams = field(default_factory=LoopParams)
    integrator: IntegratorParams = field(default_factory=IntegratorParams)


class Plant:
    """Right-hand side, integration and measurement of the full-fidelity rig.

    The object holds only constants derived from the configuration; the state is an
    array passed in and returned, so one ``Plant`` steps any number of rigs.
    """

    def __init__(self, config: PlantConfig) -> None:
        self.config = config
        c = config
        self._ir_rate = 2.0 * math.pi * c.sensors.ir_filter_hz
        self._cur_rate = 2.0 * math.pi * c.sensors.current_filter_hz
        # Linear, diagonal part of the right-hand side: the stiff decays.
        self.lam = np.array(
            [
                0.0,
                0.0,
                0.0,
                0.0,
                -c.motor.resistance_ohm / c.motor.inductance_h,
                -self._ir_rate,
                -self._cur_rate,
            ]
        )
        self._extra_mass = c.motor.reflected_mass_kg
        self._rotational_inertia = c.rig.pendulum_inertia_kgm2 + c.rig.ml * c.rig.pendulum_com_m
        self._schemes: dict[float, Etdrk4] = {}
        self.nominal_substep_s = c.loop.period_s / c.integrator.substeps
        stiffest = float(np.max(-self.lam))
        if c.integrator.method == "rk4" and self.nominal_substep_s * stiffest >= RK4_STABILITY:
            needed = math.ceil(c.loop.period_s * stiffest / RK4_STABILITY * 1.05)
            raise ConfigError(
                f"integrator.substeps = {c.integrator.substeps} is too few for rk4: the "
                f"fastest decay ({stiffest:.0f} 1/s, the armature's R/L) needs steps below "
                f"{RK4_STABILITY / stiffest * 1e3:.3f} ms; use at least {needed} substeps or "
                "integrator.method: etdrk4")

    # -- model -------------------------------------------------------------------------

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
        s = self.config.sensors
        return np.stack(
            [
                x,
                x_dot,
                theta,
                theta_dot,
                current_a,
                sensors.ir_voltage(s, x),
                sensors.current_sensor_voltage(s, current_a),
            ],
            axis=-1,
        )

    def nonlinear(self, y: np.ndarray, voltage_v: np.ndarray) -> np.ndarray:
        """N(y) of ``y' = lam * y + N(y)`` for an applied armature voltage."""
        c = self.config
        x = y[..., X]
        x_dot = y[..., X_DOT]
        theta_dot = y[..., THETA_DOT]
        current = y[..., CURRENT]
        force = motor_model.cart_force(c.motor, current, x_dot)
        x_ddot, theta_ddot = accelerations(
            c.rig, y[..., THETA], theta_dot, force, self._extra_mass
        )
        back_emf = c.motor.back_emf_v_s_per_rad * x_dot / c.motor.wheel_radius_m
        return np.stack(
            [
                x_dot,
                x_ddot,
                theta_dot,
                theta_ddot,
                (voltage_v - back_emf) / c.motor.inductance_h,
                self._ir_rate * sensors.ir_voltage(c.sensors, x),
                self._cur_rate * sensors.current_sensor_voltage(c.sensors, current),
            ],
            axis=-1,
        )

    def derivative(self, y: np.ndarray, voltage_v: ArrayLike) -> np.ndarray:
        """Full right-hand side y' (for reference integrators and checks)."""
        applied = self.config.actuator.apply(voltage_v)
        return self.lam * y + self.nonlinear(y, applied)

    # -- integration ---------------------------------------------------------------------

    def _scheme(self, step_s: float) -> Etdrk4:
        scheme = self._schemes.get(step_s)
        if scheme is None:
            scheme = Etdrk4.for_step(self.lam, step_s)
            if len(self._schemes) < 64:
                self._schemes[step_s] = scheme
        return scheme

    def advance(self, y: np.ndarray, voltage_v: ArrayLike, duration_s: float) -> np.ndarray:
        """Integrate over ``duration_s`` with the commanded voltage held constant.

        The bridge saturates and quantises the command (``actuator``); the interval is
        cut into equal substeps no longer than ``period / substeps``; after each substep
        the end stops act.
        """
        if not duration_s > 0.0:
            if duration_s == 0.0:
                return y
            raise ValueError(f"duration_s = {duration_s} must not be negative")
        applied = self.config.actuator.apply(voltage_v)
        n = max(1, math.ceil(duration_s / self.nominal_substep_s - 1e-9))
        h = duration_s / n
        if self.config.integrator.method == "etdrk4":
            scheme = self._scheme(h)

            def nonlinear(state: np.ndarray) -> np.ndarray:
                return self.nonlinear(state, applied)

            for _ in range(n):
                y = self.end_stops(scheme.step(nonlinear, y))
        else:
            lam = self.lam

            def rhs(state: np.ndarray) -> np.ndarray:
                return lam * state + self.nonlinear(state, applied)

            for _ in range(n):
                y = self.end_stops(rk4_step(rhs, y, h))
        return y

    def end_stops(self, y: np.ndarray) -> np.ndarray:
        """Perfectly inelastic end stops of the track.

        A cart past a stop is put back on it; if it was moving outwards it stops, and
        the impulse that stops it changes the pendulum rate by
        ``-m l cos(theta) dx_dot / (I + m l^2)`` (second row of (2.26) integrated over
        the impact, with the impulse acting on the cart row only).
        """
        t = self.config.track
        x = y[..., X]
        x_dot = y[..., X_DOT]
        below = (x < t.min_m) & (x_dot < 0.0)
        above = (x > t.max_m) & (x_dot > 0.0)
        outside = (x < t.min_m) | (x > t.max_m)
        if not np.any(outside):
            return y
        y = y.copy()
        hit = below | above
        dx_dot = np.where(hit, -x_dot, 0.0)
        rig = self.config.rig
        y[..., THETA_DOT] = y[..., THETA_DOT] - rig.ml * np.cos(y[..., THETA]) * dx_dot / (
            self._rotational_inertia
        )
        y[..., X_DOT] = x_dot + dx_dot
        y[..., X] = np.clip(x, t.min_m, t.max_m)
        return y

    # -- measurement ---------------------------------------------------------------------

    def raw_measurement(self, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(IR ADC code, current ADC code, encoder count) of a state."""
        s = self.config.sensors
        return (
            sensors.adc_code(s, y[..., V_IR]),
            sensors.adc_code(s, y[..., V_CUR]),
            sensors.encoder_count(s, y[..., THETA]),
        )

    def measurement(self, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(x [m], theta [rad], i [A]) as the host program decodes the raw values."""
        return sensors.decode(self.config.sensors, *self.raw_measurement(y))
