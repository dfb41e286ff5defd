"""The configuration a plant is built from: its sections, the integrator, plant sets, and
the constants the compiled kernel reads.

:class:`PlantConfig` holds the parameter sections of a rig's plant
(:data:`PLANT_SECTIONS`), :class:`IntegratorParams` the integration between samples.
A plant set (:func:`plant_set`) is a configuration whose ``rig``, ``motor``,
``friction`` and ``noise.*_std_*`` fields may hold one value a rig (1-D arrays of one
length n): its :class:`pisc_plant.plant.Plant` steps n rigs, state (n, size), each with
its own constants, and each rig gives the same bits as a plant built from its own
values. :func:`pack_constants` turns a configuration into the kernel's constants. Like
:mod:`pisc_plant.layout`, this module does not import numba.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike

from pisc_msgs_py.config import ConfigError, in_range, one_of, param
from pisc_model.params import (
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
from pisc_plant import layout

__all__ = ["PER_RIG_SECTIONS", "PLANT_SECTIONS", "IntegratorParams", "PlantConfig",
           "pack_constants", "plant_set", "rigs_of"]


@dataclass(frozen=True)
class IntegratorParams:
    """Numerical integration of the plant between control samples.

    ``exprk4`` (the default, 2 steps per period) is an exponential Runge-Kutta method of
    stiff order four that treats the armature's transient and the sensor filters in
    closed form and is stable at any step up to the period (:mod:`pisc_plant.kernel_steps`).
    ``rk4`` is the classical Runge-Kutta method; it is stable only while each step
    resolves the armature (h R / L < 2.785), which the plant checks. README, "Scenes and
    integrators", measures both against SciPy.
    """

    method: str = param("exprk4", "'exprk4' (exponential, stable at any step) or 'rk4' "
                        "(classical Runge-Kutta)", "", one_of(*layout.METHODS))
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


#: The sections whose fields a plant set may give one value a rig (noise: ``*_std_*``).
PER_RIG_SECTIONS = ("rig", "motor", "friction", "noise")


def _per_rig_fields(section: str) -> dict[str, dataclasses.Field]:
    fields = {f.name: f for f in dataclasses.fields(PLANT_SECTIONS[section])}
    if section == "noise":
        fields = {name: f for name, f in fields.items() if "_std_" in name}
    return fields


def rigs_of(config: PlantConfig) -> int | None:
    """The number of rigs of a plant set (:func:`plant_set`), None for one rig."""
    return _rig_count(config)[0]


def _rig_count(config: PlantConfig) -> tuple[int | None, str]:
    """The number of rigs of a plant set and the first parameter that says so."""
    rigs: int | None = None
    first = ""
    for section in PER_RIG_SECTIONS:
        values = getattr(config, section)
        for f in dataclasses.fields(values):
            value = getattr(values, f.name)
            if not isinstance(value, np.ndarray):
                continue
            name = f"{section}.{f.name}"
            if value.ndim != 1:
                raise ConfigError(f"{name}: one value a rig (a 1-D array), not shape "
                                  f"{value.shape}")
            if rigs is None:
                rigs, first = len(value), name
            elif len(value) != rigs:
                raise ConfigError(f"{name}: {len(value)} values, but {first} has {rigs}")
    return rigs, first


def plant_set(base: PlantConfig, values: Mapping[str, ArrayLike]) -> PlantConfig:
    """A plant set: ``base`` with one value a rig for the parameters named.

    Parameters
    ----------
    base
        The configuration every rig shares otherwise (itself a set or one rig).
    values
        Dotted parameter names of the sections :data:`PER_RIG_SECTIONS` (``rig.*``,
        ``motor.*``, ``friction.*``, ``noise.*_std_*``), each with a 1-D array of one
        value a rig, all of one length n, or a number for every rig.

    Returns
    -------
    PlantConfig
        ``base`` with the fields named holding read-only float64 arrays of shape (n,);
        a :class:`Plant` of it steps n rigs.

    Raises
    ------
    ConfigError
        Starting with the parameter's name: a name that is unknown or outside those
        sections, arrays of different lengths (or of another length than ``base``'s
        rigs), no array at all, or a value that breaks the field's rule.
    """
    rigs, first = _rig_count(base)
    arrays: dict[str, np.ndarray] = {}
    for name, value in values.items():
        section, _, field_name = name.partition(".")
        if section not in PLANT_SECTIONS or field_name not in {
                f.name for f in dataclasses.fields(PLANT_SECTIONS[section])}:
            raise ConfigError(f"{name}: unknown parameter")
        fields = _per_rig_fields(section) if section in PER_RIG_SECTIONS else {}
        if field_name not in fields:
            raise ConfigError(f"{name}: not a parameter a plant set may vary from rig to rig "
                              "(rig.*, motor.*, friction.*, noise.*_std_*)")
        try:
            array = np.array(value, dtype=float)
        except (TypeError, ValueError):
            raise ConfigError(f"{name}: must be a number or a 1-D array of numbers") from None
        if array.ndim > 1:
            raise ConfigError(f"{name}: must be a number or a 1-D array of numbers, not an "
                              f"array of shape {array.shape}")
        if array.ndim == 1:
            if len(array) == 0:
                raise ConfigError(f"{name}: no values (a plant set has at least one rig)")
            if rigs is None:
                rigs, first = len(array), name
            elif len(array) != rigs:
                raise ConfigError(f"{name}: {len(array)} values, but {first} has {rigs}")
        rule = fields[field_name].metadata["rule"]
        numbers = array.ravel().tolist()
        problem = rule(numbers)
        if problem:
            bad = next(k for k, v in enumerate(numbers) if rule(v))
            raise ConfigError(f"{name}: {problem} (rig {bad}: {numbers[bad]})" if array.ndim
                              else f"{name} = {numbers[0]}: {problem}")
        arrays[name] = array
    if rigs is None:
        raise ConfigError(f"{next(iter(values), 'plant_set')}: a plant set needs one value a "
                          "rig (a 1-D array) for at least one parameter")
    sections: dict[str, dict[str, np.ndarray]] = {}
    for name, array in arrays.items():
        section, _, field_name = name.partition(".")
        column = np.array(np.broadcast_to(array, (rigs,)), dtype=float)
        column.setflags(write=False)
        sections.setdefault(section, {})[field_name] = column
    return dataclasses.replace(base, **{
        section: dataclasses.replace(getattr(base, section), **changes)
        for section, changes in sections.items()})


def _reflected(m: MotorParams) -> tuple:
    """J_m / r^2 and b_m / r^2; with one radius a rig, r^2 with Python's arithmetic (as a
    plant of one rig computes it: numpy's square can differ from pow in the last bit)."""
    if isinstance(m.wheel_radius_m, np.ndarray):
        r2 = np.array([r**2 for r in m.wheel_radius_m.tolist()])
        return m.rotor_inertia_kgm2 / r2, m.viscous_friction_nms / r2
    return m.reflected_mass_kg, m.reflected_damping_ns_per_m


