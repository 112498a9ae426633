"""The live view: a run's channels served over Foxglove's WebSocket protocol while it goes.

``ballbeam run --live`` and ``ballbeam daemon --live`` make a :class:`LiveView`: the recorder's
:class:`~ballbeam.logs.recorder.ChunkTap` in the daemon, and a server process of its own
(``runtime/live_server.py``: the official ``foxglove-sdk`` WebSocket server, bound to the
loopback interface only). Every channel of the log goes to that process with the log's topic,
schema name, schema encoding and message encoding, and every chunk the recorder's writer thread
has written goes there as the chunk's own message records (the file's bytes before
compression), so a viewer sees exactly what the file holds, at most one flush interval (30 ms)
later.

Why a process: forwarding in the daemon cost its writer thread about 1 µs a message and held
the interpreter lock the control loop waits for (p99 lateness up to 118 µs with every topic
subscribed). Here the daemon's whole part is one non-blocking ``writev`` of bytes it already
has, a chunk at a time; parsing, filtering and the SDK's work run in the other process, which
never holds this interpreter's lock.

Never blocking, never losing the recording: the pipe is non-blocking; a chunk the pipe cannot
take (a server that does not keep up) is dropped from the view and counted, never waited for.
A server process that dies makes ``take`` raise, and the recorder drops the view and goes on
recording. The server process reads its frames from its standard input: when the daemon ends,
however it ends, the pipe closes and the server stops.
"""

from __future__ import annotations

import contextlib
import json
import os
import resource
import select
import socket
import struct
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from typing import Any

from ballbeam.errors import LiveViewError
from ballbeam.logs.mcap_file import OpenChunk

LIVE_HOST = "127.0.0.1"  # loopback only: the live view never listens beyond this host
DEFAULT_LIVE_PORT = 8765  # the Foxglove app's default connection string
# Per client. Above a chunk's worth of every channel in lock-step (~30 ms at 8x real time:
# ~2,700 messages), so a client that keeps up on average loses nothing to a chunk's burst.
BACKLOG_MESSAGES = 8192

# ---- the pipe from the daemon to the server process --------------------------------------
# A frame: kind (u8) and body length (u32), then the body.
FRAME_HEAD = struct.Struct("<BI")
FRAME_CHANNEL = 1  # body: MCAP channel id (u16), then 5 length-prefixed (u32) byte strings
FRAME_SERVE = 2  # body empty: start serving the channels sent so far; the server answers
FRAME_CHUNK = 3  # body: a written chunk's message records, exactly as the file's chunk holds
CHANNEL_ID = struct.Struct("<H")
FIELD_LENGTH = struct.Struct("<I")
# The kernel's default pipe holds 64 KiB; a lock-step chunk of every channel is ~250 KiB. 1 MiB
# is the unprivileged ceiling (/proc/sys/fs/pipe-max-size) and holds several chunks of slack.
PIPE_BYTES = 1 << 20
START_TIMEOUT_S = 60.0  # the server process imports the SDK and binds (a loaded machine: slow)
END_TIMEOUT_S = 10.0  # to forward what it holds, stop its server and say what it did
SETUP_WRITE_TIMEOUT_S = 10.0  # a channel frame (setup, not the loop) may wait this long


def live_url(port: int) -> str:
    return f"ws://{LIVE_HOST}:{port}"


def check_port_free(port: int) -> None:
    """Raise LiveViewError (one line) if ``port`` cannot be bound on the loopback interface.

    ``ballbeam run`` asks before it starts its two processes, so a taken port is one line and
    exit 2 rather than a daemon dying mid-start. (The server's own bind is the real check.)"""
    probe = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    try:
        # As the server's own listener does: a port left in TIME_WAIT is free to it.
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        probe.bind((LIVE_HOST, port))
    except OSError as exc:
        raise port_error(port, exc.strerror or str(exc), exc.errno) from exc
    finally:
        probe.close()


def port_error(port: int, reason: str, code: int | None) -> LiveViewError:
    error = LiveViewError(
        f"cannot serve the live view on {live_url(port)}: {reason} "
        "(choose another port with --live-port)"
    )
    error.errno = code
    return error


def channel_frame(
    channel_id: int,
    topic: str,
    message_encoding: str,
    schema_name: str,
    schema_encoding: str,
    schema_data: bytes,
) -> bytes:
    """A FRAME_CHANNEL body (without the frame head)."""
    parts = [CHANNEL_ID.pack(channel_id)]
    for text in (topic.encode(), message_encoding.encode(), schema_name.encode(),
                 schema_encoding.encode(), schema_data):
        parts += [FIELD_LENGTH.pack(len(text)), text]
    return b"".join(parts)


def parse_channel_frame(body: bytes) -> tuple[int, str, str, str, str, bytes]:
    """The inverse of :func:`channel_frame`: (channel id, topic, message encoding, schema name,
    schema encoding, schema data)."""
    (channel_id,) = CHANNEL_ID.unpack_from(body)
    offset = CHANNEL_ID.size
    fields: list[bytes] = []
    for _ in range(5):
        (length,) = FIELD_LENGTH.unpack_from(body, offset)
        offset += FIELD_LENGTH.size
        fields.append(body[offset : offset + length])
        offset += length
    topic, message_encoding, schema_name, schema_encoding = (f.decode() for f in fields[:4])
    return channel_id, topic, message_encoding, schema_name, schema_encoding, fields[4]


