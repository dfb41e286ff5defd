"""Moved to :mod:`pisc_model.params` (the model without the simulator); this name stays only
until the last importers move, and goes away then."""

from pisc_model.params import *  # noqa: F403
from pisc_model.params import __all__  # noqa: F401
