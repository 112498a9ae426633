"""SIGTERM at a random moment: the daemon stops cleanly at 0 V and finishes its file."""

from __future__ import annotations

import random
import signal
import time
from pathlib import Path

import pytest

from ballbeam.evaluation.replay import verify
from ballbeam.evaluation.summary import summarise
from ballbeam.logs.reader import read_log

from .harness import Bench, emulator_counters, events, shutdown_frames, summary_meta

# On wall time: alone under pytest -n (tests/conftest.py).
pytestmark = pytest.mark.realtime


@pytest.mark.bus
@pytest.mark.parametrize("index", range(5))
def test_sigterm_at_a_random_moment_stops_cleanly_at_0v(tmp_path: Path, index: int) -> None:
    rng = random.Random(500 + index)
    mode = "realtime" if index < 3 else "lockstep"
    duration_s = 2.0 if mode == "realtime" else 30.0
    with Bench(tmp_path, mode, duration_s) as bench:
        bench.wait_cycling()
        time.sleep(rng.uniform(0.1, 1.8))
        bench.daemon.send_signal(signal.SIGTERM)
        daemon_exit = bench.wait_daemon(30)
        daemon_stderr = bench.stderr(bench.daemon)
        assert bench.stop_emulator() == 0
        counters = emulator_counters(bench.stderr(bench.emulator))
        applied = counters["commands_applied"]
    assert daemon_exit == 0, daemon_stderr[-2000:]
    assert "Traceback" not in daemon_stderr
    log = read_log(bench.log_path)
    assert not log.truncated, log.truncation_reason
    assert summary_meta(log)["end_reason"] == "SIGTERM"
    assert "reason=SIGTERM" in events(log, "daemon_stop")[0]["detail"]
    stops = shutdown_frames(log)
    assert len(stops) == 3 and all(c.voltage_v == 0.0 and not c.enable for c in stops)
    assert len(log.topics["/command"]) < round(duration_s * 1000)
    # The plant obeyed every command, the stop included (lock-step too, where the stop
    # answers no particular sample).
    assert applied == len(log.topics["/command"]) + len(stops), counters
    assert verify(log).ok
    assert summarise(log)["truncated"] is False
