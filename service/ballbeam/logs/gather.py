"""The vectorised gather of :mod:`ballbeam.logs.reader`: whole channels decoded at once.

The Message Index records that follow a chunk locate its messages: every fixed-layout
(``ros2msg``/``cdr``) payload of a channel is copied out of the decompressed chunks with one
numpy fancy-index and viewed as the channel's structured dtype, after its length, encoding and
log time were checked for all messages at once. Nothing per message runs in Python except on
JSON channels, which carry rare events (and go through ``json.loads`` only), and on messages
written outside chunks.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view
from numpy.typing import NDArray

from ballbeam.errors import LogFormatError
from ballbeam.logs.mcap_records import (
    _MESSAGE_HEAD,
    _RECORD_HEAD,
    _U64,
    OP_MESSAGE,
    _Channel,
    _Chunk,
    _RecordWalk,
)
from ballbeam.logs.schema import StructSchema

# The leading bytes of a message record, as gathered for every indexed message.
_HEAD_DTYPE = np.dtype(
    {"names": ["op", "len", "ch"], "formats": ["u1", "<u8", "<u2"], "offsets": [0, 1, 9]}
)
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


@dataclass
class _TopicParts:
    times: list[NDArray[np.int64]] = field(default_factory=list)
    values: list[NDArray[np.void]] = field(default_factory=list)
    json: list[tuple[int, dict[str, Any]]] = field(default_factory=list)


class _Gather(_RecordWalk):
    """The record walk, with the chunks it hands on decoded in batches, channel by channel."""

    def __init__(self, buf: memoryview, path: str, selected: frozenset[str] | None) -> None:
        super().__init__(buf, path, selected)
        self.parts: dict[int, _TopicParts] = {}
        self.batch: list[_Chunk] = []
        self.batch_bytes = 0

    def chunk_at(self, chunks: list[_Chunk], bases: NDArray[np.int64], at: int) -> str:
        """Where a global arena offset lies, for error messages."""
        ci = int(np.searchsorted(bases, at, side="right") - 1)
        return f"chunk at byte {chunks[ci].start}, offset {at - int(bases[ci])}"

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
