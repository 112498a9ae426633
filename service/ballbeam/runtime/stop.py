"""SIGINT/SIGTERM as a flag the loops poll: they stop at a cycle boundary, command 0 V and
finish their files, instead of dying mid-write."""

from __future__ import annotations

import signal
import threading
from types import FrameType


class StopFlag:
    def __init__(self) -> None:
        self._event = threading.Event()
        self.signal_name: str | None = None

    def is_set(self) -> bool:
        return self._event.is_set()

    def set(self, reason: str = "requested") -> None:
        self.signal_name = self.signal_name or reason
        self._event.set()

    def install(self) -> StopFlag:
        """Route SIGINT and SIGTERM to this flag (main thread only)."""

        def handler(signum: int, _frame: FrameType | None) -> None:
            self.set(signal.Signals(signum).name)

        signal.signal(signal.SIGINT, handler)
        signal.signal(signal.SIGTERM, handler)
        return self


class RememberedInterrupt:
    """SIGINT as KeyboardInterrupt, and remembered. Python raises it wherever the main thread
    is, and where that is a callback the interpreter runs for a library (a garbage-collection
    callback of Dask's), it is printed and dropped: the study would then run to its end.
    Loops call :meth:`check` between units of work, which raises it again."""

    def __init__(self) -> None:
        self.received = False

    def install(self) -> RememberedInterrupt:
        def handler(_signum: int, _frame: FrameType | None) -> None:
            self.received = True
            raise KeyboardInterrupt

        signal.signal(signal.SIGINT, handler)
        return self

    def check(self) -> None:
        if self.received:
            raise KeyboardInterrupt


# The one SIGINT of a process (the CLI installs it for sweeps and tunings; not installed, it
# never fires and check() does nothing).
INTERRUPT = RememberedInterrupt()
