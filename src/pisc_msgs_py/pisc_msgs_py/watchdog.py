"""Who may drive the motor, and when a held command must end: shared by the plant and the
driver, free of rclpy (docs/safety.md).

* :class:`CommandWatchdog`: which recent sample a command answers, and from which
  sample 0 V applies once the chain stopped answering.
* :class:`PublisherPin`: the graph's own command publisher, pinned when it is first
  seen, and every other publisher on the command topic (an intruder) from what the ROS
  graph lists; the node asks the graph only when :meth:`PublisherPin.needs_look` says so.
* :func:`first_silent_stage`: the first stage of the control chain with no output for
  a sample, to name what stopped.

The nodes do the ROS calls (``get_publisher_count``, ``get_publishers_info_by_topic``)
and pass plain values in.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from pisc_msgs_py.topics import CART_FORCE, STATE, Topic

__all__ = ["CHAIN", "CommandWatchdog", "Endpoint", "PinChange", "PublisherPin",
           "first_silent_stage", "listed_publishers", "silent_stage_report"]


class CommandWatchdog:
    """Which recent sample a command answers, and when the held voltage must end (pure).

    A command is fresh when its stamp is that of one of the last ``periods`` samples.
    Once armed by a first answer, :meth:`expired` holds when the ``periods`` samples up
    to the current one all went unanswered: the voltage answering sample j is held
    through periods j .. j + periods - 1 and 0 V applies from sample j + periods.
    """

    def __init__(self, periods: int) -> None:
        self.periods = periods
        self._recent: deque[tuple[int, int]] = deque(maxlen=periods)  # (stamp, index)
        self.answered = -1  # index of the newest answered sample
        self.tripped_at: int | None = None  # sample from which 0 V applies, while it does

    def sample(self, index: int, stamp_ns: int) -> None:
        self._recent.append((stamp_ns, index))

    def fresh(self, stamp_ns: int) -> int | None:
        """The index of the recent sample a command of this stamp answers, else None."""
        return next((i for s, i in self._recent if s == stamp_ns), None)

    def stamp_of(self, index: int) -> int | None:
        return next((s for s, i in self._recent if i == index), None)

    def answer(self, index: int) -> int | None:
        """A fresh command answered ``index``; returns the sample 0 V applied from if
        this ends a trip."""
        self.answered = max(self.answered, index)
        tripped, self.tripped_at = self.tripped_at, None
        return tripped

    def expired(self, index: int) -> bool:
        """Whether the period of sample ``index`` gets 0 V (and the trip starts there)."""
        if self.answered < 0 or index - self.answered < self.periods:
            return False
        if self.tripped_at is None:
            self.tripped_at = index
        return True


UNNAMED = "_NODE_NAME_UNKNOWN_"  # rmw's node name of an endpoint not yet fully discovered
UNNAMED_TEXT = "a publisher whose node the ROS graph does not name yet"


@dataclass(frozen=True)
class Endpoint:
    """A publisher the ROS graph lists on a topic (``get_publishers_info_by_topic``)."""

    node: str  # the node's name, without namespace
    namespace: str
    gid: bytes

    @property
    def fully_qualified(self) -> str:
        if self.node == UNNAMED:  # discovery has not told the node's name yet
            return UNNAMED_TEXT
        return f"{self.namespace.rstrip('/')}/{self.node}"


@dataclass(frozen=True)
class PinChange:
    """What a look at the publishers changed: ``intruders`` appeared (or changed), or
    the ``left`` ones have all gone."""

    intruders: tuple[str, ...] = ()
    left: tuple[str, ...] = ()


class PublisherPin:
    """The one publisher allowed on a command topic: the endpoint of node ``owner``,
    pinned the first time the graph lists exactly one of it; any other matched
    publisher is an intruder while it is there (pure).

    rclpy on Jazzy gives no publisher GID with a message (ros2/rclpy#1466 came after),
    so messages cannot be sorted by sender: while an intruder is matched nothing on the
    topic may drive the motor. The subscription's matched count is cheap to read on
    every message; the graph is asked who the publishers are only when it changes, while
    an intruder is there, or before the pin is set.

    The matched count moves in DDS's discovery thread, not with the messages: a departed
    publisher's last messages can still be queued when the count has dropped, and
    :meth:`admits` refuses them by their stamps. (An arriving one's first message taken
    in the instant between the match and the count's move is not told apart; rclpy's
    EventsExecutor on Jazzy cannot deliver the message info that would carry its
    publication sequence number.)
    """

    UNLISTED = "a publisher the ROS graph does not list yet"
    UNKNOWN = "publishers of unknown nodes"
    PLACEHOLDERS = frozenset({UNLISTED, UNKNOWN, UNNAMED_TEXT})

    def __init__(self, owner: str) -> None:
        self.owner = owner
        self.pinned: bytes | None = None  # GID of the owner's publisher
        self.matched = -1  # publishers matched when last looked
        self.intruders: tuple[str, ...] = ()
        self.named: list[str] = []  # the intruders named since the last had gone
        self.fence_ns = -1  # no message answering a sample up to this stamp is admitted
        self.refused = 0  # messages not admitted while no intruder was matched

    def admits(self, stamp_ns: int) -> bool:
        """Whether a message answering the sample stamped ``stamp_ns`` may drive the
        motor (call :meth:`look` first): not while an intruder is matched, and not when
        it answers a sample no later than the newest one when an intruder's departure was
        seen (``fence_ns``): the intruder's messages still queued answer those."""
        if self.intruders:
            return False
        if stamp_ns <= self.fence_ns:
            self.refused += 1
            return False
        return True

    def needs_look(self, matched: int) -> bool:
        return not (matched == self.matched and not self.intruders
                    and (self.pinned is not None or matched == 0))

    def look(self, matched: int, listed: Sequence[Endpoint],
             newest_ns: int = -1) -> PinChange | None:
        """``matched`` publishers on the subscription, ``listed`` by the ROS graph: pin
        the owner's, and say what changed (None: nothing). ``newest_ns`` is the stamp of
        the newest sample published: when the intruders have gone, only answers to later
        samples are admitted."""
        self.matched = matched
        if self.pinned is None:
            ours = [e for e in listed if e.node == self.owner]
            if len(ours) == 1:
                self.pinned = ours[0].gid
        others = [e for e in listed if e.gid != self.pinned]
        intruders = tuple(e.fully_qualified for e in others)
        if (not intruders and self.pinned is not None
                and matched > len(listed) - len(others)):
            intruders = (self.UNLISTED,)
        if self.pinned is None and matched > 1:
            intruders = intruders or (self.UNKNOWN,)
        before, self.intruders = self.intruders, intruders
        named = [i for i in intruders if i not in self.PLACEHOLDERS]
        new = [i for i in named if i not in self.named]
        self.named += new
        if intruders and (not before or new):
            # (a named intruder that turns into a placeholder while it leaves, the graph
            # forgetting it before the count drops, is not news)
            return PinChange(intruders=intruders)
        if not intruders and before:
            self.fence_ns = max(self.fence_ns, newest_ns)
            left, self.named = tuple(self.named) or before, []
            return PinChange(left=left)
        return None


def listed_publishers(node: Any, topic: str) -> list[Endpoint]:
    """The publishers the ROS graph lists on ``topic``, as a node (any object with
    rclpy's ``get_publishers_info_by_topic``) sees them."""
    return [Endpoint(i.node_name, i.node_namespace, bytes(i.endpoint_gid))
            for i in node.get_publishers_info_by_topic(topic)]


# The chain a sample goes through before a command answers it: (stage, its output topic);
# the last stage, the current loop, publishes the command itself.
CHAIN: tuple[tuple[str, Topic], ...] = (("estimator", STATE), ("supervisor", CART_FORCE))


def first_silent_stage(stamp_ns: int, newest: Mapping[str, int],
                       last: str = "current_loop",
                       answered_ns: int | None = None) -> tuple[str, Topic | None]:
    """The stage of :data:`CHAIN` (then ``last``, the command's) that stopped, with its
    topic (``None`` for ``last``).

    Without ``answered_ns``: the first stage whose newest output (``newest[stage]``, a
    stamp) is older than ``stamp_ns``. With ``answered_ns``, the stamp of the newest
    sample the command answered (``last``'s newest output): of the stages older than
    ``stamp_ns``, the one furthest behind the stage before it (the samples, for the
    first), the first of equals. A stage that died stops where it was while the live
    ones before it go on, so it falls behind by the whole time since it died; a live stage
    slowed by the machine falls behind by its lag only (with the first rule a killed
    current loop was blamed on a supervisor one period late)."""
    if answered_ns is None:
        for name, topic in CHAIN:
            if newest.get(name, -1) < stamp_ns:
                return name, topic
        return last, None
    stages = [(name, topic, newest.get(name, -1)) for name, topic in CHAIN]
    stages.append((last, None, answered_ns))
    best: tuple[int, str, Topic | None] | None = None
    before = stamp_ns
    for name, topic, out in stages:
        behind = min(before, stamp_ns) - out
        if out < stamp_ns and (best is None or behind > best[0]):
            best = (behind, name, topic)
        before = out
    return (last, None) if best is None else (best[1], best[2])


def silent_stage_report(node: Any, stamp_ns: int, newest: Mapping[str, int], sample: int,
                        command_topic: Topic, answered_ns: int | None = None
                        ) -> tuple[str, str]:
    """(sentence, nodes) naming the stage that stopped answering sample ``sample``
    (stamp ``stamp_ns``) and the node(s) that publish its output, for /diagnostics:
    ``the supervisor (/supervisor) stopped: nothing on /pisc/cart_force answers sample
    812``."""
    stage, topic = first_silent_stage(stamp_ns, newest, answered_ns=answered_ns)
    topic = topic or command_topic
    nodes = sorted({e.fully_qualified for e in listed_publishers(node, topic.name)})
    who = ", ".join(nodes) if nodes else f"no publisher on {topic.name}"
    return (f"the {stage} ({who}) stopped: nothing on {topic.name} answers sample {sample}",
            who)
