"""pisc_bag animate: a recorded run drawn as the rig, frame by frame, to a GIF or an MP4.

    pisc_bag animate BAG [--out FILE.gif|FILE.mp4] [--overlay BAG2] [--fps N] [--speed S]
                         [--start T] [--end T]

Each frame shows the track with its end stops (``track``), the safe range the supervisor
keeps (``safety``, dashed), the cart, and the pendulum as the uniform rod the thesis's
inertia describes (length 2 l: a rod of mass m and length 2 l about its centre has
I = m (2 l)^2 / 12 = m l^2 / 3, 2.63e-5 kg m^2 for Table 6.1's m and l, the I of Table
6.1), coloured by the supervisor's mode, the force the supervisor asks of the cart as an
arrow, and the run time. The state drawn is the simulator's true state where the bag
has it (``/pisc/sim/true_state``), else the measured one (a run on the rig). With
``--overlay`` a second run is drawn behind the first, in grey.

The angle convention is the project's (SPEC section 4): theta = 0 upright, pi hanging; the
pendulum's tip is at (x + 2 l sin(theta), 2 l cos(theta)) above the pivot on the cart.

The geometry (:func:`pisc_runs.rig_drawing.rod_end`), the frame times (:func:`frame_cycles`) and the drawing
(:class:`Animator`) are separate so that a test can measure a drawn frame against the
bag's state.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pisc_runs.analysis import trace_from_messages
from pisc_runs.rig_drawing import (
    CART_COLOUR,
    CART_HEIGHT_M,
    CART_WIDTH_M,
    FORCE_ARROW_MAX_M,
    FORCE_COLOUR,
    FORCE_SCALE_M_PER_N,
    LIMIT_COLOUR,
    MODE_COLOURS,
    OVERLAY_COLOUR,
    rod_end,
)
from pisc_bag.bag import BagError, read_bag
from pisc_bag.run_files import recorded_params, recorded_section
from pisc_control.supervisor import SafetyParams
from pisc_msgs_py.convert import MessageError, cart_force_from_msg
from pisc_msgs_py.topics import CART_FORCE
from pisc_msgs_py.types import Mode
from pisc_model.params import RigParams, TrackParams

__all__ = ["Animator", "RunFrames", "frame_cycles", "load_run"]


@dataclass(frozen=True)
class RunFrames:
    """What a frame needs of one run, one row per control cycle."""

    label: str
    t: np.ndarray
    x: np.ndarray
    theta: np.ndarray
    force: np.ndarray  # N, NaN where the bag has no /pisc/cart_force of that stamp
    mode: list[Mode]
    true_state: bool  # x and theta are the simulator's true state
    rod_m: float  # drawn length of the pendulum, 2 l
    track: TrackParams
    safety: SafetyParams


def _run_params(bag: Path) -> tuple[RigParams, TrackParams, SafetyParams]:
    """The rig, track and safe range of the run (its parameter file, else defaults)."""
    flat = recorded_params(bag)
    return (recorded_section(bag, RigParams, "rig", flat),
            recorded_section(bag, TrackParams, "track", flat),
            recorded_section(bag, SafetyParams, "safety", flat))


def load_run(bag: str | Path) -> RunFrames:
    """The cycles of a bag with the force the supervisor asked for; :class:`BagError`
    names the bag and what is wrong."""
    bag = Path(bag)
    rig, track, safety = _run_params(bag)
    forces: dict[int, float] = {}

    def messages() -> Iterator[Any]:
        for m in read_bag(bag):
            if m.topic == CART_FORCE.name:
                try:
                    f = cart_force_from_msg(m.message)
                except MessageError as exc:
                    raise BagError(f"{bag}: {m.topic}: {exc}") from None
                forces.setdefault(f.stamp_ns, f.force_n)
            yield m

    try:
        trace = trace_from_messages(messages(), bag.name)
    except BagError as exc:
        raise BagError(f"{bag}: {exc}") from None
    offsets = np.round(trace.t * 1e9).astype(np.int64)
    force = np.array([forces.get(trace.start_ns + int(o), math.nan) for o in offsets])
    true = trace.true_x is not None
    return RunFrames(
        label=bag.name, t=trace.t,
        x=trace.true_x if true else trace.x,
        theta=trace.true_theta if true else trace.theta,
        force=force, mode=list(trace.mode), true_state=true,
        rod_m=2.0 * rig.pendulum_com_m, track=track, safety=safety)


def frame_cycles(t: np.ndarray, fps: float, speed: float = 1.0, start_s: float = 0.0,
                 end_s: float | None = None) -> np.ndarray:
    """Indices of the cycles shown in each frame: one frame every ``speed / fps`` seconds
    of run time from ``start_s`` to ``end_s`` (default: the end), each the last cycle at
    or before its frame's time."""
    if not (fps > 0 and math.isfinite(fps)):
        raise ValueError(f"frames per second must be positive, got {fps}")
    if not (speed > 0 and math.isfinite(speed)):
        raise ValueError(f"speed must be positive, got {speed}")
    end = float(t[-1]) if end_s is None else min(float(end_s), float(t[-1]))
    if not start_s < end or start_s < 0:
        raise ValueError(f"the window {start_s:g} .. {end:g} s holds no frame (the run is "
                         f"{float(t[-1]):.3f} s long)")
    times = np.arange(start_s, end + 1e-12, speed / fps)
    return np.clip(np.searchsorted(t, times + 1e-12, side="right") - 1, 0, len(t) - 1)


