"""The pure-Python MCAP reader and the fixed-layout schema codec.

Files are written with the ``mcap`` library's own Writer (chunk sizes, compressions and index
options we do not use ourselves), and the ``mcap`` library's reader is the independent answer.
"""

from __future__ import annotations

import io
import json
import random
import struct
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from mcap.reader import make_reader
from mcap.writer import CompressionType, IndexType, Writer

from ballbeam.errors import LogFormatError
from ballbeam.logs import StructSchema, parse_ros2msg, read_log
from ballbeam.logs.schema import CDR_LE_HEADER, PRIMITIVES

SENSOR = StructSchema(
    "ballbeam_msgs/msg/Sensor",
    (
        ("counter", "int64"),
        ("angle_rad", "float64"),
        ("position_m", "float64"),
        ("flags", "uint8[3]"),
        ("ok", "bool"),
    ),
)


def _sensor(i: int) -> tuple[Any, ...]:
    return (i, np.cos(i / 50), i * 1e-4, bytes((i % 256, 1, 2)), i % 2 == 0)


def _build(
    n: int = 2000,
    *,
    chunk_size: int = 4096,
    compression: CompressionType = CompressionType.ZSTD,
    use_chunking: bool = True,
    index_types: IndexType = IndexType.ALL,
    profile: str = "ballbeam",
    finish: bool = True,
    log_time: Any = None,
) -> tuple[bytes, list[int]]:
    """A log written by the mcap library; returns the bytes and the /sensor log times."""
    out = io.BytesIO()
    writer = Writer(
        out,
        chunk_size=chunk_size,
        compression=compression,
        use_chunking=use_chunking,
        index_types=index_types,
    )
    writer.start(profile=profile, library="test-writer")
    writer.add_metadata("run", {"config": "paper.toml"})
    writer.add_attachment(1, 2, "paper.toml", "application/toml", b"[plant]\n")
    sensor_schema = writer.register_schema(SENSOR.name, "ros2msg", SENSOR.ros2msg.encode())
    sensor = writer.register_channel("/sensor", "cdr", sensor_schema)
    event_schema = writer.register_schema("Event", "jsonschema", b'{"type":"object"}')
    events = writer.register_channel("/events", "json", event_schema)
    times = []
    for i in range(n):
        t = 1_000_000 * i + 7 if log_time is None else log_time(i)
        writer.add_message(sensor, t, SENSOR.pack(_sensor(i)), t, sequence=i)
        times.append(t)
        if i % 100 == 0:
            writer.add_message(events, t + 1, json.dumps({"i": i}).encode(), t + 1)
    if finish:
        writer.finish()
    else:
        writer.flush()  # chunks on "disk", no summary or footer: a crashed writer
    return out.getvalue(), times


def _mcap_messages(data: bytes) -> dict[str, list[tuple[int, bytes]]]:
    got: dict[str, list[tuple[int, bytes]]] = {}
    for _, channel, message in make_reader(io.BytesIO(data)).iter_messages(log_time_order=False):
        got.setdefault(channel.topic, []).append((message.log_time, message.data))
    return got


def _assert_matches_mcap(data: bytes, **read_kwargs: Any) -> None:
    log = read_log(data, **read_kwargs)
    expected = _mcap_messages(data)
    sensor = sorted(expected["/sensor"], key=lambda m: m[0])  # stable: log-time order
    topic = log.topics["/sensor"]
    assert topic.log_time_ns.tolist() == [t for t, _ in sensor]
    for name, column in zip(
        SENSOR.field_names, zip(*(SENSOR.unpack(d) for _, d in sensor), strict=True), strict=True
    ):
        values = topic.values[name]
        if name == "flags":
            assert [bytes(v) for v in values] == list(column)
        else:
            assert values.tolist() == list(column)
    events = sorted(expected["/events"], key=lambda m: m[0])
    assert log.json_topics["/events"].log_time_ns.tolist() == [t for t, _ in events]
    assert list(log.json_topics["/events"].messages) == [json.loads(d) for _, d in events]
    assert log.metadata["run"] == {"config": "paper.toml"}
    assert log.attachments["paper.toml"] == b"[plant]\n"
    assert log.library == "test-writer"


# ---- round trips against the mcap library ----------------------------------------------------


