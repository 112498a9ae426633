"""The re-planning law's planner off the cycle (runtime/planner.py, the daemon's side in
runtime/daemon/loop.py): answers equal to the in-process solve, faults that leave the run
going, a planner that never outlives its daemon, and a real-time run."""

from __future__ import annotations

import contextlib
import dataclasses
import math
import os
import secrets
import signal
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

from ballbeam.config import load_config
from ballbeam.core.replanning import (
    DesignAnswer,
    DesignRequest,
    PlanAnswer,
    PlanRequest,
    Settings,
    solve_plan_request,
)
from ballbeam.evaluation import replay
from ballbeam.logs.plan_record import recorded_plans
from ballbeam.logs.reader import read_log
from ballbeam.runtime.daemon import node
from ballbeam.runtime.planner import PlannerProcess

from .conftest import PAPER, REPO, ballbeam_argv
from .test_daemon import run_in_process

REPLANNING = ("controller.kind='replanning'",)
REST_BAND_M = 5e-4
REST_BAND_RAD = math.radians(0.5)


def _paper_request() -> PlanRequest:
    s = Settings()
    return PlanRequest(
        7, "cold", (math.radians(-51.7), 0.0, 0.0, 0.195), 0.0, s.prior_pole_per_s,
        s.prior_alpha, s.prior_gamma, 4.2, s.theta_limit_rad - s.plan_theta_margin_rad,
    )


def test_the_planner_process_answers_with_the_very_plan_of_an_in_process_solve() -> None:
    planner = PlannerProcess()
    try:
        assert planner.wait_ready(120.0)
        request = _paper_request()
        assert planner.send(request)
        answers = planner.receive(120.0)
        assert len(answers) == 1
        answer, wait_ns = answers[0]
        assert answer == solve_plan_request(request)  # every float to the bit
        assert answer.plan is not None and answer.request_cycle == 7 and wait_ns > 0
        # a request it cannot solve is an answer of none with the failure, not a dead planner
        bad = dataclasses.replace(request, state=(math.nan, 0.0, 0.0, 0.1))
        assert planner.send(bad)
        (failed, _), = planner.receive(120.0)
        assert failed.plan is None and failed.error is not None and planner.alive
    finally:
        planner.close()
    assert not planner.process.is_alive()


def _pid_alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat", encoding="ascii") as stat:
            return stat.read().split(") ")[1].split()[0] != "Z"
    except FileNotFoundError:
        return False


def _children(pid: int) -> list[int]:
    found = []
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                fields = (entry / "stat").read_text().split(") ")[1].split()
            except (FileNotFoundError, ProcessLookupError, IndexError):
                continue
            if int(fields[1]) == pid:
                found.append(int(entry.name))
    return found


def _cmdline(pid: int) -> str:
    try:
        return (Path("/proc") / str(pid) / "cmdline").read_bytes().replace(b"\0", b" ").decode()
    except (FileNotFoundError, ProcessLookupError):
        return ""


@pytest.mark.bus
def test_a_daemon_killed_with_sigkill_leaves_no_planner_behind(tmp_path: Path) -> None:
    """``ballbeam run`` (lock-step): the daemon's planner process is found, the daemon killed
    with SIGKILL (no clean-up of its own) while the launcher is stopped, and the planner is
    gone within seconds; then the launcher is killed too, and no process of the run outlives
    it (the emulator, in a session of its own, stops once the daemon and the launcher are
    both gone)."""
    launcher = subprocess.Popen(
        ballbeam_argv("run", str(PAPER), "--set", f"run.log_dir='{tmp_path}'",
                      "--set", "controller.kind='replanning'", "--set", "run.duration_s=60.0"),
        cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True,
    )
    try:
        daemon = planner = None
        give_up = time.monotonic() + 120.0
        while planner is None and time.monotonic() < give_up:
            time.sleep(0.2)
            for child in _children(launcher.pid):
                spawned = [p for p in _children(child) if "spawn_main" in _cmdline(p)]
                if spawned:
                    daemon, planner = child, spawned[0]
        assert daemon is not None and planner is not None, "no planner process found"
        # The launcher is held still, so that it cannot stop the emulator itself when the
        # daemon dies: as when both are killed at once.
        os.kill(launcher.pid, signal.SIGSTOP)
        os.kill(daemon, signal.SIGKILL)
        gone_by = time.monotonic() + 5.0
        while _pid_alive(planner) and time.monotonic() < gone_by:
            time.sleep(0.05)
        assert not _pid_alive(planner), "the planner outlived its daemon"
        others = _children(launcher.pid)
        assert others, "no emulator found"
    finally:
        os.killpg(launcher.pid, signal.SIGKILL)
        launcher.wait(timeout=30)
    gone_by = time.monotonic() + 10.0
    while any(map(_pid_alive, others)) and time.monotonic() < gone_by:
        time.sleep(0.05)
    left = [f"{pid}: {_cmdline(pid)[:120]}" for pid in others if _pid_alive(pid)]
    for pid in others:  # the test leaves nothing behind either way
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signal.SIGKILL)
    assert not left, f"outlived the launcher: {left}"


