"""``ballbeam run``: the emulator and the daemon as two OS processes on one bus.

Both children get the same config file and overrides (plus a private bus group when
``bus.isolate_runs``), so they agree on everything by construction. The run ends when the
daemon exits; the emulator is then stopped with SIGTERM.

Each child leads a session of its own. Where the kernel groups tasks by session (autogroup,
``/proc/sys/kernel/sched_autogroup_enabled``), the fair scheduler then shares the CPUs between
sessions first: a node that needs a third of a CPU is owed a whole group's share, however
many busy processes the session it was started from runs, so its timer wakes it on time beside
them. The terminal's signals no longer reach the children, so the launcher passes a stop
(SIGINT, SIGTERM, or SIGHUP as SIGTERM) on to the daemon: it commands 0 V and finishes its log,
the emulator follows, and the run is summarised as one stopped on request.
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from types import FrameType

from mcap.writer import MCAP0_MAGIC

from ballbeam.config import Config, load_config
from ballbeam.errors import BallbeamError
from ballbeam.files import remove_if_empty
from ballbeam.protocol.secoc import RunKey
from ballbeam.runtime.bus import (
    BUS_CHOICE_ENV,
    AutoChoice,
    check_before_start,
    free_udp_port,
    isolated_group,
    resolve_auto,
)
from ballbeam.runtime.exit_codes import (
    EXIT_FAILED,
    EXIT_OK,
    EXIT_PLANT_LOST,
    EXIT_SECOND_WRITER,
)
from ballbeam.runtime.owner_lock import PEER_LOCK_ENV, create_owner_lock
from ballbeam.runtime.peer_link import PEER_LINK_ENV, PEER_LINK_WRITE_ENV, peer_link_pipe
from ballbeam.runtime.process import (
    new_log_file,
    no_core_dumps_while,
    realtime_permitted,
    realtime_refused_message,
)

STOP_GRACE_S = 5.0
# The daemon's exits after which its run is recorded whole (summarised by ``ballbeam run``).
RECORDED_RUN_CODES = frozenset({EXIT_OK, EXIT_FAILED, EXIT_PLANT_LOST, EXIT_SECOND_WRITER})
STARTUP_ALLOWANCE_S = 30.0


class RunFailedError(BallbeamError, RuntimeError):
    """A child process failed; the message carries its last error lines."""


@dataclass(frozen=True)
class LaunchResult:
    config: Config
    log_path: Path
    daemon_exit: int
    emulator_exit: int
    wall_time_s: float
    emulator_stderr: str = ""  # its own report: the counters it ends with, for a cross-check
    bus_choice: str = ""  # why "auto" went where it did ("" for a named interface)


def _tail(text: str, lines: int = 8) -> str:
    return "\n".join(text.strip().splitlines()[-lines:])


class _StopRequested(KeyboardInterrupt):
    """SIGINT, SIGTERM or SIGHUP to the launcher while its run goes: passed on to the daemon
    (a KeyboardInterrupt, so one that escapes ends the command as Ctrl-C does)."""

    def __init__(self, signum: int) -> None:
        super().__init__(signal.Signals(signum).name)
        # The daemon stops on SIGINT and SIGTERM (runtime/stop.py); a hang-up is a SIGTERM.
        self.forward = signal.SIGTERM if signum == signal.SIGHUP else signum


@contextlib.contextmanager
def _stop_requests_raise() -> Iterator[None]:
    """While the run goes, a stop signal raises ``_StopRequested`` in the waiting launcher.
    Main thread only (elsewhere the caller owns the signals)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def request_stop(signum: int, _frame: FrameType | None) -> None:
        raise _StopRequested(signum)

    numbers = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
    previous = {number: signal.signal(number, request_stop) for number in numbers}
    try:
        yield
    finally:
        for number, handler in previous.items():
            signal.signal(number, handler)


def _stopped_daemon_errors(
    daemon: subprocess.Popen[str], signum: int, log_path: Path
) -> str:
    """Send the daemon ``signum`` and wait for it to finish its log; what it wrote to stderr.
    One that does not within the grace is killed, and its log made whole."""
    daemon.send_signal(signum)
    try:
        return daemon.communicate(timeout=STOP_GRACE_S * 4)[1]
    except subprocess.TimeoutExpired:
        daemon.kill()
        daemon.communicate()
        raise RunFailedError(
            f"the daemon did not stop within {STOP_GRACE_S * 4:.0f} s of "
            f"{signal.Signals(signum).name} and was killed{_recover_cut_log(log_path)}"
        ) from None


