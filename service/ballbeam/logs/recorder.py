"""The run recorder: one MCAP file per run, fed from the control loop without waiting on I/O.

The loop thread encodes each message (CDR through its channel's precompiled
:class:`~ballbeam.logs.schema.StructSchema`, or JSON) and appends it to the open chunk of a
:class:`~ballbeam.logs.mcap_file.McapFile` (:meth:`Recorder.record`). Every
``flush_interval_s`` a writer thread takes the open chunk, compresses it (zstd), writes it with
its message indexes and hands it to the OS, so a killed process loses at most about one flush
interval of data. Encoding in the loop thread costs it a microsecond more than queueing values
did, but leaves the writer thread almost nothing to do in Python, so the two no longer contend
for the interpreter lock at every message.

Header, metadata and attachments are written and flushed in the constructor, so a run that
crashes still says what it was. ``close()`` adds final metadata and the summary section.

A :class:`ChunkTap` (the live view, ``runtime/live.py``) sees every chunk the writer thread has
written, with the same encoded messages and log times as the file: it costs the loop thread
nothing, and a tap that fails is dropped without stopping the recording.
"""

from __future__ import annotations

import contextlib
import json
import math
import operator
import os
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from importlib.metadata import PackageNotFoundError, version
from types import TracebackType
from typing import IO, Any, Protocol

import numpy as np
from mcap.writer import LIBRARY_IDENTIFIER

from ballbeam.errors import OutputExistsError, RecorderError
from ballbeam.files import create_new
from ballbeam.logs.mcap_file import McapFile, OpenChunk
from ballbeam.logs.schema import MESSAGE_ENCODING, SCHEMA_ENCODING, StructSchema

PROFILE = "ballbeam"
JSON_SCHEMA_ENCODING = "jsonschema"
JSON_MESSAGE_ENCODING = "json"

try:
    _VERSION = version("ballbeam-hil")
except PackageNotFoundError:  # pragma: no cover - running from a bare checkout
    _VERSION = "0"
LIBRARY = f"ballbeam-hil/{_VERSION}; {LIBRARY_IDENTIFIER}"


@dataclass(frozen=True, slots=True)
class ChannelHandle:
    """What :meth:`Recorder.record` takes to name a channel. ``schema`` is None for JSON."""

    channel_id: int
    topic: str
    schema: StructSchema | None
    owner: object  # the recorder that issued it; a foreign handle is rejected, not misfiled


class ChunkTap(Protocol):
    """Sees the recording as the writer thread writes it (the live view).

    ``add_channel`` is called once per channel, as it is registered (any thread that
    registers); ``take`` with each chunk once it is written (the writer thread: it must not
    block, and may read the chunk until it returns; its ``records`` are never changed after);
    ``stats`` at close, for the "live" metadata record.
    """

    def add_channel(
        self,
        channel_id: int,
        topic: str,
        message_encoding: str,
        schema_name: str,
        schema_encoding: str,
        schema_data: bytes,
    ) -> None: ...

    def take(self, chunk: OpenChunk) -> None: ...

    def stats(self) -> dict[str, str]: ...


def _json_default(obj: object) -> Any:
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    raise TypeError(f"{type(obj).__name__} is not JSON serialisable")


def _finite(obj: Any) -> Any:
    """Replace NaN and infinities by null: strict JSON has no spelling for them."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, Mapping):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite(v) for v in obj]
    return obj


def encode_json(values: object) -> bytes:
    """Encode one JSON-channel message: a strict-JSON object (non-finite floats become null)."""
    if not isinstance(values, Mapping):
        raise TypeError(f"a JSON message must be a mapping, got {type(values).__name__}")
    try:
        text = json.dumps(values, separators=(",", ":"), allow_nan=False, default=_json_default)
    except ValueError:
        text = json.dumps(
            _finite(values), separators=(",", ":"), allow_nan=False, default=_json_default
        )
    return text.encode()


def _recorder_error(message: str, cause: BaseException | None) -> RecorderError:
    """A RecorderError whose message reads cleanly and whose errno is the OS's, if any."""
    error = RecorderError(message)
    if isinstance(cause, OSError):
        error.errno = cause.errno
    return error


def _os_reason(exc: BaseException) -> str:
    return exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)


def _check_str_map(what: str, data: Mapping[str, str]) -> dict[str, str]:
    if not isinstance(data, Mapping) or not all(
        isinstance(k, str) and isinstance(v, str) for k, v in data.items()
    ):
        raise TypeError(f"{what} must map str to str")
    return dict(data)


