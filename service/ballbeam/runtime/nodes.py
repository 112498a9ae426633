"""Process entry points: the controller daemon and the plant emulator, each on its own.

``ballbeam run`` starts both of these as separate OS processes; ``ballbeam daemon`` and
``ballbeam emulator`` run one side alone (two terminals, or the daemon against a real plant).
"""

from __future__ import annotations

import contextlib
import datetime as dt
import gc
import json
import logging
import os
import secrets
import subprocess
import sys
from importlib import metadata
from pathlib import Path

from ballbeam.config import Config
from ballbeam.errors import RecorderError
from ballbeam.protocol.frames import FrameContract
from ballbeam.runtime.bus import open_bus
from ballbeam.runtime.signals import StopFlag

log = logging.getLogger("ballbeam")

REPO_ROOT = Path(__file__).resolve().parents[3]
REALTIME_SWITCH_INTERVAL_S = 2e-4
PACKAGES = ("ballbeam-hil", "numpy", "scipy", "python-can", "mcap", "pydantic", "cantools")


def new_log_path(log_dir: str | Path, kind: str) -> Path:
    """A unique, sortable file name: UTC time to the microsecond, then a random suffix
    (absolute, so the path a run prints opens from anywhere)."""
    directory = Path(log_dir).absolute()
    try:
        directory.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise RecorderError(f"cannot create log directory {directory}: {error}") from error
    if not os.access(directory, os.W_OK):
        raise RecorderError(f"log directory {directory} is not writable")
    stamp = dt.datetime.now(dt.UTC).strftime("%Y%m%dT%H%M%S.%fZ")
    return directory / f"{stamp}_{kind}_{secrets.token_hex(3)}.mcap"


def git_revision() -> str:
    try:
        result = subprocess.run(
            ["git", "-C", str(REPO_ROOT), "describe", "--always", "--dirty", "--abbrev=12"],
            capture_output=True, text=True, timeout=5, check=False,
        )
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return result.stdout.strip() or "unknown"


def package_versions() -> dict[str, str]:
    versions = {}
    for name in PACKAGES:
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            versions[name] = "not installed"
    return versions


def apply_scheduling(cpu: int | None, realtime_priority: int | None) -> dict[str, str]:
    """Pin to a CPU and/or switch to SCHED_FIFO; what was refused is reported, not fatal
    (an unprivileged user still gets a working, if jittery, bench)."""
    applied: dict[str, str] = {}
    if cpu is not None and cpu >= 0:
        try:
            os.sched_setaffinity(0, {cpu})
            applied["cpu"] = str(cpu)
        except OSError as error:
            applied["cpu"] = f"refused: {error.strerror}"
            log.warning("cannot pin to CPU %d: %s", cpu, error.strerror)
    if realtime_priority is not None:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(realtime_priority))
            applied["realtime_priority"] = f"SCHED_FIFO {realtime_priority}"
        except OSError as error:
            applied["realtime_priority"] = f"refused: {error.strerror}"
            log.warning("SCHED_FIFO %d refused: %s", realtime_priority, error.strerror)
    return applied


def settle_heap() -> None:
    """Collect once, then exempt every object alive now from later collections.

    A full collection of the ~90,000 objects numpy, scipy, pydantic and the controller design
    leave behind takes about 20 ms here, and the interpreter starts one whenever enough
    allocations pile up: a 20-period stall at 1 kHz. Frozen, they are never scanned again, so
    the collections the loop's own allocations trigger take microseconds.
    """
    gc.collect()
    gc.freeze()


def run_daemon(config: Config, log_path: Path, config_path: str | None) -> Path:
    """Plan, synthesise, open the recorder and the bus, run, finish the file. Returns the log."""
    from ballbeam.assembly import controller_design
    from ballbeam.logs import design_record
    from ballbeam.logs.recorder import Recorder
    from ballbeam.runtime.daemon import ControllerDaemon

    design = controller_design(config)  # before touching the bus: a bad config fails fast
    # The recorder's writer thread shares the GIL; switching sooner bounds how long it can
    # hold up the control loop's wake-up (measured: p99 lateness roughly halved).
    scheduling: dict[str, str] = {}
    if config.run.mode == "realtime":
        sys.setswitchinterval(REALTIME_SWITCH_INTERVAL_S)
        scheduling = apply_scheduling(config.controller.cpu, config.controller.realtime_priority)
    contract = FrameContract.load()
    resolved = json.dumps(config.model_dump(mode="json"), sort_keys=True)
    attachments = [
        (design_record.ATTACHMENT_NAME, design_record.MEDIA_TYPE,
         design_record.encode_design(design)),
        ("ballbeam.dbc", "text/plain", contract.dbc_text.encode()),
        ("config.resolved.json", "application/json", resolved.encode()),
    ]
    if config_path is not None:
        # The resolved config above is what the run used; the source file is a courtesy.
        with contextlib.suppress(OSError):
            attachments.append(("config.toml", "application/toml", Path(config_path).read_bytes()))
    recorder = Recorder(
        log_path,
        metadata={
            "config": {"json": resolved, "source": config_path or "(defaults)"},
            "versions": {**package_versions(), "git_revision": git_revision()},
            "run": {
                "mode": config.run.mode,
                "plan_kind": config.plan.kind,
                "plan_duration_s": repr(design.plan_duration_s),
                "period_ns": str(config.controller.period_ns),
                "sensor_period_ns": str(1_000_000_000 // config.plant.sensor_rate_hz),
                "bus": f"{config.bus.interface}:{config.bus.channel}",
                **{f"scheduling_{key}": value for key, value in scheduling.items()},
            },
        },
        attachments=attachments,
    )
    stop = StopFlag().install()
    summary: dict[str, str] = {}
    try:
        bus = open_bus(config.bus)
        try:
            daemon = ControllerDaemon(config, design, bus, contract, recorder, stop)
            settle_heap()
            try:
                stats = daemon.run()
            finally:
                summary = daemon.stats.as_metadata(daemon.sensor_check)
            log.info("daemon finished: %s", stats.end_reason)
        finally:
            bus.shutdown()
    finally:
        summary["recorder_dropped"] = str(recorder.dropped)
        recorder.close(summary=summary)
    return log_path


def run_emulator(config: Config) -> None:
    from ballbeam_emulator.node import PlantEmulator

    contract = FrameContract.load()
    stop = StopFlag().install()
    if config.run.mode == "realtime":  # lock-step has no deadlines to protect
        apply_scheduling(config.plant.cpu, config.plant.realtime_priority)
    bus = open_bus(config.bus)
    emulator = PlantEmulator(config, bus, contract)
    settle_heap()
    try:
        if config.run.mode == "lockstep":
            emulator.run_lockstep(stop)
        else:
            emulator.run_realtime(stop)
    finally:
        emulator.stop()
        bus.shutdown()
        log.info("emulator stopped: %s", emulator.counters)
