"""Authenticated frames on the virtual bus, in the style of AUTOSAR SecOC.

The classic contract (``frames.py``: 8-byte frames, E2E CRC and an 8-bit counter) protects
against corruption and loss, not against a third process that writes well-formed frames. On a
bus that carries CAN FD (python-can's ``udp_multicast`` and ``virtual``) each frame of a run is
therefore sent as a 24-byte CAN FD frame::

    bytes  0..7   the classic payload, unchanged (CRC, counter, signals: the DBC's layout)
    bytes  8..15  freshness value, uint64 little-endian: the sender's CLOCK_MONOTONIC in ns,
                  made strictly increasing per sender (one clock for every process of a host)
    bytes 16..23  MAC: HMAC-SHA256(secret, id (uint32 LE) ‖ freshness ‖ payload), truncated
                  to 64 bits

A frame may carry an extension between the classic payload and the freshness, making a
64-byte frame whose MAC covers the payload and the extension together: a voltage command the
controller's look-ahead (``frames.encode_lookahead``, 40 bytes), a sensor frame its sample's
truth (``frames.FrameContract.encode_truth``, 40 bytes).

keyed by a per-run 32-byte secret the launcher hands to both processes through an inherited
pipe (never argv, never the environment, never the log). Each process keeps it in a
:class:`RunKey`, a buffer it overwrites when the run ends.

A receiver accepts a frame of a stream (arbitration id) only if its MAC is right, its freshness
is strictly greater than the last it accepted on that stream, and within ``window_ns`` of its
own clock. A forged frame fails the MAC; a replayed or reordered one fails the freshness test;
neither moves any state, so the real stream goes on being accepted. The window also refuses a
frame replayed from an old log to a receiver that has just started (no last value yet).

A node also hears its own frames (the bus loops them back). :meth:`FrameAuthenticator.own_echo`
tells them apart: each freshness the node sent is expected back once. A frame on the node's own
id with a right MAC that the node did not send comes from another holder of the secret: a
second writer.
"""

from __future__ import annotations

import ctypes
import hashlib
import hmac
import os
import time
from collections import deque
from typing import Final, Literal, TypeAlias

SECRET_BYTES: Final = 32
CLASSIC_LENGTH: Final = 8
FRESHNESS_BYTES: Final = 8
MAC_BYTES: Final = 8
TRAILER_BYTES: Final = FRESHNESS_BYTES + MAC_BYTES
AUTHENTICATED_LENGTH: Final = CLASSIC_LENGTH + TRAILER_BYTES  # a CAN FD length
EXTENSION_BYTES: Final = 40  # a command's look-ahead or a sample's truth (protocol/frames.py)
EXTENDED_LENGTH: Final = AUTHENTICATED_LENGTH + EXTENSION_BYTES  # 64: CAN FD's largest frame
_LENGTHS: Final = (AUTHENTICATED_LENGTH, EXTENDED_LENGTH)
DEFAULT_WINDOW_NS: Final = 1_000_000_000
MAX_SENT_KEPT: Final = 65_536  # own frames remembered (a window's worth at any sane rate)

AuthVerdict: TypeAlias = Literal["ok", "unauthenticated", "bad_mac", "replayed", "out_of_window"]
OwnVerdict: TypeAlias = Literal["echo", "replayed", "not_sent", "invalid"]


