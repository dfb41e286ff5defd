"""The command path's guards, pure: the command watchdog, the pinned publisher, the
silent stage (docs/safety.md). No rclpy."""

from __future__ import annotations

import pytest

from pisc_msgs_py.topics import CART_FORCE, STATE, VOLTAGE
from pisc_msgs_py.watchdog import (
    GRAPH_PUBLISHERS,
    CommandWatchdog,
    Endpoint,
    InputGuard,
    PinChange,
    PublisherPin,
    StopVerdict,
    StopWitness,
    first_silent_stage,
    format_publishers,
    named_trip,
    parse_publishers,
    stop_sentence,
)


def test_the_watchdog_holds_a_command_for_its_periods_then_zero_volts():
    dog = CommandWatchdog(3)
    stamps = {k: 1_000 + 5 * k for k in range(12)}
    for k in range(2):
        dog.sample(k, stamps[k])
        assert not dog.expired(k)  # not armed before a first answer
    assert dog.fresh(stamps[1]) == 1 and dog.answer(1) is None
    for k in range(2, 4):
        dog.sample(k, stamps[k])
        assert not dog.expired(k)  # periods 2, 3 hold sample 1's command
    dog.sample(4, stamps[4])
    assert dog.expired(4) and dog.tripped_at == 4  # 3 unanswered in a row: 0 V from 4
    dog.sample(5, stamps[5])
    assert dog.expired(5) and dog.tripped_at == 4
    # only the last 3 samples' stamps are fresh
    assert dog.fresh(stamps[2]) is None and dog.fresh(stamps[3]) == 3
    assert dog.answer(3) == 4 and dog.tripped_at is None  # commands resume
    dog.sample(6, stamps[6])
    assert not dog.expired(5)  # 5 - 3 < 3: sample 3's command holds through period 5
    dog.sample(7, stamps[7])
    assert not dog.expired(5 + 0) and dog.expired(6)  # 0 V again from sample 3 + 3


LOOP = Endpoint("current_loop", "/", b"\x01" * 16)
VISITOR = Endpoint("visitor", "/lab", b"\x02" * 16)


def test_the_pin_takes_the_owner_and_names_every_other_publisher_while_it_is_there():
    pin = PublisherPin("current_loop")
    assert pin.needs_look(0) and pin.look(0, []) is None and not pin.needs_look(0)
    assert pin.needs_look(1)
    assert pin.look(1, [LOOP]) is None and pin.pinned == LOOP.gid and pin.intruders == ()
    assert not pin.needs_look(1)  # pinned, count unchanged: no look at the graph
    assert pin.needs_look(2)
    assert pin.look(2, [LOOP, VISITOR]) == PinChange(intruders=("/lab/visitor",))
    assert pin.needs_look(2)  # looked at every time while an intruder is there
    assert pin.look(2, [LOOP, VISITOR]) is None  # said once
    assert pin.look(1, [LOOP]) == PinChange(left=("/lab/visitor",))
    assert pin.intruders == () and pin.pinned == LOOP.gid


def test_a_second_publisher_of_the_owners_name_is_an_intruder_and_so_is_an_unlisted_one():
    pin = PublisherPin("current_loop")
    pin.look(1, [LOOP])
    forged = Endpoint("current_loop", "/", b"\x03" * 16)  # a copy of the name
    assert pin.look(2, [LOOP, forged]) == PinChange(intruders=("/current_loop",))
    assert pin.look(1, [LOOP]).left == ("/current_loop",)
    # matched by the subscription before the graph lists it
    assert pin.look(2, [LOOP]) == PinChange(intruders=(PublisherPin.UNLISTED,))


def test_without_the_owner_every_publisher_is_an_intruder():
    pin = PublisherPin("current_loop")
    assert pin.look(1, [VISITOR]) == PinChange(intruders=("/lab/visitor",))
    assert pin.pinned is None
    pin = PublisherPin("current_loop")
    assert pin.look(2, []) == PinChange(intruders=(PublisherPin.UNKNOWN,))
    # the owner and another one seen together: the owner is pinned, the other named
    pin = PublisherPin("current_loop")
    assert pin.look(2, [VISITOR, LOOP]) == PinChange(intruders=("/lab/visitor",))
    assert pin.pinned == LOOP.gid


