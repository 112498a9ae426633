"""The emulator's own counters in the run's log (issue 13, item 6): PlantStatus frames, whole
snapshots recorded to /plant_status from authenticated frames only, the final one after the
daemon says the run is over, and replay's report of them (absent from older logs)."""

from __future__ import annotations

import dataclasses
import json
import os
import secrets
import threading
from pathlib import Path

import can
import pytest

from ballbeam.config import Config, load_config
from ballbeam.evaluation.summary import plant_counters, summarise
from ballbeam.logs.reader import read_log
from ballbeam.logs.recorder import Recorder
from ballbeam.logs.recording import RunRecording
from ballbeam.logs.topics import PlantStatusRecord
from ballbeam.protocol.frames import (
    PLANT_STATUS_FIELDS,
    PLANT_STATUS_ID,
    FrameContract,
    next_counter,
)
from ballbeam.protocol.secoc import FrameAuthenticator
from ballbeam.runtime.daemon.intake import SensorIntake
from ballbeam.runtime.daemon.node import run_daemon
from ballbeam.runtime.peer_link import PEER_LINK_WRITE_ENV, PeerLink, peer_link_pipe
from ballbeam.runtime.stop import StopFlag
from ballbeam_emulator.node import EmulatorCounters, PlantEmulator

from .conftest import PAPER, ballbeam

CONTRACT = FrameContract.load()
GOLDEN = Path(__file__).resolve().parent / "data" / "golden_paper_1s.mcap"


def virtual_config(duration_s: float, *extra: str) -> Config:
    channel = f"ballbeam-test-{secrets.token_hex(4)}"  # a bus of its own
    return load_config(None, [
        "bus.interface='virtual'", f"bus.channel='{channel}'", f"run.duration_s={duration_s}",
        *extra,
    ])


def snapshot(values: list[int], first_counter: int = 0, final: bool = False) -> list[bytes]:
    """One snapshot's classic payloads, field 0 to 12 with consecutive counters."""
    payloads, counter = [], first_counter
    for field, value in enumerate(values):
        payloads.append(CONTRACT.encode_plant_status(counter, field, final, value))
        counter = next_counter(counter)
    return payloads


def classic(data: bytes) -> can.Message:
    return can.Message(arbitration_id=PLANT_STATUS_ID, data=data, is_extended_id=False)


def test_the_status_fields_are_the_emulators_counters_and_the_records_fields() -> None:
    assert tuple(f.name for f in dataclasses.fields(EmulatorCounters)) == PLANT_STATUS_FIELDS
    assert PlantStatusRecord._fields == ("final", *PLANT_STATUS_FIELDS)


def test_only_whole_snapshots_are_recorded(tmp_path: Path) -> None:
    path = tmp_path / "status.mcap"
    recorder = Recorder(path, metadata={})
    intake = SensorIntake(CONTRACT, RunRecording(recorder))
    first = list(range(100, 113))
    for data in snapshot(first):
        intake.handle(classic(data), 1_000, 0)
    broken = snapshot(list(range(200, 213)), first_counter=13)
    del broken[5]  # one frame lost on the bus: the snapshot is not recorded
    for data in broken:
        intake.handle(classic(data), 2_000, 0)
    shuffled = snapshot(list(range(300, 313)), first_counter=26)
    shuffled[3], shuffled[4] = shuffled[4], shuffled[3]
    for data in shuffled:
        intake.handle(classic(data), 3_000, 0)
    last = list(range(400, 413))
    for data in snapshot(last, first_counter=250, final=True):  # the counter wraps inside
        intake.handle(classic(data), 4_000, 0)
    recorder.close()
    assert intake.plant_status.snapshots == 2 and intake.plant_status.incomplete == 2
    assert intake.final_status_seen
    status = read_log(path).topics["/plant_status"]
    assert list(status.log_time_ns) == [1_000, 4_000]
    assert list(status.values["final"]) == [0, 1]
    assert [int(status.values[name][1]) for name in PLANT_STATUS_FIELDS] == last


def test_forged_and_replayed_status_frames_are_refused_and_never_recorded(tmp_path: Path) -> None:
    """On an authenticated bus a whole snapshot under another key, a well-formed classic one
    (no MAC) and a replay of the plant's own are each refused by reason; the plant's next
    snapshot is recorded as sent."""
    path = tmp_path / "forged.mcap"
    recorder = Recorder(path, metadata={})
    secret = secrets.token_bytes(32)
    plant, forger = FrameAuthenticator(secret), FrameAuthenticator(secrets.token_bytes(32))
    intake = SensorIntake(CONTRACT, RunRecording(recorder), auth=FrameAuthenticator(secret))

    def fd(data: bytes, key: FrameAuthenticator) -> can.Message:
        return can.Message(arbitration_id=PLANT_STATUS_ID, data=key.protect(PLANT_STATUS_ID, data),
                           is_extended_id=False, is_fd=True)

    genuine = [fd(data, plant) for data in snapshot(list(range(13)))]
    for message in genuine:
        intake.handle(message, 1_000, 0)
    ceiling = [2**32 - 1] * 13
    for data in snapshot(ceiling, first_counter=13, final=True):
        intake.handle(fd(data, forger), 2_000, 0)  # bad MAC
        intake.handle(classic(data), 2_000, 0)  # no MAC
    for message in genuine:
        intake.handle(message, 3_000, 0)  # replayed
    plants = list(range(20, 33))
    for data in snapshot(plants, first_counter=13, final=True):
        intake.handle(fd(data, plant), 4_000, 0)
    recorder.close()
    assert dict(intake.rejected) == {"bad_mac": 13, "unauthenticated": 13, "replayed": 13}
    status = read_log(path).topics["/plant_status"]
    assert list(status.log_time_ns) == [1_000, 4_000]
    assert [int(status.values[name][1]) for name in PLANT_STATUS_FIELDS] == plants