@pytest.mark.parametrize(
    "compression", [CompressionType.ZSTD, CompressionType.LZ4, CompressionType.NONE]
)
@pytest.mark.parametrize("index_types", [IndexType.ALL, IndexType.NONE])
def test_reads_what_the_mcap_library_writes(
    compression: CompressionType, index_types: IndexType
) -> None:
    data, _ = _build(compression=compression, index_types=index_types)
    _assert_matches_mcap(data)
    assert not read_log(data).truncated


def test_reads_unchunked_files() -> None:
    data, _ = _build(300, use_chunking=False)
    _assert_matches_mcap(data)


def test_reads_one_big_chunk_from_disk(tmp_path: Path) -> None:
    data, times = _build(5000, chunk_size=1 << 24)
    path = tmp_path / "one.mcap"
    path.write_bytes(data)
    log = read_log(path)
    assert log.chunk_count == 1 and log.topics["/sensor"].log_time_ns.tolist() == times
    assert log.path == str(path)


def test_out_of_order_log_times_come_back_sorted() -> None:
    order = list(range(1500))
    random.Random(3).shuffle(order)
    data, _ = _build(1500, log_time=lambda i: order[i] * 1000)
    _assert_matches_mcap(data)
    log = read_log(data)
    assert log.topics["/sensor"].values["counter"].tolist() == sorted(
        range(1500), key=lambda i: order[i]
    )


def test_topic_selection() -> None:
    data, _ = _build(500)
    log = read_log(data, topics=["/events"])
    assert set(log.topics) == set() and set(log.json_topics) == {"/events"}
    log = read_log(data, topics=["/sensor", "/nothing"])
    assert set(log.topics) == {"/sensor"} and not log.json_topics
    assert log.message_count == 500 + 5  # every message is still located and checked


# ---- truncation --------------------------------------------------------------------------------


def test_truncated_at_random_offsets_reads_every_complete_chunk() -> None:
    data, times = _build(3000)
    summary = make_reader(io.BytesIO(data)).get_summary()
    assert summary is not None
    chunks = sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)
    assert len(chunks) > 20
    first_chunk = chunks[0].chunk_start_offset
    rng = random.Random(11)
    cuts = [rng.randrange(first_chunk, len(data)) for _ in range(50)]
    cuts += [c.chunk_start_offset + c.chunk_length for c in chunks[:3]]  # exactly at a chunk end
    cuts += [first_chunk, len(data) - 1, len(data) - 8]
    for cut in cuts:
        log = read_log(data[:cut])
        assert log.truncated, cut
        assert log.truncation_reason, cut
        complete = [c for c in chunks if c.chunk_start_offset + c.chunk_length <= cut]
        last_ns = max((c.message_end_time for c in complete), default=None)
        assert log.last_complete_time_ns == last_ns, cut
        expected = [t for t in times if last_ns is not None and t <= last_ns]
        sensor = log.topics.get("/sensor")
        got = [] if sensor is None else sensor.log_time_ns.tolist()
        assert got == expected, cut
        if sensor is not None:
            assert sensor.values["counter"].tolist() == list(range(len(expected)))
    assert "chunk" in read_log(data[: chunks[5].chunk_start_offset + 100]).truncation_reason


def test_crashed_writer_without_footer() -> None:
    data, times = _build(2000, finish=False)
    log = read_log(data)
    assert log.truncated and log.truncation_reason == "no footer: the writer did not finish"
    assert log.topics["/sensor"].log_time_ns.tolist() == times


def test_zero_filled_tail_is_truncation() -> None:
    data, times = _build(1000, finish=False)
    log = read_log(data + bytes(4096))
    assert log.truncated and "zero bytes" in (log.truncation_reason or "")
    assert log.topics["/sensor"].log_time_ns.tolist() == times


def test_damaged_last_chunk_of_unfinished_file_is_truncation() -> None:
    data, _ = _build(2000, finish=False)
    summary_source, _ = _build(2000)  # same bytes up to the summary: locates the chunks
    summary = make_reader(io.BytesIO(summary_source)).get_summary()
    assert summary is not None
    last = max(summary.chunk_indexes, key=lambda c: c.chunk_start_offset)
    damaged = bytearray(data)
    middle = last.chunk_start_offset + last.chunk_length - 20
    damaged[middle : middle + 8] = b"\xff" * 8
    log = read_log(bytes(damaged))
    assert log.truncated and "damaged" in (log.truncation_reason or "")
    assert log.last_complete_time_ns is not None
    assert log.last_complete_time_ns < last.message_start_time
    # The same damage in a finished file is corruption, not truncation.
    finished = bytearray(summary_source)
    finished[middle : middle + 8] = b"\xff" * 8
    with pytest.raises(LogFormatError, match=f"chunk at byte {last.chunk_start_offset}"):
        read_log(bytes(finished))


