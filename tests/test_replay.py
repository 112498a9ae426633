"""Replay of recorded runs: the golden log pins the log format, the analysis and the
controller (``--verify`` re-runs today's controller on its recorded sensor frames)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from ballbeam import replay
from ballbeam.analysis import summarise
from ballbeam.logs.reader import read_log

GOLDEN = Path(__file__).parent / "data" / "golden_paper_1s.mcap"


def ballbeam(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "ballbeam", *args],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )


def test_golden_log_metrics_are_pinned() -> None:
    summary = summarise(read_log(GOLDEN))
    assert summary["cycles"] == 1000
    assert summary["truncated"] is False
    assert summary["end_reason"] == "completed"
    assert summary["settle_time_s"] is None  # one second is too short to settle
    assert summary["max_abs_theta_deg"] == pytest.approx(51.985033710014726, rel=1e-12)
    assert summary["tracking_rms_mm"] == pytest.approx(0.46372882504381646, rel=1e-9)
    assert summary["saturation_fraction"] == pytest.approx(0.053)
    assert summary["theta_violation_s"] == 0.0
    assert summary["frames_lost"] == 0 and summary["frames_rejected"] == 0


def test_golden_log_verifies_bit_for_bit() -> None:
    result = replay.verify(read_log(GOLDEN))
    assert result.ok, result.mismatch
    assert result.cycles_checked == 1000


def test_verify_names_the_first_cycle_a_changed_controller_gets_wrong(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    original = replay.controller_design

    def detuned(config):  # type: ignore[no-untyped-def]
        tracker = config.tracker.model_copy(update={"r": config.tracker.r * 1.001})
        return original(config.model_copy(update={"tracker": tracker}))

    monkeypatch.setattr(replay, "controller_design", detuned)
    result = replay.verify(read_log(GOLDEN))
    assert not result.ok
    assert result.mismatch is not None
    assert result.mismatch.recorded_v != result.mismatch.replayed_v


def test_replay_cli_json_and_verify() -> None:
    completed = ballbeam("replay", str(GOLDEN), "--verify", "--json")
    assert completed.returncode == 0, completed.stderr
    payload = json.loads(completed.stdout)
    assert payload["verify_ok"] is True and payload["verify_cycles"] == 1000


def test_a_truncated_log_is_read_as_far_as_it_is_intact(tmp_path: Path) -> None:
    cut = tmp_path / "cut.mcap"
    data = GOLDEN.read_bytes()
    cut.write_bytes(data[: int(len(data) * 0.6)])
    completed = ballbeam("replay", str(cut), "--verify")
    assert completed.returncode == 0, completed.stderr
    assert "cut short" in completed.stdout
    run_log = read_log(cut)
    assert run_log.truncated
    assert 0 < len(run_log.topics["/command"]) < 1000
    assert replay.verify(run_log).ok  # what is left still explains itself


@pytest.mark.parametrize(
    ("content", "fragment"),
    [(b"", "not an MCAP"), (b"hello world, not a log" * 10, "not an MCAP")],
)
def test_not_a_log_is_one_clear_error(tmp_path: Path, content: bytes, fragment: str) -> None:
    path = tmp_path / "bad.mcap"
    path.write_bytes(content)
    completed = ballbeam("replay", str(path))
    assert completed.returncode == 2
    assert fragment in completed.stderr
    assert "Traceback" not in completed.stderr


def test_missing_log_is_one_clear_error(tmp_path: Path) -> None:
    completed = ballbeam("replay", str(tmp_path / "absent.mcap"))
    assert completed.returncode == 2
    assert completed.stderr.count("\n") == 1 and "cannot open log" in completed.stderr
