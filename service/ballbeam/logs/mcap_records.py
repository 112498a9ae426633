"""The MCAP record walk of :mod:`ballbeam.logs.reader`: records, chunks, CRCs, truncation.

The walk goes through the top-level records from the start of the file (it never needs the
summary section, which a crashed writer never wrote): it checks the magic and the header,
collects schemas, channels, metadata and attachments, checks CRCs where the writer stored them,
decompresses each complete chunk and notes the Message Index records that follow it. Complete
chunks go to :meth:`_RecordWalk.add_to_batch`, where :mod:`ballbeam.logs.gather` decodes them.
A file without a footer, or whose damage is confined to its last record, ends the walk as
truncated rather than as an error.
"""

from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ballbeam.errors import DecompressionBombError, LogFormatError
from ballbeam.logs.decompression import decompress_chunk
from ballbeam.logs.schema import MESSAGE_ENCODING, SCHEMA_ENCODING, StructSchema, parse_ros2msg

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


class _RecordWalk:
    """The walk's state and its record parsers; a subclass decodes the chunks it hands on."""

    def __init__(self, buf: memoryview, path: str, selected: frozenset[str] | None) -> None:
        self.buf = buf
        self.size = len(buf)
        self.path = path
        self.selected = selected
        self.schemas: dict[int, tuple[str, str, bytes]] = {}
        self.channels: dict[int, _Channel] = {}
        self.metadata: dict[str, dict[str, str]] = {}
        self.attachments: dict[str, bytes] = {}
        self.loose: list[tuple[int, int, int, int]] = []  # (channel, log time, start, end)
        self.pending: _Chunk | None = None  # the chunk whose message indexes may follow
        self.chunk_count = 0
        self.message_count = 0
        self.last_time_ns: int | None = None

    # ---- top level ----------------------------------------------------------------------

    def fail(self, where: int | str, what: str) -> LogFormatError:
        place = f"byte {where}" if isinstance(where, int) else where
        return LogFormatError(f"{self.path}: {place}: {what}")

    def add_to_batch(self, chunk: _Chunk) -> None:
        """Take a complete chunk, with the message indexes that followed it, for decoding."""
        raise NotImplementedError

    def header(self) -> tuple[str, str, int]:
        """Check the magic and the header record: (profile, library, where the records go on)."""
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
        return profile, library, pos

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
                # chunk, followed only by that chunk's message indexes) is truncation; a
                # decompression bomb is hostile wherever it is.
                if isinstance(exc, DecompressionBombError):
                    raise
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
        try:
            out = decompress_chunk(compression, data, uncompressed_size)
        except LogFormatError as exc:  # bounded: never more than the chunk states
            raise type(exc)(f"{self.path}: {where}: {exc}") from exc
        if crc and zlib.crc32(out) != crc:
            raise self.fail(where, "chunk fails its CRC")
        return _Chunk(pos, out)

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
