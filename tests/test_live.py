"""The live view (``--live``): a run served over Foxglove's WebSocket protocol while it goes.

The client here is not the project's code: ``websockets`` speaking the protocol as written in
Foxglove's spec (subprotocol, advertise, subscribe, binary message data), and Foxglove's own
ROS 2 CDR decoder (mcap-ros2-support) for the payloads. The answer it is held to is the same
run's MCAP, read with the official mcap reader.
"""

from __future__ import annotations

import asyncio
import io
import json
import os
import signal
import socket
import struct
import subprocess
import sys
import textwrap
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest
from mcap.reader import make_reader

from ballbeam.logs.mcap_file import McapFile, OpenChunk, records_messages
from ballbeam.logs.recorder import Recorder
from ballbeam.logs.schema import StructSchema
from ballbeam.runtime.live import LiveView

from .conftest import PAPER, REPO, ballbeam, ballbeam_argv

websockets = pytest.importorskip("websockets")
decoder_module = pytest.importorskip("mcap_ros2.decoder")
dynamic = pytest.importorskip("mcap_ros2._dynamic")

# The SDK's current subprotocol first, the spec's original name second: the server picks one.
SUBPROTOCOLS = ["foxglove.sdk.v1", "foxglove.websocket.v1"]
MESSAGE_DATA = 0x01  # binary opcode: subscription id (u32), log time (u64), payload
MESSAGE_HEAD = struct.Struct("<BIQ")
WATCHED = ("/truth", "/command")
RUN_S = 2.0


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


@dataclass
class Session:
    """What the client saw: the server's channels and each subscribed message."""

    advertised: dict[str, dict[str, Any]] = field(default_factory=dict)
    received: dict[str, list[tuple[int, bytes]]] = field(default_factory=dict)
    subprotocol: str | None = None
    statuses: list[dict[str, Any]] = field(default_factory=list)


async def watch(
    port: int, process: subprocess.Popen[str], give_up_s: float,
    subprotocols: list[str] = SUBPROTOCOLS,
) -> Session:
    """Connect as soon as the server is up, subscribe to WATCHED, read until it goes away."""
    session = Session()
    deadline = time.monotonic() + give_up_s
    while True:
        try:
            connection = await websockets.connect(
                f"ws://127.0.0.1:{port}", subprotocols=subprotocols, max_size=None
            )
            break
        except OSError:
            if process.poll() is not None or time.monotonic() > deadline:
                raise AssertionError("the live server never accepted a connection") from None
            await asyncio.sleep(0.02)
    session.subprotocol = connection.subprotocol
    by_subscription: dict[int, str] = {}
    async with connection:
        try:
            async for frame in connection:
                if isinstance(frame, str):
                    message = json.loads(frame)
                    if message["op"] == "status":
                        session.statuses.append(message)
                    if message["op"] != "advertise":
                        continue
                    wanted = []
                    for channel in message["channels"]:
                        session.advertised[channel["topic"]] = channel
                        if channel["topic"] in WATCHED:
                            subscription = len(by_subscription) + 1
                            by_subscription[subscription] = channel["topic"]
                            wanted.append({"id": subscription, "channelId": channel["id"]})
                    if wanted:
                        await connection.send(
                            json.dumps({"op": "subscribe", "subscriptions": wanted})
                        )
                elif frame[0] == MESSAGE_DATA:
                    _, subscription, log_time_ns = MESSAGE_HEAD.unpack_from(frame)
                    topic = by_subscription[subscription]
                    payload = bytes(frame[MESSAGE_HEAD.size :])
                    session.received.setdefault(topic, []).append((log_time_ns, payload))
        except websockets.ConnectionClosed:
            pass  # the run is over: the daemon stopped its server
    return session


def read_mcap(path: Path) -> tuple[dict[str, Any], dict[str, list[tuple[int, Any]]]]:
    """The log's channels (topic → channel, schema) and the WATCHED messages, decoded."""
    with path.open("rb") as stream:
        reader = make_reader(stream, decoder_factories=[decoder_module.DecoderFactory()])
        summary = reader.get_summary()
        assert summary is not None
        channels = {
            channel.topic: (channel, summary.schemas[channel.schema_id])
            for channel in summary.channels.values()
        }
        decoded: dict[str, list[tuple[int, Any]]] = {topic: [] for topic in WATCHED}
        for _, channel, message, value in reader.iter_decoded_messages(topics=list(WATCHED)):
            decoded[channel.topic].append((message.log_time, value))
    return channels, decoded


