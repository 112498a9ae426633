"""The fault tests' shared harness: the test's own bus node, a bench of two processes, and
what a run left behind (outcome, counters, faults, events, shutdown frames, figures).

See the package docstring (:mod:`tests.faults`) for how the tests use it.
"""

from __future__ import annotations

import math
import os
import re
import secrets
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import msgpack
import numpy as np

from ballbeam.config import DEFAULT_BUS_GROUP, load_config
from ballbeam.evaluation.summary import summarise
from ballbeam.logs.reader import RunLog, read_log
from ballbeam.protocol.frames import (
    SENSOR_ID,
    TRUTH_ANGLE_ID,
    VOLTAGE_COMMAND_ID,
    FrameContract,
    SensorFrame,
    TruthAngle,
    VoltageCommand,
)
from ballbeam.protocol.secoc import (
    EXTENDED_LENGTH,
    SECRET_BYTES,
    FrameAuthenticator,
    extension_of,
    is_authenticated_length,
)
from ballbeam.runtime.bus import IPV6_MULTICAST_ALL, free_udp_port, isolated_group, multicast_scope
from ballbeam.runtime.launcher import secret_pipe
from ballbeam.runtime.owner_lock import PEER_LOCK_ENV, create_owner_lock
from ballbeam.runtime.peer_link import PEER_LINK_ENV, PEER_LINK_WRITE_ENV, peer_link_pipe

from ..conftest import PAPER, REPO, ballbeam_argv

CONTRACT = FrameContract.load()
DEFAULTS = load_config(PAPER)
PERIOD_NS = DEFAULTS.controller.period_ns
TIMEOUT_PERIODS = DEFAULTS.controller.sensor_timeout_periods
WATCHDOG_MS = DEFAULTS.plant.watchdog_ms
SETTLE_TOLERANCE_S = 0.3
START_TIMEOUT_S = 60.0  # process start, planning and synthesis, on a busy machine
BENCH_PRIORITY = ("controller.realtime_priority=50", "plant.realtime_priority=40")
SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35)  # Linux values
SO_RCVBUFFORCE = getattr(socket, "SO_RCVBUFFORCE", 33)
# Every test's own figures, printed at the end of a test (pytest -s shows them).
FIGURES: dict[str, Any] = {}


def figure(name: str, value: Any) -> None:
    FIGURES[name] = value
    print(f"  figure {name}: {value}")


# ---- processes ----------------------------------------------------------------------------


def set_args(overrides: list[str]) -> list[str]:
    return [item for override in overrides for item in ("--set", override)]


# Raises the file-size limit's error (EFBIG) instead of killing the process with SIGXFSZ, the
# way a full disk fails a write; a wrapper rather than preexec_fn, which is unsafe with threads.
FSIZE_WRAPPER = (
    "import os, resource, signal, sys; limit = int(sys.argv[1]); "
    "resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit)); "
    "signal.signal(signal.SIGXFSZ, signal.SIG_IGN); "
    "os.execv(sys.executable, [sys.executable, '-m', 'ballbeam', *sys.argv[2:]])"
)


@dataclass
class Heard:
    """One frame as the test's own node heard it; ``time_ns``: kernel receive time (wall)."""

    time_ns: int
    arbitration_id: int
    is_extended_id: bool
    data: bytes


