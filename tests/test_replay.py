"""Replay of recorded runs: the golden log pins the log format, the analysis and the
controller (``--verify`` re-runs the recorded design through today's control law on the
recorded sensor frames)."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from ballbeam.errors import LogFormatError
from ballbeam.evaluation import replay
from ballbeam.evaluation.summary import summarise
from ballbeam.logs import design_record
from ballbeam.logs.reader import RunLog, read_log

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
    # The start is −52° (to the truth frame's 1e-5 rad); the guard never lets θ past it.
    assert summary["max_abs_theta_deg"] == pytest.approx(51.99993061268813, rel=1e-12)
    assert summary["tracking_rms_mm"] == pytest.approx(0.16968470932730556, rel=1e-9)
    assert summary["saturation_fraction"] == pytest.approx(0.038)
    assert summary["theta_violation_s"] == 0.0
    assert summary["frames_lost"] == 0 and summary["frames_rejected"] == 0


def _with_run_metadata(run_log: RunLog, **entries: str) -> RunLog:
    metadata = {**run_log.metadata, "run": {**run_log.metadata["run"], **entries}}
    return dataclasses.replace(run_log, metadata=metadata)


def test_the_summary_takes_the_recorded_minimum_time_and_computes_it_where_none_is() -> None:
    from ballbeam.evaluation.summary import minimum_time_from_log

    golden = read_log(GOLDEN)  # recorded before the daemon wrote T*: computed from its config
    assert "minimum_time_s" not in golden.metadata["run"]
    computed = minimum_time_from_log(golden)
    assert computed == pytest.approx(1.746, abs=1e-9)  # the paper's start, 2 ms grid
    assert minimum_time_from_log(_with_run_metadata(golden, minimum_time_s="1.25")) == 1.25
    assert minimum_time_from_log(_with_run_metadata(golden, minimum_time_s="none")) is None
    # a value that is not a time is not taken: computed again from the recorded config
    for bad in ("", "nan", "-1.0", "inf", "1.7.4"):
        assert minimum_time_from_log(_with_run_metadata(golden, minimum_time_s=bad)) == computed


def test_golden_log_verifies_bit_for_bit() -> None:
    result = replay.verify(read_log(GOLDEN))
    assert result.ok, result.mismatch
    assert result.cycles_checked == 1000
    assert result.design_source == "recorded"
    # Today's synthesis agrees with the recorded design to BLAS rounding (information only).
    assert isinstance(result.resynthesis_difference, float)
    assert result.resynthesis_difference < 1e-9


def with_design(run_log: RunLog, design_bytes: bytes | None) -> RunLog:
    attachments = dict(run_log.attachments)
    attachments.pop(design_record.ATTACHMENT_NAME)
    if design_bytes is not None:
        attachments[design_record.ATTACHMENT_NAME] = design_bytes
    return dataclasses.replace(run_log, attachments=attachments)


def test_verify_names_the_first_cycle_a_changed_design_gets_wrong() -> None:
    run_log = read_log(GOLDEN)
    recorded = design_record.decode_design(
        run_log.attachments[design_record.ATTACHMENT_NAME], "golden"
    )
    offsets = np.array(recorded.offset_v)
    offsets[500:] += 1e-3  # a different feedforward from cycle 500 on
    tampered = dataclasses.replace(recorded, offset_v=offsets)
    result = replay.verify(with_design(run_log, design_record.encode_design(tampered)))
    assert not result.ok
    assert result.mismatch is not None
    # Every cycle before the change replays; the first one after it whose voltage the clamp
    # or the guard does not hide is named.
    assert result.mismatch.cycle >= 500 and result.cycles_checked == result.mismatch.index + 1
    assert result.mismatch.recorded_v != result.mismatch.replayed_v


def test_a_log_without_a_recorded_design_is_verified_against_todays_synthesis() -> None:
    result = replay.verify(with_design(read_log(GOLDEN), None))
    assert result.design_source == "resynthesised"
    assert result.resynthesis_difference is None
    assert result.cycles_checked >= 1  # exact here only if this machine's BLAS rounds alike


@pytest.mark.parametrize(
    ("payload", "fragment"),
    [
        (b"not a zip archive", "unreadable"),
        (b"", "unreadable"),
    ],
)
def test_a_damaged_design_is_one_clear_error(payload: bytes, fragment: str) -> None:
    from ballbeam.errors import LogFormatError

    with pytest.raises(LogFormatError, match=fragment):
        replay.verify(with_design(read_log(GOLDEN), payload))


def test_replay_cli_json_and_verify() -> None:
    completed = ballbeam("replay", str(GOLDEN), "--verify", "--json")
    assert completed.returncode == 0, completed.stderr
    payload = json.loads(completed.stdout)
    assert payload["verify_ok"] is True and payload["verify_cycles"] == 1000
    assert payload["verify_design"] == "recorded"
    assert payload["resynthesis_max_rel_diff"] < 1e-9


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


def test_a_log_whose_config_todays_code_refuses_still_verifies_on_its_design() -> None:
    """A log from another version (here: a config key this version does not know) replays its
    recorded design; only the information about today's synthesis is unavailable."""
    run_log = read_log(GOLDEN)
    config = json.loads(run_log.metadata["config"]["json"])
    config["bus"]["a_key_from_another_version"] = True
    metadata = {**run_log.metadata, "config": {**run_log.metadata["config"],
                                               "json": json.dumps(config)}}
    result = replay.verify(dataclasses.replace(run_log, metadata=metadata))
    assert result.ok and result.cycles_checked == 1000
    assert isinstance(result.resynthesis_difference, str)
    assert "cannot re-synthesise" in result.resynthesis_difference


def with_config_json(run_log: RunLog, text: str) -> RunLog:
    metadata = {**run_log.metadata, "config": {**run_log.metadata["config"], "json": text}}
    return dataclasses.replace(run_log, metadata=metadata)


@pytest.mark.parametrize("value", ["NaN", "Infinity", "-Infinity", "1e999"])
def test_a_recorded_config_no_run_could_have_written_cannot_be_verified(
    value: str, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """A config with a NaN in it was written by no run (every config refuses NaN): the log is
    damaged or altered, and --verify says so and exits non-zero (before: 0, verified on the
    recorded design, as if the log were whole)."""
    from ballbeam import cli

    run_log = read_log(GOLDEN)
    text = run_log.metadata["config"]["json"].replace('"r": 0.01', f'"r": {value}', 1)
    assert text != run_log.metadata["config"]["json"]
    damaged = with_config_json(run_log, text)
    with pytest.raises(LogFormatError, match="recorded config is damaged"):
        replay.verify(damaged)
    monkeypatch.setattr(cli, "_read_log_or_fail", lambda _path: damaged)
    assert cli.main(["replay", str(GOLDEN)]) == 0  # the analysis alone still stands
    capsys.readouterr()
    assert cli.main(["replay", str(GOLDEN), "--verify"]) == 2
    error = capsys.readouterr().err
    assert error.count("\n") == 1 and "cannot verify" in error


def test_a_log_without_a_control_cycle_cannot_be_verified() -> None:
    run_log = read_log(GOLDEN)
    topics = {name: dataclasses.replace(topic, log_time_ns=topic.log_time_ns[:0],
                                        values=topic.values[:0])
              for name, topic in run_log.topics.items()}
    with pytest.raises(LogFormatError, match="nothing to verify"):
        replay.verify(dataclasses.replace(run_log, topics=topics))
