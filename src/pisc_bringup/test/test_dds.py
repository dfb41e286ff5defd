"""PISC's Fast DDS profile and the DDS environment pisc_graph gives its processes."""

from __future__ import annotations

import os
import subprocess
import sys
import xml.etree.ElementTree as ET

from pisc_bringup.dds import (
    DISCOVERY_RANGE,
    FASTDDS_PROFILE,
    FASTDDS_PROFILES,
    dds_environment,
)

# a node with a reliable publisher: Fast DDS reads the profile when its first participant
# is made, and names what it cannot parse (on stdout, its log's console)
_NODE = """
import rclpy
from rclpy.node import Node
from sensor_msgs.msg import JointState
rclpy.init()
node = Node("profile_probe")
node.create_publisher(JointState, "/profile_probe", 10)
node.destroy_node()
rclpy.shutdown()
print("made")
"""

NS = {"f": "http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles"}


def _make_a_node(profile, env_for_domain):
    env = dict(env_for_domain, **{FASTDDS_PROFILES: str(profile)})
    return subprocess.run([sys.executable, "-c", _NODE], env=env, capture_output=True,
                          text=True, timeout=60)


def test_fast_dds_reads_the_profile_without_an_error(env_for_domain, tmp_path):
    good = _make_a_node(FASTDDS_PROFILE, env_for_domain)
    assert good.returncode == 0 and good.stdout == "made\n", good.stdout + good.stderr
    # and the check sees an error: the same profile with a duration that is not a number
    broken = tmp_path / "broken.xml"
    broken.write_text(FASTDDS_PROFILE.read_text().replace("<sec>0</sec>", "<sec>zero</sec>"))
    bad = _make_a_node(broken, env_for_domain)
    said = bad.stdout + bad.stderr
    assert "XMLPARSER" in said and "<heartbeatPeriod>" in said, said


def _seconds(duration):
    sec, nanosec = (int(duration.find(f"f:{unit}", NS).text) for unit in ("sec", "nanosec"))
    return sec + nanosec * 1e-9


def test_the_profile_is_the_default_writers_with_a_heartbeat_every_100_ms():
    """... and requests to send a message again ignored for 100 ms after it was sent
    (nackSupressionDuration: one armed timer for the messages of 100 ms, fastdds.xml); the
    default participant's event thread and built-in flow controllers' thread at
    SCHED_BATCH."""
    root = ET.parse(FASTDDS_PROFILE).getroot()
    writers = root.findall("f:data_writer", NS)
    assert len(writers) == 1 and writers[0].get("is_default_profile") == "true"
    assert _seconds(writers[0].find("f:times/f:heartbeatPeriod", NS)) == 0.1
    assert _seconds(writers[0].find("f:times/f:nackSupressionDuration", NS)) == 0.1
    participants = root.findall("f:participant", NS)
    assert len(participants) == 1 and participants[0].get("is_default_profile") == "true"
    for thread in ("timed_events_thread", "builtin_controllers_sender_thread"):
        policy = participants[0].find(f"f:rtps/f:{thread}/f:scheduling_policy", NS)
        assert int(policy.text) == os.SCHED_BATCH == 3
    # nothing else: the ROS QoS of every topic stays the code's (qos_profile)
    assert [e.tag.split("}")[1] for e in root.iter()] == [
        "profiles", "participant", "rtps", "timed_events_thread", "scheduling_policy",
        "builtin_controllers_sender_thread", "scheduling_policy", "data_writer", "times", "heartbeatPeriod", "sec", "nanosec",
        "nackSupressionDuration", "sec", "nanosec"]


# every thread of a process with a node and a reliable publisher (which starts the
# built-in flow controllers' thread, dds.asyn.N.M): its name and scheduling policy.
# Fast DDS names a thread and applies its settings in the thread itself as it starts:
# under load the listing could come between the two (once, in a suite run of 2026-12-05:
# no thread at SCHED_BATCH yet). The probe waits up to 10 s for those two threads to run
# at anything but SCHED_OTHER, then lists every thread.
_THREADS = """
import os, time
import rclpy
from rclpy.node import Node
from rclpy.qos import QoSProfile, ReliabilityPolicy
from std_msgs.msg import String
rclpy.init()
node = Node("threads_probe")
publisher = node.create_publisher(String, "/probe", QoSProfile(
    depth=10, reliability=ReliabilityPolicy.RELIABLE))
publisher.publish(String(data="x"))

def policies(prefix):
    out = []
    for task in os.listdir("/proc/self/task"):
        with open(f"/proc/self/task/{task}/comm") as comm:
            if comm.read().strip().startswith(prefix):
                out.append(os.sched_getscheduler(int(task)))
    return out

deadline = time.monotonic() + 10.0
while (not all(p != os.SCHED_OTHER for prefix in ("dds.ev.", "dds.asyn.")
               for p in policies(prefix) or [os.SCHED_OTHER])
       and time.monotonic() < deadline):
    time.sleep(0.01)
for task in sorted(os.listdir("/proc/self/task")):
    with open(f"/proc/self/task/{task}/comm") as comm:
        print(comm.read().strip(), os.sched_getscheduler(int(task)))
node.destroy_node()
rclpy.shutdown()
"""


def test_with_the_profile_only_fast_dds_event_and_flow_controller_threads_run_at_sched_batch(
        env_for_domain):
    env = dict(env_for_domain, **{FASTDDS_PROFILES: str(FASTDDS_PROFILE)})
    done = subprocess.run([sys.executable, "-c", _THREADS], env=env, capture_output=True,
                          text=True, timeout=60)
    assert done.returncode == 0, done.stdout + done.stderr
    threads = [(name, int(policy)) for name, policy in
               (line.rsplit(" ", 1) for line in done.stdout.splitlines())]
    batch = {name for name, policy in threads if policy == os.SCHED_BATCH}
    assert "dds.ev.0" in batch and len(batch) >= 2 and all(
        name.startswith("dds.asyn.") for name in batch - {"dds.ev.0"}), threads
    # the transports' receive threads (dds.shm.N, dds.udp.N) deliver messages between
    # processes: they keep the process's policy, as every other thread does
    assert any(name.startswith("dds.shm.") for name, _ in threads), threads
    assert {policy for name, policy in threads if name not in batch} == {os.SCHED_OTHER}
    # without the profile every thread keeps the process's policy
    bare = {k: v for k, v in env_for_domain.items() if k != FASTDDS_PROFILES}
    done = subprocess.run([sys.executable, "-c", _THREADS.replace("10.0", "0.5")],
                          env=bare, capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stdout + done.stderr
    assert {line.rsplit(" ", 1)[1] for line in done.stdout.splitlines()} == {"0"}, done.stdout


def test_the_environment_gets_the_profile_and_local_discovery_unless_it_has_its_own():
    assert dds_environment({}) == {DISCOVERY_RANGE: "LOCALHOST",
                                   FASTDDS_PROFILES: str(FASTDDS_PROFILE)}
    own = {DISCOVERY_RANGE: "SUBNET", FASTDDS_PROFILES: "/etc/my_profile.xml"}
    assert dds_environment(dict(own)) == own
    assert FASTDDS_PROFILE.is_file()