# ---- refusing what is not a ballbeam log ----------------------------------------------------


@pytest.mark.parametrize(
    "data",
    [b"", b"\x89MCA", b"hello, world\n" * 10, bytes(range(256)) * 4, b"\x89MCAP1\r\n" + bytes(40)],
)
def test_not_an_mcap_file(data: bytes, tmp_path: Path) -> None:
    with pytest.raises(LogFormatError, match="not an MCAP file"):
        read_log(data)
    path = tmp_path / "x.mcap"
    path.write_bytes(data)
    with pytest.raises(LogFormatError, match="not an MCAP file"):
        read_log(path)


def test_other_mcap_profiles_are_refused() -> None:
    data, _ = _build(10, profile="ros2")
    with pytest.raises(LogFormatError, match="an MCAP file, but not a ballbeam log"):
        read_log(data)


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=300))
def test_random_bytes_raise_only_log_format_error(data: bytes) -> None:
    with pytest.raises(LogFormatError):
        read_log(data)


def test_random_damage_never_escapes_as_another_exception() -> None:
    good, _ = _build(400, chunk_size=2048)
    rng = random.Random(5)
    outcomes = {"ok": 0, "error": 0}
    for _ in range(300):
        bad = bytearray(good)
        for _ in range(rng.randint(1, 4)):
            at = rng.randrange(8, len(bad))
            bad[at] = rng.randrange(256)
        if rng.random() < 0.3:
            bad = bad[: rng.randrange(8, len(bad))]
        try:
            read_log(bytes(bad))
            outcomes["ok"] += 1
        except LogFormatError:
            outcomes["error"] += 1
    assert outcomes["error"] > 0


# ---- corrupt records ----------------------------------------------------------------------------


def _custom(
    schema_text: bytes = b"float64 x\n",
    payload: bytes = CDR_LE_HEADER + bytes(8),
    encoding: tuple[str, str] = ("ros2msg", "cdr"),
    extra: bool = True,
    **writer_kwargs: Any,
) -> bytes:
    out = io.BytesIO()
    writer = Writer(out, **writer_kwargs)
    writer.start(profile="ballbeam", library="test")
    schema = writer.register_schema("test/msg/X", encoding[0], schema_text)
    channel = writer.register_channel("/x", encoding[1], schema)
    writer.add_message(channel, 5, payload, 5)
    if extra:
        good = writer.register_schema("test/msg/Y", "ros2msg", b"int32 y\n")
        other = writer.register_channel("/y", "cdr", good)
        writer.add_message(other, 6, CDR_LE_HEADER + struct.pack("<i", 9), 6)
    writer.finish()
    return out.getvalue()


def test_payload_size_must_match_schema() -> None:
    with pytest.raises(LogFormatError, match=r"payload of 13 bytes does not match .* \(12 bytes\)"):
        read_log(_custom(payload=CDR_LE_HEADER + bytes(9)))
    with pytest.raises(LogFormatError, match="does not match"):
        read_log(_custom(payload=CDR_LE_HEADER + bytes(9), use_chunking=False))


def test_big_endian_cdr_is_refused() -> None:
    with pytest.raises(LogFormatError, match="little-endian"):
        read_log(_custom(payload=b"\x00\x00\x00\x00" + bytes(8)))


def test_schema_text_that_does_not_parse() -> None:
    data = _custom(schema_text=b"string name\n", payload=CDR_LE_HEADER + bytes(8))
    with pytest.raises(LogFormatError, match="unsupported field type 'string'"):
        read_log(data)
    assert read_log(data, topics=["/y"]).topics["/y"].values["y"].tolist() == [9]


def test_non_json_payload_is_refused() -> None:
    data = _custom(schema_text=b"{}", payload=b"__import__('os')", encoding=("jsonschema", "json"))
    with pytest.raises(LogFormatError, match="not JSON"):
        read_log(data)
    with pytest.raises(LogFormatError, match="not an object"):
        read_log(_custom(schema_text=b"{}", payload=b"[1, 2]", encoding=("jsonschema", "json")))
    assert "/x" not in read_log(data, topics=["/y"]).json_topics


