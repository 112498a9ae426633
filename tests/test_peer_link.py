"""The dead-man link (runtime/peer_link.py) on its own: a pipe whose write end only the peer
holds reads as open while the peer lives and as gone, for good, once it has exited."""

from __future__ import annotations

import os
import subprocess
import sys
import time

import pytest

from ballbeam.errors import ConfigError
from ballbeam.runtime.owner_lock import PEER_LOCK_ENV, OwnerLock, create_owner_lock
from ballbeam.runtime.peer_link import PEER_LINK_ENV, PeerLink, peer_link_pipe, signal_run_over


def test_the_link_reads_gone_only_after_the_peer_exits() -> None:
    read_fd, write_fd = peer_link_pipe()
    peer = subprocess.Popen(
        [sys.executable, "-c", "import sys; sys.stdin.read()"],
        stdin=subprocess.PIPE, pass_fds=(write_fd,),
    )
    os.close(write_fd)  # the peer holds the only write end now
    link = PeerLink(read_fd)
    try:
        assert not link.peer_gone()
        assert peer.stdin is not None
        peer.stdin.close()  # the peer exits
        assert peer.wait(timeout=10) == 0
        assert link.peer_gone()
        assert link.peer_gone()  # and stays gone
    finally:
        link.close()


@pytest.mark.parametrize("value", ["seven", "987654"])
def test_a_bad_link_variable_is_one_clear_error(value: str) -> None:
    with pytest.raises(ConfigError, match=PEER_LINK_ENV):
        PeerLink.from_environment({PEER_LINK_ENV: value})


def test_no_variable_no_link() -> None:
    assert PeerLink.from_environment({}) is None


def test_the_daemons_run_over_byte_reads_as_run_over_then_gone() -> None:
    read_fd, write_fd = peer_link_pipe()
    link = PeerLink(read_fd)
    try:
        assert link.state() == "running"
        assert signal_run_over(write_fd)
        assert link.state() == "run_over" and not link.peer_gone()
        os.close(write_fd)
        assert link.state() == "gone" and link.peer_gone()
        link.close()
        write_fd = -1
        # The emulator gone first: the daemon's signal fails quietly (no SIGPIPE death).
        read_fd, write_fd = peer_link_pipe()
        os.close(read_fd)
        assert not signal_run_over(write_fd)
    finally:
        if write_fd >= 0:
            os.close(write_fd)


HOLDER = (
    "import sys, time\n"
    "from ballbeam.runtime.owner_lock import OwnerLock\n"
    "lock = OwnerLock.from_environment()\n"
    "assert lock is not None and lock.hold()\n"
    "print('held', flush=True)\n"
    "sys.stdin.read()\n"  # until told; then exit (normally, or killed)
)


def _holder(lock_fd: int, write_fd: int | None = None) -> subprocess.Popen[str]:
    fds = (lock_fd,) if write_fd is None else (lock_fd, write_fd)
    holder = subprocess.Popen(
        [sys.executable, "-c", HOLDER], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
        text=True, pass_fds=fds, env={**os.environ, PEER_LOCK_ENV: str(lock_fd)},
    )
    assert holder.stdout is not None and holder.stdout.readline() == "held\n"
    return holder


@pytest.mark.parametrize("death", ["sigkill", "exit"])
def test_the_robust_lock_reads_gone_within_a_millisecond_of_the_holders_death(death: str) -> None:
    """The lock's point: it is free ("owner died") at the start of the holder's exit, before
    the kernel frees its memory and closes its files; a holder with NumPy and SciPy loaded takes
    10–20 ms to be reaped (runtime/owner_lock.py)."""
    lock_fd = create_owner_lock()
    assert lock_fd is not None, "glibc on Linux has process-shared robust mutexes"
    watcher = OwnerLock(lock_fd)
    try:
        assert not watcher.holder_gone()  # nobody holds it yet: not a death
        holder = _holder(lock_fd)
        for _ in range(3):
            assert not watcher.holder_gone()
        assert holder.stdin is not None
        start_ns = time.monotonic_ns()
        if death == "sigkill":
            holder.kill()
        else:
            holder.stdin.close()
        while not watcher.holder_gone():
            assert time.monotonic_ns() - start_ns < 5e9, "the lock never came free"
        assert watcher.holder_gone()  # and stays so
        holder.wait(timeout=10)
    finally:
        os.close(lock_fd)


def test_a_run_over_written_before_death_reads_run_over_first() -> None:
    """The daemon says "run over" and then exits: the emulator must hear the run's end, not a
    lost peer, even when it first looks after the lock has come free."""
    lock_fd = create_owner_lock()
    assert lock_fd is not None
    read_fd, write_fd = peer_link_pipe()
    link = PeerLink(read_fd, OwnerLock(lock_fd))
    try:
        holder = _holder(lock_fd, write_fd)
        assert signal_run_over(write_fd)
        os.close(write_fd)
        assert holder.stdin is not None
        holder.stdin.close()
        holder.wait(timeout=10)
        assert link.state() == "run_over"
        assert link.state() == "gone"
    finally:
        link.close()
        os.close(lock_fd)


def test_an_unusable_lock_variable_leaves_the_pipe_alone_to_do_it() -> None:
    assert OwnerLock.from_environment({PEER_LOCK_ENV: "seven"}) is None
    assert OwnerLock.from_environment({}) is None
