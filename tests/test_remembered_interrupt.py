"""A Ctrl-C that Python drops (raised inside a garbage-collection callback, as Dask registers
one) still stops a sweep or a tuning: the interrupt is remembered and raised again between
units of work. Before, an interrupted tuning could run to its end and exit 0."""

from __future__ import annotations

import gc
import os
import signal
from typing import Any

import pytest

from ballbeam.runtime.stop import RememberedInterrupt


def test_an_interrupt_dropped_in_a_gc_callback_is_raised_at_the_next_check() -> None:
    previous = signal.getsignal(signal.SIGINT)
    latch = RememberedInterrupt().install()
    delivered: list[bool] = []

    def interrupt_during_collection(phase: str, _info: dict[str, Any]) -> None:
        if phase == "start" and not delivered:
            delivered.append(True)
            os.kill(os.getpid(), signal.SIGINT)  # its handler runs here, in the callback

    gc.callbacks.append(interrupt_during_collection)
    try:
        gc.collect()  # the KeyboardInterrupt is printed and dropped by the interpreter
        assert delivered and latch.received
        with pytest.raises(KeyboardInterrupt):
            latch.check()
    finally:
        gc.callbacks.remove(interrupt_during_collection)
        signal.signal(signal.SIGINT, previous)


def test_without_an_interrupt_check_does_nothing() -> None:
    RememberedInterrupt().check()