def test_unsupported_encoding_is_named() -> None:
    data = _custom(schema_text=b"\x00", payload=b"\x01", encoding=("protobuf", "protobuf"))
    with pytest.raises(LogFormatError, match="'protobuf'"):
        read_log(data)
    assert len(read_log(data, topics=["/y"]).topics["/y"]) == 1


def _first_chunk_offset(data: bytes) -> int:
    summary = make_reader(io.BytesIO(data)).get_summary()
    assert summary is not None
    return min(c.chunk_start_offset for c in summary.chunk_indexes)


def test_chunk_crc_is_checked() -> None:
    data = bytearray(_custom())
    crc_at = _first_chunk_offset(bytes(data)) + 9 + 24
    data[crc_at] ^= 0xFF
    with pytest.raises(LogFormatError, match="CRC"):
        read_log(bytes(data))


def test_chunk_that_claims_a_huge_size_is_refused() -> None:
    data = bytearray(_custom(compression=CompressionType.NONE))
    size_at = _first_chunk_offset(bytes(data)) + 9 + 16
    data[size_at : size_at + 8] = struct.pack("<Q", 1 << 40)
    with pytest.raises(LogFormatError, match="claims"):
        read_log(bytes(data))


def test_record_length_beyond_the_file_is_not_trusted() -> None:
    data = bytearray(_custom())
    length_at = _first_chunk_offset(bytes(data)) + 1
    data[length_at : length_at + 8] = struct.pack("<Q", 1 << 60)
    log = read_log(bytes(data))  # reads as a file cut inside its first chunk
    assert log.truncated and "chunk" in (log.truncation_reason or "")
    assert not log.topics.get("/x")


def test_attachment_crc_is_checked() -> None:
    out = io.BytesIO()
    writer = Writer(out)
    writer.start(profile="ballbeam", library="test")
    writer.add_attachment(0, 0, "a.bin", "application/octet-stream", b"payload!")
    writer.finish()
    data = bytearray(out.getvalue())
    at = bytes(data).index(b"payload!")
    data[at] ^= 1
    with pytest.raises(LogFormatError, match=r"attachment 'a\.bin' fails its CRC"):
        read_log(bytes(data))


# ---- the schema codec (Hypothesis) ---------------------------------------------------------------

_INT_RANGES = {
    "int8": (-(2**7), 2**7 - 1),
    "uint8": (0, 2**8 - 1),
    "byte": (0, 255),
    "int16": (-(2**15), 2**15 - 1),
    "uint16": (0, 2**16 - 1),
    "int32": (-(2**31), 2**31 - 1),
    "uint32": (0, 2**32 - 1),
    "int64": (-(2**63), 2**63 - 1),
    "uint64": (0, 2**64 - 1),
}


def _scalar(base: str) -> st.SearchStrategy[Any]:
    if base == "bool":
        return st.booleans()
    if base == "float64":
        return st.floats(allow_nan=False)
    if base == "float32":
        return st.floats(allow_nan=False, width=32)
    low, high = _INT_RANGES[base]
    return st.integers(low, high)


def _value(type_: str) -> st.SearchStrategy[Any]:
    if "[" not in type_:
        return _scalar(type_)
    base, count = type_[:-1].split("[")
    n = int(count)
    if base in ("uint8", "byte"):
        return st.binary(min_size=n, max_size=n)
    return st.tuples(*[_scalar(base)] * n)


_TYPES = st.sampled_from(sorted(PRIMITIVES)).flatmap(
    lambda base: st.one_of(st.just(base), st.integers(1, 4).map(lambda n: f"{base}[{n}]"))
)
_NAMES = st.from_regex(r"[a-z][a-z0-9]{0,6}(_[a-z0-9]{1,3})?", fullmatch=True)


@st.composite
def _schema_and_values(draw: st.DrawFn) -> tuple[StructSchema, list[tuple[Any, ...]]]:
    names = draw(st.lists(_NAMES, min_size=1, max_size=8, unique=True))
    types = [draw(_TYPES) for _ in names]
    schema = StructSchema("test_msgs/msg/Random", tuple(zip(names, types, strict=True)))
    rows = draw(st.lists(st.tuples(*[_value(t) for t in types]), min_size=1, max_size=4))
    return schema, rows


def _same(a: Any, b: Any) -> bool:
    return bool(np.array_equal(np.asarray(a), np.asarray(b)))


