"""A node's memory holds the run's key: it never goes to a core file, and the key is overwritten
when the run ends.

A node (emulator or daemon, started as ``ballbeam run`` starts it: the key through an inherited
pipe) is given a core limit as large as the system allows, then killed with SIGABRT. It must
have lowered the limit itself (``/proc/PID/limits``) and made itself undumpable: the test raises
the limit again from outside before the kill, so only the dumpable flag stands between the
signal and a core file in the node's working directory (``core_pattern`` is read to know where
the kernel would write one).
"""

from __future__ import annotations

import contextlib
import hmac
import json
import os
import resource
import secrets
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from ballbeam.cli import main
from ballbeam.config import DEFAULT_BUS_GROUP
from ballbeam.protocol import secoc
from ballbeam.protocol.secoc import SECRET_BYTES, FrameAuthenticator, RunKey
from ballbeam.runtime.bus import free_udp_port, isolated_group
from ballbeam.runtime.launcher import secret_pipe
from ballbeam.runtime.process import dumpable

# Starts a node with the core limit as high as its hard limit (a user's `ulimit -c unlimited`);
# a wrapper rather than preexec_fn, which is unsafe with threads.
CORE_WRAPPER = (
    "import os, resource, sys; _, hard = resource.getrlimit(resource.RLIMIT_CORE); "
    "resource.setrlimit(resource.RLIMIT_CORE, (hard, hard)); "
    "os.execv(sys.executable, [sys.executable, *sys.argv[1:]])"
)
START_TIMEOUT_S = 60.0
NODES = {
    "emulator": ["-m", "ballbeam_emulator"],
    "daemon": ["-m", "ballbeam", "daemon", "--log", "daemon.mcap"],
}


def _core_limit(pid: int) -> tuple[str, str]:
    for line in Path(f"/proc/{pid}/limits").read_text().splitlines():
        if line.startswith("Max core file size"):
            soft, hard = line.split()[4:6]
            return soft, hard
    raise AssertionError("no core limit in /proc/PID/limits")


def _holds_pipe(pid: int, inode: int) -> bool:
    try:
        descriptors = list(Path(f"/proc/{pid}/fd").iterdir())
    except PermissionError:  # not root, and the node is no longer dumpable: it read the key
        return False
    for fd in descriptors:
        try:
            if os.readlink(fd) == f"pipe:[{inode}]":
                return True
        except OSError:
            continue
    return False


@pytest.mark.bus
@pytest.mark.parametrize("node", sorted(NODES))
def test_a_node_killed_with_sigabrt_writes_no_core_file(tmp_path: Path, node: str) -> None:
    _, hard = resource.getrlimit(resource.RLIMIT_CORE)
    if hard == 0:
        pytest.skip("this host allows no core file at all (hard core limit 0)")
    pattern = Path("/proc/sys/kernel/core_pattern").read_text().strip()
    overrides = [
        "run.mode='lockstep'", "run.duration_s=1.0", "controller.start_timeout_s=120",
        f"bus.channel='{isolated_group(DEFAULT_BUS_GROUP)}'", f"bus.port={free_udp_port()}",
    ]
    secret_fd = secret_pipe(os.urandom(SECRET_BYTES))
    pipe_inode = os.fstat(secret_fd).st_ino
    argv = [sys.executable, "-c", CORE_WRAPPER, *NODES[node],
            *[item for override in overrides for item in ("--set", override)],
            "--secret-fd", str(secret_fd)]
    try:
        process = subprocess.Popen(argv, cwd=tmp_path, pass_fds=(secret_fd,),
                                   stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    finally:
        os.close(secret_fd)
    try:
        # The node has read the key once the pipe is no longer among its descriptors.
        deadline = time.monotonic() + START_TIMEOUT_S
        while _holds_pipe(process.pid, pipe_inode) and process.poll() is None:
            assert time.monotonic() < deadline, "the node never read its key"
            time.sleep(0.05)
        assert process.poll() is None, process.communicate()[1].decode()[-2000:]
        assert _core_limit(process.pid) == ("0", "0")
        # Raised again from outside where this process may (CAP_SYS_RESOURCE): only the
        # dumpable flag is left to refuse a core then.
        with contextlib.suppress(PermissionError):
            infinite = (resource.RLIM_INFINITY, resource.RLIM_INFINITY)
            resource.prlimit(process.pid, resource.RLIMIT_CORE, infinite)
        os.kill(process.pid, signal.SIGABRT)
        _, errors = process.communicate(timeout=30)
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
    assert process.returncode == -signal.SIGABRT, errors.decode()[-2000:]
    if not pattern.startswith("|") and "/" not in pattern:
        # The kernel writes such a core into the process's working directory.
        prefix = pattern.split("%", 1)[0]
        assert not [path.name for path in tmp_path.iterdir() if path.name.startswith(prefix)]


def test_forbidding_core_dumps_makes_the_process_undumpable() -> None:
    """Read from inside the process with PR_GET_DUMPABLE."""
    code = ("from ballbeam.runtime.process import dumpable, forbid_core_dumps; "
            "import resource; before = dumpable(); forbid_core_dumps(); "
            "print(before, dumpable(), *resource.getrlimit(resource.RLIMIT_CORE))")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                            timeout=60, check=True)
    assert result.stdout.split() == ["1", "0", "0", "0"]


