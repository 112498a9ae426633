"""A dead-man link between the two processes of a run: a pipe whose only write end the daemon
holds, and whose read end the emulator polls.

When the daemon dies, however it dies (SIGKILL included), the kernel closes its end and the
emulator's next poll reads end-of-file: it zeroes the drive at its next sensor period instead of
waiting out its watchdog, which must be long enough for real time's worst hiccups (20 ms). The
kernel closes a dead process's files only after freeing its memory (7–16 ms for a daemon), so
the link also carries a robust mutex the daemon holds (runtime/owner_lock.py), released within
half a millisecond of the death: with it, kill → 0 V takes one or two sensor periods. A real rig
gets the same from a hardware enable line; a daemon run by hand has no link and relies on the
watchdog.

One byte is ever written: the daemon's "run over" (:func:`signal_run_over`) after its last
command, so that the emulator stops there, sends its final counters (the PlantStatus frames)
while the daemon still listens and records them, and reports on exit exactly what the log got.

The launcher (``ballbeam run``) makes the pipe and hands each end to one process by inheriting
it (``pass_fds``); the emulator learns its end's number from ``BALLBEAM_PEER_LINK_FD``, the
daemon its own from ``BALLBEAM_PEER_LINK_WRITE_FD``.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from typing import Literal, TypeAlias

from ballbeam.errors import ConfigError
from ballbeam.runtime.owner_lock import OwnerLock

PEER_LINK_ENV = "BALLBEAM_PEER_LINK_FD"
PEER_LINK_WRITE_ENV = "BALLBEAM_PEER_LINK_WRITE_FD"
RUN_OVER = b"E"

PeerState: TypeAlias = Literal["running", "run_over", "gone"]


def _inherited_fd(name: str, environ: Mapping[str, str]) -> int | None:
    value = environ.get(name)
    if value is None:
        return None
    try:
        fd = int(value)
        os.fstat(fd)
    except (ValueError, OSError):
        raise ConfigError(
            f"{name}={value!r} is not an open file descriptor (it is set by `ballbeam run`; "
            "unset it to run the process by hand)"
        ) from None
    return fd


class PeerLink:
    """The emulator's end: :meth:`peer_gone` is one non-blocking read (about a microsecond)."""

    def __init__(self, read_fd: int, owner_lock: OwnerLock | None = None) -> None:
        os.set_blocking(read_fd, False)
        self.read_fd = read_fd
        self.owner_lock = owner_lock
        self.gone = False
        self.run_over = False

    @classmethod
    def from_environment(cls, environ: Mapping[str, str] = os.environ) -> PeerLink | None:
        fd = _inherited_fd(PEER_LINK_ENV, environ)
        return None if fd is None else cls(fd, OwnerLock.from_environment(environ))

    def state(self) -> PeerState:
        """``"gone"`` once the daemon's end has closed, else ``"run_over"`` once the daemon
        said its run is over, else ``"running"`` (each state is kept once reached)."""
        if not self.gone:
            # The lock first: a "run over" the daemon wrote before dying is in the pipe by then.
            owner_gone = self.owner_lock is not None and self.owner_lock.holder_gone()
            try:
                byte = os.read(self.read_fd, 1)
            except BlockingIOError:
                byte = None
            if byte == b"":
                self.gone = True
            elif byte is not None:
                self.run_over = True  # any byte: only the daemon holds the write end
            elif owner_gone:
                self.gone = True
        return "gone" if self.gone else "run_over" if self.run_over else "running"

    def peer_gone(self) -> bool:
        """True once the daemon's end has closed (and from then on)."""
        return self.state() == "gone"

    def close(self) -> None:
        os.close(self.read_fd)


def run_over_fd(environ: Mapping[str, str] = os.environ) -> int | None:
    """The daemon's end of the link, if ``ballbeam run`` handed it one."""
    return _inherited_fd(PEER_LINK_WRITE_ENV, environ)


def signal_run_over(write_fd: int) -> bool:
    """Tell the emulator the run is over (the daemon has sent its last command); False if it
    is gone already."""
    try:
        os.write(write_fd, RUN_OVER)
    except OSError:  # EPIPE: the emulator is gone (Python ignores SIGPIPE)
        return False
    return True


def peer_link_pipe() -> tuple[int, int]:
    """(read end for the emulator, write end for the daemon), neither inheritable by default:
    each is passed to its one process explicitly."""
    return os.pipe()
