"""Who may drive the motor, and when a held command must end: shared by the plant and the
driver, free of rclpy (docs/safety.md).

* :class:`CommandWatchdog`: which recent sample a command answers, and from which
  sample 0 V applies once the chain stopped answering.
* :class:`PublisherPin`: the graph's own publisher of a topic, pinned when it is first
  seen, and every other publisher on the topic (an intruder) from what the ROS graph
  lists; the node asks the graph only when :meth:`PublisherPin.needs_look` says so.
* :class:`InputGuard`: one input of a node answering to its pinned publishers alone:
  nothing on the topic is used while an intruder is there, and the node says so.
  :data:`GRAPH_PUBLISHERS` names the node that publishes each topic of the graph as the
  launch files name them; ``start.publishers`` (every node) replaces it.
* :class:`StopWitness`: after a trip, the stage of the control chain that stopped,
  named once the evidence is in (a dead stage falls further behind the one before it
  every period; a slow one does not).
* :func:`first_silent_stage`: the first stage of the control chain with no output for
  a sample (lockstep, where nothing moves while the chain is silent).

The nodes do the ROS calls (``get_publisher_count``, ``get_publishers_info_by_topic``)
and pass plain values in.
"""

from __future__ import annotations

from collections import deque
import re
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from pisc_msgs_py.topics import (
    CART_FORCE,
    CLOCK,
    CURRENT_SETPOINT,
    JOINT_STATES,
    MODE,
    MOTOR_CURRENT,
    PENDULUM_ESTIMATE,
    SIM_STATE,
    STATE,
    VOLTAGE,
    VOLTAGE_SENT,
    Topic,
)

__all__ = ["CHAIN", "CommandWatchdog", "Endpoint", "GRAPH_PUBLISHERS", "InputGuard",
           "PinChange", "PublisherPin", "format_publishers", "parse_publishers",
           "StopVerdict", "StopWitness", "first_silent_stage", "listed_publishers",
           "named_trip", "silent_stage_report", "stop_sentence", "who_publishes"]


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
        for s, i in reversed(self._recent):  # the newest first: usually the one
            if s == stamp_ns:
                return i
        return None

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
    """The publishers allowed on a topic: one endpoint of each node named in ``owner``
    (one name, or several: the alternatives a topic may have, e.g. the plant or the
    driver, or every node of a graph on /diagnostics), each pinned the first time the
    graph lists exactly one endpoint of that name; any other matched publisher is an
    intruder while it is there (pure).

    Discovery tells an endpoint some milliseconds before the name of its node (the rmw
    lists it under ``_NODE_NAME_UNKNOWN_`` meanwhile; seen for 20-80 ms on a driver's
    start). Before any owner is pinned, publishers the graph does not name yet are
    ``pending``: nothing on the topic is admitted, nothing is said, and the graph is asked
    again on every message until it names them (the owner's own is then pinned, another
    node's is an intruder, said then). Once a pin is set, a publisher not yet named is an
    intruder at once.

    rclpy on Jazzy gives no publisher GID with a message (ros2/rclpy#1466 came after),
    so messages cannot be sorted by sender: while an intruder is matched nothing on the
    topic may be used. The subscription's matched count is cheap to read on every
    message; the graph is asked who the publishers are only when it changes, while an
    intruder is there, or before a pin is set.

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

    def __init__(self, owner: str | Sequence[str]) -> None:
        self.owners: tuple[str, ...] = (owner,) if isinstance(owner, str) else tuple(owner)
        if not self.owners or not all(self.owners):
            raise ValueError(f"owner {owner!r}: name at least one node")
        self.owner = self.owners[0]
        self.pins: dict[str, bytes] = {}  # node name -> GID of its pinned publisher
        self.matched = -1  # publishers matched when last looked
        self.intruders: tuple[str, ...] = ()
        self.named: list[str] = []  # the intruders named since the last had gone
        self.fence_ns = -1  # no message answering a sample up to this stamp is admitted
        self.refused = 0  # messages not admitted while no intruder was matched
        self.pending = False  # before a pin: publishers the graph does not name yet

    @property
    def pinned(self) -> bytes | None:
        """The GID pinned for the first owner that has one (None: none yet)."""
        return next((self.pins[o] for o in self.owners if o in self.pins), None)

    def admits(self, stamp_ns: int) -> bool:
        """Whether a message answering the sample stamped ``stamp_ns`` may be used (call
        :meth:`look` first): not while an intruder is matched, and not when it answers a
        sample no later than the newest one when an intruder's departure was seen
        (``fence_ns``): the intruder's messages still queued answer those."""
        if self.intruders or self.pending:
            return False
        if stamp_ns <= self.fence_ns:
            self.refused += 1
            return False
        return True

    def needs_look(self, matched: int) -> bool:
        return not (matched == self.matched and not self.intruders
                    and (bool(self.pins) or matched == 0))

    def look(self, matched: int, listed: Sequence[Endpoint],
             newest_ns: int = -1) -> PinChange | None:
        """``matched`` publishers on the subscription, ``listed`` by the ROS graph: pin
        the owners', and say what changed (None: nothing). ``newest_ns`` is the stamp of
        the newest sample published (or seen): when the intruders have gone, only
        messages of later samples are admitted."""
        self.matched = matched
        for name in self.owners:
            if name not in self.pins:
                ours = [e for e in listed if e.node == name]
                if len(ours) == 1:
                    self.pins[name] = ours[0].gid
        pinned = set(self.pins.values())
        others = [e for e in listed if e.gid not in pinned]
        # before a pin, an endpoint not yet named may be an owner's own: wait for its name
        self.pending = not self.pins and any(e.node == UNNAMED for e in others)
        if self.pending:
            others = [e for e in others if e.node != UNNAMED]
        intruders = tuple(e.fully_qualified for e in others)
        if (not intruders and self.pins
                and matched > len(listed) - len(others)):
            intruders = (self.UNLISTED,)
        if not self.pins and matched > len(self.owners):
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