def test_the_launcher_is_undumpable_only_while_it_holds_the_key() -> None:
    """Nested (two launches in threads overlap): the state before the first is restored when
    the last leaves, not before."""
    code = (
        "import json, resource\n"
        "from ballbeam.runtime.process import dumpable, no_core_dumps_while\n"
        "_, hard = resource.getrlimit(resource.RLIMIT_CORE)\n"
        "resource.setrlimit(resource.RLIMIT_CORE, (hard, hard))\n"
        "def state(): return [dumpable(), resource.getrlimit(resource.RLIMIT_CORE)[0] == 0]\n"
        "with no_core_dumps_while():\n"
        "    inside = state()\n"
        "    with no_core_dumps_while():\n"
        "        pass\n"
        "    after_inner = state()\n"
        "print(json.dumps([inside, after_inner, state(), hard == 0]))\n"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                            timeout=60, check=True)
    inside, after_inner, after, no_cores_at_all = json.loads(result.stdout)
    assert inside == after_inner == [0, True]
    assert after == [1, no_cores_at_all]


def test_the_run_key_is_overwritten_in_place_when_wiped() -> None:
    buffer = bytearray(os.urandom(SECRET_BYTES))
    original = bytes(buffer)
    key = RunKey(buffer)
    sender = FrameAuthenticator(key)
    frame = sender.protect(0x101, bytes(8))
    assert FrameAuthenticator(original).verify(0x101, frame) == "ok"  # the key in use is it
    # HMAC-SHA256(key, id ‖ freshness ‖ payload), truncated: the stdlib's one-shot agrees
    assert frame[16:] == hmac.digest(
        original, (0x101).to_bytes(4, "little") + frame[8:16] + frame[:8], "sha256"
    )[:8]
    sharing = FrameAuthenticator(key)  # the other end of one process: keyed, then wiped
    assert sharing.verify(0x101, frame) == "ok"
    assert original not in repr(key).encode() and original.hex() not in repr(key)
    sender.wipe()
    assert key.wiped and buffer == bytearray(SECRET_BYTES)  # the very object, all zeros
    with pytest.raises(ValueError, match="wiped"):
        sender.protect(0x101, bytes(8))
    with pytest.raises(ValueError, match="wiped"):
        sharing.authentic(0x101, frame)  # its keyed MAC went with the key


def test_a_key_read_from_its_pipe_lands_in_the_buffer_that_is_wiped() -> None:
    secret = os.urandom(SECRET_BYTES)
    key = secoc.read_secret(secret_pipe(secret))
    assert key.material == secret
    buffer = key.material
    with key:
        pass
    assert buffer == bytearray(SECRET_BYTES)
    with pytest.raises(ValueError, match="32 bytes"):
        secoc.read_secret(secret_pipe(secret + b"x"))


def test_the_daemon_wipes_its_key_when_its_run_ends(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``ballbeam daemon`` in this process (its core-dump ban spied on, not applied to the test
    process): no plant answers, the run ends, and the key it read is zeros."""
    keys: list[RunKey] = []
    real_read_secret = secoc.read_secret

    def read_and_keep(fd: int) -> RunKey:
        keys.append(real_read_secret(fd))
        return keys[-1]

    forbidden: list[bool] = []
    monkeypatch.setattr(secoc, "read_secret", read_and_keep)
    monkeypatch.setattr("ballbeam.runtime.process.forbid_core_dumps",
                        lambda: forbidden.append(True))
    secret = os.urandom(SECRET_BYTES)
    fd = secret_pipe(secret)
    # a private interface-local group of its own: nothing answers on it
    group = f"ff11:7079:7468:6f6e:{os.getpid() & 0xFFFF:x}:{secrets.randbits(16):x}::1"
    code = main(["daemon", "--set", "bus.interface='udp_multicast'",
                 "--set", f"bus.channel='{group}'",
                 "--set", "controller.start_timeout_s=0.2", "--set", "run.mode='lockstep'",
                 "--secret-fd", str(fd), "--log", str(tmp_path / "run.mcap")])
    assert code == 3  # plant lost: no emulator
    assert forbidden == [True]
    (key,) = keys
    assert key.wiped and key._buffer == bytearray(SECRET_BYTES)
    assert dumpable() == 1  # the test process itself was left as it was
