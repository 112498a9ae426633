"""The MCAP run recorder: round trips checked by the mcap library's own reader, crash safety,
back-pressure and write errors."""

from __future__ import annotations

import errno
import io
import json
import os
import random
import signal
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from mcap.reader import make_reader

from ballbeam.errors import OutputExistsError, RecorderError
from ballbeam.logs import PROFILE, Recorder, StructSchema, read_log

CAN = StructSchema(
    "ballbeam_msgs/msg/CanFrame",
    (
        ("bus_time_s", "float64"),
        ("arbitration_id", "uint32"),
        ("dlc", "uint8"),
        ("data", "uint8[8]"),
    ),
)
STATE = StructSchema(
    "ballbeam_msgs/msg/State",
    (
        ("counter", "int64"),
        ("angle_rad", "float64"),
        ("position_m", "float64"),
        ("saturated", "bool"),
        ("mode", "int8"),
        ("gains", "float32[2]"),
    ),
)
FAULT_SCHEMA = {"type": "object", "properties": {"kind": {"type": "string"}}}


def _can(i: int) -> tuple[Any, ...]:
    return (i * 1e-3, 0x100 + (i % 7), 8, bytes((i + j) % 256 for j in range(8)))


def _state(i: int) -> tuple[Any, ...]:
    return (i, np.sin(i * 1e-2), -0.25 + i * 1e-5, i % 3 == 0, (i % 5) - 2, (0.5, -1.25))


def _write_run(
    target: str | Path | io.BytesIO, n: int, **kwargs: Any
) -> dict[str, list[tuple[int, Any]]]:
    """Record n cycles of two struct channels plus a few JSON events; return what was sent."""
    sent: dict[str, list[tuple[int, Any]]] = {"/can": [], "/state": [], "/fault": []}
    kwargs.setdefault("flush_interval_s", 0.01)
    with Recorder(
        target,
        metadata={"run": {"config": "paper.toml", "seed": "7"}, "host": {"name": "bench"}},
        attachments=[("paper.toml", "application/toml", b"[plant]\nkm = 0.00767\n")],
        **kwargs,
    ) as rec:
        can = rec.add_struct_channel("/can", CAN)
        state = rec.add_struct_channel("/state", STATE)
        fault = rec.add_json_channel("/fault", "ballbeam_msgs/Fault", FAULT_SCHEMA)
        for i in range(n):
            t = 5_000_000_000 + i * 1_000_000
            rec.record(can, t, _can(i))
            rec.record(state, t + 1, _state(i))
            sent["/can"].append((t, _can(i)))
            sent["/state"].append((t + 1, _state(i)))
            if i % 250 == 0:
                event = {"kind": "overrun", "cycle": i, "late_s": float("nan") if i else 0.5}
                rec.record(fault, t + 2, event)
                sent["/fault"].append((t + 2, event))
            if i % 250 == 0:
                time.sleep(0.02)  # lets several flushes happen: several chunks
        rec.close(summary={"result": "ok", "cycles": str(n)})
        assert rec.dropped == 0 and rec.rejected == 0 and rec.error is None
    return sent


