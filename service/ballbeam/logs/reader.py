"""A fast, truncation-tolerant reader for ballbeam MCAP logs (pure Python + numpy).

Why not the ``mcap`` library's reader: it yields one Python object per message, and it leans
on the summary section, which a crashed writer never wrote. This reader walks the records from
the start, decompresses each complete chunk, and uses the Message Index records that follow a
chunk to gather all messages of a channel at once: every fixed-layout (``ros2msg``/``cdr``)
payload of a channel is copied out of the decompressed chunks with one numpy fancy-index and
viewed as the channel's structured dtype. Nothing per message runs in Python except on JSON
channels, which carry rare events. The walk is :mod:`ballbeam.logs.mcap_records`, the gather
:mod:`ballbeam.logs.gather`; this module puts them together into a :class:`RunLog`.

The file is never trusted: lengths are checked against the record and the file, CRCs are
checked where the writer stored them, schema texts must parse, and payload sizes must match
their schema, else :class:`~ballbeam.errors.LogFormatError` says what and at which byte. A file
without a footer is a run whose writer did not finish: it is read up to its last complete
chunk and reported as ``truncated``; damage confined to the last record of such a file is
treated the same way. Nothing from the file is executed or unpickled; JSON goes through
``json.loads`` only.
"""

from __future__ import annotations

import mmap
import os
from collections.abc import Iterable, Mapping
from dataclasses import dataclass

from ballbeam.errors import LogFormatError
from ballbeam.files import not_a_regular_file
from ballbeam.logs.gather import JsonTopic, StructTopic, _Gather
from ballbeam.logs.mcap_records import _RECORD_HEAD, MAGIC, PROFILE


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
    problem = not_a_regular_file(path)
    if problem is not None:
        raise LogFormatError(f"{path}: not a log: {problem}")
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


class _Reader(_Gather):
    """One read: the record walk (:mod:`ballbeam.logs.mcap_records`) and the vectorised
    gather (:mod:`ballbeam.logs.gather`), assembled into a :class:`RunLog`."""

    def read(self) -> RunLog:
        profile, library, pos = self.header()
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


__all__ = ["MAGIC", "PROFILE", "JsonTopic", "RunLog", "StructTopic", "read_log"]
