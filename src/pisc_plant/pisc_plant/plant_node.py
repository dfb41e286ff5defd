"""Plant node: the simulated rig on the graph's topics, against the wall clock or lockstep.

``simulation.clock = wall``: a sample every period of the wall clock, stamped with the
time it is published; a voltage takes effect when it arrives, as on the rig.
``simulation.clock = lockstep``: the node owns simulated time and publishes ``/clock``;
it publishes sample k, waits for the voltage stamped with sample k, integrates one
period and publishes sample k+1, so a run goes as fast as the graph answers. The other
nodes run with ``use_sim_time``; nothing in the loop depends on timers. ``/clock`` goes
out with every ``simulation.clock_every``-th sample (10: every 50 ms of simulated time,
as Gazebo publishes it at a rate of its own): in ``pisc_graph --processes`` it woke
five processes a cycle (three controllers, the recorder, the runner); what every tenth
sample saves is measured in docs/figures.md ("Fewer wake-ups a cycle").

**Command watchdog.** A command is fresh when its stamp is that of one of the last
``simulation.watchdog_periods`` samples (lockstep: of the awaited sample, the only one
that advances time). On the wall clock, once that many samples in a row went unanswered,
the plant applies 0 V until a fresh command comes and says so on ``/diagnostics`` at
once; which stage of the chain (estimator, supervisor, current loop) stopped it says a
few periods later, when that stage has fallen ``margin`` samples behind the one before it
(:class:`pisc_msgs_py.watchdog.StopWitness`; at the latest when the node stops). In
lockstep a dead controller stops simulated time, so no voltage is held over any of it,
and the plant names the first silent stage once ``resend_after_s`` passed.

**The recorder keeps up.** A reliable publisher keeps its last 100 messages for a
subscriber that trails; in lockstep the graph makes ~1,800 samples a second, so a
recorder short of the CPU for 55 ms would lose messages. With
``simulation.recorder_lag_samples`` = N > 0 (pisc_graph: 20) the plant publishes a
sample only when the run's recorder has written every message of the sample N periods
before (``/pisc/recorder/progress``, ``pisc_record --progress``): a recorder that falls
behind pauses simulated time, and the plant says so on /diagnostics when it has waited
``resend_after_s``.

**Only the graph drives the motor.** When the run starts the plant pins the command
publisher of ``simulation.command_node`` (its GID, from the ROS graph). Any other
publisher matched on the command topic is a fault on ``/diagnostics`` naming its node,
and the plant applies 0 V while it is there. rclpy on Jazzy gives no publisher GID with
a message (ros2/rclpy#1466 came after), so the plant cannot sort messages by sender: it
watches how many publishers its subscription has matched (on every command and sample)
and asks the ROS graph who they are when that changes.

**A clean stop.** Run as a process (``main``), SIGTERM and SIGINT ask the plant to stop:
the cycle in progress is finished (its joint_states, motor current and true state all
published) and the node shuts down at its next callback, before publishing another
sample. rclpy's own handler shut the context down at once, so a signal inside
``_publish_sample`` made the rest of the cycle fail. With
``simulation.duration_s`` the plant publishes no sample after the one that ends the run.
"""

from __future__ import annotations

import signal
import time
from dataclasses import dataclass
from typing import Any

import rclpy

from pisc_msgs_py.base_node import ERROR, OK, WARN, PiscNode, run_node
from pisc_msgs_py.config import ConfigError, in_range, one_of, param
from pisc_msgs_py.convert import (
    clock_to_cdr,
    joint_sample_to_cdr,
    motor_sample_from_msg,
    motor_sample_to_cdr,
    stamp_from_msg,
    true_state_to_cdr,
)
from pisc_msgs_py.topics import (
    CLOCK,
    CURRENT_SETPOINT,
    JOINT_STATES,
    MOTOR_CURRENT,
    RECORDER_PROGRESS,
    SIM_STATE,
    VOLTAGE,
    Topic,
)
from pisc_msgs_py.types import JointSample, MotorSample, TrueState
from pisc_msgs_py.watchdog import (
    CHAIN,
    CommandWatchdog,
    PublisherPin,
    StopWitness,
    listed_publishers,
    silent_stage_report,
    named_trip,
    who_publishes,
)
from pisc_model.params import (
    InitialParams,
    check_models_use,
)
from pisc_plant.command import plant_command
from pisc_plant.plant import Plant
from pisc_plant.plant_config import PLANT_SECTIONS, PlantConfig
from pisc_plant.sampled import SampledPlant


