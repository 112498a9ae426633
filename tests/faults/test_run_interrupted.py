"""``ballbeam run`` stopped by a signal to the launcher alone (its nodes lead sessions of their
own, so the terminal's Ctrl-C reaches only the launcher): the stop is passed on, the daemon
commands 0 V and finishes its log, the run is summarised as stopped on request, and no node is
left behind."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from ballbeam.logs.reader import read_log

from ..conftest import PAPER, REPO, ballbeam_argv
from .harness import START_TIMEOUT_S, log_started, shutdown_frames, summary_meta

# On wall time: alone under pytest -n (tests/conftest.py).
pytestmark = pytest.mark.realtime


def children_of(pid: int) -> list[int]:
    children = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        children += [int(child) for child in (task / "children").read_text().split()]
    return children


def processes_naming(text: str) -> list[int]:
    """Processes whose command line contains ``text`` (this run's log directory)."""
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            if text.encode() in (entry / "cmdline").read_bytes():
                found.append(int(entry.name))
        except OSError:
            continue  # gone meanwhile
    return found


@pytest.mark.bus
@pytest.mark.parametrize(
    ("signum", "end_reason"),
    [(signal.SIGINT, "SIGINT"), (signal.SIGTERM, "SIGTERM"), (signal.SIGHUP, "SIGTERM")],
)
def test_a_stopped_run_stops_its_nodes_at_0v_and_is_summarised(
    tmp_path: Path, signum: signal.Signals, end_reason: str
) -> None:
    launcher = subprocess.Popen(
        ballbeam_argv("run", str(PAPER), "--set", "run.mode='realtime'",
                      "--set", "run.duration_s=60", "--set", f"run.log_dir='{tmp_path}'",
                      "--json"),
        cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    try:
        deadline = time.monotonic() + START_TIMEOUT_S
        while not log_started(tmp_path) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert log_started(tmp_path), "the daemon never began its log"
        time.sleep(1.5)  # well into the run
        nodes = children_of(launcher.pid)
        assert len(nodes) == 2
        assert all(os.getsid(node) == node for node in nodes)  # each leads its own session
        launcher.send_signal(signum)  # to the launcher alone, as a terminal now does
        stdout, stderr = launcher.communicate(timeout=60)
    finally:
        if launcher.poll() is None:
            launcher.kill()
            launcher.communicate()
    assert launcher.returncode == 0, stderr[-2000:]
    assert "Traceback" not in stderr
    summary = json.loads(stdout)
    assert summary["end_reason"] == end_reason
    log = read_log(summary["log_path"])
    assert not log.truncated, log.truncation_reason
    assert summary_meta(log)["end_reason"] == end_reason
    assert all(c.voltage_v == 0.0 and not c.enable for c in shutdown_frames(log))
    assert 1_000 < len(log.topics["/command"]) < 50_000  # it ran, and it stopped early
    assert processes_naming(str(tmp_path)) == []  # neither node outlived the launcher


@pytest.mark.bus
def test_a_killed_launcher_takes_its_nodes_with_it(tmp_path: Path) -> None:
    """SIGKILL to the launcher, which then passes nothing on: the kernel tells the daemon
    (its parent-death signal), which stops at 0 V and finishes its log; the emulator follows."""
    launcher = subprocess.Popen(
        ballbeam_argv("run", str(PAPER), "--set", "run.mode='realtime'",
                      "--set", "run.duration_s=60", "--set", f"run.log_dir='{tmp_path}'"),
        cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )
    deadline = time.monotonic() + START_TIMEOUT_S
    while not log_started(tmp_path) and time.monotonic() < deadline:
        time.sleep(0.1)
    time.sleep(1.5)
    launcher.kill()
    launcher.wait()
    gone_by = time.monotonic() + 30
    while processes_naming(str(tmp_path)) and time.monotonic() < gone_by:
        time.sleep(0.1)
    assert processes_naming(str(tmp_path)) == []
    (log_path,) = tmp_path.glob("*.mcap")
    log = read_log(log_path)
    assert not log.truncated, log.truncation_reason
    assert summary_meta(log)["end_reason"] == "SIGTERM"
    assert all(c.voltage_v == 0.0 and not c.enable for c in shutdown_frames(log))


def test_a_daemon_that_ignores_the_stop_is_killed_with_one_clear_error(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The launcher waits the grace for a stopped daemon, then kills it: one error that says
    so, not a traceback from the expired wait."""
    from ballbeam.runtime import launcher

    monkeypatch.setattr(launcher, "STOP_GRACE_S", 0.1)
    stubborn = subprocess.Popen(
        [sys.executable, "-c", "import signal, time\n"
         "signal.signal(signal.SIGTERM, signal.SIG_IGN)\nprint('ready', flush=True)\n"
         "time.sleep(60)"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    assert stubborn.stdout is not None and stubborn.stdout.readline() == "ready\n"
    with pytest.raises(launcher.RunFailedError, match="did not stop within 0 s of SIGTERM and "
                       "was killed; it had written no log yet"):
        launcher._stopped_daemon_errors(stubborn, signal.SIGTERM, tmp_path / "none.mcap")
    assert stubborn.returncode == -signal.SIGKILL