def _rgb(colour: tuple[int, int, int], alpha: float = 1.0) -> tuple[float, float, float, float]:
    return (colour[0] / 255, colour[1] / 255, colour[2] / 255, alpha)


class Animator:
    """A matplotlib figure of the rig whose artists :meth:`draw` moves to a cycle's state.

    ``render(k)`` returns the frame of cycle ``k`` as an RGB array (height x width x 3);
    :meth:`to_pixels` maps metres on the drawing to pixel coordinates of that array
    (column, row), for tests that measure what was drawn.
    """

    def __init__(self, run: RunFrames, overlay: RunFrames | None = None,
                 width_px: int = 640, height_px: int = 360) -> None:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
        from matplotlib.patches import FancyArrow, Rectangle

        self.run, self.overlay = run, overlay
        dpi = 100
        self.fig = Figure(figsize=(width_px / dpi, height_px / dpi), dpi=dpi)
        ax = self.fig.add_axes((0.02, 0.02, 0.96, 0.84))
        self.ax = ax
        track, safety = run.track, run.safety
        low = min(track.min_m, safety.x_min_m) if math.isfinite(track.min_m) else safety.x_min_m
        high = max(track.max_m, safety.x_max_m) if math.isfinite(track.max_m) else safety.x_max_m
        reach = run.rod_m + 0.02
        ax.set_xlim(low - reach, high + reach)
        ax.set_ylim(-reach - CART_HEIGHT_M, reach)
        ax.set_aspect("equal", adjustable="box")
        ax.axis("off")
        rail_y = -CART_HEIGHT_M / 2
        ax.plot([low, high], [rail_y - 0.004] * 2, color="0.35", lw=2, solid_capstyle="butt")
        for end in (track.min_m, track.max_m):
            if math.isfinite(end):
                ax.plot([end, end], [rail_y - 0.02, rail_y + 0.035], color="0.1", lw=3)
        ax.plot([0.0, 0.0], [rail_y - 0.012, rail_y - 0.004], color="0.35", lw=1)
        ax.text(0.0, rail_y - 0.014, "0", color="0.35", fontsize=7, ha="center", va="top")
        for limit in (safety.x_min_m, safety.x_max_m):
            ax.axvline(limit, color=_rgb(LIMIT_COLOUR), lw=1, ls="--")
        ax.text(safety.x_min_m, reach * 0.97, " safe range", color=_rgb(LIMIT_COLOUR),
                fontsize=8, va="top", ha="left")
        if overlay is not None:
            self._ghost_rod, = ax.plot([], [], color=_rgb(OVERLAY_COLOUR), lw=4,
                                       solid_capstyle="round", zorder=1)
            self._ghost_cart = Rectangle((0, 0), CART_WIDTH_M, CART_HEIGHT_M, fill=False,
                                         ec=_rgb(OVERLAY_COLOUR), lw=1.5, zorder=1)
            ax.add_patch(self._ghost_cart)
        self._cart = Rectangle((0, 0), CART_WIDTH_M, CART_HEIGHT_M, fc=_rgb(CART_COLOUR),
                               ec="none", zorder=2)
        ax.add_patch(self._cart)
        self._rod, = ax.plot([], [], lw=5, solid_capstyle="butt", zorder=3)
        self._pivot, = ax.plot([], [], "o", color="0.1", ms=4, zorder=4)
        self._arrow: FancyArrow | None = None
        self._arrow_cls = FancyArrow
        self._title = self.fig.text(0.02, 0.97, "", fontsize=10, va="top", family="monospace")
        self.canvas = FigureCanvasAgg(self.fig)

    def draw(self, k: int, overlay_k: int | None = None) -> None:
        """Move the artists to cycle ``k`` (and the overlay's cycle ``overlay_k``)."""
        run = self.run
        x, theta = float(run.x[k]), float(run.theta[k])
        mode = run.mode[k]
        self._cart.set_xy((x - CART_WIDTH_M / 2, -CART_HEIGHT_M / 2))
        end_x, end_y = rod_end(x, theta, run.rod_m)
        self._rod.set_data([x, end_x], [0.0, end_y])
        self._rod.set_color(_rgb(MODE_COLOURS[mode]))
        self._pivot.set_data([x], [0.0])
        if self._arrow is not None:
            self._arrow.remove()
            self._arrow = None
        force = float(run.force[k])
        length = (float(np.clip(force * FORCE_SCALE_M_PER_N, -FORCE_ARROW_MAX_M,
                                FORCE_ARROW_MAX_M)) if math.isfinite(force) else 0.0)
        if abs(length) >= 0.004:  # below 0.1 N the arrow would be all head
            self._arrow = self._arrow_cls(
                x, -CART_HEIGHT_M / 2 - 0.02, length, 0.0, width=0.004,
                head_width=0.012, head_length=min(0.012, abs(length)),
                length_includes_head=True, color=_rgb(FORCE_COLOUR), zorder=2)
            self.ax.add_patch(self._arrow)
        if self.overlay is not None and overlay_k is not None:
            o = self.overlay
            ox, oth = float(o.x[overlay_k]), float(o.theta[overlay_k])
            self._ghost_cart.set_xy((ox - CART_WIDTH_M / 2, -CART_HEIGHT_M / 2))
            gx, gy = rod_end(ox, oth, o.rod_m)
            self._ghost_rod.set_data([ox, gx], [0.0, gy])
        state = "true state" if run.true_state else "measured"
        f_text = f"{force:+6.2f} N" if math.isfinite(force) else "   n/a  "
        overlay_text = f"   grey: {self.overlay.label}" if self.overlay is not None else ""
        self._title.set_text(f"{run.label}   t = {run.t[k]:6.3f} s   {mode.value:<9s} "
                             f"F = {f_text}   ({state}){overlay_text}")

    def render(self, k: int, overlay_k: int | None = None) -> np.ndarray:
        self.draw(k, overlay_k)
        self.canvas.draw()
        rgba = np.asarray(self.canvas.buffer_rgba())
        return np.array(rgba[..., :3])

    def to_pixels(self, x_m: Any, y_m: Any) -> tuple[np.ndarray, np.ndarray]:
        """(column, row) of points on the drawing in metres, in :meth:`render`'s array."""
        self.canvas.draw()
        points = self.ax.transData.transform(np.column_stack([np.ravel(x_m), np.ravel(y_m)]))
        height = self.canvas.get_width_height()[1]
        return points[:, 0], height - points[:, 1]

    def close(self) -> None:
        self.fig.clear()


