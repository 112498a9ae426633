"""Make a cut log whole: every intact record of a log whose writer died, written again as a
complete, indexed MCAP (what ``mcap recover`` does, with the official mcap library).

A log cut short (the daemon killed, the machine down) ends inside a chunk: the records up to the
last complete chunk are read with the library's stream reader (chunk CRCs checked), and written
with its writer, which adds the summary, the indexes and the footer that a seeking reader needs.
The messages keep their channel, sequence number and times; schemas, channels, attachments and
metadata are copied as they were.
"""

from __future__ import annotations

import os
import struct
from collections.abc import Iterator
from dataclasses import dataclass, replace
from pathlib import Path
from typing import IO, BinaryIO, cast

import zstandard
from mcap.exceptions import McapError
from mcap.records import (
    Attachment,
    Channel,
    Chunk,
    Footer,
    Header,
    McapRecord,
    Message,
    Metadata,
    Schema,
)
from mcap.stream_reader import StreamReader, breakup_chunk
from mcap.writer import CompressionType, Writer

from ballbeam.errors import DecompressionBombError, LogFormatError
from ballbeam.files import link_new, not_a_regular_file, temporary_beside
from ballbeam.logs.decompression import decompress_chunk

# What the stream reader raises where a file stops being a readable MCAP (a cut record, a bad
# CRC, a short magic).
_WHERE_THE_CUT_IS = (
    McapError, EOFError, ValueError, OSError, RuntimeError, struct.error, zstandard.ZstdError
)
RECORD_SIZE_LIMIT = 64 << 20  # no record of ours comes near this; a hostile one is refused


@dataclass(frozen=True)
class Recovery:
    source: Path
    destination: Path
    was_complete: bool  # the source already ended with a footer
    stopped_because: str | None  # why reading stopped before a footer (None: it had one)
    messages: int
    attachments: int
    metadata: int
    last_log_time_ns: int | None  # the latest message kept
    # Why reading stopped at a chunk that would inflate past its stated size (a decompression
    # bomb: hostile, not a cut); everything before it was kept. None otherwise.
    refused: str | None = None


def recovered_path(source: Path) -> Path:
    return source.with_name(f"{source.stem}.recovered.mcap")


def recover_log(source: Path, destination: Path) -> Recovery:
    """Write ``destination`` from the intact records of ``source``. LogFormatError if
    ``source`` is not an MCAP file or holds nothing to recover; OSError if a file cannot be
    read or written. ``destination`` is written to a temporary name and linked into place when
    whole, never over anything already there."""
    problem = not_a_regular_file(source)
    if problem is not None:
        raise LogFormatError(f"{source}: not a log: {problem}")
    if destination.resolve() == source.resolve():
        raise LogFormatError(f"{source}: the recovered log must go to another file")
    # A new temporary file under a random name (nothing planted there is written through),
    # linked into place only if nothing is at ``destination`` (OutputExistsError if so).
    temporary, writing = temporary_beside(destination)
    try:
        with writing:
            recovery = _copy_intact(source, destination, writing)
        link_new(temporary, destination)
    finally:
        temporary.unlink(missing_ok=True)
    return recovery


def _copy_intact(source: Path, destination: Path, writing: BinaryIO) -> Recovery:
    counts = {"messages": 0, "attachments": 0, "metadata": 0}
    last_log_time_ns: int | None = None
    was_complete = False
    stopped_because: str | None = None
    refused: str | None = None
    schema_ids: dict[int, int] = {}
    channel_ids: dict[int, int] = {}
    with open(source, "rb") as reading:
        writer: Writer | None = None
        try:
            for record in _records(reading):
                if isinstance(record, Header):
                    writer = Writer(writing, compression=CompressionType.ZSTD)
                    writer.start(profile=record.profile, library=record.library)
                    continue
                if writer is None:
                    raise LogFormatError(f"{source}: no MCAP header; nothing to recover")
                if isinstance(record, Schema):
                    schema_ids[record.id] = writer.register_schema(
                        record.name, record.encoding, record.data
                    )
                elif isinstance(record, Channel):
                    channel_ids[record.id] = writer.register_channel(
                        record.topic, record.message_encoding,
                        schema_ids.get(record.schema_id, 0), dict(record.metadata),
                    )
                elif isinstance(record, Message) and record.channel_id in channel_ids:
                    writer.add_message(
                        channel_ids[record.channel_id], record.log_time, record.data,
                        record.publish_time, record.sequence,
                    )
                    counts["messages"] += 1
                    last_log_time_ns = max(last_log_time_ns or 0, record.log_time)
                elif isinstance(record, Attachment):
                    writer.add_attachment(
                        record.create_time, record.log_time, record.name, record.media_type,
                        record.data,
                    )
                    counts["attachments"] += 1
                elif isinstance(record, Metadata):
                    writer.add_metadata(record.name, dict(record.metadata))
                    counts["metadata"] += 1
                elif isinstance(record, Footer):
                    was_complete = True
        except DecompressionBombError as error:
            refused = stopped_because = str(error)
        except _WHERE_THE_CUT_IS as error:
            # Where the cut is: everything before it has been copied.
            stopped_because = f"{type(error).__name__}: {error}".rstrip(": ")
        if writer is None:
            raise LogFormatError(f"{source}: not an MCAP file (no header); nothing to recover")
        writer.finish()  # type: ignore[no-untyped-call]
        writing.flush()
        os.fsync(writing.fileno())
    return Recovery(
        source=source,
        destination=destination,
        was_complete=was_complete,
        stopped_because=None if was_complete else stopped_because or "the file ends early",
        last_log_time_ns=last_log_time_ns,
        refused=refused,
        **counts,
    )


def _records(reading: BinaryIO) -> Iterator[McapRecord]:
    """The file's records in order, the records inside each chunk in place of the chunk. The
    library would inflate a chunk as far as its compressed data goes: here no further than the
    size the chunk states (:func:`decompress_chunk`), and the library splits what that gives."""
    source = _CappedReads(reading)
    records = StreamReader(
        cast("IO[bytes]", source),  # it calls read() only
        validate_crcs=True, record_size_limit=RECORD_SIZE_LIMIT, emit_chunks=True
    ).records
    for record in records:
        if isinstance(record, Chunk):
            try:
                data = decompress_chunk(record.compression, record.data, record.uncompressed_size)
            except LogFormatError as error:
                raise type(error)(f"the chunk ending at byte {source.tell()}: {error}") from error
            yield from breakup_chunk(replace(record, compression="", data=data), validate_crc=True)
        else:
            yield record


class _CappedReads:
    """The source file with each read capped at what is left of it: a length field inside a
    record may claim terabytes, and a buffered read allocates what it is asked for first."""

    def __init__(self, file: BinaryIO) -> None:
        self._file = file
        self._size = os.fstat(file.fileno()).st_size

    def read(self, size: int = -1) -> bytes:
        left = max(0, self._size - self._file.tell())
        return self._file.read(left if size < 0 else min(size, left))

    def tell(self) -> int:
        return self._file.tell()