@dataclass
class _Handed:
    """What the daemon's side did, for the "live" metadata record of the log."""

    chunks: int = 0  # handed to the server process whole
    chunks_dropped: int = 0  # the pipe was full: not in the view (always in the file)
    bytes: int = 0
    daemon_cpu_ns: int = 0  # writer-thread CPU time in take(): the daemon's whole per-chunk cost


class LiveView:
    """The recorder's tap into the live server process.

    Made before the recorder, and before the daemon takes real-time scheduling (so the server
    process starts at normal priority and never competes with the loop for the CPU at its
    level): the port is checked at once (a taken one fails fast) and the server process starts
    importing the SDK while the daemon plans. The recorder gives it the log's channels; then
    :meth:`start` once every channel exists (a client that subscribed to a channel advertised
    while it connected could be refused by the SDK: "Unknown channel ID", seen in about one run
    in ten), so clients only ever connect to the whole set. ``stats()`` (the recorder, at close)
    ends the server process and reports both sides; ``stop()`` when the run is over.
    """

    def __init__(self, port: int = DEFAULT_LIVE_PORT, name: str = "ballbeam-hil") -> None:
        check_port_free(port)
        self.port = port
        self.url = live_url(port)
        try:
            self._process = subprocess.Popen(
                [sys.executable, "-m", "ballbeam.runtime.live_server", "--port", str(port),
                 "--name", name, "--backlog", str(BACKLOG_MESSAGES)],
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                close_fds=True,
            )
        except OSError as exc:
            raise LiveViewError(
                f"cannot start the live view's server process: {exc.strerror or exc}"
            ) from exc
        assert self._process.stdin is not None and self._process.stdout is not None
        self._frames_fd = self._process.stdin.fileno()
        self._replies_fd = self._process.stdout.fileno()
        with contextlib.suppress(OSError, AttributeError):  # F_SETPIPE_SZ: Linux only
            import fcntl

            fcntl.fcntl(self._frames_fd, fcntl.F_SETPIPE_SZ, PIPE_BYTES)
        os.set_blocking(self._frames_fd, False)  # take() never waits for the server
        self._lock = threading.Lock()  # channel frames (any thread) against chunk frames
        self._unsent = b""  # the tail of a frame the pipe took only part of
        self._reply_buffer = b""
        self._done = _Handed()
        self._ended: dict[str, str] | None = None  # what the server process said at its end
        self._startup_cpu_ns: int | None = None
        self._stopped = False

    @property
    def server_pid(self) -> int:
        return self._process.pid

    def start(self) -> None:
        """Serve the channels added so far. LiveViewError if the server cannot start (e.g. the
        port was taken meanwhile)."""
        with self._lock:
            self._send_whole(FRAME_HEAD.pack(FRAME_SERVE, 0))
        reply = self._read_reply(START_TIMEOUT_S)
        if reply is None:
            raise LiveViewError(
                f"the live view's server process ended or did not answer within "
                f"{START_TIMEOUT_S:.0f} s (exit code {self._process.poll()})"
            )
        if "error" in reply:
            code = reply.get("errno")
            reason = os.strerror(code) if isinstance(code, int) else str(reply["error"])
            raise port_error(self.port, reason, code if isinstance(code, int) else None)
        self._startup_cpu_ns = reply.get("startup_cpu_ns")

    # ---- ChunkTap ---------------------------------------------------------------------------

    def add_channel(
        self,
        channel_id: int,
        topic: str,
        message_encoding: str,
        schema_name: str,
        schema_encoding: str,
        schema_data: bytes,
    ) -> None:
        body = channel_frame(
            channel_id, topic, message_encoding, schema_name, schema_encoding, schema_data
        )
        with self._lock:
            self._send_whole(FRAME_HEAD.pack(FRAME_CHANNEL, len(body)) + body)

    def take(self, chunk: OpenChunk) -> None:
        """Hand a written chunk's records to the server process, or drop it from the view if
        the pipe is full. Never waits. LiveViewError if the server process is gone."""
        started_ns = time.thread_time_ns()
        done = self._done
        with self._lock:
            if self._flush_unsent():
                records = chunk.records
                head = FRAME_HEAD.pack(FRAME_CHUNK, len(records))
                try:
                    sent = os.writev(self._frames_fd, (head, records))
                except BlockingIOError:
                    sent = 0
                except OSError as exc:
                    raise self._gone(exc) from exc
                if sent == 0:
                    done.chunks_dropped += 1  # nothing of it went: drop it whole
                else:
                    if sent < len(head):  # a frame once begun must be finished
                        self._unsent = head[sent:] + bytes(records)
                    elif sent < len(head) + len(records):
                        self._unsent = bytes(records[sent - len(head) :])
                    done.chunks += 1
                    done.bytes += len(records)
            else:
                done.chunks_dropped += 1
        done.daemon_cpu_ns += time.thread_time_ns() - started_ns

    def stats(self) -> dict[str, str]:
        """Both sides' figures. Ends the server process (the recording is over: the recorder
        calls this at close), so that its own count and CPU time are final."""
        self._end_server()
        done = self._done
        figures = {
            "url": self.url,
            "chunks": str(done.chunks),
            "chunks_dropped": str(done.chunks_dropped),
            "bytes": str(done.bytes),
            "daemon_cpu_ns": str(done.daemon_cpu_ns),
        }
        if self._startup_cpu_ns is not None:
            figures["server_startup_cpu_ns"] = str(self._startup_cpu_ns)
        figures.update(self._ended or {})
        return figures

    # ---- the end ----------------------------------------------------------------------------

    def stop(self) -> None:
        """End the server process (clients see the connection close). Idempotent."""
        if self._stopped:
            return
        self._stopped = True
        self._end_server()

    def _end_server(self) -> None:
        if self._ended is not None:
            return
        self._ended = {}
        process = self._process
        with self._lock:
            with contextlib.suppress(OSError, LiveViewError):
                self._send_whole(b"")  # what the pipe could not take yet (bounded wait)
            assert process.stdin is not None
            with contextlib.suppress(OSError):
                process.stdin.close()  # end of input: the server forwards what it has, stops
        reply = self._read_reply(END_TIMEOUT_S)
        if reply is not None:
            self._ended.update({f"server_{key}": str(value) for key, value in reply.items()})
        cpu_ns = _reap(process, END_TIMEOUT_S)
        if cpu_ns is not None:
            # From the kernel: every thread of the server process (Python and the SDK's own).
            self._ended["server_cpu_ns"] = str(cpu_ns)
        else:
            self._ended["server_end"] = "killed: did not end in time"
        if process.stdout is not None:
            process.stdout.close()

    # ---- the pipes --------------------------------------------------------------------------

    def _gone(self, exc: OSError) -> LiveViewError:
        error = LiveViewError(
            f"the live view's server process is gone ({exc.strerror or exc}; exit code "
            f"{self._process.poll()})"
        )
        error.errno = exc.errno
        return error

    def _flush_unsent(self) -> bool:
        """Send what is left of a begun frame; True when nothing is left (lock held)."""
        if not self._unsent:
            return True
        try:
            sent = os.write(self._frames_fd, self._unsent)
        except BlockingIOError:
            return False
        except OSError as exc:
            raise self._gone(exc) from exc
        self._unsent = self._unsent[sent:]
        return not self._unsent

    def _send_whole(self, frame: bytes) -> None:
        """Send what is left of a begun frame, then ``frame``, waiting for the pipe (setup and
        the end only, never the loop or a chunk; lock held)."""
        self._unsent += frame
        deadline_s = time.monotonic() + SETUP_WRITE_TIMEOUT_S
        while not self._flush_unsent():
            left_s = deadline_s - time.monotonic()
            if left_s <= 0:
                raise LiveViewError("the live view's server process does not read its input")
            select.select([], [self._frames_fd], [], left_s)

    def _read_reply(self, timeout_s: float) -> dict[str, Any] | None:
        """The server process's next JSON line, or None at its end or after ``timeout_s``."""
        deadline_s = time.monotonic() + timeout_s
        while b"\n" not in self._reply_buffer:
            left_s = deadline_s - time.monotonic()
            if left_s <= 0 or not select.select([self._replies_fd], [], [], left_s)[0]:
                return None
            try:
                data = os.read(self._replies_fd, 4096)
            except OSError:
                return None
            if not data:
                return None
            self._reply_buffer += data
        line, self._reply_buffer = self._reply_buffer.split(b"\n", 1)
        try:
            reply = json.loads(line)
        except ValueError:
            return None
        return reply if isinstance(reply, dict) else None