class BusWatch:
    """The test's node on a bench's private group, as cheap as a listener can be.

    Its thread only drains the socket (a large receive buffer, the kernel's receive time
    stamps) and keeps the raw datagrams; they are unpacked in the caller's thread when asked
    for. python-can's own listener costs tens of microseconds a frame in Python, which on two
    busy cores fell behind lock-step traffic (~9 k frames/s) and dropped frames.
    """

    def __init__(self, group: str, port: int = DEFAULTS.bus.port) -> None:
        assert multicast_scope(group) == 1, "interface-local groups only"
        sock = socket.socket(socket.AF_INET6, socket.SOCK_DGRAM)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT, 1)
        try:
            sock.setsockopt(socket.SOL_SOCKET, SO_RCVBUFFORCE, 16 << 20)
        except OSError:  # not root: as much as the system allows
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 16 << 20)
        sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
        sock.setsockopt(socket.IPPROTO_IPV6, IPV6_MULTICAST_ALL, 0)  # this group only
        sock.bind(("", port))
        sock.setsockopt(
            socket.IPPROTO_IPV6,
            socket.IPV6_JOIN_GROUP,
            socket.inet_pton(socket.AF_INET6, group) + struct.pack("@I", 0),
        )
        sock.settimeout(0.05)
        self._sock = sock
        self._raw: list[tuple[int, bytes]] = []
        self._frames: list[Heard] = []
        self._unpacked = 0
        self.malformed = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="bus watch", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        ancillary_size = socket.CMSG_SPACE(16)
        while not self._stop.is_set():
            try:
                data, ancillary, _, _ = self._sock.recvmsg(4096, ancillary_size)
            except TimeoutError:
                continue
            stamp_ns = time.time_ns()
            for level, kind, value in ancillary:
                if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS:
                    seconds, nanoseconds = struct.unpack("@qq", value[:16])
                    stamp_ns = seconds * 1_000_000_000 + nanoseconds
            self._raw.append((stamp_ns, data))

    @property
    def frames(self) -> list[Heard]:
        """Every frame heard so far, in order (datagrams that are no frame are counted)."""
        raw = self._raw
        for stamp_ns, data in raw[self._unpacked : len(raw)]:
            self._unpacked += 1
            try:
                fields = msgpack.unpackb(data, raw=False)
                heard = Heard(
                    stamp_ns,
                    int(fields["arbitration_id"]),
                    bool(fields["is_extended_id"]),
                    bytes(fields["data"]),
                )
            except (ValueError, TypeError, KeyError, msgpack.UnpackException):
                self.malformed += 1
                continue
            self._frames.append(heard)
        return self._frames

    def wait_for(self, predicate: Callable[[Heard], bool], timeout_s: float) -> Heard | None:
        """The first frame (heard so far or within ``timeout_s``) that satisfies ``predicate``."""
        give_up = time.monotonic() + timeout_s
        seen = 0
        while True:
            frames = self.frames
            for index in range(seen, len(frames)):
                if predicate(frames[index]):
                    return frames[index]
            seen = len(frames)
            if time.monotonic() > give_up:
                return None
            time.sleep(0.002)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        self._sock.close()


def decoded(heard: Heard) -> object | None:
    if heard.is_extended_id:
        return None
    # An authenticated frame carries the classic one first (the watch does not check MACs).
    data = heard.data[:8] if is_authenticated_length(len(heard.data)) else heard.data
    try:
        return CONTRACT.decode(heard.arbitration_id, data)
    except ValueError:
        return None


def truth_angles_heard(frames: list[Heard]) -> list[tuple[int, TruthAngle]]:
    """(time_ns, true servo state) of every sample heard: from a truth frame, or from the
    extension of an authenticated sensor frame, which carries its sample's truth."""
    angles = []
    for heard in frames:
        if heard.is_extended_id:
            continue
        if heard.arbitration_id == TRUTH_ANGLE_ID:
            angle = decoded(heard)
        elif heard.arbitration_id == SENSOR_ID and len(heard.data) == EXTENDED_LENGTH:
            sensor = decoded(heard)
            if not isinstance(sensor, SensorFrame):
                continue
            angle, _ = CONTRACT.decode_truth(extension_of(heard.data), sensor.counter)
        else:
            continue
        if isinstance(angle, TruthAngle):
            angles.append((heard.time_ns, angle))
    return angles


def is_enabled_command(heard: Heard) -> bool:
    command = decoded(heard) if heard.arbitration_id == VOLTAGE_COMMAND_ID else None
    return isinstance(command, VoltageCommand) and command.enable


