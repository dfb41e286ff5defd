"""The parser benchmark's claims, on a smaller sample than pisc_parser_bench's 200 000 frames."""

from __future__ import annotations

import numpy as np
import pytest

from pisc_driver.bench import damage, main, rig_frames, score
from pisc_driver.protocol import FrameParser, NaiveParser


@pytest.fixture(scope="module")
def rigs():
    return rig_frames(20_000, rigs=20, seed=3)


def test_frames_sweep_the_encoder_and_carry_the_header_inside_data(rigs):
    data = np.frombuffer(b"".join(b"".join(r) for r in rigs), dtype=np.uint8).reshape(-1, 7)
    assert np.all(data[:, 0] == 0xAA)
    assert np.all(data[:, 1] <= 3) and np.all(data[:, 3] <= 3)
    inside = (data[:, 1:] == 0xAA).sum(axis=0)
    # 0xAA occurs as IR_lo and CNT_lo: the reason a naive parser fails
    assert inside[1] > 30 and inside[5] > 30, inside
    assert len(np.unique(data[:, 5].astype(np.int16) * 256 + data[:, 6])) > 2000


@pytest.mark.parametrize("timed", [False, True])
def test_drops_at_1e_3_give_no_false_frame_and_resync_within_one_frame(rigs, timed):
    rng = np.random.default_rng(7)
    streams = [damage(frames, "drop", 1e-3, rng) for frames in rigs]
    ours = [score(FrameParser(), s, timed) for s in streams]
    naive = [score(NaiveParser(), s, False) for s in streams]
    assert sum(s.false_frames for s in ours) == 0
    resync = [r for s in ours for r in s.resync]
    assert len(resync) > 50 and max(resync) == 1
    assert sum(s.false_frames for s in naive) > 50


def test_drops_at_1e_2_give_no_false_frame(rigs):
    rng = np.random.default_rng(8)
    streams = [damage(frames, "drop", 1e-2, rng) for frames in rigs]
    assert sum(score(FrameParser(), s, True).false_frames for s in streams) == 0


def test_a_flipped_data_bit_is_a_false_frame_a_flipped_header_is_not(rigs):
    """Flips never misframe the locked parser; a flipped ADC low byte is invisible."""
    rng = np.random.default_rng(9)
    streams = [damage(frames, "flip", 1e-3, rng) for frames in rigs[:5]]
    results = [score(FrameParser(), s, True) for s in streams]
    assert sum(r.misframed for r in results) == 0
    flips = sum(int(s.flipped.sum()) for s in streams)
    assert 0 < sum(r.false_frames for r in results) < flips


@pytest.mark.bench
def test_parser_bench_prints_the_table(capsys):
    assert main(["--frames", "200000"]) == 0
    out = capsys.readouterr().out
    print(out)
    assert "| drop | 0.001 | FrameParser, bytes + arrival times |" in out
