"""Physical parameters of the rig: cart-pole, DC motor, sensors, actuator, track.

Values default to the thesis rig (SPEC section 2, thesis Table 6.1 and the C++ program
of appendix A.2). The thesis does not give the armature resistance, inductance, rotor
inertia or viscous friction; the defaults chosen here are assumptions, argued in the
field descriptions and in ``config/default.yaml``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from pisc_msgs_py.config import ConfigError, in_range, nonnegative, one_of, param, positive

__all__ = [
    "ActuatorParams",
    "FrictionParams",
    "ModelParams",
    "NoiseParams",
    "InitialParams",
    "LoopParams",
    "MotorParams",
    "RigParams",
    "SensorParams",
    "TrackParams",
    "UNUSED_UNDER",
    "check_models_use",
    "unused_by_models",
]


@dataclass(frozen=True)
class RigParams:
    """Cart-pole with pendulum inertia, thesis (3.1)-(3.6)."""

    cart_mass_kg: float = param(0.4735, "M, cart mass", "kg", positive)
    pendulum_mass_kg: float = param(0.01055, "m, pendulum mass", "kg", positive)
    pendulum_com_m: float = param(0.0865, "l, pivot to pendulum centre of mass", "m", positive)
    pendulum_inertia_kgm2: float = param(
        2.631524e-5, "I, pendulum inertia about its centre of mass (0 = point mass)", "kg m^2",
        nonnegative,
    )
    gravity_mps2: float = param(9.81, "g, gravity (the thesis C++ program uses 9.81; 0 is a "
                                "cart-pole lying flat, which cannot be balanced)", "m/s^2",
                                nonnegative)

    @property
    def a1(self) -> float:
        """a1 = m^2 l^2 / (m l^2 + I), thesis (3.1)."""
        m, l = self.pendulum_mass_kg, self.pendulum_com_m
        return m * m * l * l / (m * l * l + self.pendulum_inertia_kgm2)

    @property
    def a2(self) -> float:
        """a2 = M + m, thesis (3.2)."""
        return self.cart_mass_kg + self.pendulum_mass_kg

    @property
    def ml(self) -> float:
        return self.pendulum_mass_kg * self.pendulum_com_m

    @property
    def mgl(self) -> float:
        return self.pendulum_mass_kg * self.gravity_mps2 * self.pendulum_com_m


@dataclass(frozen=True)
class MotorParams:
    """Brushed permanent-magnet DC motor driving the wheels, thesis (2.81)-(2.82), (4.2).

    The armature values are assumptions (the thesis does not measure them): R = 14 ohm
    matches the largest sustained current of about 0.8 A at the 11.47 V limit
    (11.47 / 0.8 = 14.3 ohm) and keeps the thesis PI gains stable when sampled at 5 ms
    (SPEC section 3); L = 2 mH gives L/R = 0.14 ms, typical of small printer motors such
    as the HP RL1-1450; J_m and b_m are those of a small can motor and reflect to
    0.2 % of the cart mass and 1 mN s/m at the cart.
    """

    torque_constant_nm_per_a: float = param(0.0637, "k_m, torque constant", "N m/A", positive)
    back_emf_v_s_per_rad: float = param(
        0.0637, "k_e, back-EMF constant (equal to k_m in SI)", "V s/rad", positive)
    wheel_radius_m: float = param(0.032, "r, wheel radius (wheels on the motor shaft)", "m",
                                  positive)
    resistance_ohm: float = param(14.0, "R, armature resistance (assumed)", "ohm", positive)
    inductance_h: float = param(0.002, "L, armature inductance (assumed)", "H", positive)
    rotor_inertia_kgm2: float = param(2.0e-6, "J_m, rotor inertia (assumed)", "kg m^2",
                                      nonnegative)
    viscous_friction_nms: float = param(1.0e-6, "b_m, viscous friction (assumed)",
                                        "N m s/rad", nonnegative)

    @property
    def force_per_amp(self) -> float:
        """f / i = k_m / r, thesis (4.2)."""
        return self.torque_constant_nm_per_a / self.wheel_radius_m

    @property
    def reflected_mass_kg(self) -> float:
        """Rotor inertia seen at the cart, J_m / r^2."""
        return self.rotor_inertia_kgm2 / self.wheel_radius_m**2

    @property
    def reflected_damping_ns_per_m(self) -> float:
        """Rotor friction seen at the cart, b_m / r^2."""
        return self.viscous_friction_nms / self.wheel_radius_m**2


@dataclass(frozen=True)
class SensorParams:
    """Sensor calibrations of SPEC section 4 (the C++ program's conversions)."""

    adc_bits: int = param(10, "ADC resolution", "bit", in_range(1, 16))
    adc_ref_low_v: float = param(0.595, "ADC low reference (code 0)", "V")
    adc_span_v: float = param(2.514, "ADC span: V = code * span / 2^bits + low", "V", positive)
    ir_scale_m: float = param(0.2451, "IR curve: x = origin - scale * V^-exponent (4.8)", "m",
                              positive)
    ir_exponent: float = param(1.069, "IR curve exponent", "", positive)
    ir_origin_m: float = param(0.20, "IR curve offset: cart position at the sensor face", "m")
    ir_filter_hz: float = param(10.26, "IR RC low-pass corner, 47 kohm and 330 nF", "Hz",
                                positive)
    current_scale_a_per_v: float = param(5.0, "ACS712 conversion: i = scale * V - offset",
                                         "A/V", positive)
    current_offset_a: float = param(12.555, "ACS712 conversion offset", "A")
    current_filter_hz: float = param(72.0, "current sensor RC low-pass corner", "Hz", positive)
    encoder_counts_per_rev: int = param(4000, "quadrature counts per revolution (1000 lines)",
                                        "count", in_range(4, 1 << 20))
    encoder_zero_rad: float = param(math.pi, "pendulum angle at count 0 (hanging at power-up)",
                                    "rad")

    @property
    def adc_levels(self) -> int:
        return 1 << self.adc_bits

    @property
    def adc_lsb_v(self) -> float:
        return self.adc_span_v / self.adc_levels

    @property
    def encoder_rad_per_count(self) -> float:
        return 2.0 * math.pi / self.encoder_counts_per_rev


@dataclass(frozen=True)
class ActuatorParams:
    """H-bridge driven by the PIC's 7-bit magnitude and direction bit (SPEC section 4)."""

    full_scale_v: float = param(11.47, "armature voltage of the largest command byte "
                                "(12.27 V supply less 0.8 V bridge drop)", "V", positive)
    command_levels: int = param(127, "magnitude steps of the command byte (0 = ideal, "
                                "unquantised voltage)", "", in_range(0, 1 << 16))
    command_delay_s: float = param(
        0.0, "simulated command latency: the command answering a sample takes effect this "
        "long after it (the simulated plant and the pure simulations; on the wall clock the "
        "graph's own latency comes on top; the virtual rig and the driver ignore it: their "
        "latency is real)", "s", in_range(0.0, 1.0))

    @property
    def step_v(self) -> float:
        """Voltage of one magnitude step (0 when the command is not quantised)."""
        return self.full_scale_v / self.command_levels if self.command_levels else 0.0

    def magnitude(self, voltage_v: ArrayLike) -> np.ndarray:
        """Command byte magnitude, round(|u| * levels / full_scale) saturated to levels.

        Rounds half away from zero, so the boundaries are symmetric in sign.
        """
        if self.command_levels == 0:
            raise ValueError("actuator.command_levels = 0: the command is not quantised")
        scaled = np.abs(np.asarray(voltage_v, dtype=float)) / self.step_v
        return np.minimum(np.floor(scaled + 0.5), self.command_levels).astype(np.int64)

    def apply_scalar(self, voltage_v: float) -> float:
        """:meth:`apply` for one voltage, with the same arithmetic, without numpy's
        per-call cost (a plant node applies one command per period)."""
        v = min(max(float(voltage_v), -self.full_scale_v), self.full_scale_v)
        if self.command_levels == 0:
            return v
        magnitude = min(math.floor(abs(v) / self.step_v + 0.5), self.command_levels)
        sign = 1.0 if v > 0.0 else (-1.0 if v < 0.0 else 0.0)
        return sign * magnitude * self.step_v

    def apply(self, voltage_v: ArrayLike) -> np.ndarray:
        """Voltage the bridge applies for a commanded voltage: saturated, then quantised."""
        v = np.clip(np.asarray(voltage_v, dtype=float), -self.full_scale_v, self.full_scale_v)
        if self.command_levels == 0:
            return v
        return np.sign(v) * self.magnitude(v) * self.step_v


@dataclass(frozen=True)
class TrackParams:
    """End stops of the track. The IR sensor reads -0.227 m .. +0.127 m (SPEC section 4)."""

    min_m: float = param(-0.23, "far end stop", "m")
    max_m: float = param(0.13, "end stop at the IR sensor", "m")

    def __post_init__(self) -> None:
        if not self.min_m < self.max_m:
            raise ConfigError(
                f"track.min_m = {self.min_m} must be below track.max_m = {self.max_m}")


@dataclass(frozen=True)
class LoopParams:
    """The control period, paced by the microcontroller (Timer0, 98 ticks = 5 ms)."""

    period_s: float = param(0.005, "Ts, sample and control period", "s", in_range(1e-5, 1.0))

    @property
    def period_ns(self) -> int:
        return round(self.period_s * 1e9)


@dataclass(frozen=True)
class InitialParams:
    """Initial state of a simulated run (the rig starts hanging at rest)."""

    x_m: float = param(0.0, "initial cart position", "m")
    x_dot_mps: float = param(0.0, "initial cart velocity", "m/s")
    theta_rad: float = param(math.pi, "initial pendulum angle (pi = hanging down)", "rad")
    theta_dot_radps: float = param(0.0, "initial pendulum rate", "rad/s")


ARMATURE_MODELS = ("full", "quasi_static", "ideal_force")
CURRENT_LOOP_MODELS = ("sampled_pi", "ideal")
SENSOR_MODELS = ("quantised", "ideal")
FRICTION_MODELS = ("none", "viscous", "coulomb")


@dataclass(frozen=True)
class ModelParams:
    """Which sub-models a scene needs; the plant composes only these.

    ``armature``: ``full`` keeps the armature current as a state, (2.81); ``quasi_static``
    sets L di/dt = 0, i = (u - k_e phi_dot) / R, and has no electrical state;
    ``ideal_force`` drops the motor: the cart force is the plant's input. ``current_loop``:
    ``sampled_pi`` closes the PI loop (3.47) at the sample rate on the measured current;
    ``ideal`` makes the current equal its set-point (3.46), which only an ideal force
    source can do, so it goes with ``armature: ideal_force``. ``sensors``: ``quantised``
    reads the cart through the IR curve (4.8) and a 10-bit ADC, the angle through the
    encoder and the current through the ACS712 and the ADC, as the rig does; ``ideal``
    reads the true x, theta and i. ``sensor_filters`` adds the 10 Hz IR and 72 Hz current
    RC filters as states (quantised sensors only).
    """

    armature: str = param("full", "DC motor armature: 'full', 'quasi_static' or 'ideal_force'",
                          "", one_of(*ARMATURE_MODELS))
    current_loop: str = param("sampled_pi", "current loop: 'sampled_pi' or 'ideal'", "",
                              one_of(*CURRENT_LOOP_MODELS))
    sensors: str = param("quantised", "sensors: 'quantised' (the rig's) or 'ideal'", "",
                         one_of(*SENSOR_MODELS))
    sensor_filters: bool = param(True, "the IR (10 Hz) and current (72 Hz) RC filters as states",
                                 "")
    friction: str = param("none", "friction on the cart and at the pivot besides the motor's: "
                          "'none', 'viscous' or 'coulomb' (Coulomb and viscous)", "",
                          one_of(*FRICTION_MODELS))
    end_stops: bool = param(True, "inelastic end stops at the ends of the track", "")

    def __post_init__(self) -> None:
        if (self.armature == "ideal_force") != (self.current_loop == "ideal"):
            raise ConfigError(
                f"models.current_loop = {self.current_loop!r} does not go with models.armature "
                f"= {self.armature!r}: an ideal current loop is an ideal force source "
                "(armature: ideal_force, current_loop: ideal); a motor armature needs the "
                "sampled PI loop")
        if self.sensor_filters and self.sensors == "ideal":
            raise ConfigError("models.sensor_filters = true needs models.sensors = 'quantised': "
                              "the RC filters act on the sensors' voltages")

    @property
    def has_current_state(self) -> bool:
        return self.armature == "full"

    @property
    def has_current(self) -> bool:
        return self.armature != "ideal_force"

    @property
    def force_input(self) -> bool:
        return self.armature == "ideal_force"


@dataclass(frozen=True)
class FrictionParams:
    """Friction besides the motor's own b_m (used when ``models.friction`` asks for it).

    Cart: f_fric = -b_c x_dot - F_c tanh(x_dot / v_c); pivot: tau = -b_p theta_dot. The
    thesis neglects both; the Coulomb term is regularised over v_c so that fixed-step
    integrators see a smooth right-hand side.
    """

    cart_viscous_ns_per_m: float = param(0.0, "b_c, cart viscous friction", "N s/m",
                                         nonnegative)
    pivot_viscous_nms: float = param(0.0, "b_p, pivot viscous friction", "N m s/rad",
                                     nonnegative)
    cart_coulomb_n: float = param(0.0, "F_c, cart Coulomb friction", "N", nonnegative)
    coulomb_velocity_mps: float = param(1e-3, "v_c, velocity over which the Coulomb force "
                                        "builds up (tanh regularisation)", "m/s", positive)


@dataclass(frozen=True)
class NoiseParams:
    """Measurement noise: Gaussian, added to the true value before the sensor chain."""

    seed: int = param(0, "seed of the noise generator (same seed, same run)", "",
                      in_range(0, 2**31 - 1))
    x_std_m: float = param(0.0, "cart position noise, standard deviation", "m", nonnegative)
    theta_std_rad: float = param(0.0, "pendulum angle noise, standard deviation", "rad",
                                 nonnegative)
    current_std_a: float = param(0.0, "armature current noise, standard deviation", "A",
                                 nonnegative)

    @property
    def any(self) -> bool:
        """Whether any noise is drawn (for a plant set, whether any rig has some)."""
        return bool(np.any(np.asarray(self.x_std_m) > 0.0)
                    or np.any(np.asarray(self.theta_std_rad) > 0.0)
                    or np.any(np.asarray(self.current_std_a) > 0.0))


#: Parameters the plant leaves out under a choice of sub-model: (``models`` field, the
#: choices that leave them out, the parameters, what the plant does instead, the choice
#: that uses them). A value of one of them other than its default, under such a choice,
#: is a value the file states and the plant ignores (:func:`unused_by_models`).
UNUSED_UNDER: tuple[tuple[str, tuple[object, ...], tuple[str, ...], str, str], ...] = (
    ("friction", ("none",), ("friction.cart_viscous_ns_per_m", "friction.pivot_viscous_nms",
                             "friction.cart_coulomb_n", "friction.coulomb_velocity_mps"),
     "no friction besides the motor's b_m", "coulomb (or viscous, without the Coulomb term)"),
    ("friction", ("viscous",), ("friction.cart_coulomb_n", "friction.coulomb_velocity_mps"),
     "viscous friction only", "coulomb"),
    ("sensor_filters", (False,), ("sensors.ir_filter_hz", "sensors.current_filter_hz"),
     "no RC filter states", "true"),
    ("armature", ("quasi_static", "ideal_force"), ("motor.inductance_h",),
     "no armature transient, L di/dt = 0", "full"),
    ("armature", ("ideal_force",), ("motor.resistance_ohm", "motor.rotor_inertia_kgm2"),
     "the cart force is the input, no motor", "full"),
)


def unused_by_models(flat: dict[str, object]) -> list[str]:
    """What a parameter file (flat ``section.name`` values, overrides included) states and
    the plant ignores under its ``models``: one sentence a parameter, naming it, empty when
    nothing is; a value equal to the parameter's default is not counted (it changes
    nothing either way)."""
    from dataclasses import fields

    from pisc_msgs_py.config import from_flat

    models = from_flat(ModelParams, flat, "models")
    classes = {"friction": FrictionParams, "sensors": SensorParams, "motor": MotorParams}
    out = []
    for choice, leave_out, names, meaning, remedy in UNUSED_UNDER:
        chosen = getattr(models, choice)
        if chosen not in leave_out:
            continue
        for name in names:
            if name not in flat:
                continue
            section, leaf = name.split(".")
            default = next(f.default for f in fields(classes[section]) if f.name == leaf)
            value = flat[name]
            if isinstance(value, (int, float)) and not isinstance(value, bool) \
                    and float(value) == float(default):
                continue
            setting = str(chosen).lower() if isinstance(chosen, bool) else repr(chosen)
            out.append(f"{name} = {value!r} is not used: models.{choice} is {setting} "
                       f"({meaning}); set models.{choice}: {remedy} to use it, or "
                       "leave it out")
    return out


def check_models_use(flat: dict[str, object], where: str = "") -> None:
    """Refuse a parameter file whose values the plant would ignore
    (:func:`unused_by_models`): :class:`ConfigError` naming every such parameter."""
    unused = unused_by_models(flat)
    if unused:
        raise ConfigError(where + "; ".join(unused))