def _stop(process: subprocess.Popen[str], own_exit_s: float = 0.0) -> int:
    """The process's exit code: it stopped by itself within ``own_exit_s``, or on SIGTERM
    within the grace, or it is killed."""
    if own_exit_s > 0.0:
        with contextlib.suppress(subprocess.TimeoutExpired):
            return process.wait(timeout=own_exit_s)
    if process.poll() is None:
        process.send_signal(signal.SIGTERM)
        try:
            return process.wait(timeout=STOP_GRACE_S)
        except subprocess.TimeoutExpired:
            process.kill()
    return process.wait()


def secret_pipe(secret: bytes | bytearray) -> int:
    """A pipe's read end holding ``secret``, its write end closed: a child inherits it with
    ``pass_fds`` and reads the secret with ``--secret-fd N`` (the number, never the secret, is
    on its command line). 32 bytes fit in any pipe buffer, so the write never blocks."""
    read_fd, write_fd = os.pipe()
    try:
        os.write(write_fd, secret)
    finally:
        os.close(write_fd)
    return read_fd


def _recover_cut_log(log_path: Path) -> str:
    """A daemon that died without finishing its log leaves it cut short: make it whole in
    place (every intact message kept) and say so; "" if the log was whole or absent."""
    from ballbeam.logs.recover import recover_log, recovered_path

    try:
        with log_path.open("rb") as log:
            log.seek(max(log_path.stat().st_size - len(MCAP0_MAGIC), 0))
            if log.read() == MCAP0_MAGIC:
                return ""  # it ends with the closing magic: the daemon finished its log
    except FileNotFoundError:
        return "; it had written no log yet"
    if remove_if_empty(log_path):
        return "; it had written no log yet"
    try:
        recovery = recover_log(log_path, recovered_path(log_path))
        os.replace(recovery.destination, log_path)
    except (BallbeamError, OSError) as error:
        return f"; its log {log_path} is cut short and could not be recovered ({error})"
    return (
        f"; its log was cut short and has been made whole ({recovery.messages} intact "
        f"messages kept): {log_path}"
    )


def launch_run(
    config_path: str | None,
    overrides: list[str],
    on_started: Callable[[dict[str, subprocess.Popen[str]]], None] | None = None,
    live_port: int | None = None,
) -> LaunchResult:
    """Run one scenario; ``on_started`` gets both processes (benchmarks watch their memory).
    With ``live_port`` the daemon serves the run live on that loopback port (``--live``)."""
    config = load_config(config_path, overrides)
    check_before_start(config.bus)  # nothing started, no log made
    live_args: list[str] = []
    if live_port is not None:
        from ballbeam.runtime.live import check_port_free, live_url

        check_port_free(live_port)  # a taken port: one line and exit 2, nothing started
        live_args = ["--live", "--live-port", str(live_port)]
        print(
            f"live view on {live_url(live_port)} while the run goes "
            "(Foxglove: Open connection, Foxglove WebSocket)",
            file=sys.stderr,
            flush=True,
        )
    child_overrides = list(overrides)
    choice: AutoChoice | None = None
    if config.bus.interface == "auto":
        # A vcan of the run's own (held until it ends), else the group: the children are
        # told which, so that they agree by construction.
        choice = resolve_auto(config.bus, claim=True)
        child_overrides += choice.overrides_for(config.bus)
        config = load_config(config_path, child_overrides)
    try:
        return _launch(config, config_path, child_overrides, on_started, live_args, choice)
    finally:
        if choice is not None:
            choice.release()