@settings(max_examples=150, deadline=None)
@given(_schema_and_values())
def test_struct_schema_round_trip(case: tuple[StructSchema, list[tuple[Any, ...]]]) -> None:
    schema, rows = case
    payloads = [schema.pack(row) for row in rows]
    assert all(len(p) == schema.size and p[:4] == CDR_LE_HEADER for p in payloads)
    for row, payload in zip(rows, payloads, strict=True):
        assert schema.unpack(payload) == row
        assert schema.pack(dict(zip(schema.field_names, row, strict=True))) == payload
    decoded = np.frombuffer(b"".join(payloads), schema.dtype)  # many at once
    for k, (name, type_) in enumerate(schema.fields):
        for i, row in enumerate(rows):
            got = decoded[name][i]
            want = row[k]
            if isinstance(want, bytes):
                assert bytes(got) == want
            else:
                assert _same(got, want), (name, type_, got, want)


@settings(max_examples=100, deadline=None)
@given(_schema_and_values())
def test_cdr_layout_matches_the_ros2_decoder(
    case: tuple[StructSchema, list[tuple[Any, ...]]],
) -> None:
    """Independent check of the CDR layout: Foxglove's ROS 2 decoder (mcap-ros2-support)."""
    decoder_module = pytest.importorskip("mcap_ros2.decoder")
    from mcap.records import Schema

    schema, rows = case
    decode = decoder_module.DecoderFactory().decoder_for(
        "cdr", Schema(id=1, name=schema.name, encoding="ros2msg", data=schema.ros2msg.encode())
    )
    for row in rows:
        message = decode(schema.pack(row))
        for (name, _), want in zip(schema.fields, row, strict=True):
            got = getattr(message, name)
            if isinstance(want, bytes):
                assert bytes(got) == want
            else:
                assert _same(got, want), (name, got, want)


@settings(max_examples=150, deadline=None)
@given(_schema_and_values(), st.data())
def test_ros2msg_text_round_trip(
    case: tuple[StructSchema, list[tuple[Any, ...]]], data: st.DataObject
) -> None:
    schema = case[0]
    assert parse_ros2msg(schema.ros2msg, schema.name) == schema
    # Comments, blank lines, constants and defaults take no space in the layout.
    lines = []
    for name, type_ in schema.fields:
        if data.draw(st.booleans()):
            lines.append("# a comment line")
        if data.draw(st.booleans()):
            lines.append("int32 SOME_CONSTANT=5")
        lines.append(f"{type_} {name}  # trailing comment")
        lines.append("")
    text = "\n".join(lines) + "\n================\nMSG: other/Dependency\nstring ignored\n"
    parsed = parse_ros2msg(text, schema.name)
    assert parsed == schema and parsed.dtype == schema.dtype


@pytest.mark.parametrize(
    "text",
    [
        "string name",
        "char c",
        "float64[] xs",
        "float64[<=3] xs",
        "geometry_msgs/Point p",
        "float64",
        "float64 Bad",
        "float64 a\nfloat64 a",
        "float64 a__b",
        "float64 x_",
        "",
        "uint8[0] a",
    ],
)
def test_ros2msg_without_a_fixed_layout_is_refused(text: str) -> None:
    with pytest.raises(LogFormatError):
        parse_ros2msg(text, "test/msg/Bad")


def test_cdr_alignment_counts_from_after_the_header() -> None:
    schema = StructSchema(
        "t/msg/A", (("a", "uint8"), ("b", "float64"), ("c", "uint16"), ("d", "int32[2]"))
    )
    assert [f.offset for f in schema.layout] == [4, 12, 20, 24]
    assert schema.size == 32
    assert schema.pack((1, 2.0, 3, (4, 5)))[4:] == struct.pack("<B7xdH2xii", 1, 2.0, 3, 4, 5)


def test_pack_refuses_wrong_shapes() -> None:
    with pytest.raises(ValueError, match="expected 3 bytes, got 8"):
        SENSOR.pack((1, 0.0, 0.0, b"\x00" * 8, True))  # flags is uint8[3]
    with pytest.raises(ValueError, match="expected 5 values"):
        SENSOR.pack((1, 0.0))
    with pytest.raises(ValueError, match="missing field 'ok'"):
        SENSOR.pack({"counter": 1, "angle_rad": 0.0, "position_m": 0.0, "flags": b"abc"})
    with pytest.raises(ValueError):
        SENSOR.pack((2**63, 0.0, 0.0, b"abc", True))
