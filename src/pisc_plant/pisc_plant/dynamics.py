"""Moved to :mod:`pisc_model.dynamics` (the model without the simulator); this name stays only
until the last importers move, and goes away then."""

from pisc_model.dynamics import *  # noqa: F403
from pisc_model.dynamics import __all__  # noqa: F401