@dataclass(frozen=True)
class SimulationParams:
    clock: str = param("lockstep", "'wall': real time; 'lockstep': simulated time on /clock, "
                       "advancing as soon as the graph answers", "", one_of("wall", "lockstep"))
    min_subscribers: int = param(1, "lockstep: subscribers of joint_states and of the motor "
                                 "current to wait for before the first sample", "",
                                 in_range(0, 64))
    min_true_state_subscribers: int = param(0, "lockstep: subscribers of the true state to "
                                            "wait for (a recorder)", "", in_range(0, 64))
    min_clock_subscribers: int = param(0, "lockstep: subscribers of /clock to wait for (each "
                                       "node with use_sim_time, a recorder, a runner that "
                                       "starts the plant by subscribing)", "",
                                       in_range(0, 64))
    clock_every: int = param(10, "lockstep: publish /clock with every clock_every-th sample "
                             "(10: every 50 ms of simulated time at the 5 ms period, 1: every "
                             "sample); the graph's messages carry their sample's stamp and "
                             "its nodes use no timers, so only a node's now() between two "
                             "/clock messages sees time in those steps", "",
                             in_range(1, 1000))
    publish_true_state: bool = param(True, "publish the true state on /pisc/sim/true_state", "")
    resend_after_s: float = param(0.5, "lockstep: send the current sample again when no voltage "
                                  "answered it for this long (the controllers answer a repeated "
                                  "stamp with their first answer)", "s", in_range(0.01, 60.0))
    start_settle_s: float = param(0.5, "lockstep: once every subscriber is matched, wait this "
                                  "long before the first sample (a reader matches its writers "
                                  "a little after they match it, and a volatile reader drops "
                                  "what was sent before)", "s", in_range(0.0, 60.0))
    watchdog_periods: int = param(3, "wall clock: samples in a row left unanswered after which "
                                  "the plant applies 0 V (3: 0 V at most 15 ms after the last "
                                  "answered sample at 5 ms, inside the 20 ms a controller's "
                                  "death allows; 2 missed answers in a row are tolerated)", "",
                                  in_range(1, 1000))
    duration_s: float = param(0.0, "the run's length: once a voltage answers the sample this "
                              "long after the first voltage's, the plant publishes no more "
                              "samples (0 = until stopped; pisc_graph sets its --duration, so "
                              "a run in separate processes ends at its duration exactly)",
                              "s", in_range(0.0, 1e9))
    recorder_lag_samples: int = param(0, "lockstep: publish a sample only when the run's "
                                      "recorder has written every message of the sample this "
                                      "many periods before (/pisc/recorder/progress), so a "
                                      "recorder that falls behind pauses simulated time "
                                      "instead of losing messages; below the control topics' "
                                      "history depth (100); 0: no recorder is waited for",
                                      "", in_range(0, 99))
    command_node: str = param("current_loop", "the node whose command publisher the plant "
                              "pins at the start; any other publisher on the command topic "
                              "is a fault, with 0 V while it is there", "",
                              lambda v: None if v else "must name a node")


SECTIONS = {**PLANT_SECTIONS, "initial": InitialParams, "simulation": SimulationParams}


def _warm_up(plant: Plant, state: Any) -> None:
    """One sample, command and step on a throwaway copy, before the run: numba loads the
    kernel's entry points from its cache on first call (about 1 s, measured in the first
    lockstep cycle) and the plant keeps its operator tables; the run's own
    SampledPlant starts from ``state`` untouched, with its own noise generator."""
    scratch = SampledPlant(plant, state.copy())
    scratch.sample()
    scratch.command(0.0)
    scratch.advance()


