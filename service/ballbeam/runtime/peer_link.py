"""A dead-man link between the two processes of a run: a pipe whose only write end the daemon
holds, and whose read end the emulator polls.

Nothing is ever written. When the daemon dies, however it dies (SIGKILL included), the kernel
closes its end at once and the emulator's next poll reads end-of-file: it zeroes the drive
within one sensor period instead of waiting out its watchdog, which must be long enough for
real time's worst hiccups (20 ms). A real rig gets the same from a hardware enable line; a
daemon run by hand has no link and relies on the watchdog.

The launcher (``ballbeam run``) makes the pipe and hands each end to one process by inheriting
it (``pass_fds``); the emulator learns its end's number from ``BALLBEAM_PEER_LINK_FD``.
"""

from __future__ import annotations

import os
from collections.abc import Mapping

from ballbeam.errors import ConfigError

PEER_LINK_ENV = "BALLBEAM_PEER_LINK_FD"


class PeerLink:
    """The emulator's end: :meth:`peer_gone` is one non-blocking read (about a microsecond)."""

    def __init__(self, read_fd: int) -> None:
        os.set_blocking(read_fd, False)
        self.read_fd = read_fd
        self.gone = False

    @classmethod
    def from_environment(cls, environ: Mapping[str, str] = os.environ) -> PeerLink | None:
        value = environ.get(PEER_LINK_ENV)
        if value is None:
            return None
        try:
            fd = int(value)
            os.fstat(fd)
        except (ValueError, OSError):
            raise ConfigError(
                f"{PEER_LINK_ENV}={value!r} is not an open file descriptor (it is set by "
                "`ballbeam run`; unset it to run the emulator by hand)"
            ) from None
        return cls(fd)

    def peer_gone(self) -> bool:
        """True once the daemon's end has closed (and from then on)."""
        if not self.gone:
            try:
                self.gone = os.read(self.read_fd, 1) == b""
            except BlockingIOError:
                return False
        return self.gone

    def close(self) -> None:
        os.close(self.read_fd)


def peer_link_pipe() -> tuple[int, int]:
    """(read end for the emulator, write end for the daemon), neither inheritable by default:
    each is passed to its one process explicitly."""
    return os.pipe()
