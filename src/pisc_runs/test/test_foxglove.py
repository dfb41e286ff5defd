"""pisc_graph --foxglove: a real client of Foxglove's WebSocket protocol subscribes to every
channel the run advertises and decodes a message of each with the schema advertised
for it; the run's voltages are those of a run without the server; a port in use is
refused with its number before the run starts."""

from __future__ import annotations

import asyncio
import base64
import json
import socket
import struct
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from pisc_bag.bag import read_bag_raw
from pisc_runs.foxglove_live import LIVE_TOPICS, SCENE_TOPIC
from pisc_msgs_py.processes import console_command
from pisc_msgs_py.topics import VOLTAGE

pytestmark = pytest.mark.integration

# foxglove-sdk names Foxglove's WebSocket protocol v1 "foxglove.sdk.v1" and refuses the
# protocol's first name, "foxglove.websocket.v1", in every version on PyPI (docs/foxglove.md,
# "Protocol"): the client offers the one name the server accepts
SUBPROTOCOL = "foxglove.sdk.v1"
LEGACY_SUBPROTOCOL = "foxglove.websocket.v1"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def graph(bag: Path, env: dict[str, str], *extra: str) -> subprocess.Popen:
    return subprocess.Popen([*console_command("pisc_graph", "pisc_bringup.graph_cli"), "--bag",
                             str(bag), "--duration", "8", *extra], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)


async def first_messages(port: int, child: subprocess.Popen, timeout_s: float
                         ) -> tuple[dict[int, dict], dict[int, bytes]]:
    """Connect as soon as the server listens, subscribe to every advertised channel,
    and keep the first message of each: (channels by id, payloads by channel id)."""
    import websockets

    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout_s
    while True:
        try:
            ws = await websockets.connect(f"ws://127.0.0.1:{port}", subprotocols=[SUBPROTOCOL],
                                          max_size=None)
            break
        except OSError:
            if child.poll() is not None or loop.time() > deadline:
                raise AssertionError("the server never listened") from None
            await asyncio.sleep(0.05)
    assert ws.subprotocol == SUBPROTOCOL
    channels: dict[int, dict] = {}
    by_subscription: dict[int, int] = {}
    first: dict[int, bytes] = {}
    async with ws:
        while loop.time() < deadline and not (channels and set(first) == set(channels)):
            try:
                frame = await asyncio.wait_for(ws.recv(), max(0.05, deadline - loop.time()))
            except (TimeoutError, asyncio.TimeoutError):
                break
            if isinstance(frame, str):
                message = json.loads(frame)
                if message["op"] == "advertise":
                    subscriptions = []
                    for channel in message["channels"]:
                        channels[channel["id"]] = channel
                        sid = len(by_subscription) + 1
                        by_subscription[sid] = channel["id"]
                        subscriptions.append({"id": sid, "channelId": channel["id"]})
                    await ws.send(json.dumps({"op": "subscribe",
                                              "subscriptions": subscriptions}))
            elif frame[0] == 0x01:  # message data: op, subscription id, log time, payload
                sid, _ = struct.unpack_from("<IQ", frame, 1)
                first.setdefault(by_subscription[sid], bytes(frame[13:]))
    return channels, first


def decode(channel: dict, payload: bytes):
    """A payload decoded with nothing but what the channel advertised."""
    if channel["encoding"] == "cdr":
        from rosbags.typesys import Stores, get_types_from_msg, get_typestore

        assert channel["schemaEncoding"] == "ros2msg"
        store = get_typestore(Stores.EMPTY)
        store.register(get_types_from_msg(channel["schema"], channel["schemaName"]))
        return store.deserialize_cdr(payload, channel["schemaName"])
    assert (channel["encoding"], channel["schemaEncoding"]) == ("protobuf", "protobuf")
    from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

    files = descriptor_pb2.FileDescriptorSet.FromString(base64.b64decode(channel["schema"]))
    pool = descriptor_pool.DescriptorPool()
    for f in files.file:
        pool.Add(f)
    cls = message_factory.GetMessageClass(pool.FindMessageTypeByName(channel["schemaName"]))
    return cls.FromString(payload)


