"""The controller daemon's process: plan, synthesise, open the recorder and the bus, run the
loop, finish the file."""

from __future__ import annotations

import contextlib
import json
import logging
import os
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, BinaryIO

from ballbeam.assembly import control_law, controller_design, minimum_time_s
from ballbeam.config import Config
from ballbeam.core.control import ControllerDesign
from ballbeam.core.replanning_law import ReplanningLaw
from ballbeam.errors import BallbeamError, BusError
from ballbeam.logs import design_record
from ballbeam.logs.recorder import Recorder
from ballbeam.logs.recording import RunRecording
from ballbeam.protocol.frames import FrameContract
from ballbeam.protocol.secoc import FrameAuthenticator, RunKey
from ballbeam.runtime.bus import (
    BUS_CHOICE_ENV,
    open_bus,
    resolve_auto,
    resolved_bus,
)
from ballbeam.runtime.daemon.loop import ControllerDaemon
from ballbeam.runtime.owner_lock import EMULATOR_SLOT, OwnerLock
from ballbeam.runtime.peer_link import run_over_fd
from ballbeam.runtime.planner import PlannerProcess
from ballbeam.runtime.process import (
    REALTIME_SWITCH_INTERVAL_S,
    apply_scheduling,
    git_revision,
    package_versions,
    settle_heap,
    stop_with_parent,
)
from ballbeam.runtime.stop import StopFlag
from ballbeam.runtime.ticker import leave_real_time, spin_ns_for_this_process, worst_lateness_ns

if TYPE_CHECKING:
    from ballbeam.runtime.live import LiveView

log = logging.getLogger("ballbeam")

# How long the daemon gives its planner process to start and warm up (imports, a first
# solve: seconds on a loaded machine) before the run; after it the run starts regardless.
PLANNER_READY_S = 20.0

NO_SECRET = (
    "bus.authenticate is on ({bus}) but the daemon has no run secret: `ballbeam run` hands "
    "one to both processes; alone, pass the same 32 bytes to both with --secret-fd N (e.g. "
    "--secret-fd 0 < secret.bin), or set bus.authenticate=false for the classic contract"
)