def _reap(process: subprocess.Popen[bytes], timeout_s: float) -> int | None:
    """Wait for ``process`` (kill it after ``timeout_s``); its CPU time (user + system, all
    threads) in ns as the kernel counted it, or None if it had to be killed."""
    deadline_s = time.monotonic() + timeout_s
    while True:
        try:
            pid, status, usage = os.wait4(process.pid, os.WNOHANG)
        except ChildProcessError:
            return None  # already reaped (by Popen): no figures
        if pid != 0:
            process.returncode = os.waitstatus_to_exitcode(status)
            return _usage_ns(usage)
        if time.monotonic() > deadline_s:
            with contextlib.suppress(OSError):
                process.kill()
            process.wait()
            return None
        time.sleep(0.01)


def _usage_ns(usage: resource.struct_rusage) -> int:
    return round((usage.ru_utime + usage.ru_stime) * 1e9)


__all__ = [
    "BACKLOG_MESSAGES",
    "DEFAULT_LIVE_PORT",
    "FRAME_CHANNEL",
    "FRAME_CHUNK",
    "FRAME_HEAD",
    "FRAME_SERVE",
    "LIVE_HOST",
    "LiveView",
    "channel_frame",
    "check_port_free",
    "live_url",
    "parse_channel_frame",
    "port_error",
]
