"""A fast, truncation-tolerant reader for ballbeam MCAP logs (pure Python + numpy).

Why not the ``mcap`` library's reader: it yields one Python object per message (~160 k/s here),
and it leans on the summary section, which a crashed writer never wrote. This reader walks
the records from the start, decompresses each complete chunk, and uses the Message Index
records that follow a chunk to gather all messages of a channel at once: every fixed-layout
(``ros2msg``/``cdr``) payload of a channel is copied out of the decompressed chunks with one
numpy fancy-index and viewed as the channel's structured dtype. Nothing per message runs in
Python except on JSON channels, which carry rare events.

The file is never trusted: lengths are checked against the record and the file, CRCs are
checked where the writer stored them, schema texts must parse, and payload sizes must match
their schema, else :class:`~ballbeam.errors.LogFormatError` says what and at which byte. A file
without a footer is a run whose writer did not finish: it is read up to its last complete
chunk and reported as ``truncated``; damage confined to the last record of such a file is
treated the same way. Nothing from the file is executed or unpickled; JSON goes through
``json.loads`` only.
"""

from __future__ import annotations

import importlib
import json
import mmap
import os
import struct
import zlib
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import zstandard
from numpy.lib.stride_tricks import sliding_window_view
from numpy.typing import NDArray

from ballbeam.errors import LogFormatError
from ballbeam.logs.schema import MESSAGE_ENCODING, SCHEMA_ENCODING, StructSchema, parse_ros2msg

_lz4: Any
try:  # lz4 is optional: our writer uses zstd, other writers may not
    _lz4 = importlib.import_module("lz4.frame")
except ImportError:  # pragma: no cover - depends on the environment
    _lz4 = None

PROFILE = "ballbeam"
MAGIC = b"\x89MCAP0\r\n"

# Record opcodes (MCAP specification, major version 0).
OP_HEADER = 0x01
OP_FOOTER = 0x02
OP_SCHEMA = 0x03
OP_CHANNEL = 0x04
OP_MESSAGE = 0x05
OP_CHUNK = 0x06
OP_MESSAGE_INDEX = 0x07
OP_ATTACHMENT = 0x09
OP_METADATA = 0x0C
OP_DATA_END = 0x0F
_OP_NAMES = {
    0x01: "header",
    0x02: "footer",
    0x03: "schema",
    0x04: "channel",
    0x05: "message",
    0x06: "chunk",
    0x07: "message index",
    0x08: "chunk index",
    0x09: "attachment",
    0x0A: "attachment index",
    0x0B: "statistics",
    0x0C: "metadata",
    0x0D: "metadata index",
    0x0E: "summary offset",
    0x0F: "data end",
}

_OP_LEN = struct.Struct("<BQ")
_CHUNK_FIXED = struct.Struct("<QQQI")
_INDEX_FIXED = struct.Struct("<HI")
_U16 = struct.Struct("<H")
_U32 = struct.Struct("<I")
_U64 = struct.Struct("<Q")
_MSG_FIXED = struct.Struct("<HIQQ")

_RECORD_HEAD = 9  # opcode (1) + content length (8)
_MESSAGE_HEAD = 31  # record head + channel id (2) + sequence (4) + log time (8) + publish time (8)
# The leading bytes of a message record, as gathered for every indexed message.
_HEAD_DTYPE = np.dtype(
    {"names": ["op", "len", "ch"], "formats": ["u1", "<u8", "<u2"], "offsets": [0, 1, 9]}
)
_MAX_CHUNK_BYTES = 1 << 30  # a chunk that decompresses past this is not one of ours
_BATCH_BYTES = 32 << 20  # decompressed bytes gathered per vectorised pass


@dataclass(frozen=True)
class StructTopic:
    """All messages of one fixed-layout topic, in log-time order.

    ``values`` is a structured array with ``schema.dtype`` (one element per message, fields
    by name: ``values["angle_rad"]``); ``log_time_ns`` has the same length.
    """

    topic: str
    schema: StructSchema
    log_time_ns: NDArray[np.int64]
    values: NDArray[np.void]

    def __len__(self) -> int:
        return len(self.log_time_ns)


@dataclass(frozen=True)
class JsonTopic:
    """All messages of one JSON topic (events, faults), in log-time order."""

    topic: str
    schema_name: str
    log_time_ns: NDArray[np.int64]
    messages: tuple[dict[str, Any], ...]

    def __len__(self) -> int:
        return len(self.log_time_ns)