def test_the_first_stage_without_output_for_the_sample_is_named():
    assert first_silent_stage(100, {}) == ("estimator", STATE)
    assert first_silent_stage(100, {"estimator": 100, "supervisor": 95}) == (
        "supervisor", CART_FORCE)
    assert first_silent_stage(100, {"estimator": 100, "supervisor": 100}) == (
        "current_loop", None)


def _unnamed(endpoint: Endpoint) -> Endpoint:
    """The endpoint as discovery first lists it, before its node's name."""
    return Endpoint("_NODE_NAME_UNKNOWN_", "_NODE_NAMESPACE_UNKNOWN_", endpoint.gid)


def test_before_the_pin_a_publisher_not_yet_named_is_held_off_until_it_is_named():
    """A driver's own publisher was listed unnamed for 20-80 ms at its start, and was said
    to be another publisher: every run through the driver judged unsafe. Before the pin
    nothing is admitted and nothing said until discovery names it."""
    pin = PublisherPin("current_loop")
    assert pin.look(1, [_unnamed(LOOP)]) is None
    assert pin.pending and pin.intruders == () and pin.pinned is None
    assert not pin.admits(1000) and pin.needs_look(1)
    assert pin.look(1, [LOOP]) is None
    assert not pin.pending and pin.pinned == LOOP.gid and pin.admits(1000)
    # named as another node's: an intruder, said then
    pin = PublisherPin("current_loop")
    assert pin.look(1, [_unnamed(VISITOR)]) is None and not pin.admits(1000)
    assert pin.look(1, [VISITOR]) == PinChange(intruders=("/lab/visitor",))
    assert pin.pinned is None and not pin.admits(1000)


def test_after_the_pin_a_publisher_not_yet_named_is_an_intruder_at_once():
    pin = PublisherPin("current_loop")
    pin.look(1, [LOOP])
    assert pin.look(2, [LOOP, _unnamed(VISITOR)]) == PinChange(
        intruders=("a publisher whose node the ROS graph does not name yet",))
    assert not pin.pending and not pin.admits(1000) and pin.needs_look(2)
    assert pin.look(2, [LOOP, VISITOR]) == PinChange(intruders=("/lab/visitor",))
    assert pin.look(1, [LOOP]).left == ("/lab/visitor",)


def test_the_pin_admits_nothing_a_departed_intruder_left_queued():
    """The matched count lags the messages (it moves in DDS's discovery thread): after a
    visitor's departure its queued answers (to samples up to the newest one when the
    departure was seen) are refused by their stamps; the owner's next answers drive."""
    pin = PublisherPin("current_loop")
    pin.look(1, [LOOP], newest_ns=1000)
    assert pin.admits(1000) and pin.fence_ns == -1  # no departure yet: no fence
    assert pin.look(2, [LOOP, VISITOR]).intruders == ("/lab/visitor",)
    assert not pin.admits(1005) and pin.refused == 0  # held off while it is there
    # the visitor goes when sample 1010 is the newest; its answer to 1010 is still queued
    assert pin.look(1, [LOOP], newest_ns=1010).left == ("/lab/visitor",)
    assert not pin.admits(1010) and not pin.admits(1005) and pin.refused == 2
    assert pin.admits(1015)
    # a later departure seen at an older stamp does not move the fence back
    pin.look(2, [LOOP, VISITOR])
    pin.look(1, [LOOP], newest_ns=1008)
    assert pin.fence_ns == 1010


