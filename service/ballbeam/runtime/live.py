"""The live view: a run's channels served over Foxglove's WebSocket protocol while it goes.

``ballbeam run --live`` and ``ballbeam daemon --live`` start :class:`LiveView`, a WebSocket
server of the official ``foxglove-sdk`` (its Rust server runs on its own threads), bound to the
loopback interface only. It is the recorder's :class:`~ballbeam.logs.recorder.ChunkTap`: every
channel of the log is advertised with the log's topic, schema name, schema encoding and message
encoding, and every chunk the recorder's writer thread has written is forwarded message by
message with the log's own bytes and log times. So the control loop does no work for it, and a
viewer sees exactly what the file holds, at most one flush interval (30 ms) later.

Never blocking: only channels some client subscribed to are forwarded (the server's
subscribe and unsubscribe callbacks keep the set; with no client a chunk costs one look at an
empty set); handing a message to the server only queues it, and a client that does not keep up
loses its oldest queued messages (``BACKLOG_MESSAGES`` per client), never stalls the writer.
"""

from __future__ import annotations

import errno
import logging
import os
import socket
import threading
import time
from dataclasses import dataclass, field

import foxglove
from foxglove.websocket import ChannelView, Client, ServerListener, WebSocketServer

from ballbeam.errors import LiveViewError
from ballbeam.logs.mcap_file import OpenChunk, chunk_messages

LIVE_HOST = "127.0.0.1"  # loopback only: the live view never listens beyond this host
DEFAULT_LIVE_PORT = 8765  # the Foxglove app's default connection string
# Per client. Above a chunk's worth of every channel in lock-step (~30 ms at 8x real time:
# ~2,700 messages), so a client that keeps up on average loses nothing to a chunk's burst.
BACKLOG_MESSAGES = 8192


def live_url(port: int) -> str:
    return f"ws://{LIVE_HOST}:{port}"


def check_port_free(port: int) -> None:
    """Raise LiveViewError (one line) if ``port`` cannot be bound on the loopback interface.

    ``ballbeam run`` asks before it starts its two processes, so a taken port is one line and
    exit 2 rather than a daemon dying mid-start. (The daemon's own bind is the real check.)"""
    probe = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    try:
        # As the server's own listener does: a port left in TIME_WAIT is free to it.
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        probe.bind((LIVE_HOST, port))
    except OSError as exc:
        raise _port_error(port, exc.strerror or str(exc), exc.errno) from exc
    finally:
        probe.close()


def _port_error(port: int, reason: str, code: int | None) -> LiveViewError:
    error = LiveViewError(
        f"cannot serve the live view on {live_url(port)}: {reason} "
        "(choose another port with --live-port)"
    )
    error.errno = code
    return error


class _Subscriptions(ServerListener):
    """The server's listener: which channels (SDK ids) some client subscribes to. Called on the
    server's threads, concurrently; ``channels`` is replaced (under a lock, so that no update is
    lost between two callbacks), never mutated, so the forwarding thread reads it lock-free."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._pairs: set[tuple[int, int]] = set()  # (client id, channel id)
        self.channels: frozenset[int] = frozenset()

    def on_subscribe(self, client: Client, channel: ChannelView) -> None:
        with self._lock:
            self._pairs.add((client.id, channel.id))
            self.channels = frozenset(pair[1] for pair in self._pairs)

    def on_unsubscribe(self, client: Client, channel: ChannelView) -> None:
        # Also called for each subscription of a client that disconnects.
        with self._lock:
            self._pairs.discard((client.id, channel.id))
            self.channels = frozenset(pair[1] for pair in self._pairs)


@dataclass
class _Forwarded:
    """What the live path did, for the "live" metadata record of the log."""

    chunks: int = 0
    messages: int = 0
    forward_ns: int = 0  # writer-thread CPU time spent forwarding (the loop may wait on it)
    channel_ids: dict[int, foxglove.Channel] = field(default_factory=dict)  # MCAP id → channel


class LiveView:
    """The recorder's tap into a WebSocket server.

    Made before the recorder (its port checked at once: a taken one fails fast), given the
    log's channels by the recorder, then :meth:`start`-ed once every channel exists: a client
    that subscribed to a channel advertised while it connected could be refused by the SDK
    ("Unknown channel ID", seen in about one run in ten), so clients only ever connect to the
    whole set. ``stop()`` when the run is over.
    """

    def __init__(self, port: int = DEFAULT_LIVE_PORT, name: str = "ballbeam-hil") -> None:
        check_port_free(port)
        self.port = port
        self.url = live_url(port)
        self._name = name
        # The SDK logs its server's start and stop at INFO; the daemon says where to connect.
        logging.getLogger("foxglove").setLevel(logging.WARNING)
        # A private context: only the run's channels reach this server, whatever else in the
        # process logs to Foxglove's global one.
        self._context = foxglove.Context()
        self._subscriptions = _Subscriptions()
        self._server: WebSocketServer | None = None
        self._done = _Forwarded()
        self._stopped = False

    def start(self) -> None:
        """Serve the channels added so far. LiveViewError if the port was taken meanwhile."""
        try:
            self._server = foxglove.start_server(
                name=self._name,
                host=LIVE_HOST,
                port=self.port,
                context=self._context,
                server_listener=self._subscriptions,
                message_backlog_size=BACKLOG_MESSAGES,
            )
        except RuntimeError as exc:  # the SDK reports every start failure as one
            text = str(exc)
            code = errno.EADDRINUSE if "in use" in text else None
            reason = os.strerror(code) if code is not None else text
            raise _port_error(self.port, reason, code) from exc

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
        schema = foxglove.Schema(name=schema_name, encoding=schema_encoding, data=schema_data)
        self._done.channel_ids[channel_id] = foxglove.Channel(
            topic, schema=schema, message_encoding=message_encoding, context=self._context
        )

    def take(self, chunk: OpenChunk) -> None:
        """Forward a written chunk's messages on the channels some client subscribed to."""
        started_ns = time.thread_time_ns()
        forwarded = 0
        records: bytes | None = None
        subscribed = self._subscriptions.channels
        for channel_id, channel in self._done.channel_ids.items() if subscribed else ():
            if channel.id() not in subscribed or not channel.has_sinks():
                continue  # nobody listens: no work
            if records is None:
                records = bytes(chunk.records)  # one copy for every channel of the chunk
            send = channel.base.log  # the SDK's binary log, without the JSON dispatch
            for log_time_ns, payload in chunk_messages(chunk, channel_id, records):
                send(payload, log_time_ns, None)
                forwarded += 1
        done = self._done
        done.chunks += 1
        done.messages += forwarded
        done.forward_ns += time.thread_time_ns() - started_ns

    def stats(self) -> dict[str, str]:
        done = self._done
        return {
            "url": self.url,
            "chunks": str(done.chunks),
            "messages_forwarded": str(done.messages),
            "forward_ns": str(done.forward_ns),
        }

    # ---- the end ----------------------------------------------------------------------------

    def stop(self) -> None:
        """Close the channels (clients see them unadvertised) and stop the server. Idempotent."""
        if self._stopped:
            return
        self._stopped = True
        for channel in self._done.channel_ids.values():
            channel.close()
        if self._server is not None:
            self._server.stop()


__all__ = [
    "BACKLOG_MESSAGES",
    "DEFAULT_LIVE_PORT",
    "LIVE_HOST",
    "LiveView",
    "check_port_free",
    "live_url",
]