def test_foxglove_serves_every_topic_and_the_scene_and_leaves_the_voltages(tmp_path,
                                                                            env_for_domain):
    port = free_port()
    child = graph(tmp_path / "live", env_for_domain, "--foxglove", str(port))
    result: dict = {}
    thread = threading.Thread(target=lambda: result.update(
        got=asyncio.run(first_messages(port, child, 120.0))))
    thread.start()
    out, err = child.communicate(timeout=300)
    thread.join(timeout=130)
    assert child.returncode in (0, 1), err.decode()
    channels, first = result["got"]
    topics = {c["topic"]: c for c in channels.values()}
    assert set(topics) == {t.name for t in LIVE_TOPICS} | {SCENE_TOPIC}
    for topic in LIVE_TOPICS:
        assert topics[topic.name]["schemaName"] == topic.type
    assert set(first) == set(channels), "no message on " + ", ".join(
        sorted(c["topic"] for i, c in channels.items() if i not in first))
    decoded = {channels[i]["topic"]: decode(channels[i], data) for i, data in first.items()}
    assert len(decoded["/pisc/joint_states"].position) == 2
    assert decoded["/pisc/motor/voltage"].name == ["motor"]
    assert any(s.message in ("swing_up", "catch") for s in decoded["/pisc/mode"].status)
    scene = decoded[SCENE_TOPIC]
    ids = {e.id for e in scene.entities}
    assert {"track/0", "cart/0", "pendulum/0", "safe_range/0"} <= ids
    cart = next(e for e in scene.entities if e.id == "cart/0")
    assert len(cart.cubes) == 1 and cart.frame_id == "world"
    # the same run without the server: the same voltages, bit for bit
    plain = graph(tmp_path / "plain", env_for_domain)
    _, err = plain.communicate(timeout=300)
    assert plain.returncode in (0, 1), err.decode()
    live = [m.data for m in read_bag_raw(tmp_path / "live", [VOLTAGE.name])]
    alone = [m.data for m in read_bag_raw(tmp_path / "plain", [VOLTAGE.name])]
    assert len(live) == 1601 and live == alone


def test_the_sdk_server_speaks_the_protocol_under_its_new_name_only():
    """What docs/foxglove.md says of the pinned foxglove-sdk: a client that offers only
    "foxglove.websocket.v1" (older Lichtblick releases) is refused with 400;
    offered "foxglove.sdk.v1", the server takes it and sends its serverInfo."""
    import foxglove
    import websockets
    from websockets.exceptions import InvalidStatus

    server = foxglove.start_server(name="pisc-test", host="127.0.0.1", port=0)

    async def offer(names: list[str]):
        async with websockets.connect(f"ws://127.0.0.1:{server.port}",
                                      subprotocols=names) as ws:
            return ws.subprotocol, json.loads(await asyncio.wait_for(ws.recv(), 10.0))

    try:
        with pytest.raises(InvalidStatus) as refused:
            asyncio.run(offer([LEGACY_SUBPROTOCOL]))
        assert refused.value.response.status_code == 400
        assert b"sec-websocket-protocol" in refused.value.response.body
        chosen, info = asyncio.run(offer([SUBPROTOCOL]))
        assert chosen == SUBPROTOCOL and info["op"] == "serverInfo"
        assert info["name"] == "pisc-test"
    finally:
        server.stop()


def test_a_port_in_use_is_refused_with_its_number_before_the_run(tmp_path, env_for_domain):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        child = graph(tmp_path / "bag", env_for_domain, "--foxglove", str(port))
        _, err = child.communicate(timeout=120)
    assert child.returncode == 2
    assert f"port {port} on 127.0.0.1 is in use" in err.decode()
    assert not (tmp_path / "bag").exists()


def test_the_bridge_alone_refuses_a_port_in_use(tmp_path):
    params = tmp_path / "p.yaml"
    params.write_text("/**:\n  ros__parameters: {}\n")
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        port = taken.getsockname()[1]
        done = subprocess.run([sys.executable, "-m", "pisc_runs.foxglove_node", "--port",
                               str(port), "--params", str(params)], capture_output=True,
                              text=True, timeout=60)
    assert done.returncode == 2 and f"port {port}" in done.stderr


def test_bag_play_serves_the_bag_and_refuses_a_port_in_use(tmp_path, env_for_domain):
    bag = Path(__file__).resolve().parents[3] / "bags" / "default-swingup"
    port = free_port()
    command = [*console_command("pisc_bag", "pisc_bringup.bag_cli"), "play", str(bag),
               "--rate", "0", "--wait-subscribers", "0", "--topic", "/pisc/joint_states"]
    done = subprocess.run([*command, "--foxglove", str(port)], env=env_for_domain,
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert f"serving ws://127.0.0.1:{port}" in done.stdout
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", port))
        taken.listen()
        done = subprocess.run([*command, "--foxglove", str(port)], env=env_for_domain,
                              capture_output=True, text=True, timeout=120)
    assert done.returncode == 2 and f"port {port} on 127.0.0.1 is in use" in done.stderr