class Recorder:
    """Records one run to an MCAP file (or a binary stream, e.g. ``io.BytesIO`` in tests).

    Use as a context manager, or call :meth:`close`. Typical use::

        with Recorder(path, metadata={"run": {"config": "paper"}}) as rec:
            sensor = rec.add_struct_channel("/sensor", SENSOR_SCHEMA)
            ...
            rec.record(sensor, t_ns, (angle_rad, position_m))   # loop thread, never blocks

    ``path`` is created as a new file (OutputExistsError naming it if anything is there, a
    link included). A stream passed with a ``name`` (its file's path) is owned: closed at the
    end. Raises RecorderError (with the path and the OS reason) if the file cannot be created
    or its first records cannot be written.
    """

    def __init__(
        self,
        path: str | os.PathLike[str] | IO[bytes],
        *,
        profile: str = PROFILE,
        metadata: Mapping[str, Mapping[str, str]] | None = None,
        attachments: Iterable[tuple[str, str, bytes]] = (),
        queue_size: int = 65_536,
        flush_interval_s: float = 0.03,  # a killed run loses at most about this much log
        chunk_size_bytes: int = 1 << 20,
        tap: ChunkTap | None = None,
        name: str | os.PathLike[str] | None = None,
        writer_setup: Callable[[], None] | None = None,
    ) -> None:
        if queue_size < 1:
            raise ValueError("queue_size must be at least 1")
        if not flush_interval_s > 0:
            raise ValueError("flush_interval_s must be positive")
        metadata_records = {
            str(name): _check_str_map(f"metadata {name!r}", data)
            for name, data in (metadata or {}).items()
        }
        attachment_list = [(str(n), str(m), bytes(d)) for n, m, d in attachments]

        # A stream passed with its name (the file `ballbeam run` created for the daemon) is
        # the recorder's to close, like one it opens itself.
        self._owns_stream = isinstance(path, (str, os.PathLike)) or name is not None
        if isinstance(path, (str, os.PathLike)):
            self.path = os.fspath(path)
        else:
            self.path = os.fspath(name) if name is not None else "<stream>"
        stream: IO[bytes]
        if isinstance(path, (str, os.PathLike)):
            try:
                # A new file only: never over a recording, never through a planted link.
                stream = create_new(path)
            except OutputExistsError as exc:
                raise OutputExistsError(f"log {exc}") from exc
            except OSError as exc:
                raise _recorder_error(
                    f"cannot create log {self.path}: {_os_reason(exc)}", exc
                ) from exc
        else:
            stream = path
        self._stream = stream
        spill_dir = os.path.dirname(os.path.abspath(self.path)) if self._owns_stream else None
        mcap_file: McapFile | None = None
        try:
            self._file = mcap_file = McapFile(
                stream, profile=profile, library=LIBRARY, spill_dir=spill_dir
            )
            for name, record in metadata_records.items():
                self._file.add_metadata(name, record)
            now_ns = time.time_ns()
            for name, media_type, data in attachment_list:
                self._file.add_attachment(now_ns, name, media_type, data)
            # On disk now, so that a run which dies early still says what it was.
            stream.flush()
        except OSError as exc:
            if mcap_file is not None:
                mcap_file.discard()
            if self._owns_stream:
                self._close_stream_quietly()
            raise _recorder_error(f"cannot write log {self.path}: {_os_reason(exc)}", exc) from exc

        self._flush_interval_s = float(flush_interval_s)
        # Called first in the writer thread: the daemon puts it below its real-time loop.
        self._writer_setup = writer_setup
        self._chunk_size_bytes = int(chunk_size_bytes)
        self._capacity = int(queue_size)
        # Two locks: the open chunk (taken by record() for a microsecond) and the stream
        # (held by the writer thread while it compresses and writes a chunk), so that the loop
        # never waits for I/O.
        self._chunk_lock = threading.Lock()
        self._stream_lock = threading.Lock()
        self._close_lock = threading.Lock()
        self._taken: deque[OpenChunk] = deque()  # taken from the file, not yet written
        self._buffered = 0  # messages in memory: the open chunk and the taken ones
        self._accepting = True
        self._dropped = 0
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._closed = False
        self._error: BaseException | None = None
        self._written = 0
        self._writer_cpu_ns: int | None = None
        self._rejected = 0
        self._first_rejection: str | None = None
        self._schema_ids: dict[tuple[str, str, bytes], int] = {}
        self._topics: set[str] = set()
        self._tap = tap
        self._tap_error: str | None = None
        self._thread = threading.Thread(
            target=self._run, name=f"recorder {os.path.basename(self.path)}", daemon=True
        )
        self._thread.start()

    # ---- channels ---------------------------------------------------------------------------

    def add_struct_channel(self, topic: str, schema: StructSchema) -> ChannelHandle:
        """Register a fixed-layout channel (schema ``ros2msg``, messages ``cdr``)."""
        channel_id = self._register(
            topic, schema.name, SCHEMA_ENCODING, schema.ros2msg.encode(), MESSAGE_ENCODING
        )
        return ChannelHandle(channel_id, topic, schema, self)

    def add_json_channel(
        self, topic: str, schema_name: str, json_schema: Mapping[str, Any]
    ) -> ChannelHandle:
        """Register a JSON channel (schema ``jsonschema``, messages ``json``) for rare events."""
        if not isinstance(json_schema, Mapping):
            raise TypeError("json_schema must be a mapping (a JSON Schema object)")
        data = json.dumps(json_schema, separators=(",", ":"), sort_keys=True).encode()
        channel_id = self._register(
            topic, schema_name, JSON_SCHEMA_ENCODING, data, JSON_MESSAGE_ENCODING
        )
        return ChannelHandle(channel_id, topic, None, self)

    def _register(
        self, topic: str, schema_name: str, schema_encoding: str, data: bytes, encoding: str
    ) -> int:
        with self._chunk_lock, self._stream_lock:
            if self._closed or not self._accepting:
                raise RecorderError(f"recorder for {self.path} is closed or failed")
            if topic in self._topics:
                raise ValueError(f"topic {topic!r} is already registered")
            try:
                key = (schema_name, schema_encoding, data)
                schema_id = self._schema_ids.get(key)
                if schema_id is None:
                    schema_id = self._file.add_schema(schema_name, schema_encoding, data)
                    self._schema_ids[key] = schema_id
                channel_id = self._file.add_channel(topic, encoding, schema_id)
            except OSError as exc:
                raise _recorder_error(
                    f"cannot write log {self.path}: {_os_reason(exc)}", exc
                ) from exc
            self._topics.add(topic)
            if self._tap is not None:
                try:
                    self._tap.add_channel(
                        channel_id, topic, encoding, schema_name, schema_encoding, data
                    )
                except Exception as exc:  # the live view must never stop the recording
                    self._drop_tap(exc)
            return channel_id

    def _drop_tap(self, exc: BaseException) -> None:
        self._tap_error = f"{type(exc).__name__}: {exc}"
        self._tap = None

    # ---- hot path ---------------------------------------------------------------------------

    def record(
        self, handle: ChannelHandle, log_time_ns: int, values: Sequence[Any] | Mapping[str, Any]
    ) -> None:
        """Encode one message into the open chunk. Never blocks on I/O and
        never raises.

        ``values`` is a tuple in field order (fastest) or a mapping by field name; for a JSON
        channel, a JSON-able mapping, or its encoding (bytes, :func:`encode_json`'s) made
        where it costs the loop nothing. Values that do not fit the schema are counted in
        :attr:`rejected`. When ``queue_size`` messages are already waiting in memory, or
        after a write error or close, the message is dropped and counted in :attr:`dropped`.
        """
        try:
            if handle.owner is not self:
                raise ValueError(f"handle for {handle.topic!r} is not from this recorder")
            log_time_ns = operator.index(log_time_ns)
            if not 0 <= log_time_ns < 1 << 63:
                # int64 on the way back out (numpy), though MCAP stores uint64.
                raise ValueError(f"log_time_ns {log_time_ns} is outside 0..2**63")
            if handle.schema is not None:
                data = handle.schema.pack(values)
            elif isinstance(values, bytes):  # a JSON message encoded by its maker
                data = values
            else:
                data = encode_json(values)
        except (ValueError, TypeError, OverflowError, RecursionError) as exc:
            with self._chunk_lock:
                self._rejected += 1
                if self._first_rejection is None:
                    self._first_rejection = f"{handle.topic}: {exc}"
            return
        with self._chunk_lock:
            if not self._accepting or self._buffered >= self._capacity:
                self._dropped += 1
                return
            self._file.add_message(handle.channel_id, log_time_ns, data)
            self._buffered += 1
            if self._file.open_bytes >= self._chunk_size_bytes:
                self._take_chunk()
                self._wake.set()

    def _take_chunk(self) -> None:
        """Move the open chunk to the writer's queue (chunk lock held)."""
        chunk = self._file.take_chunk()
        if chunk is not None:
            self._taken.append(chunk)

    # ---- writer thread ----------------------------------------------------------------------

    def _run(self) -> None:
        if self._writer_setup is not None:
            self._writer_setup()
        next_flush_s = time.monotonic() + self._flush_interval_s
        try:
            while True:
                stopping = self._stop.is_set()
                now_s = time.monotonic()
                if stopping or now_s >= next_flush_s:
                    with self._chunk_lock:
                        self._take_chunk()
                    next_flush_s = now_s + self._flush_interval_s
                while self._taken:
                    chunk = self._taken[0]
                    with self._stream_lock:
                        self._file.write_chunk(chunk)
                    with self._chunk_lock:
                        self._taken.popleft()
                        self._buffered -= chunk.messages
                        self._written += chunk.messages
                    tap = self._tap
                    if tap is not None:
                        try:
                            tap.take(chunk)
                        except Exception as exc:  # never stops the recording
                            self._drop_tap(exc)
                with self._stream_lock:
                    self._stream.flush()  # hand the chunk to the OS: a killed run keeps it
                if stopping:
                    # Its whole CPU time (compression, writes, the live view's hand-over):
                    # what recording costs besides the loop's own encoding.
                    self._writer_cpu_ns = time.thread_time_ns()
                    return
                self._wake.wait(max(0.0, next_flush_s - time.monotonic()))
                self._wake.clear()
        except BaseException as exc:  # kept, and re-raised by close()
            with self._chunk_lock:
                self._error = exc
                self._accepting = False
                self._dropped += self._buffered
                self._buffered = 0
                self._taken.clear()
                self._file.take_chunk()

    # ---- state ------------------------------------------------------------------------------

    @property
    def dropped(self) -> int:
        """Messages not recorded: too many waiting, recorder failed or closed."""
        return self._dropped

    @property
    def rejected(self) -> int:
        """Messages whose values did not fit their channel (wrong count, type or range)."""
        return self._rejected

    @property
    def first_rejection(self) -> str | None:
        return self._first_rejection

    @property
    def messages_written(self) -> int:
        """Messages handed to the OS so far."""
        return self._written

    @property
    def queued(self) -> int:
        """Messages in memory, not yet handed to the OS."""
        return self._buffered

    @property
    def error(self) -> BaseException | None:
        """The write error that stopped the recorder, if any (close() raises it)."""
        return self._error

    # ---- closing ----------------------------------------------------------------------------

    def close(self, summary: Mapping[str, str] | None = None) -> None:
        """Write what is buffered, final metadata and the summary section; close the file.

        ``summary`` becomes a metadata record named "summary"; a record named "recorder" holds
        the message, drop and rejection counts. Idempotent. Raises RecorderError if any write
        failed: the file then ends at the last chunk that reached the OS.
        """
        with self._close_lock:
            if self._closed:
                return
            self._closed = True
            with self._chunk_lock:
                self._accepting = False
            self._stop.set()
            self._wake.set()
            self._thread.join()
            if self._error is None:
                try:
                    if summary is not None:
                        self._file.add_metadata("summary", _check_str_map("summary", summary))
                    counts = {
                        "messages_written": str(self._written),
                        "dropped": str(self._dropped),
                        "rejected": str(self._rejected),
                    }
                    if self._first_rejection is not None:
                        counts["first_rejection"] = self._first_rejection
                    if self._writer_cpu_ns is not None:
                        counts["writer_cpu_ns"] = str(self._writer_cpu_ns)
                    self._file.add_metadata("recorder", counts)
                    if self._tap is not None or self._tap_error is not None:
                        live: dict[str, str] = {}
                        if self._tap is not None:
                            try:
                                live = self._tap.stats()
                            except Exception as exc:
                                self._drop_tap(exc)
                        if self._tap_error is not None:
                            live["failed"] = self._tap_error
                        self._file.add_metadata("live", _check_str_map("live", live))
                    self._file.finish()
                    self._stream.flush()
                except OSError as exc:
                    self._error = exc
            if self._error is not None:
                self._file.discard()
            if self._owns_stream:
                try:
                    self._stream.close()
                except OSError as exc:
                    if self._error is None:
                        self._error = exc
            if self._error is not None:
                raise _recorder_error(
                    f"recording to {self.path} failed: {_os_reason(self._error)}; the log ends "
                    f"at the last chunk written before the failure "
                    f"({self._dropped} messages dropped)",
                    self._error,
                ) from self._error

    def _close_stream_quietly(self) -> None:
        with contextlib.suppress(OSError):
            self._stream.close()

    def __enter__(self) -> Recorder:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()


__all__ = [
    "JSON_MESSAGE_ENCODING",
    "JSON_SCHEMA_ENCODING",
    "LIBRARY",
    "PROFILE",
    "ChannelHandle",
    "ChunkTap",
    "Recorder",
    "encode_json",
]
