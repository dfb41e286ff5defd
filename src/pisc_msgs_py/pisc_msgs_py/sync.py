"""Pairing messages of one control cycle by their header stamp.

The current loop needs the force of cycle k and the current measured at sample k;
they come on different topics and, between processes, in either order. This is
message_filters' exact-time policy for two inputs, as a pure, bounded buffer.
"""

from __future__ import annotations

from collections import OrderedDict
from typing import Generic, TypeVar

__all__ = ["StampPairer"]

A = TypeVar("A")
B = TypeVar("B")


class StampPairer(Generic[A, B]):
    """Hold the unmatched side of each stamp until its partner arrives.

    ``add_first``/``add_second`` return the completed pair ``(a, b)`` or ``None``.
    At most ``capacity`` unmatched stamps are kept per side; older ones are dropped
    and counted in ``dropped``, so a topic that stops cannot grow memory.
    """

    def __init__(self, capacity: int = 64) -> None:
        self.capacity = capacity
        self._first: OrderedDict[int, A] = OrderedDict()
        self._second: OrderedDict[int, B] = OrderedDict()
        self.dropped = 0

    def _store(self, side: OrderedDict, stamp_ns: int, value: object) -> None:
        side[stamp_ns] = value
        while len(side) > self.capacity:
            side.popitem(last=False)
            self.dropped += 1

    def add_first(self, stamp_ns: int, value: A) -> tuple[A, B] | None:
        other = self._second.pop(stamp_ns, None)
        if other is None:
            self._store(self._first, stamp_ns, value)
            return None
        return value, other

    def add_second(self, stamp_ns: int, value: B) -> tuple[A, B] | None:
        other = self._first.pop(stamp_ns, None)
        if other is None:
            self._store(self._second, stamp_ns, value)
            return None
        return other, value