def commands_heard(frames: list[Heard]) -> list[tuple[int, int, VoltageCommand]]:
    """Distinct voltage commands in the order sent: (running index, time_ns, command).

    The running index unwraps the 8-bit counter (a lock-step resend repeats a counter and is
    left out), so index i is the daemon's i-th command, i.e. row i of its /command channel.
    """
    out: list[tuple[int, int, VoltageCommand]] = []
    index = -1
    for heard in frames:
        if heard.arbitration_id != VOLTAGE_COMMAND_ID:
            continue
        command = decoded(heard)
        if not isinstance(command, VoltageCommand):
            continue
        if index < 0:
            index = command.counter
        else:
            delta = (command.counter - index) % 256
            if delta == 0 or delta >= 128:
                continue  # a resend, or older than the last
            index += delta
        out.append((index, heard.time_ns, command))
    return out


def emulator_counters(stderr: str) -> dict[str, int]:
    match = re.search(r"EmulatorCounters\((.*?)\)", stderr)
    assert match is not None, f"the emulator did not report its counters:\n{stderr[-2000:]}"
    return {key: int(value) for key, value in re.findall(r"(\w+)=(\d+)", match.group(1))}


def watchdog_trips_ms(stderr: str) -> list[float]:
    return [
        float(value)
        for value in re.findall(
            r"watchdog: no valid command for ([0-9.]+) ms, voltage zeroed", stderr
        )
    ]


def assert_watchdog_tripped_only_when_the_daemon_was_silent(outcome: Outcome) -> None:
    """The plant's watchdog trips at the end (the daemon left) and otherwise only where the
    daemon sent nothing for ``plant.watchdog_ms`` (its process was off the CPU that long, on
    a shared machine): never for a command that was sent."""
    watchdog_ms = DEFAULTS.plant.watchdog_ms
    sent_ns = outcome.log.topics["/can/tx"].log_time_ns
    silences = int((np.diff(sent_ns) > watchdog_ms * 1e6).sum())
    trips = outcome.emulator["watchdog_trips"]
    assert trips <= 1 + silences, (trips, silences, outcome.emulator)
    if silences:
        figure("daemon_silences_over_watchdog", silences)