#: The node that publishes each topic of the graph, as the launch files name them (the
#: samples: the plant, or the driver on the rig). A node's ``start.publishers`` replaces
#: an entry (pisc_graph gives every node the names of the graph it started).
GRAPH_PUBLISHERS: dict[str, tuple[str, ...]] = {
    JOINT_STATES.name: ("plant", "driver"),
    MOTOR_CURRENT.name: ("plant", "driver"),
    STATE.name: ("estimator",),
    CART_FORCE.name: ("supervisor",),
    MODE.name: ("supervisor",),
    PENDULUM_ESTIMATE.name: ("supervisor",),
    CURRENT_SETPOINT.name: ("current_loop",),
    VOLTAGE.name: ("current_loop",),
    VOLTAGE_SENT.name: ("driver",),
    SIM_STATE.name: ("plant",),
    CLOCK.name: ("plant",),
}

_NODE_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")


def parse_publishers(text: str) -> dict[str, tuple[str, ...]]:
    """``TOPIC=NODE[|NODE...][,TOPIC=...]`` (``start.publishers``) as a mapping; raises
    ValueError naming the item that is not of that form."""
    out: dict[str, tuple[str, ...]] = {}
    if not text.strip():
        return out
    for item in text.split(","):
        topic, sep, names = (part.strip() for part in item.partition("="))
        nodes = tuple(n.strip() for n in names.split("|"))
        if (not sep or not topic.startswith("/") or not all(_NODE_NAME.fullmatch(n)
                                                            for n in nodes)):
            raise ValueError(f"must list TOPIC=NODE[|NODE...] (an absolute topic name, node "
                             f"names): {item.strip()!r} is not")
        if topic in out:
            raise ValueError(f"names {topic} twice")
        out[topic] = nodes
    return out


def format_publishers(mapping: Mapping[str, Sequence[str]]) -> str:
    """The text :func:`parse_publishers` reads."""
    return ",".join(f"{topic}={'|'.join(nodes)}" for topic, nodes in mapping.items())


class InputGuard:
    """One input topic of a node that answers to the publishers of ``owners`` alone
    (:class:`PublisherPin`): while another publisher is matched, no message of the topic
    is used, and ``say(level, message, **values)`` names it and the topic once (level
    2, an error) and says when it has gone (level 0). After it has gone, a message whose
    stamp is no later than the newest one seen before is refused too (what it left
    queued). ``subscription`` (anything with ``get_publisher_count``) is set once the
    node has made it; ``node`` lists the publishers (``get_publishers_info_by_topic``)."""

    def __init__(self, node: Any, topic: str, owners: Sequence[str], reader: str,
                 say: Callable[..., None]) -> None:
        self.node, self.topic, self.reader, self.say = node, topic, reader, say
        self.pin = PublisherPin(owners)
        self.subscription: Any = None
        self.newest_ns = -1  # newest stamp seen on the topic, used or not
        self.refused = 0  # messages not used

    def admits(self, stamp_ns: int | None) -> bool:
        """Whether the message just taken (header stamp ``stamp_ns``, None: none) may be
        used."""
        self.check()
        ok = self.pin.admits(self.newest_ns + 1 if stamp_ns is None else stamp_ns)
        if stamp_ns is not None and stamp_ns > self.newest_ns:
            self.newest_ns = stamp_ns
        if not ok:
            self.refused += 1
        return ok

    def check(self) -> None:
        """Look at the topic's publishers (cheap unless their count changed)."""
        if self.subscription is None:
            return
        matched = self.subscription.get_publisher_count()
        if not self.pin.needs_look(matched):
            return
        change = self.pin.look(matched, listed_publishers(self.node, self.topic),
                               self.newest_ns)
        if change is None:
            return
        owners = " or ".join(f"/{o}" for o in self.pin.owners)
        if change.intruders:
            intruders = ", ".join(change.intruders)
            self.say(2, f"another publisher on {self.topic}: {intruders}; the {self.reader} "
                     f"uses none of its messages while it is there, and the graph commands "
                     f"0 V (only {owners}, pinned at the start, publishes it)",
                     intruders=intruders, topic=self.topic, refused=self.refused)
        else:
            self.say(0, f"{', '.join(change.left)} left {self.topic}: the {self.reader} "
                     "uses its messages again", topic=self.topic, refused=self.refused)