def _check_with_mcap(data: bytes, sent: dict[str, list[tuple[int, Any]]]) -> None:
    """The independent answer: the mcap library's reader and our schema's unpack."""
    reader = make_reader(io.BytesIO(data))
    assert reader.get_header().profile == PROFILE
    summary = reader.get_summary()
    assert summary is not None
    schemas = {s.name: s for s in summary.schemas.values()}
    assert schemas[CAN.name].encoding == "ros2msg"
    assert schemas[CAN.name].data.decode() == CAN.ros2msg
    assert schemas["ballbeam_msgs/Fault"].encoding == "jsonschema"
    encodings = {c.topic: c.message_encoding for c in summary.channels.values()}
    assert encodings == {"/can": "cdr", "/state": "cdr", "/fault": "json"}
    assert summary.statistics is not None and summary.statistics.chunk_count > 1

    got: dict[str, list[tuple[int, Any]]] = {"/can": [], "/state": [], "/fault": []}
    for _, channel, message in reader.iter_messages(log_time_order=False):
        if channel.topic == "/can":
            got["/can"].append((message.log_time, CAN.unpack(message.data)))
        elif channel.topic == "/state":
            got["/state"].append((message.log_time, STATE.unpack(message.data)))
        else:
            got["/fault"].append((message.log_time, json.loads(message.data)))
    assert [t for t, _ in got["/can"]] == [t for t, _ in sent["/can"]]
    assert [v for _, v in got["/can"]] == [v for _, v in sent["/can"]]
    for (t_got, v_got), (t_sent, v_sent) in zip(got["/state"], sent["/state"], strict=True):
        assert t_got == t_sent
        assert v_got[:5] == v_sent[:5]  # float32 gains are exact for 0.5 and -1.25
        assert v_got[5] == v_sent[5]
    assert [t for t, _ in got["/fault"]] == [t for t, _ in sent["/fault"]]
    assert got["/fault"][0][1] == {"kind": "overrun", "cycle": 0, "late_s": 0.5}
    assert got["/fault"][1][1]["late_s"] is None  # NaN is not JSON: written as null

    metadata = {m.name: m.metadata for m in reader.iter_metadata()}
    assert metadata["run"] == {"config": "paper.toml", "seed": "7"}
    assert metadata["summary"]["result"] == "ok"
    assert metadata["recorder"]["dropped"] == "0"
    attachments = {a.name: (a.media_type, a.data) for a in reader.iter_attachments()}
    assert attachments["paper.toml"] == ("application/toml", b"[plant]\nkm = 0.00767\n")


def _check_with_read_log(data: bytes, sent: dict[str, list[tuple[int, Any]]]) -> None:
    log = read_log(data)
    assert not log.truncated and log.truncation_reason is None
    can = log.topics["/can"]
    assert can.log_time_ns.tolist() == [t for t, _ in sent["/can"]]
    assert can.values["arbitration_id"].tolist() == [v[1] for _, v in sent["/can"]]
    assert [bytes(row) for row in can.values["data"]] == [v[3] for _, v in sent["/can"]]
    state = log.topics["/state"]
    np.testing.assert_array_equal(state.values["angle_rad"], [v[1] for _, v in sent["/state"]])
    assert state.values["saturated"].tolist() == [v[3] for _, v in sent["/state"]]
    assert log.json_topics["/fault"].messages[0]["kind"] == "overrun"
    assert log.metadata["host"] == {"name": "bench"}
    assert log.last_complete_time_ns == max(t for msgs in sent.values() for t, _ in msgs)


def test_round_trip_in_memory() -> None:
    buffer = io.BytesIO()
    sent = _write_run(buffer, 1500)
    data = buffer.getvalue()
    _check_with_mcap(data, sent)
    _check_with_read_log(data, sent)


