"""The plant kernel's layout: its methods, armature codes, the indices of its packed
constants and :class:`Layout`, without the kernel (numba) itself.

What a configuration needs (:class:`pisc_plant.plant_config.PlantConfig` checks the
method against :data:`METHODS`, :func:`pisc_plant.plant_config.pack_constants` fills the
``P_*`` slots) is here, so that a process that loads a configuration but runs no plant (the
controller nodes, ``pisc_bag replay``) does not import numba: 75 MB of resident memory
and about 0.3 s (``python -X importtime -c "import pisc_plant.kernel"``).
"""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["ARM_FORCE", "ARM_FULL", "ARM_QUASI_STATIC", "EXPRK4", "METHODS", "N_CONSTANTS",
           "Layout", "RK4"]

METHODS = ("rk4", "exprk4")
RK4, EXPRK4 = 0, 1

ARM_FULL, ARM_QUASI_STATIC, ARM_FORCE = 0, 1, 2

# Indices into the packed constants.
(P_A1, P_A2, P_ML, P_G, P_KF, P_BM, P_R, P_L, P_KER, P_BC, P_BP, P_FC, P_VC, P_WIR,
 P_WCUR, P_IRO, P_IRS, P_IRX, P_CUROFF, P_CURSCALE, P_XMIN, P_XMAX, P_JROT) = range(23)
N_CONSTANTS = 23


@dataclass(frozen=True)
class Layout:
    """Which components a scene's state has, and where, and which terms the kernel
    computes."""

    armature: int  # ARM_FULL, ARM_QUASI_STATIC or ARM_FORCE
    filters: bool
    end_stops: bool
    # Coulomb friction on the cart (models.friction = coulomb): not a state component,
    # but the kernel compiles its term only into the layouts that have it
    coulomb: bool = False

    @property
    def current_index(self) -> int:
        return 4 if self.armature == ARM_FULL else -1

    @property
    def ir_index(self) -> int:
        return (5 if self.armature == ARM_FULL else 4) if self.filters else -1

    @property
    def current_sensor_index(self) -> int:
        return self.ir_index + 1 if self.filters else -1

    @property
    def size(self) -> int:
        return 4 + (self.armature == ARM_FULL) + 2 * self.filters
