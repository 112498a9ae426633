"""MCAP file assembly for the recorder: cheap per message, flat in memory.

The mcap library's ``Writer`` spends several microseconds of Python on each message and keeps
every chunk's index record in memory until ``finish()``. At ten messages per control cycle that
was the daemon's largest cost in lock-step, and a run's memory grew with its length (a chunk
every 50 ms). This writer produces the same format with two differences (figures: README,
benchmarks):

* a message is one ``struct.pack`` appended to the open chunk, and its index entry two
  integers appended to an array;
* each chunk's index record is spilled to an anonymous temporary file as the chunk is written,
  and read back once into the summary section at the end.

Everything except messages, message indexes and the footer (whose CRC covers its own leading
fields) is serialised by the mcap library's own record classes. Schemas and channels are
written to the data section outside chunks, before any chunk that uses them. Not thread-safe:
the recorder serialises access.
"""

from __future__ import annotations

import contextlib
import struct
import sys
import tempfile
import zlib
from array import array
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from typing import IO

import zstandard
from mcap.data_stream import RecordBuilder
from mcap.opcode import Opcode
from mcap.records import Attachment as AttachmentRecord
from mcap.records import (
    AttachmentIndex,
    Channel,
    Chunk,
    ChunkIndex,
    DataEnd,
    Header,
    McapRecord,
    Metadata,
    MetadataIndex,
    Schema,
    Statistics,
    SummaryOffset,
)
from mcap.writer import MCAP0_MAGIC

# opcode, record length, channel id, sequence, log time, publish time (MCAP "Message")
_MESSAGE_HEAD = struct.Struct("<BQHIQQ")
_MESSAGE_FIXED_BYTES = 2 + 4 + 8 + 8
# opcode, record length, channel id, byte length of the (log time, offset) pairs
_MESSAGE_INDEX_HEAD = struct.Struct("<BQHI")
# opcode, record length, summary start, summary offset start; then the summary CRC
_FOOTER_HEAD = struct.Struct("<BQQQ")
_U32 = struct.Struct("<I")
_RECORD_LENGTH = struct.Struct("<Q")
_LITTLE_ENDIAN = sys.byteorder == "little"
COMPRESSION = "zstd"


def _record_bytes(record: McapRecord) -> bytes:
    builder = RecordBuilder()
    record.write(builder)
    data: bytes = builder.end()  # type: ignore[no-untyped-call]
    return data


def _spill_file(directory: str | None) -> IO[bytes]:
    """An unnamed file for chunk indexes: in ``directory`` (the log's, so that a full disk is
    the log's own disk) where it may be created there, else in the system's temporary one."""
    if directory is not None:
        with contextlib.suppress(OSError):
            return tempfile.TemporaryFile(dir=directory)
    return tempfile.TemporaryFile()


@dataclass
class OpenChunk:
    """Messages not yet written: their records, and per channel (log time, offset) pairs."""

    records: bytearray = field(default_factory=bytearray)
    index: dict[int, array[int]] = field(default_factory=dict)
    start_ns: int = 0
    end_ns: int = 0
    messages: int = 0


def records_messages(records: bytes) -> Iterator[tuple[int, int, bytes]]:
    """The (channel id, log time, payload) of each message in a chunk's records, in order.

    ``records`` is an uncompressed chunk's content as :meth:`McapFile.write_chunk` compresses
    it (:attr:`OpenChunk.records`): the live view's server process reads the chunks the
    daemon hands it with this. Records other than messages are skipped."""
    unpack_head = _MESSAGE_HEAD.unpack_from
    head = _MESSAGE_HEAD.size
    offset, size = 0, len(records)
    while offset < size:
        opcode, length, channel_id, _, log_time_ns, _ = unpack_head(records, offset)
        # A record's length field counts the bytes after it (opcode: 1, length: 8).
        end = offset + 9 + length
        if opcode == Opcode.MESSAGE:
            yield channel_id, log_time_ns, records[offset + head : end]
        offset = end


