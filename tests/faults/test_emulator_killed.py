"""The emulator dies: the daemon faults to 0 V, stops, and finishes its file."""

from __future__ import annotations

import random
import signal
import time
from pathlib import Path

import pytest

from ballbeam.evaluation.replay import verify
from ballbeam.logs.reader import RunLog, read_log
from ballbeam.runtime.exit_codes import EXIT_PLANT_LOST

from ..conftest import ballbeam
from .harness import (
    DEFAULTS,
    PERIOD_NS,
    START_TIMEOUT_S,
    TIMEOUT_PERIODS,
    Bench,
    events,
    faults,
    figure,
    shutdown_frames,
    summary_meta,
)

# On wall time: alone under pytest -n (tests/conftest.py).
pytestmark = pytest.mark.realtime


def kill_emulator_then_daemon_lost(bench: Bench, after_s: float) -> None:
    """Once the loop cycles, wait ``after_s``, SIGKILL the emulator; the daemon must then end
    the run itself, with the plant-lost exit code."""
    bench.wait_cycling()
    time.sleep(after_s)
    bench.emulator.kill()
    bench.emulator.wait()
    daemon_exit = bench.wait_daemon(START_TIMEOUT_S)
    assert daemon_exit == EXIT_PLANT_LOST, bench.stderr(bench.daemon)[-2000:]


def _last_sample_cycle(log: RunLog, before_cycle: int) -> int:
    """The last cycle before ``before_cycle`` that took a sample, on time or late: a late
    sample (``fresh`` 1 + n, read n cycles behind the stream on a loaded host) shows the plant
    alive as much as one of its own period, and restarts the timeout the same."""
    sensor = log.topics["/sensor"].values
    mask = (sensor["fresh"] >= 1) & (sensor["cycle"] < before_cycle)
    return int(sensor["cycle"][mask].max())


@pytest.mark.bus
@pytest.mark.parametrize("stall_daemon", [False, True], ids=["plain", "daemon-stalled"])
def test_emulator_killed_realtime_daemon_faults_to_0v_and_finishes_its_file(
    tmp_path: Path, stall_daemon: bool
) -> None:
    """SIGKILL the plant. The daemon must fault at its first cycle that is at least
    ``sensor_timeout_periods`` periods after the last fresh sample (3 cycles when it runs on
    time), command 0 V disabled from then on, end the run after ``plant_lost_s`` and close a
    complete file. "daemon-stalled" also freezes the daemon (SIGSTOP) twice: 20 ms just after
    the kill (when that lands inside the first 3 periods, the detection straddles an overrun)
    and 50 ms a tenth of a second later (always inside the silence): skipped periods are
    silent periods too, for the fault and for ``plant_lost_s``."""
    rng = random.Random(31 + stall_daemon)
    with Bench(tmp_path, "realtime", 4.0) as bench:
        bench.wait_cycling()
        time.sleep(rng.uniform(0.4, 1.0))
        bench.emulator.kill()
        if stall_daemon:
            for pause_s, stall_s in ((0.0003, 0.02), (0.1, 0.05)):
                time.sleep(pause_s)
                bench.daemon.send_signal(signal.SIGSTOP)
                time.sleep(stall_s)
                bench.daemon.send_signal(signal.SIGCONT)
        bench.emulator.wait()
        daemon_exit = bench.wait_daemon(START_TIMEOUT_S)
        daemon_stderr = bench.stderr(bench.daemon)
    # plant_lost ends the run in order (0 V, the file finished) and says so: exit 3.
    assert daemon_exit == EXIT_PLANT_LOST, daemon_stderr[-2000:]
    log = read_log(bench.log_path)
    assert not log.truncated, log.truncation_reason
    assert summary_meta(log)["end_reason"] == "plant_lost"
    # The last timeout is the kill's (a scheduling hiccup may have caused a brief earlier one).
    fault_cycle = int(faults(log, "sensor_timeout")[-1]["cycle"])
    last_sample = _last_sample_cycle(log, fault_cycle)
    executed = log.topics["/timing"].values["cycle"]

    def first_executed(at_least: int) -> int:
        return int(executed[executed >= at_least][0])

    # The fault came at the first executed cycle at least TIMEOUT_PERIODS after the last sample.
    assert fault_cycle == first_executed(last_sample + TIMEOUT_PERIODS), (
        last_sample,
        fault_cycle,
        executed[-20:],
    )
    if not stall_daemon:
        assert fault_cycle - last_sample <= TIMEOUT_PERIODS
    else:  # the second stall did happen, inside the silence
        skipped = log.topics["/timing"].values["skipped"]
        assert (skipped[executed > fault_cycle] >= 20).any(), skipped[executed > fault_cycle]
    # 0 V, disabled, in every command from the fault on, then the stop frames.
    command = log.topics["/command"].values
    after = command["cycle"] >= fault_cycle
    assert after.sum() > 0
    assert (command["enable"][after] == 0).all()
    assert (command["voltage_v"][after] == 0.0).all()
    assert (command["requested_v"][after] == 0.0).all()
    stops = shutdown_frames(log)
    assert len(stops) == 3 and all(c.voltage_v == 0.0 and not c.enable for c in stops)
    # Then the plant is declared lost after plant_lost_s of silence and the run ends.
    lost = faults(log, "plant_lost")
    assert len(lost) == 1
    lost_after_periods = int(lost[0]["cycle"]) - last_sample
    plant_lost_periods = round(DEFAULTS.controller.plant_lost_s * 1e9 / PERIOD_NS)
    assert int(lost[0]["cycle"]) == first_executed(last_sample + plant_lost_periods)
    assert "reason=plant_lost" in events(log, "daemon_stop")[0]["detail"]
    assert verify(log).ok
    replay = ballbeam("replay", str(bench.log_path))
    assert replay.returncode == 0, replay.stderr
    assert "plant_lost" in replay.stdout
    figure(
        f"emulator_kill_{'stalled' if stall_daemon else 'plain'}",
        {"detection_periods": fault_cycle - last_sample, "plant_lost_periods": lost_after_periods},
    )


