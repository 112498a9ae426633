"""``ballbeam run``: the emulator and the daemon as two OS processes on one bus.

Both children get the same config file and overrides (plus a private bus group when
``bus.isolate_runs``), so they agree on everything by construction. The run ends when the
daemon exits; the emulator is then stopped with SIGTERM.
"""

from __future__ import annotations

import os
import secrets
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from ballbeam.config import Config, load_config
from ballbeam.errors import BallbeamError
from ballbeam.protocol.secoc import SECRET_BYTES
from ballbeam.runtime.bus import check_stays_on_host, free_udp_port, isolated_group
from ballbeam.runtime.exit_codes import RECORDED_RUN_CODES
from ballbeam.runtime.process import new_log_path

STOP_GRACE_S = 5.0
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


def _tail(text: str, lines: int = 8) -> str:
    return "\n".join(text.strip().splitlines()[-lines:])


def _spawn(argv: list[str], secret: bytes | None) -> subprocess.Popen[str]:
    if secret is None:
        return subprocess.Popen(
            argv, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True
        )
    fd = secret_pipe(secret)
    try:
        return subprocess.Popen(
            [*argv, "--secret-fd", str(fd)],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
            pass_fds=(fd,),
        )
    finally:
        os.close(fd)


def _stop(process: subprocess.Popen[str]) -> int:
    if process.poll() is None:
        process.send_signal(signal.SIGTERM)
        try:
            return process.wait(timeout=STOP_GRACE_S)
        except subprocess.TimeoutExpired:
            process.kill()
    return process.wait()


def secret_pipe(secret: bytes) -> int:
    """A pipe's read end holding ``secret`` (its write end closed): a child inherits it with
    ``pass_fds`` and reads the secret with ``--secret-fd``. 32 bytes fit in any pipe buffer."""
    read_fd, write_fd = os.pipe()
    try:
        os.write(write_fd, secret)
    finally:
        os.close(write_fd)
    return read_fd


def launch_run(
    config_path: str | None,
    overrides: list[str],
    on_started: Callable[[dict[str, subprocess.Popen[str]]], None] | None = None,
) -> LaunchResult:
    """Run one scenario; ``on_started`` gets both processes (benchmarks watch their memory)."""
    config = load_config(config_path, overrides)
    check_stays_on_host(config.bus)
    child_overrides = list(overrides)
    if config.bus.interface == "udp_multicast" and config.bus.isolate_runs:
        # Group and port both: open_bus makes its sockets hear their own group only, and a
        # port of its own keeps the run apart from listeners that do not.
        group = isolated_group(config.bus.channel)
        child_overrides += [f"bus.channel='{group}'", f"bus.port={free_udp_port()}"]
        config = load_config(config_path, child_overrides)
    log_path = new_log_path(config.run.log_dir, config.plan.kind)
    base = [sys.executable, "-m"]
    config_args = ([config_path] if config_path else []) + [
        argument for override in child_overrides for argument in ("--set", override)
    ]
    # The run's frame-authentication secret: to each child through a pipe of its own, never
    # on a command line, in the environment or in the log.
    secret = secrets.token_bytes(SECRET_BYTES) if config.bus.authenticated else None
    started = time.monotonic()
    emulator = _spawn([*base, "ballbeam_emulator", *config_args], secret)
    daemon = _spawn([*base, "ballbeam", "daemon", *config_args, "--log", str(log_path)], secret)
    if on_started is not None:
        on_started({"emulator": emulator, "daemon": daemon})
    budget_s = (
        STARTUP_ALLOWANCE_S
        + config.controller.start_timeout_s
        + (config.run.duration_s * (1.5 if config.run.mode == "realtime" else 20.0))
    )
    try:
        try:
            _, daemon_errors = daemon.communicate(timeout=budget_s)
        except subprocess.TimeoutExpired:
            daemon.send_signal(signal.SIGTERM)
            _, daemon_errors = daemon.communicate(timeout=STOP_GRACE_S * 4)
            raise RunFailedError(
                f"the daemon did not finish within {budget_s:.0f} s and was stopped; "
                f"its log: {log_path}"
            ) from None
    except BaseException:
        _stop(emulator)
        _stop(daemon)
        raise
    emulator_exit = _stop(emulator)
    _, emulator_errors = emulator.communicate()
    # A run that ended with a verdict (exit_codes.py) left a log to summarise; exit 1 is also
    # what Python gives an uncaught exception, which leaves a traceback instead.
    recorded = (
        daemon.returncode in RECORDED_RUN_CODES
        and log_path.exists()
        and "Traceback (most recent call last)" not in daemon_errors
    )
    if not recorded:
        raise RunFailedError(
            f"the daemon exited with {daemon.returncode}:\n{_tail(daemon_errors)}"
            + (f"\nemulator said:\n{_tail(emulator_errors)}" if emulator_errors.strip() else "")
        )
    return LaunchResult(
        config=config,
        log_path=log_path,
        daemon_exit=daemon.returncode,
        emulator_exit=emulator_exit,
        wall_time_s=time.monotonic() - started,
    )
