"""The run recorder: one MCAP file per run, fed from the control loop without ever blocking it.

The loop thread only appends ``(handle, log_time_ns, values)`` to a bounded in-memory queue
(:meth:`Recorder.record`, a fraction of a microsecond). A writer thread encodes the values
(CDR through each channel's precompiled :class:`~ballbeam.logs.schema.StructSchema`, or JSON),
feeds them to :class:`mcap.writer.Writer` (zstd chunks, message indexes) and calls its
``flush()`` every ``flush_interval_s``: that closes the open chunk and hands it to the OS, so a
killed process loses at most about one flush interval of data.

Header, metadata and attachments are written and flushed in the constructor, so a run that
crashes still says what it was. ``close()`` adds final metadata and the summary section.
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
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from importlib.metadata import PackageNotFoundError, version
from types import TracebackType
from typing import IO, Any

import numpy as np
from mcap.writer import LIBRARY_IDENTIFIER, CompressionType, Writer

from ballbeam.errors import RecorderError
from ballbeam.logs.schema import MESSAGE_ENCODING, SCHEMA_ENCODING, StructSchema

PROFILE = "ballbeam"
JSON_SCHEMA_ENCODING = "jsonschema"
JSON_MESSAGE_ENCODING = "json"

# Writer-thread batch: small enough that it hands the GIL back to the loop thread often.
_BATCH = 16
_YIELD_S = 50e-6

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


def encode_json(values: Mapping[str, Any]) -> bytes:
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

    Raises RecorderError (with the path and the OS reason) if the file cannot be created or
    its first records cannot be written.
    """

    def __init__(
        self,
        path: str | os.PathLike[str] | IO[bytes],
        *,
        profile: str = PROFILE,
        metadata: Mapping[str, Mapping[str, str]] | None = None,
        attachments: Iterable[tuple[str, str, bytes]] = (),
        queue_size: int = 65_536,
        flush_interval_s: float = 0.05,
        chunk_size_bytes: int = 1 << 20,
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

        self._owns_stream = isinstance(path, (str, os.PathLike))
        self.path = os.fspath(path) if isinstance(path, (str, os.PathLike)) else "<stream>"
        stream: IO[bytes]
        if isinstance(path, (str, os.PathLike)):
            try:
                stream = open(path, "wb")  # noqa: SIM115 - kept open for the recorder's lifetime
            except OSError as exc:
                raise _recorder_error(
                    f"cannot create log {self.path}: {_os_reason(exc)}", exc
                ) from exc
        else:
            stream = path
        self._stream = stream
        self._writer = Writer(stream, chunk_size=chunk_size_bytes, compression=CompressionType.ZSTD)
        try:
            self._writer.start(profile=profile, library=LIBRARY)
            for name, record in metadata_records.items():
                self._writer.add_metadata(name, record)
            now_ns = time.time_ns()
            for name, media_type, data in attachment_list:
                self._writer.add_attachment(now_ns, now_ns, name, media_type, data)
            # On disk now, so that a run which dies early still says what it was.
            stream.flush()
        except OSError as exc:
            if self._owns_stream:
                self._close_stream_quietly()
            raise _recorder_error(f"cannot write log {self.path}: {_os_reason(exc)}", exc) from exc

        self._flush_interval_s = float(flush_interval_s)
        self._capacity = int(queue_size)
        self._queue: deque[tuple[ChannelHandle, int, Any]] = deque()
        self._accepting = True
        self._dropped = 0
        self._drop_lock = threading.Lock()
        self._writer_lock = threading.Lock()  # the mcap Writer is not thread-safe
        self._close_lock = threading.Lock()
        self._stop = threading.Event()
        self._closed = False
        self._error: BaseException | None = None
        self._written = 0
        self._rejected = 0
        self._first_rejection: str | None = None
        self._schema_ids: dict[tuple[str, str, bytes], int] = {}
        self._topics: set[str] = set()
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
        with self._writer_lock:
            if self._closed or not self._accepting:
                raise RecorderError(f"recorder for {self.path} is closed or failed")
            if topic in self._topics:
                raise ValueError(f"topic {topic!r} is already registered")
            try:
                key = (schema_name, schema_encoding, data)
                schema_id = self._schema_ids.get(key)
                if schema_id is None:
                    schema_id = self._writer.register_schema(schema_name, schema_encoding, data)
                    self._schema_ids[key] = schema_id
                channel_id: int = self._writer.register_channel(topic, encoding, schema_id)
            except OSError as exc:
                raise _recorder_error(
                    f"cannot write log {self.path}: {_os_reason(exc)}", exc
                ) from exc
            self._topics.add(topic)
            return channel_id

    # ---- hot path ---------------------------------------------------------------------------

    def record(
        self, handle: ChannelHandle, log_time_ns: int, values: Sequence[Any] | Mapping[str, Any]
    ) -> None:
        """Queue one message. Never blocks and never raises.

        ``values`` is a tuple in field order (fastest) or a mapping by field name; for a JSON
        channel, a JSON-able mapping. The recorder takes ownership: do not mutate it afterwards.
        When the queue is full, or after a write error or close, the message is dropped and
        counted in :attr:`dropped`. Values that do not fit the schema are counted in
        :attr:`rejected` by the writer thread.
        """
        if self._accepting and len(self._queue) < self._capacity:
            self._queue.append((handle, log_time_ns, values))
        else:
            with self._drop_lock:
                self._dropped += 1

    # ---- writer thread ----------------------------------------------------------------------

    def _run(self) -> None:
        queue = self._queue
        poll_s = min(0.005, self._flush_interval_s / 4)
        next_flush_s = time.monotonic() + self._flush_interval_s
        try:
            while True:
                stopping = self._stop.is_set()
                while queue:
                    self._write_batch(queue)
                    if queue:
                        time.sleep(_YIELD_S)  # give the loop thread the GIL between batches
                now_s = time.monotonic()
                if stopping or now_s >= next_flush_s:
                    with self._writer_lock:
                        self._writer.flush()  # type: ignore[no-untyped-call]
                    next_flush_s = now_s + self._flush_interval_s
                if stopping:
                    return
                self._stop.wait(poll_s)
        except BaseException as exc:  # kept, and re-raised by close()
            self._error = exc
            self._accepting = False
            with self._drop_lock:
                self._dropped += len(queue)
            queue.clear()

    def _write_batch(self, queue: deque[tuple[ChannelHandle, int, Any]]) -> None:
        writer = self._writer
        with self._writer_lock:
            for _ in range(min(len(queue), _BATCH)):
                handle, log_time_ns, values = queue.popleft()
                try:
                    if handle.owner is not self:
                        raise ValueError(f"handle for {handle.topic!r} is not from this recorder")
                    log_time_ns = operator.index(log_time_ns)
                    if not 0 <= log_time_ns < 1 << 63:
                        # int64 on the way back out (numpy), though MCAP stores uint64.
                        raise ValueError(f"log_time_ns {log_time_ns} is outside 0..2**63")
                    if handle.schema is not None:
                        data = handle.schema.pack(values)
                    else:
                        data = encode_json(values)
                except (ValueError, TypeError, OverflowError, RecursionError) as exc:
                    self._rejected += 1
                    if self._first_rejection is None:
                        self._first_rejection = f"{handle.topic}: {exc}"
                    continue
                writer.add_message(handle.channel_id, log_time_ns, data, log_time_ns)
                self._written += 1

    # ---- state ------------------------------------------------------------------------------

    @property
    def dropped(self) -> int:
        """Messages not recorded: queue full, recorder failed or closed."""
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
        """Messages handed to the MCAP writer so far (on disk after the next flush)."""
        return self._written

    @property
    def queued(self) -> int:
        """Messages waiting for the writer thread."""
        return len(self._queue)

    @property
    def error(self) -> BaseException | None:
        """The write error that stopped the recorder, if any (close() raises it)."""
        return self._error

    # ---- closing ----------------------------------------------------------------------------

    def close(self, summary: Mapping[str, str] | None = None) -> None:
        """Drain the queue, write final metadata and the summary section, close the file.

        ``summary`` becomes a metadata record named "summary"; a record named "recorder" holds
        the message, drop and rejection counts. Idempotent. Raises RecorderError if any write
        failed: the file then ends at the last chunk that reached the OS.
        """
        with self._close_lock:
            if self._closed:
                return
            self._closed = True
            self._accepting = False
            self._stop.set()
            self._thread.join()
            # A record() racing with close() may have appended after the last drain.
            with self._drop_lock:
                self._dropped += len(self._queue)
            self._queue.clear()
            if self._error is None:
                try:
                    if summary is not None:
                        self._writer.add_metadata("summary", _check_str_map("summary", summary))
                    counts = {
                        "messages_written": str(self._written),
                        "dropped": str(self._dropped),
                        "rejected": str(self._rejected),
                    }
                    if self._first_rejection is not None:
                        counts["first_rejection"] = self._first_rejection
                    self._writer.add_metadata("recorder", counts)
                    self._writer.finish()  # type: ignore[no-untyped-call]
                    self._stream.flush()
                except OSError as exc:
                    self._error = exc
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
    "Recorder",
    "encode_json",
]
