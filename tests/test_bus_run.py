"""Runs of the two processes over the ff11 udp_multicast bus (and SocketCAN where present)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from ballbeam.assembly import run_offline
from ballbeam.config import load_config
from ballbeam.evaluation.replay import verify
from ballbeam.logs import topics
from ballbeam.logs.reader import read_log

from .conftest import PAPER, ballbeam

pytestmark = pytest.mark.bus
SETTLE_TOLERANCE_S = 0.3


def run_json(config: Path, tmp_path: Path, *overrides: str) -> dict[str, object]:
    sets = [
        item
        for override in (f"run.log_dir='{tmp_path}'", *overrides)
        for item in ("--set", override)
    ]
    result = ballbeam("run", str(config), *sets, "--json")
    assert result.returncode == 0, result.stderr
    summary: dict[str, object] = json.loads(result.stdout)
    return summary


@pytest.fixture(scope="module")
def offline_settle_s() -> float:
    settle = run_offline(load_config(PAPER)).metrics.settle_time_s
    assert settle is not None
    return settle


def test_lockstep_run_matches_offline_and_records_every_channel(
    tmp_path: Path, offline_settle_s: float
) -> None:
    summary = run_json(PAPER, tmp_path)
    assert summary["mode"] == "lockstep"
    settle = summary["settle_time_s"]
    assert isinstance(settle, float)
    assert abs(settle - offline_settle_s) <= SETTLE_TOLERANCE_S
    assert summary["theta_violation_s"] == 0.0
    assert summary["end_reason"] == "completed"
    log_path = Path(str(summary["log_path"]))
    run_log = read_log(log_path)
    assert not run_log.truncated
    for topic in topics.STRUCT_TOPICS:
        assert len(run_log.topics[topic]) > 0, topic
    assert {"config", "versions", "run", "summary"} <= set(run_log.metadata)
    # T* as the daemon recorded it for the summary: the paper's start, on the 2 ms grid
    assert float(run_log.metadata["run"]["minimum_time_s"]) == pytest.approx(1.746, abs=1e-9)
    assert {"ballbeam.dbc", "config.resolved.json", "config.toml"} <= set(run_log.attachments)
    assert verify(run_log).ok
    # The independent reader: the mcap library opens it and sees the same message count.
    from mcap.reader import make_reader

    with log_path.open("rb") as stream:
        reader = make_reader(stream)
        assert sum(1 for _ in reader.iter_messages()) == run_log.message_count


def test_lockstep_is_deterministic(tmp_path: Path) -> None:
    commands = []
    for index in range(2):
        summary = run_json(PAPER, tmp_path / str(index), "run.duration_s=1.0")
        values = read_log(Path(str(summary["log_path"]))).topics["/command"].values
        commands.append(np.asarray(values["voltage_v"]))
    assert len(commands[0]) == 1000
    assert np.array_equal(commands[0], commands[1])


@pytest.mark.realtime
def test_realtime_run_at_1khz_settles_like_offline(tmp_path: Path, offline_settle_s: float) -> None:
    summary = run_json(PAPER, tmp_path, "run.mode='realtime'")
    assert summary["mode"] == "realtime"
    settle = summary["settle_time_s"]
    assert isinstance(settle, float)
    assert abs(settle - offline_settle_s) <= SETTLE_TOLERANCE_S
    assert summary["cycles"] == 5000 or summary["overruns"]
    assert verify(read_log(Path(str(summary["log_path"])))).ok


def test_a_bus_group_that_leaves_the_host_is_refused(tmp_path: Path) -> None:
    for group in ("ff15:7079:7468:6f6e:6465:6d6f:6d63:6173", "239.74.163.2"):
        result = ballbeam(
            "run", "--set", f"bus.channel='{group}'", "--set", f"run.log_dir='{tmp_path}'"
        )
        assert result.returncode == 2
        assert "leaves this host" in result.stderr
        assert "Traceback" not in result.stderr
    assert not list(tmp_path.glob("*.mcap"))


def test_lockstep_is_the_offline_run_sample_for_sample(tmp_path: Path) -> None:
    """The emulator drives each command as its frame carries it (1 mV steps) and the offline
    loop rounds it the same way, so the two processes over the bus produce the offline run's
    every sensor count and command (before: one encoder count apart after ~250 cycles)."""
    overrides = ("run.duration_s=1.5",)
    summary = run_json(PAPER, tmp_path, *overrides)
    run_log = read_log(Path(str(summary["log_path"])))
    offline = run_offline(load_config(PAPER, overrides)).trace
    sensor = run_log.topics["/sensor"].values
    assert np.array_equal(np.asarray(sensor["angle_counts"]), offline.angle_counts)
    assert np.array_equal(np.asarray(sensor["position_counts"]), offline.position_counts)
    sent = np.asarray(run_log.topics["/command"].values["voltage_v"])
    assert np.array_equal(np.round(sent / 1e-3) * 1e-3, offline.voltage_v)


def test_lockstep_tap_and_target_match_offline_and_replay(tmp_path: Path) -> None:
    """A run to a target of 0.05 m with a tap at 1.0 s: over the bus in lock-step the plant
    applies the tap as the offline simulation does, the log records it on /disturbances, and
    the replay re-runs the law bit for bit."""
    overrides = ("run.duration_s=1.5", "task.target_m=0.05", "plant.disturbances=[[1.0, 0.05]]")
    summary = run_json(PAPER, tmp_path, *overrides)
    run_log = read_log(Path(str(summary["log_path"])))
    assert verify(run_log).ok
    truth = run_log.topics["/truth"].values
    index = np.asarray(truth["sample_index"], dtype=int)
    velocity = np.asarray(truth["ball_velocity_m_s"])
    offline = run_offline(load_config(PAPER, overrides)).trace.true_states[:, 2]
    keep = index < len(offline)
    # The same run to the frames' resolution (1e-5 m/s) and the last bits of the emulator's
    # physics, which differ from the offline one's in this environment with or without a tap.
    np.testing.assert_allclose(velocity[keep], offline[index[keep]], atol=1e-4)
    # The tap: from sample 999 to 1000 the velocity steps by 0.05 m/s more than from 998 to
    # 999 (the ball's own acceleration changes by under 1e-5 m/s a period here).
    step = {int(i): float(v) for i, v in zip(index, velocity, strict=True)}
    jump = (step[1000] - step[999]) - (step[999] - step[998])
    assert jump == pytest.approx(0.05, abs=3e-5)
    assert (offline[1000] - offline[999]) - (offline[999] - offline[998]) == pytest.approx(
        jump, abs=3e-5
    )
    taps = run_log.json_topics["/disturbances"].messages
    assert [dict(tap) for tap in taps] == [
        {"cycle": 1000, "time_s": pytest.approx(1.0), "plant_step": 10_000,
         "ball_velocity_change_m_s": 0.05}
    ]
    # The reference is recorded in x: from the start to (by the run's end, near) the target.
    reference = run_log.topics["/reference"].values["ball_position_m"]
    assert reference[0] == pytest.approx(0.195) and abs(reference[-1] - 0.05) < 1e-3