def test_a_visitor_the_graph_forgets_before_the_count_drops_is_named_when_it_leaves():
    """Seen under load: while a visitor left, the graph stopped listing it
    before the subscription's matched count dropped; the driver then said "a publisher
    the ROS graph does not list yet" had left, never that /lab/visitor had."""
    pin = PublisherPin("current_loop")
    pin.look(1, [LOOP])
    assert pin.look(2, [LOOP, VISITOR]) == PinChange(intruders=("/lab/visitor",))
    assert pin.look(2, [LOOP]) is None  # forgotten by the graph, still matched: no news
    assert pin.intruders == (PublisherPin.UNLISTED,) and not pin.admits(2000)
    assert pin.look(1, [LOOP], 2000) == PinChange(left=("/lab/visitor",))
    # a second visitor while the first is leaving is news, and both are said to leave
    other = Endpoint("other", "/", b"\x04" * 16)
    pin.look(2, [LOOP, VISITOR])
    assert pin.look(3, [LOOP, VISITOR, other]) == PinChange(
        intruders=("/lab/visitor", "/other"))
    assert pin.look(1, [LOOP]) == PinChange(left=("/lab/visitor", "/other"))


def _stamp(k: int) -> int:
    return 1_000_000 + 5_000 * k  # sample k, 5 us apart (any increasing stamps do)


def _run(witness: StopWitness, first: int, last: int, outputs, answered) -> list:
    """Samples first .. last; after each, ``outputs(k)`` (newest stamp per stage) and
    ``answered(k)`` (the command's) are judged; the verdicts, with their sample."""
    found = []
    for k in range(first, last + 1):
        witness.sample(k, _stamp(k))
        verdict = witness.verdict(outputs(k), answered(k))
        if verdict is not None:
            found.append((k, verdict))
    return found


def _tripped(margin: int = 8, deadline: int = 30) -> StopWitness:
    """Samples 0 .. 10, tripped at 10 with 7 the newest answered."""
    w = StopWitness(margin=margin, deadline=deadline)
    _run(w, 0, 10, lambda k: {}, lambda k: -1)
    w.trip(10, 7)
    return w


def test_a_killed_current_loop_two_samples_behind_is_named_once_it_falls_behind():
    """The CI run's case: the current loop killed having answered 596, the
    live supervisor one sample late and the estimator keeping up; judged at the trip
    (599) each stage is one sample behind the one before it. Eight samples later only
    the dead one is."""
    w = StopWitness(margin=8, deadline=30)
    live = lambda k: {"estimator": _stamp(k), "supervisor": _stamp(k - 1)}  # noqa: E731
    assert _run(w, 590, 599, live, lambda k: _stamp(min(k - 1, 596))) == []
    w.trip(599, 596)
    [(k, verdict)] = _run(w, 600, 640, live, lambda k: _stamp(596))
    # the supervisor's newest output 604 - 596 = 8 samples behind, at sample 605
    assert k == 605 and verdict == StopVerdict("current_loop", None, 596, 604, 8, True,
                                               599, 596, _stamp(599))
    assert w.pending is None  # the question is closed: said once
    assert named_trip(verdict, "/current_loop", VOLTAGE) == (
        "command watchdog: no command answered samples 597 .. 599: 0 V from sample 599; "
        "the current_loop (/current_loop) stopped: nothing on /pisc/motor/voltage since "
        "sample 596 while /pisc/cart_force went on to sample 604")


def test_a_killed_supervisor_and_a_killed_estimator_are_named():
    w = _tripped()
    dead_supervisor = lambda k: {"estimator": _stamp(k - 1), "supervisor": _stamp(7)}  # noqa: E731
    [(k, verdict)] = _run(w, 11, 40, dead_supervisor, lambda k: _stamp(7))
    assert (k, verdict.stage, verdict.topic, verdict.since, verdict.before_at) == (
        16, "supervisor", CART_FORCE, 7, 15)
    assert stop_sentence(verdict, "/supervisor", VOLTAGE) == (
        "the supervisor (/supervisor) stopped: nothing on /pisc/cart_force since sample 7 "
        "while /pisc/state went on to sample 15")
    w = _tripped()
    dead_estimator = lambda k: {"estimator": _stamp(7), "supervisor": _stamp(7)}  # noqa: E731
    [(k, verdict)] = _run(w, 11, 40, dead_estimator, lambda k: _stamp(7))
    assert (k, verdict.stage, verdict.topic, verdict.since, verdict.before_at) == (
        15, "estimator", STATE, 7, 15)
    assert stop_sentence(verdict, "/estimator", VOLTAGE).endswith(
        "nothing on /pisc/state since sample 7 while the samples went on to sample 15")


