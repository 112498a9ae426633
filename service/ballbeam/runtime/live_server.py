"""The live view's server process: ``python -m ballbeam.runtime.live_server --port N``.

Started by the daemon's :class:`~ballbeam.runtime.live.LiveView`, never by hand. It reads
frames from its standard input (``runtime/live.py`` defines them): the log's channels, then
"serve", then each chunk the daemon's recorder has written, as the chunk's message records.
It serves the channels with the official ``foxglove-sdk`` WebSocket server on the loopback
interface, behind a relay that also accepts the protocol's older subprotocol name
(``runtime/live_relay.py``), and forwards each chunk's messages on the channels some client
subscribed to, with the log's own bytes and log times. It answers on its standard output, one
JSON line each: once serving (or why it cannot), and at the end of its input (the daemon's run
is over, or the daemon died) what it forwarded, after it has stopped its server.

Its work (parsing, filtering, the SDK's calls and its server threads) is its own CPU time and
its own interpreter lock: the control loop in the daemon never waits for it.
"""

from __future__ import annotations

import argparse
import contextlib
import errno
import json
import logging
import os
import resource
import signal
import sys
import threading
import time
from typing import IO, Any

import foxglove
from foxglove.websocket import ChannelView, Client, ServerListener, WebSocketServer

from ballbeam.logs.mcap_file import records_messages
from ballbeam.runtime.live import (
    FRAME_CHANNEL,
    FRAME_CHUNK,
    FRAME_HEAD,
    FRAME_SERVE,
    LIVE_HOST,
    parse_channel_frame,
)
from ballbeam.runtime.live_relay import SubprotocolRelay
from ballbeam.runtime.ticker import leave_real_time

POLL_S = 0.005  # how often an idle server looks for the daemon's next frame
READ_BYTES = 1 << 20  # the pipe's size: one read takes whatever is there
LINGER_S = 0.1  # after the last chunk: the server's queues drain before it stops
NICE = 10  # the server process yields the CPU to the run's processes at normal priority


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


class LiveServer:
    """The log's channels on a foxglove-sdk WebSocket server, fed chunk by chunk."""

    def __init__(self, port: int, name: str, backlog_messages: int) -> None:
        self._port = port
        self._name = name
        self._backlog_messages = backlog_messages
        # The SDK logs its server's start and stop at INFO; the daemon says where to connect.
        logging.getLogger("foxglove").setLevel(logging.WARNING)
        # A private context: only the run's channels reach this server.
        self._context = foxglove.Context()
        self._subscriptions = _Subscriptions()
        self._server: WebSocketServer | None = None
        self._relay: SubprotocolRelay | None = None
        self._channels: dict[int, foxglove.Channel] = {}  # MCAP channel id → SDK channel
        self.chunks = 0
        self.messages = 0
        self.forward_cpu_ns = 0  # this process's forwarding thread, for the log's record

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
        self._channels[channel_id] = foxglove.Channel(
            topic, schema=schema, message_encoding=message_encoding, context=self._context
        )

    def serve(self) -> dict[str, Any]:
        """Start the server; the answer for the daemon (``serving``, or ``error`` and errno)."""
        try:
            # On a private loopback port: clients come through the relay (both subprotocol
            # names; runtime/live_relay.py).
            self._server = foxglove.start_server(
                name=self._name,
                host=LIVE_HOST,
                port=0,
                context=self._context,
                server_listener=self._subscriptions,
                message_backlog_size=self._backlog_messages,
            )
        except RuntimeError as exc:  # the SDK reports every start failure as one
            text = str(exc)
            return {"error": text, "errno": errno.EADDRINUSE if "in use" in text else None}
        relay = SubprotocolRelay(LIVE_HOST, self._port, self._server.port)
        try:
            relay.start()
        except OSError as exc:
            return {"error": exc.strerror or str(exc), "errno": exc.errno}
        self._relay = relay
        # What starting cost (the interpreter, the SDK, the server's threads), apart from
        # what serving the run costs after it.
        usage = resource.getrusage(resource.RUSAGE_SELF)
        return {"serving": True, "startup_cpu_ns": round((usage.ru_utime + usage.ru_stime) * 1e9)}

    def forward(self, records: bytes) -> None:
        """Forward a chunk's messages on the channels some client subscribed to."""
        started_ns = time.thread_time_ns()
        self.chunks += 1
        subscribed = self._subscriptions.channels
        if subscribed:  # none: the chunk costs one look at an empty set
            # The SDK's binary log, without the JSON dispatch, by MCAP channel id.
            send = {
                channel_id: channel.base.log
                for channel_id, channel in self._channels.items()
                if channel.id() in subscribed and channel.has_sinks()
            }
            forwarded = 0
            for channel_id, log_time_ns, payload in records_messages(records):
                log = send.get(channel_id)
                if log is not None:
                    log(payload, log_time_ns, None)
                    forwarded += 1
            self.messages += forwarded
        self.forward_cpu_ns += time.thread_time_ns() - started_ns

    def stop(self) -> None:
        """Close the channels (clients see them unadvertised) and stop the server."""
        for channel in self._channels.values():
            channel.close()
        if self._server is not None:
            self._server.stop()
        if self._relay is not None:
            self._relay.stop()

    def figures(self) -> dict[str, int]:
        return {
            "chunks": self.chunks,
            "messages_forwarded": self.messages,
            "forward_cpu_ns": self.forward_cpu_ns,
        }