class RunKey:
    """The run's secret in a buffer of this process's own, overwritten by :meth:`wipe`.

    What a wipe reaches, and what it cannot: the key lives only in this ``bytearray`` (read
    into it from the pipe or the OS, never through a ``bytes`` object, which is immutable and
    whose memory is freed unwiped). An authenticator keys one HMAC context from this buffer
    (``hmac.new``, which CPython hands to OpenSSL) and copies it for each MAC (half the cost
    of keying one per frame); OpenSSL cleanses a context (key pads included) when it frees
    it, the keyed one when the authenticator drops it (at its wipe, or once the key is seen
    wiped). The pure-Python fallback, used only without OpenSSL, makes ``bytes`` copies of
    the padded key that no one can wipe. A key given as ``bytes`` (tests, benchmarks) is
    copied in, and the caller's object stays as it was. Nothing here keeps the pages out of
    swap (no ``mlock``): the nodes forbid core dumps instead (``runtime/process.py``).
    """

    __slots__ = ("_buffer", "_wiped")

    def __init__(self, buffer: bytearray) -> None:
        """Takes ``buffer`` over (no copy): wiping the key overwrites that very object."""
        if len(buffer) != SECRET_BYTES:
            raise ValueError(f"the run secret must be {SECRET_BYTES} bytes, got {len(buffer)}")
        self._buffer = buffer
        self._wiped = False

    @classmethod
    def generate(cls) -> RunKey:
        """A new key from the OS's random source, read straight into the buffer."""
        buffer = bytearray(SECRET_BYTES)
        with open("/dev/urandom", "rb", buffering=0) as source:
            if source.readinto(buffer) != SECRET_BYTES:
                raise OSError("a short read from /dev/urandom")
        return cls(buffer)

    @property
    def material(self) -> bytearray:
        """The key's bytes (the buffer itself: do not keep or copy it)."""
        if self._wiped:
            raise ValueError("the run key has been wiped")
        return self._buffer

    @property
    def wiped(self) -> bool:
        return self._wiped

    def wipe(self) -> None:
        """Overwrite the key's bytes in place with zeros; using the key afterwards raises."""
        if len(self._buffer):
            ctypes.memset((ctypes.c_char * len(self._buffer)).from_buffer(self._buffer), 0,
                          len(self._buffer))
        self._wiped = True

    def __enter__(self) -> RunKey:
        return self

    def __exit__(self, *_: object) -> None:
        self.wipe()

    def __repr__(self) -> str:  # never the key itself, not even in a traceback
        return f"RunKey({'wiped' if self._wiped else f'{SECRET_BYTES} bytes'})"