def test_a_chain_that_stalls_and_resumes_names_nobody():
    """A live supervisor late at the trip catches up: commands resume, and with them the
    question ends; nothing is named."""
    w = _tripped()
    slow = lambda k: {"estimator": _stamp(k), "supervisor": _stamp(min(k, 7 + (k - 10) // 2))}  # noqa: E731
    assert _run(w, 11, 13, slow, lambda k: _stamp(7)) == []
    w.resumed()
    assert _run(w, 14, 60, slow, lambda k: _stamp(7)) == []


def test_a_stop_names_at_once_and_a_crawling_chain_is_named_at_the_deadline():
    w = _tripped()
    stalled = {"estimator": _stamp(7), "supervisor": _stamp(7)}
    assert w.verdict(stalled, _stamp(7)) is None  # 3 behind: not yet
    w.sample(11, _stamp(11))
    w.sample(12, _stamp(12))
    # a stop at sample 12: named now from what is known, not sure
    verdict = w.verdict(stalled, _stamp(7), force=True)
    assert (verdict.stage, verdict.behind, verdict.sure) == ("estimator", 5, False)
    assert stop_sentence(verdict, "/estimator", VOLTAGE) == (
        "the estimator (/estimator) stopped: nothing on /pisc/state since sample 7 while "
        "the samples went on to sample 12 (named from 5 sample(s) behind, short of sure: "
        "the chain may have stalled as a whole)")
    # with a margin no stage reaches, the deadline names one: 30 samples after the trip
    w = _tripped(margin=29)
    crawling = lambda k: {"estimator": _stamp(7 + (k - 7) // 2), "supervisor": _stamp(7)}  # noqa: E731
    [(k, verdict)] = _run(w, 11, 60, crawling, lambda k: _stamp(7))
    assert (k, verdict.stage, verdict.behind, verdict.sure) == (40, "estimator", 17, False)


def test_a_stage_never_heard_from_while_a_later_one_was_is_not_judged():
    """The plant's subscription of a stage's topic may match late (its own process, a
    loaded machine): a supervisor never heard from while the current loop answered was
    running. Killed, the estimator is named (it was the supervisor, "in the samples
    kept", taken as behind every kept sample). A stage never heard from with nothing
    after it heard either may have been dead from the start, and is judged."""
    w = _tripped()
    unmatched = lambda k: {"estimator": _stamp(7)}  # noqa: E731
    [(k, verdict)] = _run(w, 11, 40, unmatched, lambda k: _stamp(7))
    assert (k, verdict.stage, verdict.topic, verdict.since, verdict.before_at, verdict.sure) == (
        15, "estimator", STATE, 7, 15, True)
    # the current loop is judged against the estimator, the stage heard before it (the
    # samples went on to 40: 8 .. 40 are newer than the estimator's output)
    assert [(v.stage, v.behind) for v in w.standing(unmatched(40), _stamp(7))] == [
        ("estimator", 33), ("current_loop", 0)]
    # nothing heard from any stage: the first is named, behind every kept sample
    w = _tripped()
    [(k, verdict)] = _run(w, 11, 40, lambda k: {}, lambda k: -1)
    assert (k, verdict.stage, verdict.since, verdict.sure) == (11, "estimator", None, True)


def test_the_witness_refuses_a_margin_outside_its_deadline():
    with pytest.raises(ValueError, match=r"margin 30 must lie in 1 \.\. deadline - 1 \(29\)"):
        StopWitness(margin=30, deadline=30)


# -- every input pinned: several owners, the guard of a node's input -----------------------

DRIVER = Endpoint("driver", "/", b"\x03" * 16)
SECOND_DRIVER = Endpoint("driver", "/", b"\x04" * 16)  # a visitor that took its name


def test_a_pin_of_alternatives_takes_the_one_that_runs_and_names_a_second_of_its_name():
    pin = PublisherPin(("plant", "driver"))
    assert pin.look(1, [DRIVER]) is None and pin.pins == {"driver": DRIVER.gid}
    assert pin.admits(10)
    change = pin.look(2, [DRIVER, SECOND_DRIVER])
    assert change == PinChange(intruders=("/driver",)) and not pin.admits(11)
    # two endpoints of one name before either was pinned: neither is taken
    fresh = PublisherPin(("plant", "driver"))
    assert fresh.look(2, [DRIVER, SECOND_DRIVER]).intruders == ("/driver", "/driver")
    assert fresh.pins == {}
    # several owners matched, none listed yet (discovery): not an intruder until more
    # are matched than there are owners
    assert PublisherPin(("plant", "driver")).look(2, []) is None
    assert PublisherPin(("plant", "driver")).look(3, []).intruders == (PublisherPin.UNKNOWN,)


def test_the_publishers_parameter_reads_and_writes_its_form_and_names_a_bad_item():
    text = "/pisc/joint_states=plant|driver,/clock=plant"
    assert parse_publishers(text) == {"/pisc/joint_states": ("plant", "driver"),
                                      "/clock": ("plant",)}
    assert format_publishers(parse_publishers(text)) == text
    assert parse_publishers("") == {}
    for bad, why in [("pisc/state=estimator", "'pisc/state=estimator' is not"),
                     ("/pisc/state", "'/pisc/state' is not"),
                     ("/pisc/state=est-imator", "'/pisc/state=est-imator' is not"),
                     ("/a=x,/a=y", "names /a twice")]:
        with pytest.raises(ValueError, match=why):
            parse_publishers(bad)
    assert set(GRAPH_PUBLISHERS) >= {"/pisc/joint_states", "/pisc/state", "/clock"}


class _Subscription:
    def __init__(self) -> None:
        self.count = 0

    def get_publisher_count(self) -> int:
        return self.count


class _Graph:
    def __init__(self) -> None:
        self.listed: list[Endpoint] = []

    def get_publishers_info_by_topic(self, topic):
        class Info:
            def __init__(self, e):
                self.node_name, self.node_namespace, self.endpoint_gid = (
                    e.node, e.namespace, e.gid)
        return [Info(e) for e in self.listed]


def test_an_input_guard_uses_nothing_while_a_visitor_is_there_and_says_so_once():
    said: list[tuple[int, str, dict]] = []
    graph, sub = _Graph(), _Subscription()
    guard = InputGuard(graph, "/pisc/state", ("estimator",), "supervisor",
                       lambda level, message, **values: said.append((level, message, values)))
    guard.subscription = sub
    estimator = Endpoint("estimator", "/", b"\x05" * 16)
    graph.listed, sub.count = [estimator], 1
    assert guard.admits(5) and guard.admits(10)
    graph.listed, sub.count = [estimator, VISITOR], 2
    assert not guard.admits(20) and not guard.admits(15) and guard.refused == 2
    assert said == [(2, "another publisher on /pisc/state: /lab/visitor; the supervisor uses "
                        "none of its messages while it is there, and the graph commands 0 V "
                        "(only /estimator, pinned at the start, publishes it)",
                     {"intruders": "/lab/visitor", "topic": "/pisc/state", "refused": 0})]
    graph.listed, sub.count = [estimator], 1
    # what it left queued (stamped up to the newest seen before it went) is not used
    assert not guard.admits(20) and guard.admits(25)
    assert said[-1][0] == 0 and said[-1][1] == ("/lab/visitor left /pisc/state: the "
                                                "supervisor uses its messages again")