class PolledFrames:
    """The frames the daemon sends, read from a non-blocking pipe that is looked at every
    ``POLL_S`` rather than waited on. Why: a reader blocked in read() is woken by each write,
    and on this virtual machine that wake-up is paid by the writer, the daemon's recorder
    thread: about 10 µs of its CPU time a chunk (measured). A reader that sleeps and looks
    costs the writer only the copy, and the view at most ``POLL_S`` more lag."""

    def __init__(self, fd: int) -> None:
        os.set_blocking(fd, False)
        self._fd = fd
        self._buffer = bytearray()
        self._ended = False

    def next(self) -> tuple[int, bytes] | None:
        """The next (kind, body), or None at the end of the input (a cut frame ends it too)."""
        buffer = self._buffer
        while True:
            if len(buffer) >= FRAME_HEAD.size:
                kind, length = FRAME_HEAD.unpack_from(buffer)
                end = FRAME_HEAD.size + length
                if len(buffer) >= end:
                    body = bytes(buffer[FRAME_HEAD.size : end])
                    del buffer[:end]
                    return kind, body
            if self._ended:
                return None
            try:
                data = os.read(self._fd, READ_BYTES)
            except BlockingIOError:
                time.sleep(POLL_S)
                continue
            if data:
                buffer += data
            else:
                self._ended = True


def _answer(replies: IO[str], answer: dict[str, Any]) -> None:
    replies.write(json.dumps(answer) + "\n")
    replies.flush()


def _leave_real_time() -> None:
    """Normal scheduling, whatever the parent had, and below the run's processes: this process
    must never take the CPU from the control loop (the daemon starts it before it takes
    SCHED_FIFO; this makes sure), nor, without SCHED_FIFO, delay the daemon's and the plant's
    wake-ups (lock-step's ping-pong over the bus)."""
    leave_real_time()
    with contextlib.suppress(OSError):
        os.nice(NICE)


def serve_frames(server: LiveServer, frames: PolledFrames, replies: IO[str]) -> None:
    """Read frames until the input ends, then stop the server and report."""
    try:
        while (frame := frames.next()) is not None:
            kind, body = frame
            if kind == FRAME_CHUNK:
                server.forward(body)
            elif kind == FRAME_CHANNEL:
                server.add_channel(*parse_channel_frame(body))
            elif kind == FRAME_SERVE:
                _answer(replies, server.serve())
        # Let the server send what it has queued for its clients before it goes.
        time.sleep(LINGER_S)
    finally:
        server.stop()
    _answer(replies, server.figures())


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--port", type=int, required=True)
    parser.add_argument("--name", default="ballbeam-hil")
    parser.add_argument("--backlog", type=int, default=8192, help="messages queued per client")
    args = parser.parse_args(argv)
    # Ctrl-C in the terminal reaches the whole process group: the daemon then finishes its
    # run, and the end of this input is what stops this server, after the last chunk.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _leave_real_time()
    server = LiveServer(args.port, args.name, args.backlog)
    try:
        serve_frames(server, PolledFrames(sys.stdin.fileno()), sys.stdout)
    except BrokenPipeError:
        # The daemon is gone: nobody to answer, and nothing to say at exit either.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
