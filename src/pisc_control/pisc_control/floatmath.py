"""numpy's arithmetic on one float: the helpers the one-rig laws call.

The laws of :mod:`pisc_control` are written on Python floats, one rig at a time (the
nodes call them as they are, the batch compiles them with numba). Where ``math`` differs
from numpy on a value (it raises on an infinite angle and on the floor of NaN, where
numpy gives NaN), these give numpy's answer, so that a law gives the same bits from a
node, from the compiled batch and from an array element. Plain functions of floats,
calling nothing but ``math``: :mod:`pisc_sim.batch_controllers` compiles them.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["clip", "cos", "floor", "sin", "wrap"]

TWO_PI = 2.0 * np.pi  # pisc_model.dynamics.wrap_to_upright's constant, as numpy forms it


def clip(v: float, lo: float, hi: float) -> float:
    """np.clip of one value (NaN passes through, as numpy's does)."""
    if v < lo:
        return lo
    if v > hi:
        return hi
    return v


def floor(v: float) -> float:
    """np.floor of one value: NaN and the infinities pass through (``math.floor`` raises
    on them) and so do values too large to have a fraction (2^52 and up), which compiled
    code would otherwise overflow into a 64-bit integer."""
    if v != v or abs(v) >= 4503599627370496.0:
        return v
    return float(math.floor(v))


def sin(v: float) -> float:
    """np.sin of one value: NaN for the infinities (``math.sin`` raises on them)."""
    return v - v if math.isinf(v) else math.sin(v)


def cos(v: float) -> float:
    """np.cos of one value: NaN for the infinities (``math.cos`` raises on them)."""
    return v - v if math.isinf(v) else math.cos(v)


def wrap(theta: float) -> float:
    """:func:`pisc_model.dynamics.wrap_to_upright` of one value: the angle from the
    nearest upright, in [-pi, pi)."""
    return theta - TWO_PI * floor(theta / TWO_PI + 0.5)
