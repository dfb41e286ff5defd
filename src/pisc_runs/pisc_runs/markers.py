"""The rig as RViz/Foxglove markers: plain descriptions, no rclpy (the node is markers_node).

Two pure pieces:

* :func:`rig_markers` draws one :class:`RigFrame` (cart position, pendulum angle, mode,
  cart force, run time) as :class:`MarkerSpec` descriptions in a fixed frame (``world``
  by default): x along the track, z up, the pendulum swinging in the x-z plane. The
  geometry is :mod:`pisc_runs.animate`'s: the pivot at (x, 0) on the cart, the
  pendulum the uniform rod of length 2 l whose free end is :func:`~pisc_runs.animate.
  rod_end` (x + 2 l sin(theta), 2 l cos(theta)), theta = 0 upright and positive towards
  +x (SPEC section 4); the pendulum has the mode's colour of
  :data:`~pisc_runs.animate.MODE_COLOURS`.
* :class:`MarkerFeed` turns the node's inputs (state samples, cart forces, mode changes,
  each with its stamp) into the frames to draw: at most ``markers.rate_hz`` per second
  *of the samples' stamps* (one per slot of 1/rate_hz s on the stamps' own time line),
  each with the force and the mode of its own stamp, so that the same samples are drawn
  in lockstep, on the wall clock and when a bag is played.

Every array carries every marker, the static ones (track, end stops, safe range)
included, each under a fixed namespace and id (:data:`MARKER_IDS`), so RViz and Foxglove
replace rather than accumulate, and a viewer that joins late, or a bag opened in the
middle, shows the whole rig at once: a latched one-off message of the static parts would
be missed by a bag viewer that seeks past it. The cost is four markers more per array,
at 30 arrays a second.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from pisc_runs.rig_drawing import (
    CART_COLOUR,
    CART_HEIGHT_M,
    CART_WIDTH_M,
    FORCE_ARROW_MAX_M,
    FORCE_COLOUR,
    FORCE_SCALE_M_PER_N,
    LIMIT_COLOUR,
    MODE_COLOURS,
    rod_end,
)
from pisc_control.supervisor import SafetyParams
from pisc_msgs_py.config import one_of, param, positive
from pisc_msgs_py.types import Mode
from pisc_model.params import RigParams, TrackParams

__all__ = ["MARKER_IDS", "SOURCES", "MarkerFeed", "MarkerScene", "MarkerSpec", "MarkersParams",
           "RigFrame", "rig_markers"]

#: Where the node takes the state from: ``true`` the simulator's true state
#: (``/pisc/sim/true_state``), ``measured`` the joint states (``/pisc/joint_states``, the
#: rig's encoders), ``auto`` the true state when it is published, else the measured one.
SOURCES = ("auto", "true", "measured")

_FRAME_ID = re.compile(r"[A-Za-z_][A-Za-z0-9_/]*")


def _frame_id(value: Any) -> str | None:
    if not isinstance(value, str) or not _FRAME_ID.fullmatch(value):
        return ("must be a frame name: letters, digits, '_' and '/', starting with a letter "
                "or '_' (tf2 refuses a leading '/')")
    return None


@dataclass(frozen=True)
class MarkersParams:
    """What the markers node draws from, how often, and in which frame."""

    source: str = param("auto", "state drawn: true (/pisc/sim/true_state), measured "
                        "(/pisc/joint_states) or auto (the true state when published)",
                        rule=one_of(*SOURCES))
    rate_hz: float = param(30.0, "at most this many marker arrays per second of the samples' "
                           "stamps", "Hz", positive)
    frame_id: str = param("world", "fixed frame of the markers (x along the track, z up)",
                          rule=_frame_id)


# -- drawing -------------------------------------------------------------------------------

@dataclass(frozen=True)
class MarkerSpec:
    """One marker as plain data; the node maps it onto ``visualization_msgs/Marker``.

    ``kind`` is one of ``cube``, ``line_strip``, ``line_list``, ``arrow``, ``text``;
    ``action`` ``add`` or ``delete`` (the force arrow when there is no force to show).
    Positions in metres in the scene's frame, colours RGBA in 0..1, ``scale`` as the
    Marker message reads it for the kind (a cube's size; a line's width in x; an arrow's
    shaft and head diameters and head length; a text's height in z).
    """

    ns: str
    id: int
    kind: str
    action: str = "add"
    position: tuple[float, float, float] = (0.0, 0.0, 0.0)
    orientation: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 1.0)  # x, y, z, w
    scale: tuple[float, float, float] = (1.0, 1.0, 1.0)
    colour: tuple[float, float, float, float] = (1.0, 1.0, 1.0, 1.0)
    points: tuple[tuple[float, float, float], ...] = ()
    text: str = ""


#: (namespace, id) of every marker of an array, in the order :func:`rig_markers` gives them.
MARKER_IDS = (("track", 0), ("end_stops", 0), ("end_stops", 1), ("safe_range", 0),
              ("cart", 0), ("pendulum", 0), ("force", 0), ("status", 0))

UNKNOWN_MODE_COLOUR = (150, 150, 150)  # before the node has heard the supervisor's mode
CART_DEPTH_M = 0.04  # the cart's extent across the track (y), for a 3D view
ROD_WIDTH_M = 0.006
RAIL_Z_M = -CART_HEIGHT_M / 2 - 0.004  # animate's rail, under the cart
ARROW_Z_M = -CART_HEIGHT_M / 2 - 0.02  # animate's force arrow, under the rail
ARROW_MIN_M = 0.004  # animate's: a shorter arrow would be all head
TEXT_HEIGHT_M = 0.018


def _rgba(colour: tuple[int, int, int], alpha: float = 1.0) -> tuple[float, float, float, float]:
    return (colour[0] / 255, colour[1] / 255, colour[2] / 255, alpha)


@dataclass(frozen=True)
class MarkerScene:
    """The fixed parts of the picture: pendulum length, end stops, safe range, frame."""

    rod_m: float  # 2 l, the drawn pendulum (animate's RunFrames.rod_m)
    track: TrackParams = field(default_factory=TrackParams)
    safety: SafetyParams = field(default_factory=SafetyParams)
    frame_id: str = "world"

    @classmethod
    def of(cls, rig: RigParams, track: TrackParams, safety: SafetyParams,
           frame_id: str = "world") -> MarkerScene:
        return cls(2.0 * rig.pendulum_com_m, track, safety, frame_id)


@dataclass(frozen=True)
class RigFrame:
    """What one array shows: the state of one sample, with the mode and force of its stamp."""

    stamp_ns: int
    x_m: float
    theta_rad: float
    mode: Mode | None  # None: no mode heard yet
    force_n: float  # NaN: no force of this stamp
    true_state: bool  # x and theta are the simulator's true state
    run_time_s: float  # since the first sample the feed saw


def _static_markers(scene: MarkerScene) -> list[MarkerSpec]:
    track, safety = scene.track, scene.safety
    reach = scene.rod_m + 0.02
    grey, black = _rgba((90, 90, 90)), _rgba((25, 25, 25))
    out = [MarkerSpec("track", 0, "cube",
                      position=((track.min_m + track.max_m) / 2, 0.0, RAIL_Z_M - 0.002),
                      scale=(track.max_m - track.min_m, 0.02, 0.004), colour=grey)]
    # animate's stops: from 0.02 m below the rail to 0.035 m above it
    for k, end in enumerate((track.min_m, track.max_m)):
        out.append(MarkerSpec("end_stops", k, "cube", position=(end, 0.0, RAIL_Z_M + 0.0075),
                              scale=(0.006, 0.03, 0.055), colour=black))
    out.append(MarkerSpec(
        "safe_range", 0, "line_list", scale=(0.002, 0.0, 0.0), colour=_rgba(LIMIT_COLOUR, 0.7),
        points=tuple((limit, 0.0, z) for limit in (safety.x_min_m, safety.x_max_m)
                     for z in (-reach - CART_HEIGHT_M, reach))))
    return out


def force_arrow_length_m(force_n: float) -> float:
    """The arrow's signed length: animate's scale and cut (0 when there is no force)."""
    if not math.isfinite(force_n):
        return 0.0
    return max(-FORCE_ARROW_MAX_M, min(FORCE_ARROW_MAX_M, force_n * FORCE_SCALE_M_PER_N))


def status_text(frame: RigFrame) -> str:
    mode = frame.mode.value if frame.mode is not None else "mode ?"
    force = f"{frame.force_n:+.2f} N" if math.isfinite(frame.force_n) else "n/a"
    state = "true state" if frame.true_state else "measured"
    return f"{mode}   t = {frame.run_time_s:.3f} s   F = {force}   ({state})"


def rig_markers(frame: RigFrame, scene: MarkerScene) -> list[MarkerSpec]:
    """Every marker of one array, in the order of :data:`MARKER_IDS`."""
    x, theta = frame.x_m, frame.theta_rad
    mode_colour = _rgba(MODE_COLOURS[frame.mode] if frame.mode is not None
                        else UNKNOWN_MODE_COLOUR)
    end_x, end_z = rod_end(x, theta, scene.rod_m)
    out = _static_markers(scene)
    out.append(MarkerSpec("cart", 0, "cube", position=(x, 0.0, 0.0),
                          scale=(CART_WIDTH_M, CART_DEPTH_M, CART_HEIGHT_M),
                          colour=_rgba(CART_COLOUR)))
    # the rod lies in front of the cart (y < 0 faces a viewer looking along +y)
    y_rod = -CART_DEPTH_M / 2 - ROD_WIDTH_M
    out.append(MarkerSpec("pendulum", 0, "line_strip", scale=(ROD_WIDTH_M, 0.0, 0.0),
                          colour=mode_colour,
                          points=((x, y_rod, 0.0), (float(end_x), y_rod, float(end_z)))))
    length = force_arrow_length_m(frame.force_n)
    if abs(length) >= ARROW_MIN_M:
        out.append(MarkerSpec("force", 0, "arrow", scale=(0.004, 0.012, min(0.012, abs(length))),
                              colour=_rgba(FORCE_COLOUR),
                              points=((x, 0.0, ARROW_Z_M), (x + length, 0.0, ARROW_Z_M))))
    else:  # stable id: the arrow of an earlier array goes away
        out.append(MarkerSpec("force", 0, "arrow", action="delete"))
    track = scene.track
    out.append(MarkerSpec("status", 0, "text",
                          position=((track.min_m + track.max_m) / 2, 0.0, scene.rod_m + 0.04),
                          scale=(0.0, 0.0, TEXT_HEIGHT_M), colour=mode_colour,
                          text=status_text(frame)))
    return out


# -- which samples, with which force and mode ----------------------------------------------

@dataclass(frozen=True)
class _Pending:
    stamp_ns: int
    x_m: float
    theta_rad: float
    true_state: bool


class MarkerFeed:
    """Chooses the samples to draw and pairs each with the force and mode of its stamp.

    A sample is drawn when it is the first of its slot of ``1 / rate_hz`` seconds on the
    stamps' time line (slot ``floor(stamp * rate_hz)``), so at most ``rate_hz`` arrays are
    drawn per second of stamps whatever the wall clock does. A chosen sample waits for the
    cart force of its stamp (the supervisor answers it a moment later) and is given out
    when that force arrives, or without a force (no arrow) when a newer sample arrives
    first. The mode is the last change at or before the sample's stamp. A stamp older
    than the last sample's starts over (a new run, a bag played again).

    ``source``: :data:`SOURCES`. With ``auto``, a true-state sample is always used, and a
    measured one only while no true state has arrived and ``true_state_published()`` says
    nothing publishes one.
    """

    KEEP = 16  # forces and mode changes remembered (a few cycles' worth)

    def __init__(self, params: MarkersParams) -> None:
        self.params = params
        self.reset()

    def reset(self) -> None:
        self._first_ns: int | None = None
        self._last_ns: int | None = None
        self._last_slot: int | None = None
        self._pending: _Pending | None = None
        self._forces: dict[int, float] = {}
        self._modes: list[tuple[int, Mode]] = []
        self.true_seen = False

    def slot(self, stamp_ns: int) -> int:
        return math.floor(stamp_ns * self.params.rate_hz / 1e9)

    def _uses(self, true_state: bool, true_state_published: Callable[[], bool]) -> bool:
        source = self.params.source
        if source == "true":
            return true_state
        if source == "measured":
            return not true_state
        if true_state:
            self.true_seen = True
            return True
        return not self.true_seen and not true_state_published()

    def on_state(self, stamp_ns: int, x_m: float, theta_rad: float, true_state: bool,
                 true_state_published: Callable[[], bool] = lambda: False) -> list[RigFrame]:
        """A state sample; returns the frames to draw now (oldest first)."""
        if not self._uses(true_state, true_state_published):
            return []
        out: list[RigFrame] = []
        if self._last_ns is not None and stamp_ns < self._last_ns:
            modes = [(s, m) for s, m in self._modes if s <= stamp_ns]
            seen = self.true_seen
            self.reset()
            self._modes, self.true_seen = modes, seen
        if self._pending is not None and stamp_ns > self._pending.stamp_ns:
            out.append(self._frame(self._pending))  # its force never came: no arrow
            self._pending = None
        if self._first_ns is None:
            self._first_ns = stamp_ns
        self._last_ns = stamp_ns
        slot = self.slot(stamp_ns)
        if self._last_slot is not None and slot <= self._last_slot:
            return out
        self._last_slot = slot
        pending = _Pending(stamp_ns, float(x_m), float(theta_rad), true_state)
        if stamp_ns in self._forces:
            out.append(self._frame(pending))
        else:
            self._pending = pending
        return out

    def on_force(self, stamp_ns: int, force_n: float) -> list[RigFrame]:
        """The supervisor's force of a stamp; returns the frame that waited for it, if any."""
        self._forces[stamp_ns] = float(force_n)
        if len(self._forces) > self.KEEP:
            del self._forces[min(self._forces)]
        if self._pending is not None and self._pending.stamp_ns == stamp_ns:
            pending, self._pending = self._pending, None
            return [self._frame(pending)]
        return []

    def on_mode(self, stamp_ns: int, mode: Mode) -> None:
        """A mode change announced at ``stamp_ns``."""
        self._modes.append((stamp_ns, mode))
        self._modes.sort(key=lambda change: change[0])  # stable: arrival order within a stamp
        del self._modes[:-self.KEEP]

    @property
    def last_stamp_ns(self) -> int | None:
        """The stamp of the last sample taken (None before the first)."""
        return self._last_ns

    def force_heard(self, stamp_ns: int) -> bool:
        return stamp_ns in self._forces

    def mode_at(self, stamp_ns: int) -> Mode | None:
        mode = None
        for stamp, changed in self._modes:
            if stamp > stamp_ns:
                break
            mode = changed
        return mode

    def _frame(self, p: _Pending) -> RigFrame:
        first = self._first_ns if self._first_ns is not None else p.stamp_ns
        return RigFrame(p.stamp_ns, p.x_m, p.theta_rad, self.mode_at(p.stamp_ns),
                        self._forces.get(p.stamp_ns, math.nan), p.true_state,
                        (p.stamp_ns - first) * 1e-9)