def test_in_process_the_log_ends_with_the_emulators_own_final_counters(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The daemon tells the emulator through the peer link that the run is over; the emulator
    stops and sends its counters marked final while the daemon still listens: the log's last
    snapshot is the emulator's counters, exactly, and the periodic ones come every 100 ms."""
    config = virtual_config(1.0)
    secret = secrets.token_bytes(32)
    read_fd, write_fd = peer_link_pipe()
    plant_bus = can.Bus(interface="virtual", channel=config.bus.channel)
    emulator = PlantEmulator(config, plant_bus, CONTRACT, PeerLink(read_fd),
                             FrameAuthenticator(secret))
    stop_plant = StopFlag()

    def plant_process() -> None:  # what the emulator's main does around its loop
        emulator.run_lockstep(stop_plant)
        emulator.stop()
        emulator.send_final_status()

    plant = threading.Thread(target=plant_process, daemon=True)
    plant.start()
    monkeypatch.setenv(PEER_LINK_WRITE_ENV, str(write_fd))
    log_path = tmp_path / "run.mcap"
    try:
        assert run_daemon(config, log_path, None, secret=secret) == "completed"
        plant.join(timeout=10)
        assert not plant.is_alive(), "the emulator did not stop when the run was over"
        assert stop_plant.signal_name == "run_over"
    finally:
        stop_plant.set()
        plant.join(timeout=10)
        plant_bus.shutdown()
        os.close(write_fd)
        os.close(read_fd)
    run_log = read_log(log_path)
    status, counters = plant_counters(run_log)
    assert status == "final"
    assert counters == dataclasses.asdict(emulator.counters)
    # The run's commands and the 3 stop frames (a lock-step resend's duplicate is stale).
    assert counters["commands_applied"] == 1000 + 3
    periodic = run_log.topics["/plant_status"].values["final"] == 0
    assert 8 <= int(periodic.sum()) <= 11  # 1 s of plant time: one at 0 s, then every 100 ms
    assert summarise(run_log)["plant_counters"] == counters


def test_replay_of_a_log_recorded_before_the_topic_reports_the_counters_absent() -> None:
    assert "/plant_status" not in read_log(GOLDEN).topics
    result = ballbeam("replay", str(GOLDEN), "--json")
    assert result.returncode == 0, result.stderr
    summary = json.loads(result.stdout)
    assert summary["plant_status"].startswith("absent")
    assert summary["plant_counters"] is None
    table = ballbeam("replay", str(GOLDEN))
    assert table.returncode == 0 and "plant_status" in table.stdout


def test_an_emulator_stopping_by_itself_is_waited_for_not_terminated() -> None:
    """The launcher's stop of an emulator the run's end already stopped: a SIGTERM that meets a
    Python process on its way out (its handlers gone) kills it (exit −15, as CI once saw); the
    launcher waits for it first."""
    import signal
    import subprocess
    import sys

    from ballbeam.runtime.launcher import _stop

    exiting = "import time; time.sleep(0.3)"  # no handler: SIGTERM's default kills it
    process = subprocess.Popen([sys.executable, "-c", exiting], text=True)
    assert _stop(process, own_exit_s=30.0) == 0
    process = subprocess.Popen([sys.executable, "-c", exiting], text=True)
    assert _stop(process) == -signal.SIGTERM


@pytest.mark.bus
def test_a_lockstep_run_logs_the_counters_the_emulator_reports_and_replay_agrees(
    tmp_path: Path,
) -> None:
    """Two processes (``ballbeam run``'s launcher): the emulator's own report on stderr (an
    independent source: its last words, not the bus) equals the log's final snapshot; the run's
    summary and ``ballbeam replay`` report the same counters."""
    from ballbeam.runtime.launcher import launch_run

    from .faults.harness import emulator_counters

    result = launch_run(str(PAPER), [f"run.log_dir='{tmp_path}'", "run.duration_s=1.0"])
    assert result.daemon_exit == 0 and result.emulator_exit == 0
    assert result.config.bus.authenticated
    reported = emulator_counters(result.emulator_stderr)
    assert set(reported) == set(PLANT_STATUS_FIELDS)
    run_summary = summarise(read_log(result.log_path))
    assert run_summary["plant_status"] == "final"
    assert run_summary["plant_counters"] == reported
    assert reported["commands_applied"] >= 1000 and reported["peer_lost"] == 0
    replayed = ballbeam("replay", str(result.log_path), "--json")
    assert replayed.returncode == 0, replayed.stderr
    summary = json.loads(replayed.stdout)
    assert (summary["plant_status"], summary["plant_counters"]) == ("final", reported)