@dataclass(frozen=True)
class RunLog:
    """What :func:`read_log` found in one log.

    ``truncated`` is True when the file has no footer (the writer did not finish) or ends
    damaged; ``truncation_reason`` then says where. ``last_complete_time_ns`` is the latest
    log time among the messages that were read (None if none were).
    """

    path: str
    profile: str
    library: str
    topics: Mapping[str, StructTopic]
    json_topics: Mapping[str, JsonTopic]
    metadata: Mapping[str, Mapping[str, str]]
    attachments: Mapping[str, bytes]
    truncated: bool
    truncation_reason: str | None
    last_complete_time_ns: int | None
    chunk_count: int
    message_count: int


def read_log(
    source: str | os.PathLike[str] | bytes | bytearray | memoryview,
    *,
    topics: Iterable[str] | None = None,
) -> RunLog:
    """Read a ballbeam MCAP log from a path (or from bytes already in memory).

    ``topics`` limits decoding to those topics (metadata and attachments are always read);
    unselected channels are still checked for structure but not decoded.
    Raises LogFormatError if the file is not a ballbeam MCAP log or is corrupt; OSError if
    it cannot be opened.
    """
    selected = None if topics is None else frozenset(topics)
    if isinstance(source, (bytes, bytearray, memoryview)):
        return _Reader(memoryview(source).cast("B"), "<memory>", selected).read()
    path = os.fspath(source)
    with open(path, "rb") as file:
        size = os.fstat(file.fileno()).st_size
        if size < len(MAGIC) + _RECORD_HEAD:
            return _Reader(memoryview(file.read()), path, selected).read()
        mapped = mmap.mmap(file.fileno(), 0, access=mmap.ACCESS_READ)
    view = memoryview(mapped)
    try:
        return _Reader(view, path, selected).read()
    finally:
        # Results never point into the map; release it now rather than at garbage collection.
        try:
            view.release()
            mapped.close()
        except BufferError:  # pragma: no cover - a stray export; the GC closes it later
            pass


# ---- internals ----------------------------------------------------------------------------


class _Cursor:
    """Bounds-checked field reader over one record's content."""

    __slots__ = ("buf", "end", "pos", "where")

    def __init__(self, buf: memoryview, pos: int, end: int, where: str) -> None:
        self.buf, self.pos, self.end, self.where = buf, pos, end, where

    def take(self, n: int) -> int:
        start = self.pos
        if n < 0 or start + n > self.end:
            raise LogFormatError(f"{self.where}: a field runs past the end of the record")
        self.pos = start + n
        return start

    def u16(self) -> int:
        return int(_U16.unpack_from(self.buf, self.take(2))[0])

    def u32(self) -> int:
        return int(_U32.unpack_from(self.buf, self.take(4))[0])

    def u64(self) -> int:
        return int(_U64.unpack_from(self.buf, self.take(8))[0])

    def raw(self, n: int) -> bytes:
        start = self.take(n)
        return bytes(self.buf[start : start + n])

    def string(self) -> str:
        n = self.u32()
        try:
            return self.raw(n).decode("utf-8")
        except UnicodeDecodeError as exc:
            raise LogFormatError(f"{self.where}: a string is not UTF-8") from exc

    def str_map(self) -> dict[str, str]:
        n = self.u32()
        start = self.take(n)
        sub = _Cursor(self.buf, start, start + n, self.where)
        out: dict[str, str] = {}
        while sub.pos < sub.end:
            key = sub.string()
            out[key] = sub.string()
        return out


@dataclass
class _Channel:
    channel_id: int
    topic: str
    message_encoding: str
    schema_id: int
    schema_name: str
    kind: str  # "struct", "json", or "other"
    struct_schema: StructSchema | None
    record: tuple[Any, ...]  # the raw fields, to check that a repeated record agrees


@dataclass
class _Chunk:
    start: int  # byte offset of the chunk record in the file
    buf: bytes
    indexes: list[tuple[int, int, int]] = field(default_factory=list)  # (channel, offset, n)


@dataclass
class _TopicParts:
    times: list[NDArray[np.int64]] = field(default_factory=list)
    values: list[NDArray[np.void]] = field(default_factory=list)
    json: list[tuple[int, dict[str, Any]]] = field(default_factory=list)


