"""recv_frame: the nodes' one way of reading the bus (poll, then block; noise skipped)."""

from __future__ import annotations

import threading
from collections import deque
from typing import Any

import can
import pytest

from ballbeam.runtime.bus import recv_frame


class ScriptedBus:
    """Answers ``recv`` from a script: a message, None (nothing yet) or an exception."""

    def __init__(self, script: list[Any]) -> None:
        self.script = deque(script)
        self.timeouts: list[float | None] = []

    def recv(self, timeout: float | None = None) -> can.Message | None:
        self.timeouts.append(timeout)
        if not self.script:
            return None
        item = self.script.popleft()
        if isinstance(item, BaseException):
            raise item
        return item  # type: ignore[no-any-return]


def _malformed() -> can.CanOperationError:
    error = can.CanOperationError("could not unpack received message")
    error.__cause__ = ValueError("not msgpack")
    return error


def _frame(arbitration_id: int = 0x101) -> can.Message:
    return can.Message(arbitration_id=arbitration_id, data=bytes(8), is_extended_id=False)


def test_polling_catches_a_frame_that_arrives_during_the_poll() -> None:
    with can.Bus(interface="virtual", channel="poll") as ours, can.Bus(
        interface="virtual", channel="poll"
    ) as theirs:
        timeouts: list[float | None] = []
        recv = ours.recv

        def spied_recv(timeout: float | None = None) -> can.Message | None:
            timeouts.append(timeout)
            return recv(timeout)

        ours.recv = spied_recv  # type: ignore[method-assign]
        sender = threading.Timer(0.002, lambda: theirs.send(_frame()))
        sender.start()
        message = recv_frame(ours, 20.0, lambda _: None, poll_s=10.0)
        sender.join()
    assert message is not None and message.arbitration_id == 0x101
    assert timeouts and set(timeouts) == {0.0}  # caught while polling: never blocked


def test_polls_without_blocking_then_blocks_for_the_rest() -> None:
    bus = ScriptedBus([None, None])
    assert recv_frame(bus, 10.0, lambda _: None, poll_s=0.01) is None  # type: ignore[arg-type]
    assert bus.timeouts[0] == 0.0
    assert bus.timeouts[-1] is not None and 0.0 < bus.timeouts[-1] <= 10.0


def test_malformed_datagrams_while_polling_are_reported_and_skipped() -> None:
    reports: list[str] = []
    bus = ScriptedBus([_malformed(), None, _malformed(), _frame(0x102)])
    message = recv_frame(bus, 1.0, reports.append, poll_s=0.5)  # type: ignore[arg-type]
    assert message is not None and message.arbitration_id == 0x102
    assert len(reports) == 2 and "not msgpack" in reports[0]


@pytest.mark.parametrize("poll_s", [0.0, 0.1])
def test_a_failing_socket_still_raises(poll_s: float) -> None:
    error = can.CanOperationError("recv failed")
    error.__cause__ = OSError(9, "Bad file descriptor")
    bus = ScriptedBus([error])
    with pytest.raises(can.CanOperationError):
        recv_frame(bus, 1.0, lambda _: None, poll_s=poll_s)  # type: ignore[arg-type]


def test_a_stream_of_noise_cannot_hold_a_non_blocking_read() -> None:
    bus = ScriptedBus([_malformed() for _ in range(10_000)])
    reports: list[str] = []
    assert recv_frame(bus, 0.0, reports.append) is None  # type: ignore[arg-type]
    assert len(reports) == 64


def test_the_receive_queue_goes_short_and_back_and_the_kernel_drops_what_it_cannot_hold() -> None:
    """ReceiveQueue sets the socket's SO_RCVBUF short and back to the kernel's size: short, a
    burst beyond it is dropped by the kernel (tail drop), long, the same burst is kept."""
    import socket
    import time

    from ballbeam.config import DEFAULT_BUS_GROUP, BusSection
    from ballbeam.runtime.bus import ReceiveQueue, free_udp_port, isolated_group, open_bus

    section = BusSection(channel=isolated_group(DEFAULT_BUS_GROUP), port=free_udp_port())
    sender, receiver = open_bus(section), open_bus(section)
    queue = ReceiveQueue(receiver)
    probe = socket.socket(fileno=receiver.fileno())
    try:
        long_bytes = probe.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)

        def burst_kept() -> int:
            for _ in range(150):
                sender.send(can.Message(arbitration_id=0x7AB, data=bytes(8), is_extended_id=False))
            time.sleep(0.1)
            kept = 0
            while recv_frame(receiver, 0.0, lambda _: None) is not None:
                kept += 1
            return kept

        queue.set_short(True)
        assert probe.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF) == 2 * queue.SHORT_BYTES
        short_kept = burst_kept()
        queue.set_short(False)
        assert probe.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF) == long_bytes
        assert burst_kept() == 150 > short_kept > 0
        assert queue.shortened == 1 and queue.sizes() == f"{long_bytes} / {2 * queue.SHORT_BYTES}"
    finally:
        probe.detach()
        queue.close()
        sender.shutdown()
        receiver.shutdown()


def test_the_queue_goes_short_only_when_the_loop_stays_behind() -> None:
    """A stall's catch-up (behind for fewer than SHORTEN_AFTER_CYCLES cycles) leaves the queue
    long; behind for longer, short; caught up for RESTORE_AFTER_CYCLES, long again."""
    from ballbeam.runtime.daemon.loop import (
        RESTORE_AFTER_CYCLES,
        SHORTEN_AFTER_CYCLES,
        StandingQueue,
    )

    standing = StandingQueue()
    burst = [True] * (SHORTEN_AFTER_CYCLES - 1) + [False]
    assert not any(standing.update(behind) for behind in burst * 3)
    states = [standing.update(True) for _ in range(SHORTEN_AFTER_CYCLES)]
    assert states[-1] and not any(states[:-1])
    # a cycle caught up now and then does not make it long again
    assert all(standing.update(k % 50 != 0) for k in range(2 * RESTORE_AFTER_CYCLES))
    states = [standing.update(False) for _ in range(RESTORE_AFTER_CYCLES)]
    assert not states[-1] and all(states[:-1])