def listed_publishers(node: Any, topic: str) -> list[Endpoint]:
    """The publishers the ROS graph lists on ``topic``, as a node (any object with
    rclpy's ``get_publishers_info_by_topic``) sees them."""
    return [Endpoint(i.node_name, i.node_namespace, bytes(i.endpoint_gid))
            for i in node.get_publishers_info_by_topic(topic)]


# The chain a sample goes through before a command answers it: (stage, its output topic);
# the last stage, the current loop, publishes the command itself.
CHAIN: tuple[tuple[str, Topic], ...] = (("estimator", STATE), ("supervisor", CART_FORCE))


def first_silent_stage(stamp_ns: int, newest: Mapping[str, int],
                       last: str = "current_loop") -> tuple[str, Topic | None]:
    """The first stage of :data:`CHAIN` whose newest output (``newest[stage]``, a stamp)
    is older than ``stamp_ns``, with its topic; ``(last, None)`` when all have one (the
    command's stage). For lockstep, where no sample comes while the chain is silent: on
    the wall clock a slow stage looks the same for a while (:class:`StopWitness`)."""
    for name, topic in CHAIN:
        if newest.get(name, -1) < stamp_ns:
            return name, topic
    return last, None


@dataclass(frozen=True)
class StopVerdict:
    """The stage that stopped (``topic`` None: the command's own stage), by the samples:
    its newest output answers sample ``since`` (None: none of the last samples kept), the
    stage before it went on to sample ``before_at``, ``behind`` samples further; ``sure``:
    that is ``margin`` or more, not named at a deadline or a stop from what was known.
    The trip it explains: 0 V from sample ``trip`` (stamp ``trip_stamp_ns``), the newest
    answered sample ``last_answered``."""

    stage: str
    topic: Topic | None
    since: int | None
    before_at: int | None
    behind: int
    sure: bool = False
    trip: int = -1
    last_answered: int = -1
    trip_stamp_ns: int = -1


