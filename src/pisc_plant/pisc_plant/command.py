"""What drives the plant: the current loop's voltage, or the force of its set-point.

The plant node and the pure closed loop (:mod:`pisc_sim.closed_loop`) both take the
plant's command from here, so that a lockstep graph and the pure simulation drive the
plant with the same bits.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from numpy.typing import ArrayLike

if TYPE_CHECKING:
    from pisc_plant.plant_config import PlantConfig

__all__ = ["plant_command"]


def plant_command(config: PlantConfig, *, setpoint_a: ArrayLike | None = None,
                  voltage_v: ArrayLike | None = None) -> ArrayLike:
    """The plant's command for the current loop's answer to one sample.

    A motor armature is driven by the voltage ``voltage_v`` (3.47). An ideal force source
    (``models.armature = ideal_force``, with ``models.current_loop = ideal``: the current
    equals its set-point) is driven by the force ``k_m i_d / r`` of the set-point
    ``setpoint_a`` (4.2), with the plant's own ``k_m / r``; the voltage then acts on
    nothing. The value the plant does not use may be left out (a node that hears only
    the topic that drives the plant); the one it uses may not.

    Raises
    ------
    ValueError
        When the value that drives this plant is not given.
    """
    if config.models.force_input:
        if setpoint_a is None:
            raise ValueError("an ideal force source (models.armature = ideal_force) is driven "
                             "by the current set-point: setpoint_a is required")
        return config.motor.force_per_amp * setpoint_a
    if voltage_v is None:
        raise ValueError(f"a motor armature (models.armature = {config.models.armature}) is "
                         "driven by the voltage: voltage_v is required")
    return voltage_v