def fields_of(value: Any) -> dict[str, Any]:
    return {name: getattr(value, name) for name in value.__slots__}


@pytest.mark.bus
@pytest.mark.parametrize(
    "offered",
    [
        SUBPROTOCOLS,
        # Only the older name: @foxglove/ws-protocol's FoxgloveClient, Lichtblick, older
        # Foxglove Studio (the SDK's own server answers them HTTP 400).
        ["foxglove.websocket.v1"],
    ],
)
def test_a_websocket_client_sees_the_runs_messages_as_the_mcap_records_them(
    tmp_path: Path, offered: list[str]
) -> None:
    port = free_port()
    process = subprocess.Popen(
        [
            *ballbeam_argv("run", str(PAPER), "--live", "--live-port", str(port), "--json"),
            "--set", f"run.log_dir='{tmp_path}'", "--set", f"run.duration_s={RUN_S}",
        ],
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        session = asyncio.run(watch(port, process, give_up_s=120.0, subprotocols=offered))
        stdout, stderr = process.communicate(timeout=300)
    finally:
        if process.poll() is None:
            process.kill()
            process.communicate()
    assert process.returncode == 0, stderr
    assert f"ws://127.0.0.1:{port}" in stderr  # run says where to connect
    summary = json.loads(stdout)
    assert summary["mode"] == "lockstep"
    channels, recorded = read_mcap(Path(summary["log_path"]))

    # Same topics, schema names and encodings, message encodings and schema text as the file.
    assert session.subprotocol in offered
    # Level 2 is an error, e.g. "Unknown channel ID" for a subscription the server refused.
    assert not [status for status in session.statuses if status.get("level") == 2], (
        session.statuses
    )
    assert set(session.advertised) == set(channels)
    for topic, advertised in session.advertised.items():
        channel, schema = channels[topic]
        assert advertised["encoding"] == channel.message_encoding, topic
        assert advertised["schemaName"] == schema.name, topic
        assert advertised["schemaEncoding"] == schema.encoding, topic
        assert advertised["schema"] == schema.data.decode(), topic

    for topic in WATCHED:
        received = session.received.get(topic, [])
        expected = recorded[topic]
        assert len(expected) >= RUN_S * 1000 * 0.99, topic
        # Live means while it goes, not afterwards: most of the run came through (a client
        # that falls behind loses its oldest messages rather than slowing the run).
        assert len(received) >= 0.5 * len(expected), (topic, len(received), len(expected))
        advertised = session.advertised[topic]
        decode = dynamic.generate_dynamic(advertised["schemaName"], advertised["schema"])[
            advertised["schemaName"]
        ]
        # Every received message is the file's message with the same log time and values,
        # in the file's order.
        position = 0
        for log_time_ns, payload in received:
            while position < len(expected) and expected[position][0] != log_time_ns:
                position += 1
            assert position < len(expected), (topic, log_time_ns, "not in the log, or out of order")
            assert fields_of(decode(payload)) == fields_of(expected[position][1]), (
                topic, log_time_ns
            )
            position += 1
    truth_values = [fields_of(decode_value) for _, decode_value in recorded["/truth"][:1]]
    assert truth_values and truth_values[0]["ball_position_m"] > 0.19  # the paper's start


def test_a_taken_port_is_one_line_and_exit_2() -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as holder:
        holder.bind(("127.0.0.1", 0))
        holder.listen()
        port = holder.getsockname()[1]
        for command in ("run", "daemon"):
            result = ballbeam(command, "--live", "--live-port", str(port), timeout_s=120)
            assert result.returncode == 2, (command, result.stderr)
            lines = result.stderr.strip().splitlines()
            assert len(lines) == 1, (command, result.stderr)
            assert f"ws://127.0.0.1:{port}" in lines[0]
            assert "already in use" in lines[0]
            assert "Traceback" not in result.stderr


def test_live_port_without_live_is_refused() -> None:
    result = ballbeam("daemon", "--live-port", "9000", timeout_s=120)
    assert result.returncode == 2
    assert result.stderr.strip() == "ballbeam: error: --live-port needs --live"


class _FailingTap:
    """A tap that fails on its first chunk: the recording must go on without it."""

    def __init__(self) -> None:
        self.channels: list[str] = []

    def add_channel(
        self, channel_id: int, topic: str, message_encoding: str, schema_name: str,
        schema_encoding: str, schema_data: bytes,
    ) -> None:
        self.channels.append(topic)

    def take(self, chunk: OpenChunk) -> None:
        raise RuntimeError("viewer gone")

    def stats(self) -> dict[str, str]:
        return {}


def test_a_failing_tap_never_stops_the_recording() -> None:
    schema = StructSchema("test/Value", (("value", "float64"),))
    buffer = io.BytesIO()
    tap = _FailingTap()
    with Recorder(buffer, tap=tap, flush_interval_s=0.001) as recorder:
        handle = recorder.add_struct_channel("/value", schema)
        for index in range(2_000):
            recorder.record(handle, 1_000 + index, (float(index),))
            if index == 1_000:
                time.sleep(0.02)  # let the writer take a chunk (and the tap fail) mid-run
    assert tap.channels == ["/value"]
    reader = make_reader(io.BytesIO(buffer.getvalue()))
    assert sum(1 for _ in reader.iter_messages()) == 2_000
    live = {record.name: record.metadata for record in reader.iter_metadata()}["live"]
    assert live["failed"] == "RuntimeError: viewer gone"


def test_a_chunks_records_read_back_as_the_messages_put_in() -> None:
    mcap = McapFile(io.BytesIO(), profile="test", library="test")
    schema_id = mcap.add_schema("s", "ros2msg", b"float64 value")
    first = mcap.add_channel("/a", "cdr", schema_id)
    second = mcap.add_channel("/b", "cdr", schema_id)
    sent = [(first if index % 3 else second, 1_000 + index, bytes([index]) * index)
            for index in range(50)]
    for channel_id, log_time_ns, payload in sent:
        mcap.add_message(channel_id, log_time_ns, payload)
    chunk = mcap.take_chunk()
    assert chunk is not None
    assert list(records_messages(bytes(chunk.records))) == sent


def _recorded_run(live: LiveView, messages: int, during: Any = None) -> dict[str, str]:
    """Record ``messages`` values through a recorder tapped by ``live`` (``during(index)`` on
    each); every one must be in the file, whatever the view did. The log's "live" record."""
    schema = StructSchema("test/Value", (("value", "float64"),))
    buffer = io.BytesIO()
    with Recorder(buffer, tap=live, flush_interval_s=0.002) as recorder:
        handle = recorder.add_struct_channel("/value", schema)
        live.start()
        for index in range(messages):
            recorder.record(handle, 1_000 + index, (float(index),))
            if during is not None:
                during(index)
    live.stop()
    reader = make_reader(io.BytesIO(buffer.getvalue()))
    assert sum(1 for _ in reader.iter_messages()) == messages
    return {record.name: record.metadata for record in reader.iter_metadata()}["live"]


def _ended(pid: int, within_s: float) -> bool:
    """Whether process ``pid`` is gone (or a zombie nobody reaps) within ``within_s``."""
    deadline = time.monotonic() + within_s
    while time.monotonic() < deadline:
        try:
            with open(f"/proc/{pid}/stat", encoding="ascii") as stat:
                if stat.read().rsplit(")", 1)[1].split()[0] == "Z":
                    return True
        except FileNotFoundError:
            return True
        time.sleep(0.02)
    return False


def test_the_view_reports_both_processes() -> None:
    live = LiveView(free_port())
    record = _recorded_run(live, 2_000, lambda index: time.sleep(0.01) if index == 1_000 else None)
    assert int(record["chunks"]) >= 1 and record["chunks_dropped"] == "0"
    assert int(record["server_chunks"]) == int(record["chunks"])  # every handed chunk read
    assert record["server_messages_forwarded"] == "0"  # no client: nothing to forward
    assert int(record["server_cpu_ns"]) >= int(record["server_startup_cpu_ns"]) > 0
    assert int(record["daemon_cpu_ns"]) > 0
    assert _ended(live.server_pid, 1.0)


def test_a_dead_live_server_is_dropped_and_the_recording_goes_on() -> None:
    live = LiveView(free_port())

    def kill_server(index: int) -> None:
        if index == 500:
            os.kill(live.server_pid, signal.SIGKILL)
        if index % 100 == 0:
            time.sleep(0.005)  # let the writer take chunks after the kill

    record = _recorded_run(live, 2_000, kill_server)
    assert record["failed"].startswith("LiveViewError: the live view's server process is gone")


def test_a_stalled_live_server_never_holds_up_the_recording() -> None:
    """A server that reads nothing (stopped): chunks the pipe cannot take leave the view, the
    recording takes them all. Resumed before the end, it ends as usual."""
    live = LiveView(free_port())
    schema = StructSchema("test/Blob", (("blob", "uint8[4096]"),))
    payload = (bytes(4096),)
    buffer = io.BytesIO()
    messages = 1_500  # ~6 MiB: several times the pipe's 1 MiB
    with Recorder(buffer, tap=live, flush_interval_s=0.002) as recorder:
        handle = recorder.add_struct_channel("/blob", schema)
        live.start()
        os.kill(live.server_pid, signal.SIGSTOP)
        try:
            for index in range(messages):
                recorder.record(handle, 1_000 + index, payload)
                if index % 50 == 0:
                    time.sleep(0.004)
        finally:
            os.kill(live.server_pid, signal.SIGCONT)
    live.stop()
    assert recorder.dropped == 0
    reader = make_reader(io.BytesIO(buffer.getvalue()))
    assert sum(1 for _ in reader.iter_messages()) == messages
    record = {r.name: r.metadata for r in reader.iter_metadata()}["live"]
    assert int(record["chunks_dropped"]) > 0
    assert "failed" not in record


def test_the_live_server_ends_with_its_daemon() -> None:
    """However the daemon's process ends (here SIGKILL: no clean-up at all), its server ends."""
    script = textwrap.dedent(f"""
        import os, signal, sys
        from ballbeam.runtime.live import LiveView
        live = LiveView({free_port()})
        live.add_channel(1, "/value", "cdr", "test/Value", "ros2msg", b"float64 value")
        live.start()
        print(live.server_pid, flush=True)
        os.kill(os.getpid(), signal.SIGKILL)
    """)
    daemon = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=120, check=False
    )
    assert daemon.returncode == -signal.SIGKILL, daemon.stderr
    assert _ended(int(daemon.stdout.strip()), 10.0)