class Bench:
    """An emulator and a daemon on a private group, started and ended by the test itself."""

    def __init__(
        self,
        tmp: Path,
        mode: str,
        duration_s: float,
        *extra: str,
        watch: bool = True,
        file_size_limit: int | None = None,
        peer_link: bool = False,
    ) -> None:
        tmp.mkdir(parents=True, exist_ok=True)
        self.tmp = tmp
        self.group = isolated_group(DEFAULT_BUS_GROUP)
        self.port = free_udp_port()
        self.overrides = [
            f"run.mode='{mode}'",
            f"run.duration_s={duration_s}",
            "bus.interface='udp_multicast'",  # its group: what the attackers write to
            f"bus.channel='{self.group}'",
            f"bus.port={self.port}",
            f"run.log_dir='{tmp}'",
            # the emulator may be slow to start on a loaded machine: wait for it for longer
            f"controller.start_timeout_s={START_TIMEOUT_S / 2}",
            # real time only: lock-step keeps no clock, and would run flat out at FIFO
            *(BENCH_PRIORITY if mode == "realtime" else ()),
            *extra,
        ]
        self.config = load_config(PAPER, self.overrides)
        # The run secret, handed to both processes as `ballbeam run` does (an inherited pipe);
        # the test keeps it, to play a second holder of the key when it wants to.
        self.secret = secrets.token_bytes(SECRET_BYTES) if self.config.bus.authenticated else None
        self.log_path = tmp / f"{mode}-{secrets.token_hex(4)}.mcap"
        self.watch = BusWatch(self.group, self.port) if watch else None
        self._files: list[Any] = []
        # The launcher's dead-man link (runtime/peer_link.py), as `ballbeam run` makes it: the
        # pipe, and the robust lock the daemon holds (runtime/owner_lock.py).
        link = peer_link_pipe() if peer_link else None
        lock_fd = create_owner_lock() if peer_link else None
        lock_fds = () if lock_fd is None else (lock_fd,)
        lock_env = {} if lock_fd is None else {PEER_LOCK_ENV: str(lock_fd)}
        try:
            self.emulator = self._spawn(
                "emulator", ballbeam_argv("emulator", str(PAPER), *set_args(self.overrides)),
                pass_fds=(link[0], *lock_fds) if link else (),
                env={**os.environ, PEER_LINK_ENV: str(link[0]), **lock_env} if link else None,
            )
            daemon_args = [
                "daemon", str(PAPER), *set_args(self.overrides), "--log", str(self.log_path)
            ]
            if file_size_limit is None:
                argv = ballbeam_argv(*daemon_args)
            else:
                argv = [sys.executable, "-c", FSIZE_WRAPPER, str(file_size_limit), *daemon_args]
            self.daemon = self._spawn(
                "daemon", argv,
                pass_fds=(link[1], *lock_fds) if link else (),
                env={**os.environ, PEER_LINK_WRITE_ENV: str(link[1]), **lock_env}
                if link else None,
            )
        finally:
            for fd in (*(link or ()), *lock_fds):
                os.close(fd)

    def _spawn(
        self,
        name: str,
        argv: list[str],
        pass_fds: tuple[int, ...] = (),
        env: dict[str, str] | None = None,
    ) -> subprocess.Popen[bytes]:
        # stderr to a file: a pipe nobody reads could fill up and stall the process.
        stream = (self.tmp / f"{name}-{secrets.token_hex(3)}.stderr").open("w+b")
        self._files.append(stream)
        fds = pass_fds
        secret_fd = secret_pipe(self.secret) if self.secret is not None else None
        if secret_fd is not None:
            fds = (*fds, secret_fd)
            argv = [*argv, "--secret-fd", str(secret_fd)]
        try:
            process = subprocess.Popen(
                argv, stdout=subprocess.PIPE, stderr=stream, cwd=REPO, pass_fds=fds, env=env,
            )
        finally:
            if secret_fd is not None:
                os.close(secret_fd)
        process.stderr_file = stream  # type: ignore[attr-defined]
        return process

    def authenticator(self) -> FrameAuthenticator:
        """A node holding this run's secret (a second writer, when the test sends with it)."""
        assert self.secret is not None, "the bench's bus is not authenticated"
        return FrameAuthenticator(self.secret)

    @staticmethod
    def stderr(process: subprocess.Popen[bytes]) -> str:
        stream = process.stderr_file  # type: ignore[attr-defined]
        stream.flush()
        stream.seek(0)
        return str(stream.read().decode(errors="replace"))

    def wait_cycling(self) -> Heard:
        assert self.watch is not None
        first = self.watch.wait_for(is_enabled_command, START_TIMEOUT_S)
        if first is None:
            heard = {hex(h.arbitration_id) for h in self.watch.frames}
            raise AssertionError(
                f"the daemon never commanded (port {self.port}; heard ids {sorted(heard)}; "
                f"exits: daemon {self.daemon.poll()}, emulator {self.emulator.poll()}):\n"
                f"{self.stderr(self.daemon)[-2000:]}\n{self.stderr(self.emulator)[-2000:]}"
            )
        return first

    def wait_daemon(self, timeout_s: float) -> int:
        try:
            return self.daemon.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            self.daemon.kill()
            self.daemon.wait()
            raise AssertionError(f"the daemon did not end within {timeout_s} s") from None

    def stop_emulator(self) -> int:
        if self.emulator.poll() is None:
            self.emulator.send_signal(signal.SIGTERM)
        try:
            return self.emulator.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.emulator.kill()
            self.emulator.wait()
            raise AssertionError("the emulator ignored SIGTERM for 10 s") from None

    def close(self) -> None:
        for process in (self.daemon, self.emulator):
            if process.poll() is None:
                process.kill()
                process.wait()
            if process.stdout is not None:
                process.stdout.close()
        if self.watch is not None:
            self.watch.close()
        for stream in self._files:
            stream.close()

    def __enter__(self) -> Bench:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()


