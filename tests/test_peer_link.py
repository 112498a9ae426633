"""The dead-man link (runtime/peer_link.py) on its own: a pipe whose write end only the peer
holds reads as open while the peer lives and as gone, for good, once it has exited."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

from ballbeam.errors import ConfigError
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