class PlantNode(PiscNode):
    def __init__(self, **kwargs: Any) -> None:
        super().__init__("plant", SECTIONS, **kwargs)
        plant_config, initial, self._sim_params = self.config
        plant = Plant(plant_config)
        state = plant.initial_state(initial.x_m, initial.x_dot_mps, initial.theta_rad,
                                    initial.theta_dot_radps)
        self._lockstep = self._sim_params.clock == "lockstep"
        self._sim = SampledPlant(plant, state)
        self._stamp_ns = 0  # stamp of the current sample
        self._published_ns = 0  # wall time the current sample was published
        self._started = False
        self._matched_ns: int | None = None  # wall time every subscriber was first matched
        self._resent = 0
        self._stale = 0
        self._missed = 0
        self._joint_pub = self.publisher(JOINT_STATES)
        self._current_pub = self.publisher(MOTOR_CURRENT)
        self._true_pub = self.publisher(SIM_STATE)
        self._clock_pub = self.publisher(CLOCK) if self._lockstep else None
        # the command topics are pinned by the plant itself (_check_publishers): 0 V while
        # another publisher is there, and lockstep goes on
        self._sub = self.subscription(VOLTAGE, self._on_voltage, guarded=False)
        # An ideal current loop (models.current_loop = ideal) makes the current equal its
        # set-point: the plant is then driven by the set-point's force (plant_command),
        # and the voltage the current loop computes acts on nothing.
        self._command_topic: Topic = VOLTAGE
        self._command_sub = self._sub
        if plant.force_input:
            self._setpoint_sub = self.subscription(CURRENT_SETPOINT, self._on_setpoint,
                                                   guarded=False)
            self._command_topic, self._command_sub = CURRENT_SETPOINT, self._setpoint_sub
        self._watchdog = CommandWatchdog(self._sim_params.watchdog_periods)
        self._answered_ns = -1  # stamp of the newest sample an admitted command answered
        self._witness = StopWitness()  # after a trip: which stage stopped
        # lockstep with a recorder to wait for: the newest sample it has written whole
        self._lag_ns = (self._sim_params.recorder_lag_samples
                        * round(plant_config.loop.period_s * 1e9))
        self._recorded_ns = -1  # before the first sample: the first sample's stamp
        self._held_ns: int | None = None  # wall time the next sample began to wait for it
        self._hold_said = False  # that wait is said on /diagnostics
        self._recorder_waits = 0  # samples that waited for the recorder
        self._progress_sub = (self.subscription(RECORDER_PROGRESS, self._on_progress)
                              if self._lockstep and self._lag_ns else None)
        # newest stamp out of each stage of the chain, to say which one stopped
        self._upstream = self.newest_stamps(CHAIN)
        self._pin = PublisherPin(self._sim_params.command_node)
        self._first_voltage_ns: int | None = None  # stamp of the first voltage seen
        self._finished = False  # the voltage ending the run (duration_s) has come
        self._duration_ns = round(self._sim_params.duration_s * 1e9)
        self._stop_requested = False  # a signal asked the process to stop
        # with the topics created: discovery goes on meanwhile, in DDS's threads
        _warm_up(plant, state)
        period = plant_config.loop.period_s
        self._timer = self.create_timer(0.01 if self._lockstep else period, self._on_timer)

    def build(self, flat: dict[str, Any]) -> tuple[PlantConfig, InitialParams, SimulationParams]:
        config = PlantConfig(**{n: self.section(flat, n) for n in PLANT_SECTIONS})
        check_models_use(dict(flat))  # a value the plant would ignore is refused
        initial = self.section(flat, "initial")
        if not config.track.min_m <= initial.x_m <= config.track.max_m:
            raise ConfigError(f"initial.x_m = {initial.x_m} lies outside the track "
                              f"(track.min_m .. track.max_m = {config.track.min_m} .. "
                              f"{config.track.max_m} m)")
        return config, initial, self.section(flat, "simulation")

    def on_config(self, config: Any) -> None:
        self.get_logger().warning("plant parameters are read at start-up; restart to apply")

    def _wall_ns(self) -> int:
        """Now on the node's clock. Without a /clock override (``use_sim_time``) that is
        the system's realtime clock, which rcl reads as ``time.time_ns`` does, read here
        without building an rclpy Time (three calls a wall-clock cycle, 13 us each in a
        running graph: timers around them, 2026-12-05)."""
        clock = self.get_clock()
        if clock.ros_time_is_active:
            return clock.now().nanoseconds
        return time.time_ns()

    def _publish_sample(self) -> None:
        sample = self._sim.sample()
        if self._lockstep:
            self._stamp_ns = self._sim.time_ns
            if self._sim.index % self._sim_params.clock_every == 0:
                self._clock_pub.publish(clock_to_cdr(self._stamp_ns))
        else:
            self._stamp_ns = self._wall_ns()
        self._watchdog.sample(sample.index, self._stamp_ns)
        self._witness.sample(sample.index, self._stamp_ns)
        self._joint_pub.publish(joint_sample_to_cdr(
            JointSample(self._stamp_ns, sample.position_m, sample.angle_rad)))
        self._current_pub.publish(
            motor_sample_to_cdr(MotorSample(self._stamp_ns, sample.current_a)))
        if self._sim_params.publish_true_state:
            self._true_pub.publish(true_state_to_cdr(TrueState(self._stamp_ns, *sample.true_state)))
        self._published_ns = self._wall_ns()
        if self.routine_diagnostics(sample.index + 1):
            self.diagnose(OK, "simulating", self._stamp_ns, sample=sample.index,
                          deadline_misses=self._missed, stale_commands=self._stale,
                          resent_samples=self._resent, recorder_waits=self._recorder_waits)

    def request_stop(self) -> None:
        """Stop at the next callback (a signal handler's whole work: it may run in the
        middle of a cycle, which is then finished)."""
        self._stop_requested = True

    def _stopping(self) -> bool:
        """Whether to do nothing more: the run ended (``duration_s``) or a stop was
        asked for, in which case the node's context is shut down here, between cycles."""
        if self._stop_requested:
            if self.context.ok():
                self._name_the_stopped_stage(force=True)
                self.get_logger().info(f"stopping after sample {self._sim.index}")
                rclpy.try_shutdown(context=self.context)
            return True
        return self._finished

    def _on_timer(self) -> None:
        if self._stopping():
            return
        self._check_publishers()
        if self._lockstep:
            if not self._started:
                need = self._sim_params.min_subscribers
                if (self._joint_pub.get_subscription_count() >= need
                        and self._current_pub.get_subscription_count() >= need
                        and self._true_pub.get_subscription_count()
                        >= self._sim_params.min_true_state_subscribers
                        and self._clock_pub.get_subscription_count()
                        >= self._sim_params.min_clock_subscribers
                        and self._sub.get_publisher_count() > 0
                        and (self._progress_sub is None
                             or self._progress_sub.get_publisher_count() > 0)):
                    now = self._wall_ns()
                    if self._matched_ns is None:
                        self._matched_ns = now
                    if (now - self._matched_ns) * 1e-9 >= self._sim_params.start_settle_s:
                        self._started = True
                        self._recorded_ns = self._sim.time_ns
                        self._publish_sample()
                else:
                    self._matched_ns = None
            elif self._held_ns is not None:
                self._say_recorder_wait()
            else:
                waited_s = (self._wall_ns() - self._published_ns) * 1e-9
                if waited_s > self._sim_params.resend_after_s:
                    self._resent += 1
                    if self._watchdog.tripped_at is None:  # once per silence
                        self._watchdog.tripped_at = self._sim.index
                        self.diagnose(
                            ERROR, f"command watchdog: no command answered sample "
                            f"{self._sim.index} for {waited_s:.2f} s; simulated time stands "
                            f"still, no voltage is held over it; {self._silent_stage()}",
                            self._stamp_ns, sample=self._sim.index, applied_v=0.0,
                            silent=self._silent_stage(node_only=True))
                    self.diagnose(WARN, f"lockstep: no voltage answered sample {self._sim.index} "
                                  f"for {waited_s:.2f} s; sending it again", self._stamp_ns,
                                  resent=self._resent)
                    self._publish_sample()
            return
        if self._started:
            index = self._sim.index
            if not self._sim.answered:
                self._missed += 1
            if self._pin.intruders:
                self._sim.command(0.0)
            elif not self._sim.answered and self._watchdog.expired(index):
                self._sim.command(0.0)  # 0 V over this period
                if self._watchdog.tripped_at == index:
                    self.diagnose(
                        ERROR, f"command watchdog: no command answered samples "
                        f"{self._watchdog.answered + 1} .. {index}: 0 V from sample {index} "
                        "(the stage that stopped is named when it has fallen behind)",
                        self._stamp_ns, sample=index,
                        last_answered_sample=self._watchdog.answered, applied_v=0.0)
                    self._witness.trip(index, self._watchdog.answered)
            self._sim.advance()
        self._started = True
        self._publish_sample()
        self._name_the_stopped_stage()

    def _name_the_stopped_stage(self, force: bool = False) -> None:
        """After a trip, once the evidence is in (or ``force``: now), the stage that
        stopped, on /diagnostics with the trip's stamp and values."""
        if self._witness.pending is None:  # no trip to name a stage for
            return
        verdict = self._witness.verdict(self._upstream.read(), self._answered_ns, force=force)
        if verdict is None:
            return
        who = who_publishes(self, verdict.topic or self._command_topic)
        self.diagnose(
            ERROR, named_trip(verdict, who, self._command_topic), verdict.trip_stamp_ns,
            sample=verdict.trip, last_answered_sample=verdict.last_answered, applied_v=0.0,
            silent=who,
            named_at_sample=self._sim.index, behind=verdict.behind, sure=verdict.sure)

    def _on_voltage(self, msg: Any) -> None:
        if self._stopping():
            return
        self._watch_duration(msg)
        if not self._sim.plant.force_input:
            self._on_command(msg, "voltage command", "voltage_v")

    def _on_setpoint(self, msg: Any) -> None:
        if self._stopping():
            return
        self._on_command(msg, "current set-point", "setpoint_a")

    def _watch_duration(self, msg: Any) -> None:
        """The run's end, by pisc_graph's own rule (a voltage stamped ``duration_s`` after
        the first voltage, whatever answered): the plant publishes no sample after it."""
        duration_ns = self._duration_ns
        if not duration_ns:
            return
        stamp = stamp_from_msg(msg.header.stamp)
        if self._first_voltage_ns is None:
            self._first_voltage_ns = stamp
        if stamp - self._first_voltage_ns >= duration_ns and not self._finished:
            self._finished = True
            self.get_logger().info(f"the run's {self._sim_params.duration_s} s are over at "
                                   f"sample {self._sim.index}: no more samples")

    def _on_command(self, msg: Any, what: str, value_name: str) -> None:
        """A message of the topic that drives the plant; ``value_name`` is the argument of
        :func:`pisc_plant.command.plant_command` its value is (set-point or voltage)."""
        sample = self.parse(msg, motor_sample_from_msg, what, WARN)
        if sample is None:
            return
        stamp_ns = sample.stamp_ns
        command = plant_command(self._sim.plant.config, **{value_name: sample.value})
        self._check_publishers()
        if not self._started:
            return
        answers = self._watchdog.fresh(stamp_ns)
        if stamp_ns != self._stamp_ns:
            self._stale += 1
            if self._lockstep or answers is None:
                # lockstep only takes the awaited sample; on the wall clock a command older
                # than the watchdog's window is not fresh and drives nothing
                return
        # while another publisher is there, nothing on the topic drives the motor, nor do
        # answers to samples from before its departure was seen (PublisherPin.admits)
        admitted = self._pin.admits(stamp_ns)
        value = command if admitted else 0.0
        if admitted:
            self._answered_ns = max(self._answered_ns, stamp_ns)
            resumed = self._watchdog.answer(answers)
            if resumed is not None:
                self._witness.resumed()
                self.diagnose(OK, f"command watchdog: commands resumed at sample {answers} "
                              f"(0 V from sample {resumed})", self._stamp_ns)
        if self._lockstep:
            self._sim.command(value)
            if self._finished:
                return  # the run is over: no sample after it
            self._sim.advance()
            self._publish_when_recorded()
        else:
            delay_s = (self._wall_ns() - self._published_ns) * 1e-9
            self._sim.command(value, delay_s)

    # -- lockstep: the recorder keeps up -----------------------------------------------

    def _publish_when_recorded(self) -> None:
        """Lockstep: the next sample now, or once the recorder has written the sample
        ``recorder_lag_samples`` periods before it (:meth:`_on_progress`)."""
        if self._progress_sub is not None and (
                self._sim.time_ns - self._recorded_ns > self._lag_ns):
            self._held_ns = self._wall_ns()
            self._hold_said = False
            self._recorder_waits += 1
            return
        self._publish_sample()

    def _on_progress(self, msg: Any) -> None:
        self._recorded_ns = max(self._recorded_ns, stamp_from_msg(msg.clock))
        if self._held_ns is not None and not self._stopping() and (
                self._sim.time_ns - self._recorded_ns <= self._lag_ns):
            if self._hold_said:
                self.diagnose(OK, f"lockstep: the recorder caught up; sample "
                              f"{self._sim.index} published", self._stamp_ns,
                              recorder_waits=self._recorder_waits)
            self._held_ns = None
            self._publish_sample()

    def _say_recorder_wait(self) -> None:
        """Timer: a sample held for the recorder longer than ``resend_after_s`` is said
        once (the recorder may be stopped or starved; pisc_graph stops a run whose
        recorder died)."""
        if self._hold_said:
            return
        waited_s = (self._wall_ns() - self._held_ns) * 1e-9
        if waited_s > self._sim_params.resend_after_s:
            self._hold_said = True
            said = (f"lockstep: waiting for the recorder: sample {self._sim.index} is held "
                    f"for {waited_s:.2f} s; the recorder has written the samples up to "
                    f"{self._recorded_ns * 1e-9:.3f} s, and the plant runs at most "
                    f"{self._sim_params.recorder_lag_samples} samples ahead of it")
            self.get_logger().warning(said)
            self.diagnose(WARN, said, self._stamp_ns, sample=self._sim.index,
                          recorded_ns=self._recorded_ns, recorder_waits=self._recorder_waits)

    # -- who drives the motor, and who stopped ------------------------------------------

    def _check_publishers(self) -> None:
        """Pin the graph's command publisher; a fault while any other one is matched.

        Cheap on every call (the subscription's matched count); the ROS graph is asked
        who the publishers are only when that count changes or an intruder is there.
        """
        matched = self._command_sub.get_publisher_count()
        if not self._pin.needs_look(matched):
            return
        # before the first sample no answer to any sample can be queued: nothing to fence
        # off when a publisher the graph did not name yet turns out to be the pinned one
        newest_ns = self._stamp_ns if self._started else -1
        change = self._pin.look(matched, listed_publishers(self, self._command_topic.name),
                                newest_ns)
        if change is None:
            return
        if change.intruders:
            intruders = ", ".join(change.intruders)
            if self._started and not self._lockstep:
                self._sim.command(0.0, (self._wall_ns() - self._published_ns) * 1e-9)
            self.diagnose(
                ERROR, f"another publisher on {self._command_topic.name}: "
                f"{intruders}; the plant applies 0 V while it is there (only "
                f"/{self._sim_params.command_node}, pinned at the start, drives the motor)",
                self._stamp_ns, intruders=intruders, sample=self._sim.index,
                applied_v=0.0)
        else:
            self.diagnose(OK, f"{', '.join(change.left)} left "
                          f"{self._command_topic.name}: commands apply again", self._stamp_ns,
                          sample=self._sim.index)

    def _silent_stage(self, node_only: bool = False) -> str:
        """Lockstep: the first stage of the chain with no output for the current sample,
        and who publishes it (:func:`pisc_msgs_py.watchdog.silent_stage_report`)."""
        sentence, who = silent_stage_report(self, self._stamp_ns, self._upstream.read(),
                                            self._sim.index, self._command_topic)
        return who if node_only else sentence


def main(args: list[str] | None = None) -> int:
    def stop_between_cycles(**kwargs: Any) -> PlantNode:
        node = PlantNode(**kwargs)
        # after rclpy.init: these replace rclpy's handlers, which shut the context down at
        # once, in the middle of a cycle (module docstring, "A clean stop")
        for signum in (signal.SIGTERM, signal.SIGINT):
            signal.signal(signum, lambda *_: node.request_stop())
        return node

    return run_node(stop_between_cycles, args)


if __name__ == "__main__":
    raise SystemExit(main())