@dataclass
class Outcome:
    daemon_exit: int
    log: RunLog
    summary: dict[str, Any]
    emulator: dict[str, int]
    emulator_stderr: str
    daemon_stderr: str


def finish_flood(flood: subprocess.Popen[str]) -> tuple[str, str]:
    """A flood process's stdout and stderr once it has stopped by itself (it is bounded in
    count and time); one that does not is killed and fails the test."""
    try:
        return flood.communicate(timeout=START_TIMEOUT_S + 10)
    except subprocess.TimeoutExpired:
        raise AssertionError("the flood did not stop by itself") from None
    finally:
        if flood.poll() is None:
            flood.kill()
            flood.communicate()


def run_to_end(bench: Bench, extra_budget_s: float = 0.0) -> Outcome:
    """Let a bench run its course, stop the emulator, read the log."""
    budget_s = START_TIMEOUT_S + bench.config.run.duration_s * 3 + extra_budget_s
    daemon_exit = bench.wait_daemon(budget_s)
    assert bench.stop_emulator() == 0, bench.stderr(bench.emulator)[-2000:]
    log = read_log(bench.log_path)
    return Outcome(
        daemon_exit,
        log,
        summarise(log),
        emulator_counters(bench.stderr(bench.emulator)),
        bench.stderr(bench.emulator),
        bench.stderr(bench.daemon),
    )


def summary_meta(log: RunLog) -> dict[str, str]:
    return dict(log.metadata.get("summary", {}))


def faults(log: RunLog, kind: str | None = None) -> list[dict[str, Any]]:
    topic = log.json_topics.get("/faults")
    messages = list(topic.messages) if topic is not None else []
    return [m for m in messages if kind is None or m["kind"] == kind]


def events(log: RunLog, kind: str) -> list[dict[str, Any]]:
    return [m for m in log.json_topics["/events"].messages if m["kind"] == kind]


def shutdown_frames(log: RunLog) -> list[VoltageCommand]:
    """The daemon's last sent frames that follow its last recorded /command (the stop)."""
    tx = log.topics["/can/tx"].values
    sent = [
        CONTRACT.decode(int(i), bytes(d))
        for i, d in zip(tx["arbitration_id"], tx["data"], strict=True)
    ]
    last_counter = int(log.topics["/command"].values["counter"][-1])
    tail_start = max(
        i for i, c in enumerate(sent) if isinstance(c, VoltageCommand) and c.counter == last_counter
    )
    return [c for c in sent[tail_start + 1 :] if isinstance(c, VoltageCommand)]


def assert_settles_like(outcome: Outcome, clean: Outcome) -> None:
    settle = outcome.summary["settle_time_s"]
    assert settle is not None and math.isfinite(settle), outcome.summary
    assert abs(settle - clean.summary["settle_time_s"]) <= SETTLE_TOLERANCE_S, (
        settle,
        clean.summary["settle_time_s"],
    )


def log_started(directory: Path) -> bool:
    """A daemon has begun its log in ``directory`` (``ballbeam run`` creates the file empty,
    before the daemon starts; the daemon's first write is its header)."""
    return any(path.stat().st_size > 0 for path in directory.glob("*.mcap"))


def one_error_line(stderr: str) -> str:
    assert "Traceback" not in stderr, stderr
    lines = [line for line in stderr.splitlines() if line.strip()]
    errors = [line for line in lines if line.startswith("ballbeam: error:")]
    assert len(errors) == 1, stderr
    return errors[0]