class StopWitness:
    """Which stage of the control chain stopped, after a command watchdog trip (pure).

    The trip zeroes the motor at once; the stage is named when the evidence is in. A stage
    that died stops where it was while the stages before it go on, so it falls one sample
    further behind the stage before it (the samples themselves, for the estimator) every
    period; a live stage slowed by the machine falls behind by its lag and catches up.
    Judged at one instant the two look alike (a killed current loop two
    samples behind was taken for a supervisor one sample late), so the stage is named
    when it is ``margin`` samples behind the one before it, the furthest behind of those,
    the first of equals. If none is, ``deadline`` samples after the trip (the chain
    stalled as a whole) or at a stop, the one furthest behind is named from what is
    known (``sure`` false). Commands resuming end the question (:meth:`resumed`).
    """

    def __init__(self, margin: int = 8, deadline: int = 30,
                 last: str = "current_loop") -> None:
        if not 1 <= margin < deadline:
            raise ValueError(f"margin {margin} must lie in 1 .. deadline - 1 ({deadline - 1})")
        self.margin, self.deadline, self.last = margin, deadline, last
        self._samples: deque[tuple[int, int]] = deque(maxlen=deadline + 16)  # (stamp, index)
        self.pending: tuple[int, int, int] | None = None  # (trip sample, last answered, stamp)

    def sample(self, index: int, stamp_ns: int) -> None:
        self._samples.append((stamp_ns, index))

    def trip(self, index: int, last_answered: int) -> None:
        """A trip at sample ``index`` (the newest sample given to :meth:`sample`, or one
        before it); the newest answered one was ``last_answered``."""
        stamp = next((s for s, i in reversed(self._samples) if i == index), -1)
        self.pending = (index, last_answered, stamp)

    def resumed(self) -> None:
        self.pending = None

    def _index_of(self, stamp_ns: int) -> int | None:
        """The newest kept sample at or before ``stamp_ns`` (None: older than all kept)."""
        found = None
        for s, i in self._samples:
            if s > stamp_ns:
                break
            found = i
        return found

    def standing(self, newest: Mapping[str, int], answered_ns: int) -> list[StopVerdict]:
        """Each stage, how many samples behind the stage before it (not ``sure``). A stage
        never heard from (no stamp) while a later one was has been running unheard (its
        topic not yet matched): it is left out, and the next judged against the one
        before it."""
        out = []
        before = self._samples[-1][0] if self._samples else -1
        stages = [(n, t, newest.get(n, -1)) for n, t in CHAIN] + [(self.last, None, answered_ns)]
        stages = [stage for k, stage in enumerate(stages)
                  if stage[2] >= 0 or all(later[2] < 0 for later in stages[k + 1:])]
        for name, topic, stamp in stages:
            behind = sum(1 for s, _ in self._samples if stamp < s <= before)
            out.append(StopVerdict(name, topic, self._index_of(stamp), self._index_of(before),
                                   behind))
            before = stamp
        return out

    def verdict(self, newest: Mapping[str, int], answered_ns: int,
                force: bool = False) -> StopVerdict | None:
        """The stage that stopped, once known (then the question is closed), else None;
        ``force``: name the one furthest behind now (a stop)."""
        if self.pending is None or not self._samples:
            return None
        standing = self.standing(newest, answered_ns)
        worst = max(standing, key=lambda v: v.behind)  # (max keeps the first of equals)
        sure = worst.behind >= self.margin
        if not (sure or force or self._samples[-1][1] - self.pending[0] >= self.deadline):
            return None
        trip, self.pending = self.pending, None
        return StopVerdict(worst.stage, worst.topic, worst.since, worst.before_at,
                           worst.behind, sure, *trip)


def stop_sentence(verdict: StopVerdict, who: str, command_topic: Topic) -> str:
    """``the supervisor (/supervisor) stopped: nothing on /pisc/cart_force since sample
    596 while /pisc/state went on to sample 606``, for /diagnostics."""
    topics = [t for _, t in CHAIN]
    k = topics.index(verdict.topic) if verdict.topic in topics else len(CHAIN)
    before = "the samples" if k == 0 else topics[k - 1].name
    since = (f"since sample {verdict.since}" if verdict.since is not None
             else "in the samples kept")
    sentence = (f"the {verdict.stage} ({who}) stopped: nothing on "
                f"{(verdict.topic or command_topic).name} {since} while {before} went on to "
                f"sample {verdict.before_at}")
    if not verdict.sure:
        sentence += (f" (named from {verdict.behind} sample(s) behind, short of sure: the "
                     "chain may have stalled as a whole)")
    return sentence


def named_trip(verdict: StopVerdict, who: str, command_topic: Topic) -> str:
    """The trip's status once its stage is named: ``command watchdog: no command answered
    samples j+1 .. j+3: 0 V from sample j+3; the ... stopped: ...``."""
    return (f"command watchdog: no command answered samples {verdict.last_answered + 1} .. "
            f"{verdict.trip}: 0 V from sample {verdict.trip}; "
            f"{stop_sentence(verdict, who, command_topic)}")


def who_publishes(node: Any, topic: Topic) -> str:
    """The node(s) the ROS graph lists as publishing ``topic``, for a sentence."""
    nodes = sorted({e.fully_qualified for e in listed_publishers(node, topic.name)})
    return ", ".join(nodes) if nodes else f"no publisher on {topic.name}"


def silent_stage_report(node: Any, stamp_ns: int, newest: Mapping[str, int], sample: int,
                        command_topic: Topic) -> tuple[str, str]:
    """(sentence, nodes) naming the first stage with no output for sample ``sample``
    (stamp ``stamp_ns``) and the node(s) that publish its output, for /diagnostics:
    ``the supervisor (/supervisor) stopped: nothing on /pisc/cart_force answers sample
    812`` (lockstep; on the wall clock :class:`StopWitness`)."""
    stage, topic = first_silent_stage(stamp_ns, newest)
    topic = topic or command_topic
    who = who_publishes(node, topic)
    return (f"the {stage} ({who}) stopped: nothing on {topic.name} answers sample {sample}",
            who)