def _matching(overlay: RunFrames, t: float) -> int:
    return int(np.clip(np.searchsorted(overlay.t, t + 1e-12, side="right") - 1, 0,
                       len(overlay.t) - 1))


def write_animation(run: RunFrames, out: Path, overlay: RunFrames | None = None,
                    fps: float = 25.0, speed: float = 1.0, start_s: float = 0.0,
                    end_s: float | None = None, progress: Any = None) -> int:
    """Write the frames to ``out`` (.gif through Pillow, .mp4 through imageio-ffmpeg's
    ffmpeg); returns the number of frames. Writes to a temporary name and renames it, so
    a failure leaves no partial file."""
    suffix = out.suffix.lower()
    if suffix not in (".gif", ".mp4"):
        raise BagError(f"{out}: the animation must be a .gif or an .mp4 file")
    cycles = frame_cycles(run.t, fps, speed, start_s, end_s)
    animator = Animator(run, overlay)
    tmp = out.with_name(f".{out.name}.partial{suffix}")
    try:
        frames = (animator.render(int(k), None if overlay is None
                                  else _matching(overlay, float(run.t[k])))
                  for k in cycles)
        if suffix == ".gif":
            _write_gif(tmp, frames, fps, progress)
        else:
            _write_mp4(tmp, frames, fps, animator.canvas.get_width_height(), progress)
        tmp.replace(out)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    finally:
        animator.close()
    return len(cycles)


def _write_gif(path: Path, frames: Iterator[np.ndarray], fps: float, progress: Any) -> None:
    from PIL import Image

    images = []
    for frame in frames:
        # one palette per frame: the drawing has few colours, so ADAPTIVE keeps them exact
        images.append(Image.fromarray(frame).convert("P", palette=Image.Palette.ADAPTIVE,
                                                     colors=64))
        if progress is not None:
            progress(1)
    images[0].save(path, format="GIF", save_all=True, append_images=images[1:],
                   duration=round(1000 / fps), loop=0, optimize=False, disposal=1)


def _write_mp4(path: Path, frames: Iterator[np.ndarray], fps: float,
               size: tuple[int, int], progress: Any) -> None:
    import imageio_ffmpeg

    writer = imageio_ffmpeg.write_frames(str(path), size, fps=fps, codec="libx264",
                                         pix_fmt_out="yuv420p", macro_block_size=8,
                                         output_params=["-f", "mp4"])
    writer.send(None)
    try:
        for frame in frames:
            writer.send(np.ascontiguousarray(frame))
            if progress is not None:
                progress(1)
    finally:
        writer.close()


# -- pisc_bag animate ----------------------------------------------------------------------