class _Reader:
    def __init__(self, buf: memoryview, path: str, selected: frozenset[str] | None) -> None:
        self.buf = buf
        self.size = len(buf)
        self.path = path
        self.selected = selected
        self.schemas: dict[int, tuple[str, str, bytes]] = {}
        self.channels: dict[int, _Channel] = {}
        self.parts: dict[int, _TopicParts] = {}
        self.metadata: dict[str, dict[str, str]] = {}
        self.attachments: dict[str, bytes] = {}
        self.loose: list[tuple[int, int, int, int]] = []  # (channel, log time, start, end)
        self.batch: list[_Chunk] = []
        self.pending: _Chunk | None = None  # the chunk whose message indexes may follow
        self.batch_bytes = 0
        self.chunk_count = 0
        self.message_count = 0
        self.last_time_ns: int | None = None
        self.decompressor = zstandard.ZstdDecompressor()

    # ---- top level ----------------------------------------------------------------------

    def fail(self, where: int | str, what: str) -> LogFormatError:
        place = f"byte {where}" if isinstance(where, int) else where
        return LogFormatError(f"{self.path}: {place}: {what}")

    def chunk_at(self, chunks: list[_Chunk], bases: NDArray[np.int64], at: int) -> str:
        """Where a global arena offset lies, for error messages."""
        ci = int(np.searchsorted(bases, at, side="right") - 1)
        return f"chunk at byte {chunks[ci].start}, offset {at - int(bases[ci])}"

    def read(self) -> RunLog:
        buf, size = self.buf, self.size
        if size < len(MAGIC) or bytes(buf[: len(MAGIC)]) != MAGIC:
            raise LogFormatError(f"{self.path}: not an MCAP file (no MCAP magic at the start)")
        pos = len(MAGIC)
        if size < pos + _RECORD_HEAD:
            raise LogFormatError(f"{self.path}: an MCAP file that ends before its header")
        opcode, length = _OP_LEN.unpack_from(buf, pos)
        if opcode != OP_HEADER:
            raise self.fail(pos, "an MCAP file whose first record is not a header")
        if pos + _RECORD_HEAD + length > size:
            raise LogFormatError(f"{self.path}: an MCAP file that ends inside its header")
        cur = _Cursor(buf, pos + _RECORD_HEAD, pos + _RECORD_HEAD + length, f"{self.path}: header")
        profile, library = cur.string(), cur.string()
        if profile != PROFILE:
            raise LogFormatError(
                f"{self.path}: an MCAP file, but not a ballbeam log (profile {profile!r})"
            )
        pos += _RECORD_HEAD + length

        finished, reason = self.walk(pos)
        if self.pending is not None:  # the last chunk the walk saw, indexes or not
            self.add_to_batch(self.pending)
            self.pending = None
        self.flush_batch()
        self.decode_loose()
        topics, json_topics = self.assemble()
        return RunLog(
            path=self.path,
            profile=profile,
            library=library,
            topics=topics,
            json_topics=json_topics,
            metadata=self.metadata,
            attachments=self.attachments,
            truncated=not finished,
            truncation_reason=reason,
            last_complete_time_ns=self.last_time_ns,
            chunk_count=self.chunk_count,
            message_count=self.message_count,
        )

    def walk(self, pos: int) -> tuple[bool, str | None]:
        """Walk the top-level records; returns (finished with a footer, truncation reason)."""
        buf, size = self.buf, self.size
        unpack_head = _OP_LEN.unpack_from
        index_fixed = _INDEX_FIXED.unpack_from
        while pos < size:
            if pos + _RECORD_HEAD > size:
                return False, f"file ends inside a record header at byte {size}"
            opcode, length = unpack_head(buf, pos)
            body = pos + _RECORD_HEAD
            end = body + length
            if end > size:
                name = _OP_NAMES.get(opcode, f"opcode 0x{opcode:02x}")
                return False, (
                    f"file ends inside a {name} record at byte {size} "
                    f"(the record starts at byte {pos} and needs {end - size} more bytes)"
                )
            last = end == size
            chunk = self.pending
            if opcode != OP_MESSAGE_INDEX and chunk is not None:
                # Outside the try: errors in earlier chunks are never "last-record damage".
                self.add_to_batch(chunk)
                self.pending = chunk = None
            try:
                if opcode == OP_MESSAGE_INDEX:
                    if chunk is not None:
                        if length < 6:
                            raise self.fail(pos, "message index record too short")
                        channel_id, n_bytes = index_fixed(buf, body)
                        if n_bytes % 16 or 6 + n_bytes > length:
                            raise self.fail(pos, "message index length is inconsistent")
                        chunk.indexes.append((channel_id, body + 6, n_bytes // 16))
                    pos = end
                    continue
                if opcode == OP_CHUNK:
                    self.pending = self.open_chunk(pos, body, end)
                elif opcode == OP_MESSAGE:
                    self.loose_message(pos, body, end)
                elif opcode in (OP_SCHEMA, OP_CHANNEL):
                    self.definition(opcode, buf, body, end, f"byte {pos}")
                elif opcode == OP_METADATA:
                    cur = _Cursor(buf, body, end, f"{self.path}: metadata at byte {pos}")
                    name = cur.string()
                    self.metadata[name] = cur.str_map()
                elif opcode == OP_ATTACHMENT:
                    self.attachment(pos, body, end)
                elif opcode == OP_DATA_END:
                    self.data_end(pos, body, end)
                elif opcode == OP_FOOTER:
                    if end == size - len(MAGIC) and bytes(buf[end:]) == MAGIC:
                        return True, None
                    if size - end < len(MAGIC) and MAGIC.startswith(bytes(buf[end:])):
                        return False, f"file ends inside the closing magic at byte {size}"
                    raise self.fail(end, "the footer is not followed by the closing magic")
                elif opcode == OP_HEADER:
                    raise self.fail(pos, "a second header record")
                elif opcode == 0:
                    if not np.frombuffer(buf[pos:], np.uint8).any():
                        return False, f"file ends in {size - pos} zero bytes from byte {pos}"
                    raise self.fail(pos, "invalid record opcode 0x00")
                # Index, statistics, summary offset and unknown records carry nothing we need.
            except LogFormatError as exc:
                # Damage confined to the last record of an unfinished file (or to its last
                # chunk, followed only by that chunk's message indexes) is truncation.
                if last or (opcode == OP_CHUNK and self.only_indexes_follow(end)):
                    return False, f"damaged last record at byte {pos}: {exc}"
                raise
            pos = end
        return False, "no footer: the writer did not finish"

    def only_indexes_follow(self, pos: int) -> bool:
        """True if the file ends after complete message-index records from ``pos`` on."""
        while pos < self.size:
            if pos + _RECORD_HEAD > self.size:
                return True  # cut inside the last index: still the end of the file
            opcode, length = _OP_LEN.unpack_from(self.buf, pos)
            if opcode != OP_MESSAGE_INDEX:
                return False
            pos += _RECORD_HEAD + length
        return True

    # ---- top-level records --------------------------------------------------------------

    def definition(self, opcode: int, buf: memoryview, body: int, end: int, pos: str) -> None:
        """A schema or channel record, top-level or inside a chunk; ``pos`` says where."""
        cur = _Cursor(buf, body, end, f"{self.path}: {_OP_NAMES[opcode]} at {pos}")
        if opcode == OP_SCHEMA:
            schema_id = cur.u16()
            name, encoding = cur.string(), cur.string()
            data = cur.raw(cur.u32())
            if schema_id == 0:
                raise self.fail(pos, "schema id 0 is reserved")
            known = self.schemas.get(schema_id)
            if known is not None and known != (name, encoding, data):
                raise self.fail(pos, f"schema {schema_id} redefined differently")
            self.schemas[schema_id] = (name, encoding, data)
            return
        channel_id, schema_id = cur.u16(), cur.u16()
        topic, encoding = cur.string(), cur.string()
        meta = cur.str_map()
        record = (schema_id, topic, encoding, tuple(sorted(meta.items())))
        known_channel = self.channels.get(channel_id)
        if known_channel is not None:
            if known_channel.record != record:
                raise self.fail(pos, f"channel {channel_id} redefined differently")
            return
        self.channels[channel_id] = self.make_channel(pos, channel_id, record)

    def make_channel(self, pos: str, channel_id: int, record: tuple[Any, ...]) -> _Channel:
        schema_id, topic, encoding = record[0], record[1], record[2]
        schema_name, schema_encoding, schema_data = "", "", b""
        if schema_id != 0:
            if schema_id not in self.schemas:
                raise self.fail(pos, f"channel {topic!r} refers to unknown schema {schema_id}")
            schema_name, schema_encoding, schema_data = self.schemas[schema_id]
        kind, struct_schema = "other", None
        wanted = self.selected is None or topic in self.selected
        if encoding == MESSAGE_ENCODING and schema_encoding == SCHEMA_ENCODING:
            kind = "struct"
            if wanted:
                try:
                    text = schema_data.decode("utf-8")
                except UnicodeDecodeError as exc:
                    raise self.fail(pos, f"schema {schema_name!r} text is not UTF-8") from exc
                try:
                    struct_schema = parse_ros2msg(text, schema_name)
                except LogFormatError as exc:
                    raise self.fail(pos, f"channel {topic!r}: {exc}") from exc
        elif encoding == "json":
            kind = "json"
        elif wanted:
            raise self.fail(
                pos,
                f"channel {topic!r} uses {encoding!r}/{schema_encoding!r}, which this reader "
                "does not decode (pass topics= to skip it)",
            )
        for other in self.channels.values():
            if (
                other.topic == topic
                and other.kind == kind == "struct"
                and wanted
                and other.struct_schema != struct_schema
            ):
                raise self.fail(pos, f"topic {topic!r} has two channels with other schemas")
        return _Channel(
            channel_id, topic, encoding, schema_id, schema_name, kind, struct_schema, record
        )

    def attachment(self, pos: int, body: int, end: int) -> None:
        cur = _Cursor(self.buf, body, end, f"{self.path}: attachment at byte {pos}")
        cur.u64()  # log time
        cur.u64()  # create time
        name = cur.string()
        cur.string()  # media type
        data = cur.raw(cur.u64())
        crc_at = cur.pos
        crc = cur.u32()
        if crc and zlib.crc32(self.buf[body:crc_at]) != crc:
            raise self.fail(pos, f"attachment {name!r} fails its CRC")
        self.attachments[name] = data

    def data_end(self, pos: int, body: int, end: int) -> None:
        crc = _Cursor(self.buf, body, end, f"{self.path}: data end at byte {pos}").u32()
        # The CRC covers everything before this record, magic included; 0 means not computed.
        if crc and zlib.crc32(self.buf[:pos]) != crc:
            raise self.fail(pos, "the data section fails its CRC")

    def loose_message(self, pos: int, body: int, end: int) -> None:
        if end - body < _MESSAGE_HEAD - _RECORD_HEAD:
            raise self.fail(pos, "message record too short")
        channel_id, _, log_time, _ = _MSG_FIXED.unpack_from(self.buf, body)
        self.loose.append((channel_id, log_time, body + 22, end))
        self.message_count += 1
        self.note_time(int(log_time))

    def note_time(self, log_time_ns: int) -> None:
        if self.last_time_ns is None or log_time_ns > self.last_time_ns:
            self.last_time_ns = log_time_ns

    # ---- chunks -------------------------------------------------------------------------

    def open_chunk(self, pos: int, body: int, end: int) -> _Chunk:
        where = f"chunk at byte {pos}"
        cur = _Cursor(self.buf, body, end, f"{self.path}: {where}")
        _, _, uncompressed_size, crc = _CHUNK_FIXED.unpack_from(self.buf, cur.take(28))
        compression = cur.string()
        n = cur.u64()
        start = cur.take(n)
        data = self.buf[start : start + n]
        if uncompressed_size > _MAX_CHUNK_BYTES:
            raise self.fail(where, f"chunk claims {uncompressed_size} bytes uncompressed")
        try:
            if compression == "zstd":
                declared = zstandard.frame_content_size(data)
                if declared not in (-1, uncompressed_size):
                    raise ValueError(f"frame says {declared} bytes")
                out = self.decompressor.decompress(data, max_output_size=uncompressed_size)
            elif compression == "lz4":
                if _lz4 is None:
                    raise self.fail(where, "chunk is lz4-compressed and the lz4 module is missing")
                declared = _lz4.get_frame_info(data).get("content_size", 0)
                if declared not in (0, uncompressed_size):
                    raise ValueError(f"frame says {declared} bytes")
                out = _lz4.decompress(data)
            elif compression == "":
                out = bytes(data)
            else:
                raise self.fail(where, f"unknown chunk compression {compression!r}")
        except (zstandard.ZstdError, ValueError, RuntimeError) as exc:
            if isinstance(exc, LogFormatError):
                raise
            raise self.fail(where, f"{compression} data does not decompress: {exc}") from exc
        if len(out) != uncompressed_size:
            raise self.fail(
                where, f"chunk decompresses to {len(out)} bytes, not the {uncompressed_size} stated"
            )
        if crc and zlib.crc32(out) != crc:
            raise self.fail(where, "chunk fails its CRC")
        return _Chunk(pos, out)

    def add_to_batch(self, chunk: _Chunk) -> None:
        self.batch.append(chunk)
        self.batch_bytes += len(chunk.buf)
        self.chunk_count += 1
        if self.batch_bytes >= _BATCH_BYTES:
            self.flush_batch()

    def flush_batch(self) -> None:
        chunks, self.batch, self.batch_bytes = self.batch, [], 0
        if chunks:
            self.decode_chunks(chunks)

    def decode_chunks(self, chunks: list[_Chunk]) -> None:
        """Locate and decode every message of a batch of chunks, vectorised per channel."""
        sizes = np.array([len(c.buf) for c in chunks], np.int64)
        bases = np.zeros(len(chunks), np.int64)
        np.cumsum(sizes[:-1], out=bases[1:])
        arena = chunks[0].buf if len(chunks) == 1 else b"".join(c.buf for c in chunks)
        arr = np.frombuffer(arena, np.uint8)

        # 1. Every message-index entry of the batch, chunk by chunk.
        views: list[NDArray[np.uint64]] = []
        idx_channel: list[int] = []
        idx_chunk: list[int] = []
        idx_count: list[int] = []
        for ci, chunk in enumerate(chunks):
            for channel_id, offset, n in chunk.indexes:
                if n:
                    views.append(np.frombuffer(self.buf, "<u8", 2 * n, offset))
                    idx_channel.append(channel_id)
                    idx_chunk.append(ci)
                    idx_count.append(n)
        if views:
            entries = np.concatenate(views).reshape(-1, 2)
            del views
            counts = np.array(idx_count, np.int64)
            ts_all = entries[:, 0].astype(np.int64)
            chunk_of = np.repeat(np.array(idx_chunk, np.int64), counts)
            chan_all = np.repeat(np.array(idx_channel, np.int64), counts)
            # Offsets and times are unsigned in the file; bound them before any arithmetic.
            huge = (entries[:, 0] >= np.uint64(1 << 63)) | (entries[:, 1] >= np.uint64(1 << 62))
            off = np.where(huge, 0, entries[:, 1]).astype(np.int64)
            bad = huge | (off > sizes[chunk_of] - 11)
            if bad.any():
                ci = int(chunk_of[np.argmax(bad)])
                raise self.fail(
                    chunks[ci].start, "a message index entry lies outside its chunk or time range"
                )
            goff = off + bases[chunk_of]
            head = sliding_window_view(arr, 11)[goff].view(_HEAD_DTYPE)[:, 0]
            lengths = head["len"]
            ok = (
                (head["op"] == OP_MESSAGE)
                & (head["ch"] == chan_all)
                & (lengths >= _MESSAGE_HEAD - _RECORD_HEAD)
                & (lengths <= (sizes[chunk_of] - off - _RECORD_HEAD).astype(np.uint64))
            )
            if not ok.all():
                ci = int(chunk_of[np.argmin(ok)])
                raise self.fail(
                    chunks[ci].start, "a message index entry does not point at its message"
                )
            # 2. Chunks whose indexed messages fill them exactly need no scanning beyond
            #    their head (schema and channel records); others are scanned record by record.
            covered = np.bincount(
                chunk_of, weights=(lengths + _RECORD_HEAD).astype(np.float64), minlength=len(chunks)
            )
            starts = np.flatnonzero(np.r_[True, chunk_of[1:] != chunk_of[:-1]])
            first = np.full(len(chunks), -1, np.int64)
            first[chunk_of[starts]] = np.minimum.reduceat(off, starts)
        else:
            ts_all = np.zeros(0, np.int64)
            chunk_of = chan_all = goff = np.zeros(0, np.int64)
            lengths = np.zeros(0, np.uint64)
            covered = np.zeros(len(chunks), np.float64)
            first = np.full(len(chunks), -1, np.int64)

        scanned: list[tuple[int, int, int, int]] = []  # (global offset, log time, channel, len)
        rescan = np.zeros(len(chunks), bool)
        for ci, chunk in enumerate(chunks):
            head_bytes = int(first[ci]) if first[ci] >= 0 else 0
            if first[ci] >= 0 and head_bytes + int(covered[ci]) == len(chunk.buf):
                if head_bytes:
                    self.scan(chunk, 0, head_bytes, int(bases[ci]), scanned)
            else:
                rescan[ci] = True
                self.scan(chunk, 0, len(chunk.buf), int(bases[ci]), scanned)
        if rescan.any():
            keep = ~rescan[chunk_of]
            ts_all, chan_all, goff, lengths = (
                ts_all[keep],
                chan_all[keep],
                goff[keep],
                lengths[keep],
            )
        if scanned:
            extra = np.array(scanned, np.int64).reshape(-1, 4)
            goff = np.concatenate([goff, extra[:, 0]])
            ts_all = np.concatenate([ts_all, extra[:, 1]])
            chan_all = np.concatenate([chan_all, extra[:, 2]])
            lengths = np.concatenate([lengths, extra[:, 3].astype(np.uint64)])
        if len(ts_all) == 0:
            return
        self.message_count += len(ts_all)
        self.note_time(int(ts_all.max()))

        # 3. Decode, one channel at a time.
        for channel_id in np.unique(chan_all).tolist():
            channel = self.channels.get(channel_id)
            mask = chan_all == channel_id
            if channel is None:
                where = self.chunk_at(chunks, bases, int(goff[mask][0]))
                raise self.fail(where, f"messages on undefined channel {channel_id}")
            if self.selected is not None and channel.topic not in self.selected:
                continue
            if channel.kind == "struct":
                self.gather_struct(
                    channel, arr, goff[mask], ts_all[mask], lengths[mask], chunks, bases
                )
            elif channel.kind == "json":
                self.gather_json(channel, arena, goff[mask], lengths[mask])

    def scan(
        self,
        chunk: _Chunk,
        start: int,
        stop: int,
        base: int,
        out: list[tuple[int, int, int, int]],
    ) -> None:
        """Parse the records of chunk.buf[start:stop] one by one (the slow, general path)."""
        data = memoryview(chunk.buf)
        pos = start
        while pos < stop:
            if pos + _RECORD_HEAD > stop:
                raise self.fail(chunk.start, f"chunk content is cut inside a record at {pos}")
            opcode, length = _OP_LEN.unpack_from(data, pos)
            body = pos + _RECORD_HEAD
            end = body + length
            if end > stop:
                raise self.fail(chunk.start, f"a record in the chunk overruns it (at {pos})")
            if opcode == OP_MESSAGE:
                if length < _MESSAGE_HEAD - _RECORD_HEAD:
                    raise self.fail(chunk.start, f"message record too short at {pos}")
                channel_id, _, log_time, _ = _MSG_FIXED.unpack_from(data, body)
                if log_time >= 1 << 63:
                    raise self.fail(chunk.start, f"message log time out of range at {pos}")
                out.append((base + pos, log_time, channel_id, length))
            elif opcode in (OP_SCHEMA, OP_CHANNEL):
                where = f"chunk at byte {chunk.start}, offset {pos}"
                self.definition(opcode, data, body, end, where)
            pos = end

    def gather_struct(
        self,
        channel: _Channel,
        arr: NDArray[np.uint8],
        goff: NDArray[np.int64],
        ts: NDArray[np.int64],
        lengths: NDArray[np.uint64],
        chunks: list[_Chunk],
        bases: NDArray[np.int64],
    ) -> None:
        schema = channel.struct_schema
        assert schema is not None
        expected = _MESSAGE_HEAD - _RECORD_HEAD + schema.size
        wrong = lengths != expected
        if wrong.any():
            raise self.fail(
                self.chunk_at(chunks, bases, int(goff[np.argmax(wrong)])),
                f"topic {channel.topic!r}: a payload of {int(lengths[np.argmax(wrong)]) - 22} "
                f"bytes does not match schema {schema.name!r} ({schema.size} bytes)",
            )
        width = _MESSAGE_HEAD + schema.size
        rows = sliding_window_view(arr, width)[goff]  # (n, width): one copy per message
        record = np.dtype(
            {
                "names": ["log_time", "enc", "payload"],
                "formats": ["<u8", ">u2", schema.dtype],
                "offsets": [15, _MESSAGE_HEAD, _MESSAGE_HEAD],
                "itemsize": width,
            }
        )
        rec = rows.view(record)[:, 0]
        not_cdr = rec["enc"] != 1
        if not_cdr.any():
            raise self.fail(
                self.chunk_at(chunks, bases, int(goff[np.argmax(not_cdr)])),
                f"topic {channel.topic!r}: a payload is not little-endian plain CDR",
            )
        times = rec["log_time"].astype(np.int64)
        disagree = times != ts
        if disagree.any():
            raise self.fail(
                self.chunk_at(chunks, bases, int(goff[np.argmax(disagree)])),
                f"topic {channel.topic!r}: the message index and the message disagree on time",
            )
        parts = self.parts.setdefault(channel.channel_id, _TopicParts())
        parts.times.append(times)
        parts.values.append(rec["payload"].copy())

    def gather_json(
        self,
        channel: _Channel,
        arena: bytes,
        goff: NDArray[np.int64],
        lengths: NDArray[np.uint64],
    ) -> None:
        parts = self.parts.setdefault(channel.channel_id, _TopicParts())
        for at, length in zip(goff.tolist(), lengths.tolist(), strict=True):
            log_time = int(_U64.unpack_from(arena, at + 15)[0])
            payload = arena[at + _MESSAGE_HEAD : at + _RECORD_HEAD + length]
            parts.json.append((log_time, self.json_message(channel, payload)))

    def json_message(self, channel: _Channel, payload: bytes) -> dict[str, Any]:
        try:
            value = json.loads(payload)
        except (ValueError, RecursionError) as exc:
            raise LogFormatError(
                f"{self.path}: topic {channel.topic!r}: a message is not JSON: {exc}"
            ) from exc
        if not isinstance(value, dict):
            raise LogFormatError(
                f"{self.path}: topic {channel.topic!r}: a message is not an object"
            )
        return value

    # ---- unchunked messages -------------------------------------------------------------

    def decode_loose(self) -> None:
        by_channel: dict[int, list[tuple[int, int, int]]] = {}
        for channel_id, log_time, start, end in self.loose:
            by_channel.setdefault(channel_id, []).append((log_time, start, end))
        for channel_id, items in by_channel.items():
            channel = self.channels.get(channel_id)
            if channel is None:
                raise LogFormatError(f"{self.path}: messages on undefined channel {channel_id}")
            if self.selected is not None and channel.topic not in self.selected:
                continue
            parts = self.parts.setdefault(channel_id, _TopicParts())
            if channel.kind == "json":
                for log_time, start, end in items:
                    parts.json.append(
                        (log_time, self.json_message(channel, bytes(self.buf[start:end])))
                    )
                continue
            schema = channel.struct_schema
            assert schema is not None
            if any(end - start != schema.size for _, start, end in items):
                raise LogFormatError(
                    f"{self.path}: topic {channel.topic!r}: a payload does not match schema "
                    f"{schema.name!r} ({schema.size} bytes)"
                )
            joined = b"".join(self.buf[start:end] for _, start, end in items)
            values = np.frombuffer(joined, schema.dtype).copy()
            # (A structured copy leaves out the unnamed header bytes: check the raw bytes.)
            if (np.frombuffer(joined, np.uint8).reshape(len(items), -1)[:, :2] != (0, 1)).any():
                raise LogFormatError(
                    f"{self.path}: topic {channel.topic!r}: a payload is not little-endian CDR"
                )
            parts.times.append(np.array([t for t, _, _ in items], np.int64))
            parts.values.append(values)

    # ---- results ------------------------------------------------------------------------

    def assemble(self) -> tuple[dict[str, StructTopic], dict[str, JsonTopic]]:
        topics: dict[str, StructTopic] = {}
        json_topics: dict[str, JsonTopic] = {}
        by_topic: dict[str, list[_Channel]] = {}
        for channel in self.channels.values():
            if self.selected is None or channel.topic in self.selected:
                by_topic.setdefault(channel.topic, []).append(channel)
        for topic, channels in by_topic.items():
            kind = channels[0].kind
            parts = [self.parts[c.channel_id] for c in channels if c.channel_id in self.parts]
            if kind == "struct":
                schema = channels[0].struct_schema
                assert schema is not None
                times_list = [t for p in parts for t in p.times]
                values_list = [v for p in parts for v in p.values]
                times = np.concatenate(times_list) if times_list else np.zeros(0, np.int64)
                values = np.concatenate(values_list) if values_list else np.zeros(0, schema.dtype)
                if len(times) > 1 and (times[1:] < times[:-1]).any():
                    order = np.argsort(times, kind="stable")
                    times, values = times[order], values[order]
                topics[topic] = StructTopic(topic, schema, times, values)
            elif kind == "json":
                items = sorted((item for p in parts for item in p.json), key=lambda x: x[0])
                json_topics[topic] = JsonTopic(
                    topic,
                    channels[0].schema_name,
                    np.array([t for t, _ in items], np.int64),
                    tuple(m for _, m in items),
                )
        return topics, json_topics


__all__ = ["MAGIC", "PROFILE", "JsonTopic", "RunLog", "StructTopic", "read_log"]
