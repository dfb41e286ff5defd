"""Moved to :mod:`pisc_sim.configuration` (the simulation without ROS); this name stays only until
the last importers move, and goes away then."""

from pisc_sim import configuration as _moved

globals().update({k: v for k, v in vars(_moved).items() if not k.startswith("__")})
__all__ = _moved.__all__