def test_round_trip_on_disk(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    sent = _write_run(path, 3000, flush_interval_s=0.01)
    data = path.read_bytes()
    _check_with_mcap(data, sent)
    _check_with_read_log(data, sent)
    assert read_log(path).topics["/can"].values.shape == (3000,)


def test_a_log_whose_directory_takes_no_new_files_is_still_written(tmp_path: Path) -> None:
    """The chunk-index scratch file goes next to the log where it can; where it cannot (here
    a file open under its /proc/self/fd name, a directory that refuses new files even to
    root) it goes elsewhere."""
    target = tmp_path / "run.mcap"
    with target.open("wb") as opened:
        sent = _write_run(opened, 1500, name=f"/proc/self/fd/{opened.fileno()}")
    data = target.read_bytes()
    _check_with_mcap(data, sent)
    _check_with_read_log(data, sent)


def test_indexes_and_checksums_follow_the_mcap_specification() -> None:
    """Every index the summary gives is checked against the bytes it points at, parsed
    straight from the specification: chunk offsets, lengths and CRCs, message index entries,
    the summary offsets and the summary CRC; and the seeking reader's time-ordered, time-ranged
    reads (which go through those indexes) return exactly the messages sent."""
    import struct
    import zlib

    import zstandard

    buffer = io.BytesIO()
    sent = _write_run(buffer, 2000, flush_interval_s=0.005)
    data = buffer.getvalue()
    summary = make_reader(io.BytesIO(data)).get_summary()
    assert summary is not None and len(summary.chunk_indexes) > 2
    topic_of = {c.id: c.topic for c in summary.channels.values()}
    counted: dict[str, int] = {}
    for index in summary.chunk_indexes:
        at = index.chunk_start_offset
        opcode, length = struct.unpack_from("<BQ", data, at)
        assert opcode == 0x06 and 9 + length == index.chunk_length
        start, end, size, crc, name_len = struct.unpack_from("<QQQII", data, at + 9)
        assert (start, end) == (index.message_start_time, index.message_end_time)
        compression = data[at + 41 : at + 41 + name_len].decode()
        (compressed_len,) = struct.unpack_from("<Q", data, at + 41 + name_len)
        body = data[at + 49 + name_len : at + 49 + name_len + compressed_len]
        assert compression == index.compression == "zstd"
        records = zstandard.ZstdDecompressor().decompress(body, max_output_size=size)
        assert len(records) == size == index.uncompressed_size and zlib.crc32(records) == crc
        for channel_id, offset in index.message_index_offsets.items():
            opcode, _ = struct.unpack_from("<BQ", data, offset)
            assert opcode == 0x07
            record_channel, pairs_len = struct.unpack_from("<HI", data, offset + 9)
            assert record_channel == channel_id
            for k in range(pairs_len // 16):
                log_time, message_at = struct.unpack_from("<QQ", data, offset + 15 + 16 * k)
                opcode, _, channel, _, message_time = struct.unpack_from(
                    "<BQHIQ", records, message_at
                )
                assert (opcode, channel, message_time) == (0x05, channel_id, log_time)
                assert start <= log_time <= end
            counted[topic_of[channel_id]] = counted.get(topic_of[channel_id], 0) + pairs_len // 16
    assert counted == {topic: len(messages) for topic, messages in sent.items()}

    (summary_start, offsets_start, summary_crc) = struct.unpack_from("<QQI", data, len(data) - 28)
    assert zlib.crc32(data[summary_start : len(data) - 12]) == summary_crc
    pos = offsets_start
    while data[pos] == 0x0E:  # summary offsets: each group starts with its opcode
        group_opcode, group_start, group_length = struct.unpack_from("<BQQ", data, pos + 9)
        assert data[group_start] == group_opcode and group_length > 0
        pos += 9 + 17

    reader = make_reader(io.BytesIO(data))
    ordered = [(m.log_time, c.topic) for _, c, m in reader.iter_messages(log_time_order=True)]
    expected = sorted((t, topic) for topic, msgs in sent.items() for t, _ in msgs)
    assert ordered == expected
    window = [m.log_time for _, _, m in reader.iter_messages(
        topics=["/can"], starting_at=5_500_000_000, ending_before=5_600_000_000)]
    assert window == [t for t, _ in sent["/can"] if 5_500_000_000 <= t < 5_600_000_000]


def test_foxglove_ros2_decoder_reads_our_cdr() -> None:
    """Foxglove's own ROS 2 decoder (mcap-ros2-support) decodes our ros2msg/cdr channels."""
    decoder = pytest.importorskip("mcap_ros2.decoder")
    buffer = io.BytesIO()
    sent = _write_run(buffer, 300)
    reader = make_reader(
        io.BytesIO(buffer.getvalue()), decoder_factories=[decoder.DecoderFactory()]
    )
    decoded = list(reader.iter_decoded_messages(topics=["/state"]))
    assert len(decoded) == len(sent["/state"])
    for (_, _, message, value), (t, expected) in zip(decoded, sent["/state"], strict=True):
        assert message.log_time == t
        assert value.counter == expected[0]
        assert value.angle_rad == expected[1]
        assert value.position_m == expected[2]
        assert bool(value.saturated) == expected[3]
        assert value.mode == expected[4]
        assert list(value.gains) == list(expected[5])


def test_record_is_cheap_and_never_blocks_when_the_queue_overflows() -> None:
    buffer = io.BytesIO()
    with Recorder(buffer, queue_size=16) as rec:
        can = rec.add_struct_channel("/can", CAN)
        worst_s = 0.0
        n = 20_000
        for i in range(n):
            t0 = time.perf_counter()
            rec.record(can, i, _can(0))
            worst_s = max(worst_s, time.perf_counter() - t0)
        rec.close()
        assert rec.dropped > 0
        assert rec.messages_written + rec.dropped == n
    # Generous bound: a blocking put would wait for the writer (milliseconds).
    assert worst_s < 0.05
    log = read_log(buffer.getvalue())
    assert len(log.topics["/can"]) == rec.messages_written
    assert log.metadata["recorder"]["dropped"] == str(rec.dropped)


def test_bad_values_are_counted_not_fatal() -> None:
    buffer = io.BytesIO()
    with Recorder(buffer) as rec:
        can = rec.add_struct_channel("/can", CAN)
        rec.record(can, 1, _can(1))
        rec.record(can, 2, (0.0, 1, 8, b"short"))  # 5 bytes for uint8[8]
        rec.record(can, 3, (0.0, -1, 8, bytes(8)))  # uint32 out of range
        rec.record(can, 4, {"bus_time_s": 0.5, "arbitration_id": 7, "dlc": 0, "data": bytes(8)})
        rec.record(can, -5, _can(5))  # negative time
        rec.close()
    assert rec.rejected == 3
    assert rec.first_rejection is not None and "/can" in rec.first_rejection
    log = read_log(buffer.getvalue())
    assert log.topics["/can"].log_time_ns.tolist() == [1, 4]
    assert log.metadata["recorder"]["rejected"] == "3"


def test_close_is_idempotent_and_later_records_are_dropped() -> None:
    buffer = io.BytesIO()
    rec = Recorder(buffer)
    can = rec.add_struct_channel("/can", CAN)
    rec.close()
    rec.close()
    rec.record(can, 1, _can(1))
    assert rec.dropped == 1
    with pytest.raises(RecorderError):
        rec.add_struct_channel("/other", CAN)


def test_handle_from_another_recorder_is_rejected() -> None:
    with Recorder(io.BytesIO()) as first, Recorder(io.BytesIO()) as second:
        foreign = first.add_struct_channel("/can", CAN)
        second.add_struct_channel("/can", CAN)
        second.record(foreign, 1, _can(1))
        second.close()
        assert second.rejected == 1


def test_missing_directory_raises_recorder_error(tmp_path: Path) -> None:
    path = tmp_path / "no" / "such" / "run.mcap"
    with pytest.raises(RecorderError) as info:
        Recorder(path)
    assert str(path) in str(info.value)
    assert "No such file or directory" in str(info.value)
    assert isinstance(info.value, OSError) and info.value.errno == errno.ENOENT


def test_path_that_is_a_directory_is_refused_as_there_already(tmp_path: Path) -> None:
    with pytest.raises(OutputExistsError, match="exists"):
        Recorder(tmp_path)


def test_unwritable_location_raises_recorder_error(tmp_path: Path) -> None:
    # chmod cannot stop root (CI runs as root); a "directory" that is a regular file can.
    blocker = tmp_path / "not_a_directory"
    blocker.write_text("")
    with pytest.raises(RecorderError, match="Not a directory"):
        Recorder(blocker / "run.mcap")


@pytest.mark.skipif(not os.path.exists("/dev/full"), reason="needs /dev/full")
def test_full_disk_at_start_raises_recorder_error() -> None:
    # A log is a new file: the full disk is /dev/full opened and passed with its name.
    with open("/dev/full", "wb") as full, pytest.raises(RecorderError) as info:
        Recorder(full, name="/dev/full")
    assert info.value.errno == errno.ENOSPC and "/dev/full" in str(info.value)


class _FillingStream(io.RawIOBase):
    """A file that runs out of space after ``capacity`` bytes, as a full disk does."""

    def __init__(self, capacity: int) -> None:
        self.capacity = capacity
        self.data = bytearray()

    def writable(self) -> bool:
        return True

    def tell(self) -> int:  # the mcap writer records offsets for its indexes
        return len(self.data)

    def write(self, b: Any) -> int:
        if len(self.data) + len(b) > self.capacity:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        self.data += b
        return len(b)


def test_disk_full_mid_run_is_reported_not_silent() -> None:
    stream = _FillingStream(capacity=20_000)
    rec = Recorder(io.BufferedWriter(stream, 1024), flush_interval_s=0.005)
    can = rec.add_struct_channel("/can", CAN)
    deadline = time.monotonic() + 5
    i = 0
    while rec.error is None and time.monotonic() < deadline:
        rec.record(can, i, _can(i))
        i += 1
        if i % 100 == 0:
            time.sleep(0.002)
    assert isinstance(rec.error, OSError)
    before = rec.dropped
    rec.record(can, i, _can(i))  # still never raises: counted
    assert rec.dropped == before + 1
    with pytest.raises(RecorderError, match="No space left on device") as info:
        rec.close()
    assert info.value.errno == errno.ENOSPC
    rec.close()  # idempotent, even after a failure
    # What reached the "disk" before it filled up is a readable, truncated log.
    log = read_log(bytes(stream.data))
    assert log.truncated
    assert 0 < len(log.topics["/can"]) <= i


def test_concurrent_producers_share_one_recorder() -> None:
    buffer = io.BytesIO()
    with Recorder(buffer) as rec:
        handles = [rec.add_struct_channel(f"/can{k}", CAN) for k in range(3)]

        def produce(k: int) -> None:
            for i in range(2000):
                rec.record(handles[k], i, _can(i))

        threads = [threading.Thread(target=produce, args=(k,)) for k in range(3)]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
        rec.close()
    assert rec.dropped == 0
    log = read_log(buffer.getvalue())
    for k in range(3):
        assert log.topics[f"/can{k}"].log_time_ns.tolist() == list(range(2000))


_KILL_HELPER = textwrap.dedent(
    """
    import sys, time
    from ballbeam.logs import Recorder, StructSchema

    path, progress_path = sys.argv[1], sys.argv[2]
    tick = StructSchema("test_msgs/msg/Tick", (("cycle", "int64"), ("value", "float64")))
    with open(progress_path, "w", buffering=1) as progress, Recorder(
        path, metadata={"run": {"kind": "kill test"}}, flush_interval_s=0.05
    ) as rec:
        handle = rec.add_struct_channel("/tick", tick)
        print("ready", file=progress)
        due_ns = time.monotonic_ns()
        cycle = 0
        while True:
            now_ns = time.monotonic_ns()
            rec.record(handle, now_ns, (cycle, cycle * 0.5))
            if cycle % 5 == 0:
                print(cycle, now_ns, file=progress)
            cycle += 1
            due_ns += 1_000_000
            delay_ns = due_ns - time.monotonic_ns()
            if delay_ns > 0:
                time.sleep(delay_ns / 1e9)
    """
)


def test_recorder_killed_mid_write_leaves_a_readable_log(tmp_path: Path) -> None:
    helper = tmp_path / "kill_helper.py"
    helper.write_text(_KILL_HELPER)
    rng = random.Random(20240611)
    for rep in range(5):
        log_path = tmp_path / f"killed{rep}.mcap"
        progress_path = tmp_path / f"progress{rep}.txt"
        proc = subprocess.Popen([sys.executable, str(helper), str(log_path), str(progress_path)])
        try:
            deadline = time.monotonic() + 20
            while not (progress_path.exists() and "ready" in progress_path.read_text()):
                assert proc.poll() is None, "helper exited early"
                assert time.monotonic() < deadline, "helper never became ready"
                time.sleep(0.01)
            time.sleep(rng.uniform(0.2, 0.5))
        finally:
            proc.send_signal(signal.SIGKILL)
            proc.wait()
        lines = [ln.split() for ln in progress_path.read_text().splitlines()[1:]]
        complete = [ln for ln in lines if len(ln) == 2]
        reported_cycle, reported_ns = int(complete[-1][0]), int(complete[-1][1])

        log = read_log(log_path)
        assert log.truncated
        assert log.truncation_reason
        assert log.metadata["run"] == {"kind": "kill test"}
        tick = log.topics["/tick"]
        cycles = tick.values["cycle"]
        assert len(cycles) > 0
        np.testing.assert_array_equal(cycles, np.arange(len(cycles)))  # a gapless prefix
        np.testing.assert_array_equal(tick.values["value"], cycles * 0.5)
        assert log.last_complete_time_ns == int(tick.log_time_ns[-1])
        # At most about one flush interval (50 ms) lost, with slack for scheduling.
        assert log.last_complete_time_ns >= reported_ns - 100_000_000, (
            f"rep {rep}: lost {(reported_ns - log.last_complete_time_ns) / 1e6:.1f} ms "
            f"(read {len(cycles)} cycles, reported {reported_cycle})"
        )


def test_channel_registered_mid_run() -> None:
    """A channel added while a chunk is open is defined before that chunk in the file."""
    buffer = io.BytesIO()
    with Recorder(buffer, flush_interval_s=10.0) as rec:
        can = rec.add_struct_channel("/can", CAN)
        for i in range(50):
            rec.record(can, i, _can(i))
        state = rec.add_struct_channel("/state", STATE)
        with pytest.raises(ValueError, match="already registered"):
            rec.add_struct_channel("/can", CAN)
        for i in range(50, 100):
            rec.record(can, i, _can(i))
            rec.record(state, i, _state(i))
    topics = [channel.topic for _, channel, _ in make_reader(io.BytesIO(buffer.getvalue()))
              .iter_messages(log_time_order=False)]
    assert topics.count("/state") == 50 and topics.count("/can") == 100
    log = read_log(buffer.getvalue())
    assert log.chunk_count == 1
    assert log.topics["/can"].log_time_ns.tolist() == list(range(100))
    assert log.topics["/state"].values["counter"].tolist() == list(range(50, 100))


WRITER_POLICY = textwrap.dedent("""
    import os, sys, time
    from ballbeam.logs import Recorder
    from ballbeam.runtime.ticker import leave_real_time
    all_cpus = os.sched_getaffinity(0)
    os.sched_setaffinity(0, {min(all_cpus)})
    os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
    for name, setup in (("inherited", None), ("left", leave_real_time)):
        recorder = Recorder(os.path.join(sys.argv[1], name + ".mcap"), writer_setup=setup)
        time.sleep(0.05)  # the writer thread has started and run its setup
        writer = recorder._thread.native_id
        print(name, os.sched_getscheduler(writer),
              "pinned" if os.sched_getaffinity(writer) != all_cpus else "free")
        recorder.close()
""")


def test_the_writer_thread_leaves_a_real_time_loops_scheduling(tmp_path: Path) -> None:
    """On Linux a thread inherits its creator's SCHED_FIFO and CPU: the writer, compressing a
    chunk at the loop's priority on the loop's CPU, kept the CPU until it blocked, and the
    loop's timer woke it in vain (a ~0.7 ms late cycle every flush); at normal priority but
    still on the loop's CPU it was starved (a killed run lost 128 ms of log). The daemon hands
    the recorder ``leave_real_time`` as the writer's setup: normal policy, any CPU."""
    from ballbeam.runtime.process import realtime_permitted

    if not realtime_permitted(1):
        pytest.skip("SCHED_FIFO not permitted here: no real-time loop to leave")
    done = subprocess.run([sys.executable, "-c", WRITER_POLICY, str(tmp_path)],
                          capture_output=True, text=True, timeout=60, check=False)
    assert done.returncode == 0, done.stderr
    policies = {name: rest for name, *rest in map(str.split, done.stdout.splitlines())}
    pinned = "pinned" if len(os.sched_getaffinity(0)) > 1 else "free"  # one CPU: nowhere to go
    assert policies == {
        "inherited": [str(os.SCHED_FIFO), pinned], "left": [str(os.SCHED_OTHER), "free"],
    }