def pack_constants(c: PlantConfig) -> np.ndarray:
    """The configuration as the kernel's constants (``kernel.P_*``): (N_CONSTANTS,), or
    for a plant set of n rigs (N_CONSTANTS, n), rig k's constants in column k (the
    kernel reads them in the blocks of :func:`pisc_plant.kernel_sets.lanes`)."""
    rigs = rigs_of(c)
    p = np.zeros(layout.N_CONSTANTS if rigs is None else (layout.N_CONSTANTS, rigs))
    rig, m, s, t, f = c.rig, c.motor, c.sensors, c.track, c.friction
    friction = c.models.friction
    reflected_mass, reflected_damping = _reflected(m)
    p[layout.P_A1] = rig.a1
    # the rotor's inertia reflected to the cart, J_m / r^2, joins the cart row only
    p[layout.P_A2] = rig.a2 + (reflected_mass if c.models.has_current else 0.0)
    p[layout.P_ML] = rig.ml
    p[layout.P_G] = rig.gravity_mps2
    p[layout.P_KF] = m.force_per_amp
    p[layout.P_BM] = reflected_damping
    p[layout.P_R] = m.resistance_ohm
    p[layout.P_L] = m.inductance_h
    p[layout.P_KER] = m.back_emf_v_s_per_rad / m.wheel_radius_m
    if friction != "none":
        p[layout.P_BC] = f.cart_viscous_ns_per_m
        p[layout.P_BP] = f.pivot_viscous_nms
    if friction == "coulomb":
        p[layout.P_FC] = f.cart_coulomb_n
    p[layout.P_VC] = f.coulomb_velocity_mps
    p[layout.P_WIR] = 2.0 * math.pi * s.ir_filter_hz
    p[layout.P_WCUR] = 2.0 * math.pi * s.current_filter_hz
    p[layout.P_IRO] = s.ir_origin_m
    p[layout.P_IRS] = s.ir_scale_m
    p[layout.P_IRX] = -1.0 / s.ir_exponent
    p[layout.P_CUROFF] = s.current_offset_a
    p[layout.P_CURSCALE] = s.current_scale_a_per_v
    p[layout.P_XMIN] = t.min_m
    p[layout.P_XMAX] = t.max_m
    p[layout.P_JROT] = rig.pendulum_inertia_kgm2 + rig.ml * rig.pendulum_com_m
    return p