def test_the_relay_asks_the_sdk_for_its_name_only_for_an_old_only_client() -> None:
    from ballbeam.runtime.live_relay import translated_answer, translated_request

    def request(*protocol_lines: str) -> bytes:
        lines = ["GET / HTTP/1.1", "Host: 127.0.0.1:8765", "Upgrade: websocket",
                 *protocol_lines, "Sec-WebSocket-Version: 13"]
        return ("\r\n".join(lines) + "\r\n\r\n").encode()

    old_only = translated_request(request("sec-websocket-protocol: foxglove.websocket.v1"))
    assert old_only == request("Sec-WebSocket-Version: 13").replace(
        b"Sec-WebSocket-Version: 13\r\nSec-WebSocket-Version: 13",
        b"Sec-WebSocket-Version: 13\r\nSec-WebSocket-Protocol: foxglove.sdk.v1",
    )
    # Offers the SDK can answer itself pass as they are (the SDK picks its own name).
    for lines in (
        ["Sec-WebSocket-Protocol: foxglove.websocket.v1, foxglove.sdk.v1"],
        ["Sec-WebSocket-Protocol: foxglove.websocket.v1", "Sec-WebSocket-Protocol: "
         "foxglove.sdk.v1.1"],
        ["Sec-WebSocket-Protocol: something.else"],
        [],
    ):
        assert translated_request(request(*lines)) is None, lines
    upgraded = (b"HTTP/1.1 101 Switching Protocols\r\nConnection: Upgrade\r\n"
                b"sec-websocket-protocol: foxglove.sdk.v1\r\nUpgrade: websocket\r\n\r\n")
    assert translated_answer(upgraded) == (
        b"HTTP/1.1 101 Switching Protocols\r\nConnection: Upgrade\r\nUpgrade: websocket\r\n"
        b"Sec-WebSocket-Protocol: foxglove.websocket.v1\r\n\r\n"
    )
    refused = b"HTTP/1.1 400 Bad Request\r\ncontent-length: 0\r\n\r\n"
    assert translated_answer(refused) == refused
