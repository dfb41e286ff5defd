"""pisc_bag animate: the frames show the recorded state (measured from the drawn pixels),
the files hold the frames asked for, and bad input is refused without a partial file."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from pisc_runs.rig_drawing import CART_COLOUR, FORCE_COLOUR, MODE_COLOURS, OVERLAY_COLOUR, rod_end
from pisc_runs.animate import (
    Animator,
    frame_cycles,
    load_run,
    write_animation,
)
from pisc_bringup.bag_cli import main as pisc_bag
from pisc_msgs_py.types import Mode
from pisc_model.dynamics import wrap_to_upright

BAG = Path(__file__).resolve().parents[1] / "bags" / "default-swingup"


@pytest.fixture(scope="module")
def run():
    return load_run(BAG)


def _pixels_of(image: np.ndarray, colour: tuple[int, int, int], tol: int = 30) -> np.ndarray:
    """(row, column) of the pixels within ``tol`` of ``colour`` in every channel."""
    close = np.all(np.abs(image.astype(int) - np.array(colour)) <= tol, axis=-1)
    return np.argwhere(close)


def test_rod_geometry_follows_the_angle_convention():
    # theta = 0 upright, pi hanging (SPEC section 4); positive theta leans towards +x
    assert rod_end(0.1, 0.0, 0.2) == pytest.approx((0.1, 0.2))
    assert rod_end(0.1, math.pi, 0.2) == pytest.approx((0.1, -0.2))
    assert rod_end(0.1, math.pi / 2, 0.2) == pytest.approx((0.3, 0.0))
    assert rod_end(-0.05, -math.pi / 6, 0.2) == pytest.approx((-0.15, 0.2 * math.sqrt(3) / 2))


def test_frame_times_pick_the_cycle_in_force():
    t = np.arange(2001) * 0.005  # 10 s at 200 Hz
    assert np.array_equal(frame_cycles(t, 25.0), np.arange(251) * 8)
    slow = frame_cycles(t, 25.0, speed=0.5, start_s=1.0, end_s=2.0)
    assert len(slow) == 51 and slow[0] == 200 and slow[-1] == 400
    assert np.array_equal(frame_cycles(t, 10.0, start_s=0.0021, end_s=0.5)[:3], [0, 20, 40])
    for bad, message in [({"fps": 0.0}, "frames per second"), ({"speed": -1.0}, "speed"),
                         ({"start_s": 11.0}, "holds no frame")]:
        kwargs = {"fps": 25.0, **bad}
        with pytest.raises(ValueError, match=message):
            frame_cycles(t, **kwargs)


def test_the_run_carries_its_rig_track_force_and_true_state(run):
    assert run.true_state and run.rod_m == pytest.approx(2 * 0.0865)
    assert (run.track.min_m, run.track.max_m) == (-0.23, 0.13)
    assert (run.safety.x_min_m, run.safety.x_max_m) == (-0.225, 0.125)
    assert len(run.t) == len(run.x) == len(run.force) == len(run.mode) > 1500
    assert np.all(np.isfinite(run.force))  # every cycle of the bag has its force
    assert {Mode.SWING_UP, Mode.CATCH} <= set(run.mode)


def test_each_frame_draws_the_recorded_state(run):
    """Cart position, pendulum angle, mode colour and force direction measured from the
    pixels of rendered frames agree with the bag's state at that cycle."""
    animator = Animator(run)
    try:
        col0, _ = animator.to_pixels(0.0, 0.0)
        col1, _ = animator.to_pixels(0.1, 0.0)
        px_per_m = float(col1[0] - col0[0]) / 0.1
        assert px_per_m > 300  # enough resolution for the tolerances below
        catch = run.mode.index(Mode.CATCH)
        cycles = [0, 100, 160, 220, 280, catch - 5, catch + 20, len(run.t) - 1]
        for k in cycles:
            image = animator.render(k)
            x, theta, mode, force = run.x[k], run.theta[k], run.mode[k], run.force[k]
            # the cart: the middle of its coloured pixels' extent
            cart = _pixels_of(image, CART_COLOUR)
            assert len(cart) > 200, f"cycle {k}: no cart drawn"
            middle = 0.5 * (cart[:, 1].min() + cart[:, 1].max())
            x_drawn = (middle - col0[0]) / px_per_m
            assert x_drawn == pytest.approx(x, abs=2.0 / px_per_m), f"cycle {k}"
            # the pendulum: the direction from the pivot to its pixels' centroid
            rod = _pixels_of(image, MODE_COLOURS[mode])
            assert len(rod) > 150, f"cycle {k}: no {mode.value} rod drawn"
            pivot_col, pivot_row = animator.to_pixels(x, 0.0)
            d_col = rod[:, 1].mean() - pivot_col[0]
            d_up = pivot_row[0] - rod[:, 0].mean()
            theta_drawn = math.atan2(d_col, d_up)
            assert wrap_to_upright(theta_drawn - theta) == pytest.approx(0.0, abs=0.02), \
                f"cycle {k}: drawn at {theta_drawn:.3f} rad, recorded {theta:.3f} rad"
            others = [c for m, c in MODE_COLOURS.items() if m is not mode]
            assert all(len(_pixels_of(image, c, 10)) == 0 for c in others), f"cycle {k}"
            # the force: an arrow from the cart's middle towards the force's sign
            arrow = _pixels_of(image, FORCE_COLOUR)
            if abs(force) >= 0.2:
                assert len(arrow) > 20, f"cycle {k}: no arrow for {force:.2f} N"
                reach = arrow[:, 1].mean() - pivot_col[0]
                assert np.sign(reach) == np.sign(force), f"cycle {k}"
    finally:
        animator.close()