class FrameAuthenticator:
    """Protects outgoing frames and judges incoming ones for one node of one run."""

    __slots__ = ("_echoed", "_key", "_keyed", "_last_accepted", "_last_sent", "_sent",
                 "_sent_frames", "window_ns")

    def __init__(self, secret: RunKey | bytes, window_ns: int = DEFAULT_WINDOW_NS) -> None:
        """``secret``: the run's key (shared, not copied: wiping it ends this authenticator
        too), or its 32 bytes (copied into a key of its own)."""
        self._key = secret if isinstance(secret, RunKey) else RunKey(bytearray(secret))
        self._keyed: hmac.HMAC | None = None  # made at the first MAC (RunKey's docstring)
        self.window_ns = window_ns
        self._last_sent = 0
        self._last_accepted: dict[int, int] = {}
        # What this node sent within the window, (id, freshness), and which came back already.
        self._sent: deque[tuple[int, int]] = deque()
        # Their bytes: a frame heard that is byte for byte one of them is ours without a MAC
        # computed again (every echo: a MAC costs the loop ~10 µs here).
        self._sent_frames: dict[tuple[int, int], bytes] = {}
        self._echoed: set[tuple[int, int]] = set()

    def _mac(self, arbitration_id: int, freshness: bytes, payload: bytes) -> bytes:
        if self._key.wiped:
            self._keyed = None  # the keyed context goes with the key
        if self._keyed is None:
            self._keyed = hmac.new(self._key.material, digestmod=hashlib.sha256)  # wiped: raises
        mac = self._keyed.copy()
        mac.update(arbitration_id.to_bytes(4, "little") + freshness + payload)
        return mac.digest()[:MAC_BYTES]

    def wipe(self) -> None:
        """Overwrite the key (the run is over): no frame can be protected or judged after."""
        self._keyed = None
        self._key.wipe()

    def protect(self, arbitration_id: int, payload: bytes, extension: bytes = b"") -> bytes:
        """The authenticated frame data for a classic 8-byte ``payload`` (24 bytes), or with
        an ``extension`` of EXTENSION_BYTES after it (64 bytes)."""
        if len(payload) != CLASSIC_LENGTH:
            raise ValueError(f"a classic payload is {CLASSIC_LENGTH} bytes, got {len(payload)}")
        if extension and len(extension) != EXTENSION_BYTES:
            raise ValueError(f"an extension is {EXTENSION_BYTES} bytes, got {len(extension)}")
        payload += extension
        value = max(self._last_sent + 1, time.monotonic_ns())
        self._last_sent = value
        key = (arbitration_id, value)
        sent = self._sent
        sent.append(key)
        # Forget what left the window (the freshness is the send time); a bounded memory.
        while sent and (sent[0][1] < value - self.window_ns or len(sent) > MAX_SENT_KEPT):
            old = sent.popleft()
            self._sent_frames.pop(old, None)
            self._echoed.discard(old)
        freshness = value.to_bytes(FRESHNESS_BYTES, "little")
        frame = payload + freshness + self._mac(arbitration_id, freshness, payload)
        self._sent_frames[key] = frame
        return frame

    @staticmethod
    def freshness_of(data: bytes) -> int:
        return int.from_bytes(data[-TRAILER_BYTES:-MAC_BYTES], "little")

    def authentic(self, arbitration_id: int, data: bytes) -> bool:
        """True when ``data`` is an authenticated frame whose MAC is right (no state change)."""
        if len(data) not in _LENGTHS:
            return False
        payload = data[:-TRAILER_BYTES]
        freshness = data[-TRAILER_BYTES:-MAC_BYTES]
        return hmac.compare_digest(
            data[-MAC_BYTES:], self._mac(arbitration_id, freshness, payload)
        )

    def own_frame(
        self, arbitration_id: int, data: bytes, now_ns: int | None = None
    ) -> OwnVerdict:
        """A frame on one of this node's own ids: ``"echo"`` (one it sent, heard back for the
        first time), ``"replayed"`` (one it sent, heard again; or a right MAC from outside the
        window: an old frame), ``"not_sent"`` (a right MAC and a fresh freshness it never
        sent: another holder of the secret writes this id, a second writer), or
        ``"invalid"`` (no right MAC: a stranger's)."""
        if len(data) not in _LENGTHS:
            return "invalid"
        value = self.freshness_of(data)
        key = (arbitration_id, value)
        sent = self._sent_frames.get(key)
        if sent != data and not self.authentic(arbitration_id, data):
            return "invalid"  # (the very bytes this node sent carry its MAC: not checked again)
        if sent is not None:
            if key in self._echoed:
                return "replayed"
            self._echoed.add(key)
            return "echo"
        now = time.monotonic_ns() if now_ns is None else now_ns
        oldest_kept = self._sent[0][1] if self._sent else 0
        if abs(value - now) > self.window_ns or value < oldest_kept:
            return "replayed"  # older than what this node remembers sending: not a live writer
        return "not_sent"

    def verify(self, arbitration_id: int, data: bytes, now_ns: int | None = None) -> AuthVerdict:
        """Judge a frame from a peer; only ``"ok"`` moves the stream's freshness forward."""
        if len(data) not in _LENGTHS:
            return "unauthenticated"
        if not self.authentic(arbitration_id, data):
            return "bad_mac"
        value = self.freshness_of(data)
        if value <= self._last_accepted.get(arbitration_id, 0):
            return "replayed"
        now = time.monotonic_ns() if now_ns is None else now_ns
        if abs(value - now) > self.window_ns:
            return "out_of_window"
        self._last_accepted[arbitration_id] = value
        return "ok"


def is_authenticated_length(length: int) -> bool:
    """Whether a frame of ``length`` bytes has the layout of an authenticated one."""
    return length in _LENGTHS


def extension_of(data: bytes) -> bytes:
    """The extension of an authenticated frame's data (empty for a 24-byte frame)."""
    return data[CLASSIC_LENGTH:-TRAILER_BYTES]


def read_secret(fd: int) -> RunKey:
    """The run secret from an inherited file descriptor (a pipe the launcher wrote and closed,
    or a file), read straight into a :class:`RunKey`'s buffer; the descriptor is closed
    afterwards. ValueError unless exactly 32 bytes."""
    buffer = bytearray(SECRET_BYTES)
    view = memoryview(buffer)
    filled = 0
    try:
        while filled < SECRET_BYTES:
            count = os.readv(fd, [view[filled:]])
            if not count:
                break
            filled += count
        longer = filled == SECRET_BYTES and os.read(fd, 1) != b""  # longer input is refused
    finally:
        view.release()
        os.close(fd)
    key = RunKey(buffer)
    if filled != SECRET_BYTES or longer:
        key.wipe()
        raise ValueError(f"the run secret on fd {fd} must be {SECRET_BYTES} bytes")
    return key