def with_measured_latency(config: Config) -> tuple[Config, dict[str, str]]:
    """The config with the lateness this process measures now (its scheduling, this machine's
    load) as the angle guard's starting lateness, and what was measured.

    The guard judges the servo's state a latency allowance ahead; a loop that runs late lets
    the previous command act that much longer, so a guard that assumed less brakes too late (at
    normal priority on a busy machine: 52.3° and more). In the run the guard keeps the worst
    lateness of the last 0.5–1 s as margin (core/guard.py, LatenessWatch); the probe's is the
    first it keeps, so the run's first swings are covered before the run has measured its
    own. Only as long, then: a run that kept the probe's worst for good (it did, up to
    2026-11) braked every later swing early too, and one stall while the emulator started
    (7 ms, under load) cost it the rest time (1.82–1.93 s, not 1.776 s). Where real-time
    scheduling was granted the probe finds well under the 1 ms allowance."""
    controller = config.controller
    if controller.lateness_probe_s <= 0:
        return config, {}
    worst_ns = worst_lateness_ns(
        controller.period_ns, controller.lateness_probe_s,
        spin_ns_for_this_process(controller.spin_us),
    )
    start_us = min(worst_ns // 1000, controller.max_guard_latency_us)
    probe = {"lateness_probe_max_us": str(worst_ns // 1000), "start_lateness_us": str(start_us)}
    if start_us > controller.theta_guard_latency_us:
        log.warning(
            "this process ran up to %.1f ms late before the run (the angle guard allows "
            "%.1f ms): the guard starts the run braking that much earlier, and keeps any "
            "lateness it measures for up to %.1f s",
            worst_ns / 1e6, controller.theta_guard_latency_us / 1e3,
            2 * controller.guard_lateness_hold_s,
        )
    config = config.model_copy(update={
        "controller": controller.model_copy(update={"start_lateness_us": start_us})
    })
    return config, probe


def run_daemon(
    config: Config,
    log_path: Path,
    config_path: str | None,
    *,
    live_port: int | None = None,
    secret: RunKey | bytes | None = None,
    log_stream: BinaryIO | None = None,
) -> str:
    """Plan, synthesise, open the recorder and the bus, run, finish the file. Returns how the
    run ended (``DaemonStats.end_reason``); PlantLostError if no plant answered at the start.
    ``secret``: the run's frame-authentication key (needed when ``bus.authenticated``).
    ``log_stream``: the file ``log_path`` names, created and open already (else the recorder
    creates it, a new file only).

    With ``live_port``, the run is also served live on ``ws://127.0.0.1:<live_port>``
    (``runtime/live.py``); LiveViewError, before anything else, if the port is taken."""
    live = None
    if live_port is not None:
        from ballbeam.runtime.live import LiveView

        live = LiveView(live_port)  # its port is checked now; it serves once channels exist
    try:
        return _run_recorded(config, log_path, config_path, live, secret, log_stream)
    finally:
        if live is not None:
            live.stop()


def _run_recorded(
    config: Config,
    log_path: Path,
    config_path: str | None,
    live: LiveView | None,
    secret: RunKey | bytes | None,
    log_stream: BinaryIO | None,
) -> str:
    tracker = config.controller.kind == "tracker"
    # Before touching the bus: a bad config fails fast.
    design = controller_design(config) if tracker else None
    # The re-planning law's planner, started before this process takes real-time scheduling
    # or a CPU (it must not compete with the loop); it ends with the pipe, however we end.
    planner = None if tracker else PlannerProcess()
    if planner is not None:
        ready = planner.wait_ready(PLANNER_READY_S)
        log.info("planner process %s %s", planner.pid,
                 "ready" if ready else f"not ready within {PLANNER_READY_S} s")
    try:
        return _run_with_planner(
            config, log_path, config_path, live, secret, log_stream, design, planner
        )
    finally:
        if planner is not None:
            planner.close()


def _first_plan(law: ReplanningLaw, planner: PlannerProcess) -> None:
    """The re-planning law's first plan (from the configured start) before the bus is open: the
    plant's first samples would wait unread meanwhile, and be refused as stale."""
    for request in law.take_requests():
        if not planner.send(request):
            return  # the daemon's loop finds the planner gone and says so
    give_up = time.monotonic() + PLANNER_READY_S
    while law.answer_due_cycle is not None and planner.alive and time.monotonic() < give_up:
        for answer, _ in planner.receive(0.1):
            law.offer(answer)


def _run_with_planner(
    config: Config,
    log_path: Path,
    config_path: str | None,
    live: LiveView | None,
    secret: RunKey | bytes | None,
    log_stream: BinaryIO | None,
    design: ControllerDesign | None,
    planner: PlannerProcess | None,
) -> str:
    tracker = design is not None
    # The bus the run goes on, named in its log: "auto" as the launcher resolved it (it says
    # why), or as this daemon does when started by hand.
    bus_choice = os.environ.get(BUS_CHOICE_ENV, "")
    if config.bus.interface == "auto":
        choice = resolve_auto(config.bus, claim=False)
        config = config.model_copy(update={"bus": resolved_bus(config.bus, choice)})
        bus_choice = f"auto: {choice.reason}"
    # The recorder's writer thread shares the GIL; switching sooner bounds how long it can
    # hold up the control loop's wake-up (measured: p99 lateness roughly halved).
    scheduling: dict[str, str] = {}
    if config.run.mode == "realtime":
        sys.setswitchinterval(REALTIME_SWITCH_INTERVAL_S)
        controller = config.controller
        scheduling = apply_scheduling(
            controller.cpu, controller.realtime_priority, controller.fair_slice_us
        )
        measured, probe = with_measured_latency(config)
        scheduling.update(probe)
        if measured != config:
            config = measured
            design = controller_design(config) if tracker else None  # as recorded
    contract = FrameContract.load()
    resolved = json.dumps(config.model_dump(mode="json"), sort_keys=True)
    # T* from this config, for the summary: whoever reads the log (`ballbeam run` at the
    # end, `replay`) then needs neither the planner nor its imports (it recomputes where a
    # log has none). A figure of the summary's only: no run fails for want of it.
    t_star: dict[str, str] = {}
    with contextlib.suppress(BallbeamError):
        value = minimum_time_s(config)
        t_star["minimum_time_s"] = "none" if value is None else repr(value)
    attachments = [
        ("ballbeam.dbc", "text/plain", contract.dbc_text.encode()),
        ("config.resolved.json", "application/json", resolved.encode()),
    ]
    if design is not None:
        # The tracker's design replays bit for bit (a re-planning law's plans go on /plans).
        attachments.insert(0, (design_record.ATTACHMENT_NAME, design_record.MEDIA_TYPE,
                               design_record.encode_design(design)))
    if config_path is not None:
        # The resolved config above is what the run used; the source file is a courtesy.
        with contextlib.suppress(OSError):
            attachments.append(("config.toml", "application/toml", Path(config_path).read_bytes()))
    recorder = Recorder(
        log_stream if log_stream is not None else log_path,
        name=log_path if log_stream is not None else None,
        writer_setup=leave_real_time,
        metadata={
            "config": {"json": resolved, "source": config_path or "(defaults)"},
            "versions": {**package_versions(), "git_revision": git_revision()},
            "run": {
                "mode": config.run.mode,
                "controller_kind": config.controller.kind,
                "plan_kind": config.plan.kind,
                **({"plan_duration_s": repr(design.plan_duration_s)} if design is not None
                   else {}),
                **t_star,
                "period_ns": str(config.controller.period_ns),
                "sensor_period_ns": str(1_000_000_000 // config.plant.sensor_rate_hz),
                "bus": f"{config.bus.interface}:{config.bus.channel}",
                "authenticated": str(config.bus.authenticated).lower(),
                **({"bus_choice": bus_choice} if bus_choice else {}),
                **{f"scheduling_{key}": value for key, value in scheduling.items()},
            },
        },
        attachments=attachments,
        tap=live,
    )
    stop = StopFlag().install()
    summary: dict[str, str] = {}
    try:
        # After the log is open (an unwritable log is the first thing to hear about), before
        # the bus: no frame goes out unauthenticated.
        auth = None
        if config.bus.authenticated:
            if secret is None:
                raise BusError(NO_SECRET.format(bus=config.bus.interface))
            auth = FrameAuthenticator(secret)
        link_fd = run_over_fd()  # `ballbeam run`'s peer link: the run's end is told through it
        if link_fd is not None:
            stop_with_parent()  # in a session of its own, no terminal signal reaches it
        peer_lock = OwnerLock.from_environment()  # held till death: the emulator hears of it
        if peer_lock is not None:
            peer_lock.hold()
        emulator_lock = OwnerLock.from_environment(slot=EMULATOR_SLOT)  # the emulator's, held
        # Every channel of the log, the live view's too.
        recording = RunRecording(recorder, plans=not tracker)
        if live is not None:
            live.start()
            log.info("live view on %s (Foxglove: Open connection, Foxglove WebSocket)", live.url)
        law = control_law(config, design, plans_in_process=False)
        if isinstance(law, ReplanningLaw) and planner is not None:
            _first_plan(law, planner)
        bus = open_bus(config.bus)
        try:
            daemon = ControllerDaemon(config, law, bus, contract, recording, stop, auth,
                                      run_over_fd=link_fd, emulator_lock=emulator_lock,
                                      planner=planner)
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
    return stats.end_reason
