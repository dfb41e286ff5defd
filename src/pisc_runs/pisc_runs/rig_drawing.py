"""How the rig is drawn, one look for every picture of it: the animation of a bag
(:mod:`pisc_runs.animate`) and the live markers for RViz and Foxglove
(:mod:`pisc_runs.markers`) share these colours, sizes and the pendulum's geometry.

The angle convention is the project's (SPEC section 4): theta = 0 upright, pi hanging; the
rod's free end is at (x + L sin(theta), L cos(theta)) above the pivot on the cart.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from pisc_msgs_py.types import Mode

__all__ = ["CART_COLOUR", "CART_HEIGHT_M", "CART_WIDTH_M", "FORCE_ARROW_MAX_M", "FORCE_COLOUR",
           "FORCE_SCALE_M_PER_N", "LIMIT_COLOUR", "MODE_COLOURS", "OVERLAY_COLOUR", "rod_end"]

#: The pendulum's colour in each mode (RGB, 0-255): distinct hues, so that a test can
#: find the rod by its colour.
MODE_COLOURS = {Mode.SWING_UP: (230, 120, 0), Mode.CATCH: (0, 150, 60),
                Mode.FAULT: (210, 20, 20)}
CART_COLOUR = (40, 80, 170)
FORCE_COLOUR = (140, 40, 160)
OVERLAY_COLOUR = (150, 150, 150)
LIMIT_COLOUR = (90, 90, 90)  # the safe range, dashed
CART_WIDTH_M = 0.05
CART_HEIGHT_M = 0.025
FORCE_SCALE_M_PER_N = 0.025  # arrow length per newton of cart force
FORCE_ARROW_MAX_M = 0.1  # longer arrows are cut to this (the title gives the value)


def rod_end(x_m: Any, theta_rad: Any, length_m: float) -> tuple[Any, Any]:
    """The pendulum's free end for a pivot at (x, 0): (x + L sin(theta), L cos(theta))."""
    return x_m + length_m * np.sin(theta_rad), length_m * np.cos(theta_rad)
