"""The files a run's bag holds beside its MCAP, and the one reader of them.

``pisc_graph`` writes the parameters the controllers ran with into the bag directory
(:data:`PARAMS_FILE`) and, when the plant ran with parameters of its own (model error),
the plant's (:data:`PLANT_PARAMS_FILE`). Every tool that reads a run's parameters back
(summary, analysis, animation, replay, identification) reads them here, so a missing or
broken file is refused the same way everywhere: a :class:`~pisc_bag.bag.BagError` that
names the file and what is wrong.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any, TypeVar

from pisc_bag.bag import BagError
from pisc_msgs_py.config import ConfigError, from_flat, load_params_file

__all__ = ["PARAMS_FILE", "PLANT_PARAMS_FILE", "recorded_params", "recorded_section"]

PARAMS_FILE = "pisc_params.yaml"  # the controllers' parameters of the run
PLANT_PARAMS_FILE = "plant_params.yaml"  # the plant's, when they differ (model error)

T = TypeVar("T")


def recorded_params(bag: str | Path, required: bool = False) -> dict[str, Any]:
    """The flat parameters (``section.name`` -> value) a run was recorded with; ``{}``
    when the bag holds no :data:`PARAMS_FILE` (an older bag or one from elsewhere), or a
    :class:`BagError` if ``required``."""
    path = Path(bag) / PARAMS_FILE
    if not path.is_file():
        if required:
            raise BagError(f"{bag}: no {PARAMS_FILE} (the parameters of the run); name the "
                           "configuration it ran with (--config)")
        return {}
    try:
        return load_params_file(path)
    except ConfigError as exc:
        raise BagError(f"{path}: {exc}") from None


def recorded_section(bag: str | Path, cls: type[T], section: str,
                     flat: Mapping[str, Any] | None = None) -> T:
    """One typed section (e.g. ``SafetyParams``, ``"safety"``) of the run's parameters, its
    defaults where the file or the value is missing; ``flat`` when already read."""
    flat = recorded_params(bag) if flat is None else flat
    try:
        return from_flat(cls, {k: v for k, v in flat.items() if k.startswith(section + ".")},
                         section)
    except ConfigError as exc:
        raise BagError(f"{Path(bag) / PARAMS_FILE}: {exc}") from None