def test_gif_and_mp4_hold_the_frames(run, tmp_path):
    import imageio_ffmpeg
    from PIL import Image

    gif = tmp_path / "swing.gif"
    n = write_animation(run, gif, fps=20.0, start_s=1.0, end_s=2.0)
    assert n == 21
    with Image.open(gif) as im:
        assert im.n_frames == 21 and im.size == (640, 360)
        im.seek(10)
        frame = np.asarray(im.convert("RGB"))
    # the palette keeps the drawing's colours: the rod of cycle 300 (t = 1.5 s) is there
    k = int(np.searchsorted(run.t, 1.5 + 1e-12, side="right") - 1)
    assert len(_pixels_of(frame, MODE_COLOURS[run.mode[k]], 12)) > 150
    assert len(_pixels_of(frame, CART_COLOUR, 12)) > 200
    mp4 = tmp_path / "swing.mp4"
    assert write_animation(run, mp4, fps=20.0, start_s=0.0, end_s=0.5) == 11
    reader = imageio_ffmpeg.read_frames(str(mp4))
    meta = next(reader)
    assert tuple(meta["size"]) == (640, 360)
    assert sum(1 for _ in reader) == 11
    assert sorted(p.name for p in tmp_path.iterdir()) == ["swing.gif", "swing.mp4"]


def test_overlay_draws_the_second_run_in_grey(run, tmp_path):
    animator = Animator(run, overlay=run)
    try:
        image = animator.render(400, overlay_k=0)  # the overlay still hangs at rest
        grey = _pixels_of(image, OVERLAY_COLOUR, 12)
        col, row = animator.to_pixels(run.x[0], 0.0)
        rod = grey[(grey[:, 0] > row[0] + 20) & (np.abs(grey[:, 1] - col[0]) < 6)]
        assert len(rod) > 100  # a hanging grey rod under the overlay's cart
    finally:
        animator.close()


def test_command_writes_the_animation_and_refuses_bad_input(tmp_path, capsys):
    out = tmp_path / "a.gif"
    assert pisc_bag(["animate", str(BAG), "--out", str(out), "--end", "0.4"]) == 0
    assert out.exists() and "11 frames at 25 fps" in capsys.readouterr().out
    cases = [
        (["--out", str(tmp_path / "a.png")], "must be a .gif or an .mp4"),
        (["--out", str(tmp_path / "nodir" / "a.gif")], "no such directory"),
        (["--out", str(tmp_path / "b.gif"), "--start", "50"], "holds no frame"),
    ]
    for extra, message in cases:
        assert pisc_bag(["animate", str(BAG), *extra]) == 2
        assert message in capsys.readouterr().err
    assert pisc_bag(["animate", str(tmp_path / "nosuchbag"), "--out", str(tmp_path / "c.gif")]) == 2
    assert "nosuchbag" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.gif"]
