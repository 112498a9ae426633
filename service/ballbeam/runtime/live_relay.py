"""The live view's front door: both names of Foxglove's WebSocket protocol on one port.

The protocol has two subprotocol names for the same messages: ``foxglove.sdk.v1`` (the
``foxglove-sdk`` server and the current Foxglove app) and ``foxglove.websocket.v1`` (the older
name, still the only one of the ``@foxglove/ws-protocol`` client, Lichtblick and older Foxglove
Studio). The SDK's server accepts only its own names (its handshake answers any other offer
with HTTP 400) and has no option for the older one. This relay listens on the live view's
port, on the loopback interface only; each connection is passed byte for byte to the SDK's
server on a private loopback port, except for the upgrade handshake of a client that offers
only ``foxglove.websocket.v1``: the SDK is asked for ``foxglove.sdk.v1`` and the client
answered with the name it offered. Everything else, frames and close included, is relayed as
it comes; a client that falls behind holds up its relay, and the SDK's queue for it drops its
oldest messages as it does for a direct client.
"""

from __future__ import annotations

import asyncio
import contextlib
import threading
from concurrent.futures import Future

SDK_SUBPROTOCOL = "foxglove.sdk.v1"
OLD_SUBPROTOCOL = "foxglove.websocket.v1"
SUBPROTOCOLS = (SDK_SUBPROTOCOL, OLD_SUBPROTOCOL)  # what a client may offer (the README's)
PROTOCOL_HEADER = b"sec-websocket-protocol"
HEAD_END = b"\r\n\r\n"
MAX_HEAD_BYTES = 64 * 1024  # an upgrade request or answer is a few hundred bytes
HEAD_TIMEOUT_S = 10.0  # a connection that sends no whole request head in this long is closed
READ_BYTES = 64 * 1024
START_TIMEOUT_S = 10.0
FINISH_TIMEOUT_S = 1.0  # at the end: for relayed connections to close on their own


def _offered(head: bytes) -> list[str]:
    """The subprotocols a request head offers, in order (every such header line)."""
    offered: list[str] = []
    for line in head.split(b"\r\n")[1:]:
        name, _, value = line.partition(b":")
        if name.strip().lower() == PROTOCOL_HEADER:
            offered += [part.strip().decode("latin-1") for part in value.split(b",")]
    return [name for name in offered if name]


def _with_protocol(head: bytes, protocol: str) -> bytes:
    """``head`` with its subprotocol header lines replaced by one naming ``protocol``."""
    lines = head[: -len(HEAD_END)].split(b"\r\n")
    kept = [
        line for line in lines[1:]
        if line.partition(b":")[0].strip().lower() != PROTOCOL_HEADER
    ]
    header = b"Sec-WebSocket-Protocol: " + protocol.encode("latin-1")
    return b"\r\n".join([lines[0], *kept, header]) + HEAD_END


def translated_request(head: bytes) -> bytes | None:
    """The request head to pass to the SDK's server, and None where it is passed as it is:
    a client that offers the old name and none of the SDK's (``foxglove.sdk.*``) asks the SDK
    for its own name."""
    offered = _offered(head)
    if OLD_SUBPROTOCOL not in offered or any(
        name.startswith("foxglove.sdk.") for name in offered
    ):
        return None
    return _with_protocol(head, SDK_SUBPROTOCOL)


def translated_answer(head: bytes) -> bytes:
    """The SDK's answer to a translated request, naming the old subprotocol (an upgrade: the
    client may only be given a name it offered); any other answer (a refusal) as it is."""
    if not head.startswith(b"HTTP/1.1 101"):
        return head
    return _with_protocol(head, OLD_SUBPROTOCOL)


async def _pump(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
    """Copy until the end of ``reader``, then end ``writer``'s side. Waits for the writer to
    drain: a slow client slows its own relay, not the others."""
    try:
        while data := await reader.read(READ_BYTES):
            writer.write(data)
            await writer.drain()
    except (ConnectionError, OSError):
        pass
    finally:
        with contextlib.suppress(ConnectionError, OSError):
            if writer.can_write_eof():
                writer.write_eof()
            else:
                writer.close()


class SubprotocolRelay:
    """Listens on ``host``:``port`` and relays each connection to the SDK's server on
    ``host``:``sdk_port`` (module docstring). Its own thread runs an asyncio loop."""

    def __init__(self, host: str, port: int, sdk_port: int) -> None:
        self._host = host
        self._port = port
        self._sdk_port = sdk_port
        self._loop = asyncio.new_event_loop()
        self._server: asyncio.Server | None = None
        self._connections: set[asyncio.Task[None]] = set()
        self._thread = threading.Thread(target=self._run, name="live-relay", daemon=True)
        self._started: Future[None] = Future()

    def start(self) -> None:
        """Bind and serve; OSError (e.g. the port is taken) as the bind raised it."""
        self._thread.start()
        self._started.result(timeout=START_TIMEOUT_S)

    def stop(self) -> None:
        """Close the listener and every relayed connection; wait for the thread."""
        if not self._thread.is_alive():
            return
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(START_TIMEOUT_S + FINISH_TIMEOUT_S)

    def _run(self) -> None:
        asyncio.set_event_loop(self._loop)
        try:
            self._server = self._loop.run_until_complete(
                asyncio.start_server(
                    self._relay, self._host, self._port, reuse_address=True,
                    limit=MAX_HEAD_BYTES,
                )
            )
        except OSError as error:
            self._started.set_exception(error)
            self._loop.close()
            return
        self._started.set_result(None)
        try:
            self._loop.run_forever()
        finally:
            # The SDK's server stopped first: its connections end on their own once the last
            # bytes (its close frames) are through; a client that never closes is cut.
            self._server.close()
            self._loop.run_until_complete(self._finish())
            self._loop.close()

    async def _finish(self) -> None:
        if self._connections:
            _, left = await asyncio.wait(self._connections, timeout=FINISH_TIMEOUT_S)
            for task in left:
                task.cancel()
            await asyncio.gather(*left, return_exceptions=True)

    async def _relay(
        self, client_reader: asyncio.StreamReader, client_writer: asyncio.StreamWriter
    ) -> None:
        task = asyncio.current_task()
        assert task is not None
        self._connections.add(task)
        sdk_writer: asyncio.StreamWriter | None = None
        try:
            request = await asyncio.wait_for(
                client_reader.readuntil(HEAD_END), HEAD_TIMEOUT_S
            )
            sdk_reader, sdk_writer = await asyncio.open_connection(
                self._host, self._sdk_port, limit=MAX_HEAD_BYTES
            )
            translated = translated_request(request)
            sdk_writer.write(translated or request)
            if translated is not None:
                answer = await asyncio.wait_for(sdk_reader.readuntil(HEAD_END), HEAD_TIMEOUT_S)
                client_writer.write(translated_answer(answer))
            await asyncio.gather(
                _pump(client_reader, sdk_writer), _pump(sdk_reader, client_writer)
            )
        except (asyncio.IncompleteReadError, asyncio.LimitOverrunError, TimeoutError,
                ConnectionError, OSError):
            pass  # not a WebSocket client, or gone: nothing to relay
        finally:
            for writer in (client_writer, sdk_writer):
                if writer is not None:
                    writer.close()
            self._connections.discard(task)