class _FailingPlanner(PlannerProcess):
    """The daemon's planner, failing from its ``after``-th request: with ``crash``, it dies
    (killed); else it is sent requests it cannot solve (its answer: no plan, an error)."""

    def __init__(self, after: int, crash: bool) -> None:
        super().__init__()
        self.after, self.crash, self.count = after, crash, 0

    def send(self, request: object) -> bool:
        self.count += 1
        if self.count >= self.after and isinstance(request, PlanRequest):
            if self.crash and self.process.is_alive():
                self.process.kill()
                self.process.join(10.0)
            request = dataclasses.replace(request, state=(math.nan, 0.0, 0.0, 0.1))
        return super().send(request)  # type: ignore[arg-type]


class _SlowPlanner(PlannerProcess):
    """The daemon's planner, whose answer to the ``which``-th request it is sent reaches the
    daemon only ``delay_s`` after it was sent (a solve that slow: a loaded machine)."""

    def __init__(self, which: int, delay_s: float) -> None:
        super().__init__()
        self.which, self.delay_s, self.count = which, delay_s, 0
        self.held_until = 0.0

    def send(self, request: PlanRequest | DesignRequest) -> bool:
        self.count += 1
        if self.count == self.which:
            self.held_until = time.monotonic() + self.delay_s
        return super().send(request)

    def receive(
        self, timeout_s: float | None = 0.0
    ) -> list[tuple[PlanAnswer | DesignAnswer, int]]:
        if time.monotonic() < self.held_until:
            time.sleep(min(timeout_s or 0.0, self.held_until - time.monotonic()))
            return []
        return super().receive(timeout_s)


def test_lockstep_waiting_longer_than_the_freshness_window_refuses_no_frame(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A plan that takes longer than the frames' freshness window (1 s): lock-step waits for
    it, and the frames the plant sends meanwhile (its resends) are judged while fresh, not
    refused as stale when the wait ends; the run equals the offline one command for
    command."""
    monkeypatch.setattr(node, "PlannerProcess", lambda: _SlowPlanner(8, 1.5))
    config = load_config(PAPER, (
        *REPLANNING, "bus.interface='virtual'", f"bus.channel='bb-{secrets.token_hex(4)}'",
        "run.duration_s=0.3",
    ))
    log_path = tmp_path / "run.mcap"
    started = time.monotonic()
    assert run_in_process(config, log_path) == "completed"
    assert time.monotonic() - started > 1.5  # the wait happened
    run_log = read_log(log_path)
    faults = [m["kind"] for m in run_log.json_topics["/faults"].messages]
    assert faults == [], faults
    assert replay.verify(run_log).ok


@pytest.mark.parametrize(("crash", "fault"), [(False, "planner_error"), (True, "planner_lost")])
def test_a_planner_that_fails_or_dies_leaves_the_law_on_its_plan_and_the_run_going(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, crash: bool, fault: str
) -> None:
    after = 6  # the first plans (before the run, and the first re-plans) come through
    monkeypatch.setattr(node, "PlannerProcess", lambda: _FailingPlanner(after, crash))
    config = load_config(PAPER, (
        *REPLANNING, "bus.interface='virtual'", f"bus.channel='bb-{secrets.token_hex(4)}'",
        "run.duration_s=0.6",
    ))
    log_path = tmp_path / "run.mcap"
    assert run_in_process(config, log_path) == "completed"
    run_log = read_log(log_path)
    assert len(run_log.topics["/command"].values["voltage_v"]) >= 600  # every cycle ran
    faults = [m["kind"] for m in run_log.json_topics["/faults"].messages]
    assert faults == [fault]  # once, not a flood
    taken = sorted(recorded_plans(run_log).values(), key=lambda t: (t.cycle, t.design))
    plans = [t for t in taken if t.plan is not None]
    nones = [t for t in taken if t.plan is None and not t.design]
    assert plans and nones and max(t.cycle for t in plans) < min(t.cycle for t in nones)
    # the law tracked its last plan on: its feedforward goes on after the failures
    reference_input = np.asarray(run_log.topics["/reference"].values["input_v"])
    assert np.count_nonzero(reference_input[min(t.cycle for t in nones):]) > 100
    assert replay.verify(run_log).ok