class McapFile:
    """One MCAP file being written to ``stream`` (which must be open for binary writing).

    The magic and the header are written at once; :meth:`finish` writes the summary and the
    footer. Offsets are counted here, so the stream need not be seekable. ``spill_dir`` holds
    the unnamed file of chunk indexes where it can (else: the system's temporary directory).
    """

    def __init__(
        self, stream: IO[bytes], *, profile: str, library: str, spill_dir: str | None = None
    ) -> None:
        self._stream = stream
        self._position = 0
        # CRC-32 of everything before the Data End record (the spec's data-section CRC): a
        # duplicated, removed or altered chunk is then detected by a reader that checks it.
        self._data_crc = 0
        self._in_data_section = True
        self._compressor = zstandard.ZstdCompressor()
        self._schemas: list[Schema] = []
        self._channels: list[Channel] = []
        self._sequence: dict[int, int] = {}
        self._channel_counts: dict[int, int] = {}
        self._message_count = 0
        self._start_ns = 0
        self._end_ns = 0
        self._chunk_count = 0
        self._attachment_indexes: list[AttachmentIndex] = []
        self._metadata_indexes: list[MetadataIndex] = []
        # Chunk indexes go to disk as they are made: memory stays flat however long the run.
        # An unnamed file: nothing is left behind by a crash.
        self._chunk_index_spill = _spill_file(spill_dir)
        self._chunk = OpenChunk()
        self._write(MCAP0_MAGIC)
        self._write(_record_bytes(Header(profile=profile, library=library)))

    def _write(self, data: bytes | bytearray | memoryview) -> None:
        self._stream.write(data)
        self._position += len(data)
        if self._in_data_section:
            self._data_crc = zlib.crc32(data, self._data_crc)

    # -- definitions and out-of-chunk records (rare; each written at once) --------------------
    def add_schema(self, name: str, encoding: str, data: bytes) -> int:
        schema = Schema(id=len(self._schemas) + 1, name=name, encoding=encoding, data=data)
        self._write(_record_bytes(schema))
        self._schemas.append(schema)
        return schema.id

    def add_channel(self, topic: str, message_encoding: str, schema_id: int) -> int:
        channel = Channel(
            id=len(self._channels) + 1,
            topic=topic,
            message_encoding=message_encoding,
            schema_id=schema_id,
            metadata={},
        )
        self._write(_record_bytes(channel))
        self._channels.append(channel)
        self._sequence[channel.id] = 0
        self._channel_counts[channel.id] = 0
        return channel.id

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        record = _record_bytes(Metadata(name=name, metadata=data))
        self._metadata_indexes.append(
            MetadataIndex(offset=self._position, length=len(record), name=name)
        )
        self._write(record)

    def add_attachment(self, time_ns: int, name: str, media_type: str, data: bytes) -> None:
        record = _record_bytes(
            AttachmentRecord(
                create_time=time_ns, log_time=time_ns, name=name, media_type=media_type, data=data
            )
        )
        self._attachment_indexes.append(
            AttachmentIndex(
                offset=self._position,
                length=len(record),
                create_time=time_ns,
                log_time=time_ns,
                data_size=len(data),
                name=name,
                media_type=media_type,
            )
        )
        self._write(record)

    # -- messages (hot path) ------------------------------------------------------------------
    def add_message(self, channel_id: int, log_time_ns: int, data: bytes) -> None:
        """Append one message to the open chunk. ``channel_id`` must come from add_channel."""
        chunk = self._chunk
        records = chunk.records
        offset = len(records)
        sequence = self._sequence[channel_id]
        self._sequence[channel_id] = (sequence + 1) & 0xFFFF_FFFF
        records += _MESSAGE_HEAD.pack(
            Opcode.MESSAGE, _MESSAGE_FIXED_BYTES + len(data), channel_id, sequence,
            log_time_ns, log_time_ns,
        )
        records += data
        pairs = chunk.index.get(channel_id)
        if pairs is None:
            pairs = chunk.index[channel_id] = array("Q")
        pairs.append(log_time_ns)
        pairs.append(offset)
        if chunk.messages == 0:
            chunk.start_ns = chunk.end_ns = log_time_ns
        elif log_time_ns < chunk.start_ns:
            chunk.start_ns = log_time_ns
        elif log_time_ns > chunk.end_ns:
            chunk.end_ns = log_time_ns
        chunk.messages += 1

    @property
    def open_bytes(self) -> int:
        return len(self._chunk.records)

    def take_chunk(self) -> OpenChunk | None:
        """Close the open chunk and return it for :meth:`write_chunk` (None when empty).

        Cheap: the expensive part (compression, I/O) is write_chunk, which a writer thread
        may run while messages go on into the next chunk."""
        chunk = self._chunk
        if chunk.messages == 0:
            return None
        self._chunk = OpenChunk()
        return chunk

    def write_chunk(self, chunk: OpenChunk) -> None:
        """Compress and write a taken chunk, then its message indexes."""
        records = chunk.records
        compressed = self._compressor.compress(records)
        chunk_start = self._position
        self._write(
            _record_bytes(
                Chunk(
                    compression=COMPRESSION,
                    data=compressed,
                    message_start_time=chunk.start_ns,
                    message_end_time=chunk.end_ns,
                    uncompressed_crc=zlib.crc32(records),
                    uncompressed_size=len(records),
                )
            )
        )
        chunk_length = self._position - chunk_start

        index_offsets: dict[int, int] = {}
        index_start = self._position
        for channel_id, pairs in chunk.index.items():
            self._channel_counts[channel_id] += len(pairs) // 2
            if not _LITTLE_ENDIAN:
                pairs.byteswap()
            entries = pairs.tobytes()
            index_offsets[channel_id] = self._position
            self._write(
                _MESSAGE_INDEX_HEAD.pack(
                    Opcode.MESSAGE_INDEX, 2 + 4 + len(entries), channel_id, len(entries)
                )
                + entries
            )
        self._chunk_index_spill.write(
            _record_bytes(
                ChunkIndex(
                    message_start_time=chunk.start_ns,
                    message_end_time=chunk.end_ns,
                    chunk_start_offset=chunk_start,
                    chunk_length=chunk_length,
                    message_index_offsets=index_offsets,
                    message_index_length=self._position - index_start,
                    compression=COMPRESSION,
                    compressed_size=len(compressed),
                    uncompressed_size=len(records),
                )
            )
        )
        if self._chunk_count == 0:
            self._start_ns, self._end_ns = chunk.start_ns, chunk.end_ns
        else:
            self._start_ns = min(self._start_ns, chunk.start_ns)
            self._end_ns = max(self._end_ns, chunk.end_ns)
        self._chunk_count += 1
        self._message_count += chunk.messages

    # -- the end ------------------------------------------------------------------------------
    def finish(self) -> None:
        """Write any open chunk, the data end, the summary (with its offsets) and the footer."""
        chunk = self.take_chunk()
        if chunk is not None:
            self.write_chunk(chunk)
        self._in_data_section = False
        self._write(_record_bytes(DataEnd(data_section_crc=self._data_crc)))
        summary_start = self._position
        summary_crc = 0
        offsets: list[SummaryOffset] = []

        def group(opcode: Opcode | None, blocks: Iterable[bytes]) -> None:
            """Write summary bytes (into the CRC) and, unless ``opcode`` is None, offer them
            to readers as one group through a summary offset."""
            nonlocal summary_crc
            start = self._position
            for block in blocks:
                summary_crc = zlib.crc32(block, summary_crc)
                self._write(block)
            if opcode is not None and self._position > start:
                offsets.append(SummaryOffset(opcode, start, self._position - start))

        group(Opcode.SCHEMA, map(_record_bytes, self._schemas))
        group(Opcode.CHANNEL, map(_record_bytes, self._channels))
        group(Opcode.STATISTICS, [_record_bytes(self._statistics())])
        spill = self._chunk_index_spill
        spill.seek(0)
        group(Opcode.CHUNK_INDEX, iter(lambda: spill.read(1 << 20), b""))
        spill.close()
        group(Opcode.ATTACHMENT_INDEX, map(_record_bytes, self._attachment_indexes))
        group(Opcode.METADATA_INDEX, map(_record_bytes, self._metadata_indexes))
        summary_offset_start = self._position
        group(None, map(_record_bytes, offsets))
        footer_head = _FOOTER_HEAD.pack(
            Opcode.FOOTER, 8 + 8 + 4, summary_start, summary_offset_start
        )
        self._write(footer_head + _U32.pack(zlib.crc32(footer_head, summary_crc)))
        self._write(MCAP0_MAGIC)

    def discard(self) -> None:
        """Give up on the file (after a write error): free the spill file."""
        self._chunk_index_spill.close()

    def _statistics(self) -> Statistics:
        return Statistics(
            message_count=self._message_count,
            schema_count=len(self._schemas),
            channel_count=len(self._channels),
            attachment_count=len(self._attachment_indexes),
            metadata_count=len(self._metadata_indexes),
            chunk_count=self._chunk_count,
            message_start_time=self._start_ns,
            message_end_time=self._end_ns,
            channel_message_counts={
                channel_id: count for channel_id, count in self._channel_counts.items() if count
            },
        )