def _launch(
    config: Config,
    config_path: str | None,
    child_overrides: list[str],
    on_started: Callable[[dict[str, subprocess.Popen[str]]], None] | None,
    live_args: list[str],
    choice: AutoChoice | None,
) -> LaunchResult:
    if config.bus.interface == "udp_multicast" and config.bus.isolate_runs:
        # Group and port both: open_bus makes its sockets hear their own group only, and a
        # port of its own keeps the run apart from listeners that do not.
        group = isolated_group(config.bus.channel)
        child_overrides += [f"bus.channel='{group}'", f"bus.port={free_udp_port()}"]
        config = load_config(config_path, child_overrides)
    if config.run.mode == "realtime":
        priority = max(config.controller.realtime_priority, config.plant.realtime_priority)
        if not realtime_permitted(priority):
            # The children say so in their own logs too; the user hears it once, up front.
            print(f"ballbeam: {realtime_refused_message(priority)}", file=sys.stderr)
    # Created here, before its name is on any command line, and handed to the daemon open:
    # nothing planted at the name in between can be written through.
    log_path, log_stream = new_log_file(config.run.log_dir, config.plan.kind)
    log_fd = log_stream.fileno()
    base = [sys.executable, "-m"]
    config_args = ([config_path] if config_path else []) + [
        argument for override in child_overrides for argument in ("--set", override)
    ]
    started = time.monotonic()
    # The dead-man link (runtime/peer_link.py): the emulator zeroes the drive within a sensor
    # period of the daemon's death, whatever kills it, and stops when the daemon's run is over.
    link_read, link_write = peer_link_pipe()
    lock_fd = create_owner_lock()  # its fast half, where glibc has robust mutexes
    lock_env = {} if lock_fd is None else {PEER_LOCK_ENV: str(lock_fd)}
    # The run's frame-authentication key (protocol/secoc.py): to each child through a pipe of
    # its own, never on a command line, in the environment or in the log. The launcher holds
    # it only to write the pipes, undumpable meanwhile, then overwrites it.
    emulator_secret = daemon_secret = None
    if config.bus.authenticated:
        with no_core_dumps_while(), RunKey.generate() as key:
            emulator_secret = secret_pipe(key.material)
            daemon_secret = secret_pipe(key.material)

    def secret_args(fd: int | None) -> list[str]:
        return [] if fd is None else ["--secret-fd", str(fd)]

    try:
        emulator = subprocess.Popen(
            [*base, "ballbeam_emulator", *config_args, *secret_args(emulator_secret)],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
            pass_fds=tuple(
                fd for fd in (link_read, lock_fd, emulator_secret) if fd is not None
            ),
            env={**os.environ, PEER_LINK_ENV: str(link_read), **lock_env},
            start_new_session=True,  # a scheduling group of its own (module docstring)
        )
        daemon = subprocess.Popen(
            [*base, "ballbeam", "daemon", *config_args, "--log", str(log_path),
             "--log-fd", str(log_fd), *live_args, *secret_args(daemon_secret)],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
            pass_fds=tuple(
                fd for fd in (link_write, lock_fd, daemon_secret, log_fd) if fd is not None
            ),
            # Its end of the link also says when the run is over (the emulator then sends its
            # final counters, and the daemon records them).
            env={**os.environ, PEER_LINK_WRITE_ENV: str(link_write), **lock_env,
                 **({} if choice is None else {BUS_CHOICE_ENV: f"auto: {choice.reason}"})},
            start_new_session=True,
        )
    except BaseException:
        remove_if_empty(log_path)  # no daemon started to write it
        raise
    finally:
        log_stream.close()  # the daemon has its own descriptor
        for fd in (link_read, link_write, lock_fd, emulator_secret, daemon_secret):
            if fd is not None:
                os.close(fd)
    if on_started is not None:
        on_started({"emulator": emulator, "daemon": daemon})
    budget_s = (
        STARTUP_ALLOWANCE_S
        + config.controller.start_timeout_s
        + (config.run.duration_s * (1.5 if config.run.mode == "realtime" else 20.0))
    )
    try:
        with _stop_requests_raise():
            try:
                _, daemon_errors = daemon.communicate(timeout=budget_s)
            except _StopRequested as request:
                # Stopped on request: the daemon commands 0 V, finishes its log and the run is
                # summarised as usual (a second request while it does stops both at once).
                daemon_errors = _stopped_daemon_errors(daemon, request.forward, log_path)
            except subprocess.TimeoutExpired:
                _stopped_daemon_errors(daemon, signal.SIGTERM, log_path)
                raise RunFailedError(
                    f"the daemon did not finish within {budget_s:.0f} s and was stopped; "
                    f"its log: {log_path}"
                ) from None
    except BaseException:
        # The daemon first: it commands 0 V and finishes its log; the emulator, told by the
        # peer link that the run is over, then sends its final counters.
        _stop(daemon)
        _stop(emulator)
        raise
    # A daemon whose run is recorded has told the emulator so (the peer link) and it stops by
    # itself; a SIGTERM that met it exiting found Python's handlers already gone and killed it
    own_exit_s = STOP_GRACE_S if daemon.returncode in RECORDED_RUN_CODES else 0.0
    emulator_exit = _stop(emulator, own_exit_s)
    _, emulator_errors = emulator.communicate()
    if daemon.returncode not in RECORDED_RUN_CODES:
        how = f"exited with {daemon.returncode}"
        if daemon.returncode < 0:
            how = f"was killed by signal {-daemon.returncode}"
            with contextlib.suppress(ValueError):
                how = f"was killed by {signal.Signals(-daemon.returncode).name}"
        raise RunFailedError(
            f"the daemon {how}{_recover_cut_log(log_path)}:\n{_tail(daemon_errors)}"
            + (f"\nemulator said:\n{_tail(emulator_errors)}" if emulator_errors.strip() else "")
        )
    return LaunchResult(
        config=config,
        log_path=log_path,
        daemon_exit=daemon.returncode,
        emulator_exit=emulator_exit,
        wall_time_s=time.monotonic() - started,
        emulator_stderr=emulator_errors,
        bus_choice="" if choice is None else f"auto: {choice.reason}",
    )
