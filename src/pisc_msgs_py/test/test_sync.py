"""Pairing the force and the current of one cycle by stamp."""

from pisc_msgs_py.sync import StampPairer


def test_pairs_in_either_order():
    p = StampPairer()
    assert p.add_first(5, "f5") is None
    assert p.add_second(5, "i5") == ("f5", "i5")
    assert p.add_second(10, "i10") is None
    assert p.add_first(10, "f10") == ("f10", "i10")


def test_unmatched_stamps_are_bounded_and_counted():
    p = StampPairer(capacity=3)
    for stamp in range(5):
        p.add_second(stamp, stamp)
    assert p.dropped == 2
    assert p.add_first(0, "late") is None  # stamp 0 was dropped
    assert p.add_first(4, "f4") == ("f4", 4)