@pytest.mark.bus
def test_with_the_launchers_link_a_killed_emulator_gets_0v_at_the_first_silent_period(
    tmp_path: Path,
) -> None:
    """`ballbeam run`'s link also carries a robust mutex the emulator holds
    (runtime/owner_lock.py): the daemon, finding no sample, tries it, and a dead emulator is
    not waited for (0 V from the first silent cycle on), where a live one whose samples are
    late is coasted over for ``sensor_timeout_alive_periods``."""
    with Bench(tmp_path, "realtime", 3.0, peer_link=True) as bench:
        kill_emulator_then_daemon_lost(bench, random.Random(5).uniform(0.4, 1.0))
    log = read_log(bench.log_path)
    fault_cycle = int(faults(log, "sensor_timeout")[-1]["cycle"])
    last_sample = _last_sample_cycle(log, fault_cycle)
    executed = log.topics["/timing"].values["cycle"]
    # The first executed cycle after the last sample (one period, if on time) is the fault.
    assert fault_cycle == int(executed[executed > last_sample][0]), (last_sample, fault_cycle)
    command = log.topics["/command"].values
    after = command["cycle"] >= fault_cycle
    assert (command["enable"][after] == 0).all() and (command["voltage_v"][after] == 0.0).all()
    assert verify(log).ok
    figure("emulator_kill_linked", {"detection_periods": fault_cycle - last_sample})


@pytest.mark.bus
def test_emulator_killed_lockstep_daemon_stops_on_silence_and_finishes_its_file(
    tmp_path: Path,
) -> None:
    with Bench(tmp_path, "lockstep", 20.0, "controller.lockstep_timeout_s=0.5") as bench:
        kill_emulator_then_daemon_lost(bench, 0.5)
    log = read_log(bench.log_path)
    assert not log.truncated
    assert summary_meta(log)["end_reason"] == "plant_silent"
    assert len(faults(log, "plant_silent")) == 1
    stops = shutdown_frames(log)
    assert len(stops) == 3 and all(c.voltage_v == 0.0 and not c.enable for c in stops)
    assert verify(log).ok
