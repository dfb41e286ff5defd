"""Moved to :mod:`pisc_model.motor` (the model without the simulator); this name stays only
until the last importers move, and goes away then."""

from pisc_model.motor import *  # noqa: F403
from pisc_model.motor import __all__  # noqa: F401
