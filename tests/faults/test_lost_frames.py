"""Lost frames: sensor and command frames dropped by the emulator are survived and visible.

Sensor frame loss is visible to the controller (the rolling counter: ``sensor_frames_lost``,
coasted cycles). Command frame loss is not, by design: the sensor frame carries no command
acknowledgement, and a real-time plant simply holds the last voltage (a DAC) for another
period. Its effect is observable as the emulator's own count of dropped commands, as the
absence of watchdog trips (the status bit recorded on ``/sensor``) and as the settle time.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from ballbeam.evaluation.replay import verify
from ballbeam.protocol.frames import STATUS_WATCHDOG

from .harness import (
    Bench,
    Outcome,
    assert_settles_like,
    assert_watchdog_tripped_only_when_the_daemon_was_silent,
    figure,
    run_to_end,
    summary_meta,
)

# On wall time: alone under pytest -n (tests/conftest.py).
pytestmark = pytest.mark.realtime


@pytest.mark.bus
@pytest.mark.parametrize("loss", ["sensor_loss", "command_loss"])
def test_lost_frames_are_survived_and_visible(
    tmp_path: Path, clean_realtime: Outcome, loss: str
) -> None:
    with Bench(tmp_path, "realtime", 4.0, f"plant.{loss}=0.05", watch=False) as bench:
        outcome = run_to_end(bench)
    assert outcome.daemon_exit == 0, outcome.daemon_stderr[-2000:]
    summary = outcome.summary
    assert summary["end_reason"] == "completed" and not summary["truncated"]
    assert_settles_like(outcome, clean_realtime)
    assert summary["theta_violation_s"] == 0.0 or summary["max_abs_theta_deg"] < 53.0
    dropped = outcome.emulator["dropped_by_injection"]
    # 5 % of about 4000 frames: 200 expected, binomial sd 14.
    assert 100 <= dropped <= 350, outcome.emulator
    status = outcome.log.topics["/sensor"].values["status"]
    assert not (status & STATUS_WATCHDOG).any(), "the plant's watchdog tripped"
    assert_watchdog_tripped_only_when_the_daemon_was_silent(outcome)
    # The sensor counter counts the plant's sample periods (ef49084): a period the emulator's
    # process was not run in time is never sent, and the daemon sees it as a lost frame. That
    # is the machine's stall, not the bus's loss; the bounds below are on the frames lost on
    # the bus. (Measured under other jobs' load on this 2-core machine: a command_loss run
    # with 6 "lost" sensor frames had 6 missed plant periods; one in a full fault run had 13,
    # over the old bound of 5; clean real-time runs missed 0-50 periods in
    # bench/secoc_attack.py.)
    missed = summary["plant_missed_periods"] or 0
    lost_on_bus = summary["frames_lost"] - missed
    if loss == "sensor_loss":
        assert 100 <= lost_on_bus <= 350, summary
        meta = summary_meta(outcome.log)
        # Each lost sample leaves a cycle without one of its own period: it coasts, faults,
        # (the loop behind the stream) takes a sample of an earlier period late, or is not run
        # at all (a period the loop skipped: the daemon's socket drops what comes while the
        # process is off its CPU longer than its short queue holds).
        without_own_sample = (
            summary["coasted_cycles"] + int(meta["fault_cycles"]) + summary["late_readings"]
            + int(meta["skipped_periods"])
        )
        assert without_own_sample >= 0.9 * summary["frames_lost"], summary
        # Truth still comes for every sample; one whose sensor frame was lost is logged when
        # it arrives, not at the time of an older sample with the same (wrapped) counter.
        # (Misplaced, it would sit beside that older sample's truth: the same counter twice.)
        # The plant's own period index (its counter unwrapped) only ever moves on: by 1, or by
        # more where the plant itself missed periods (counted apart).
        steps = np.diff(outcome.log.topics["/truth"].values["sample_index"].astype(int))
        assert (steps >= 1).all(), np.bincount(np.clip(steps, 0, None))[:4]
        assert int(np.sum(steps - 1)) == summary["plant_missed_periods"]
    else:
        # Invisible to the controller by design (see the module docstring): its sensor stream
        # is complete, and the emulator's own count shows the commands it never applied.
        assert lost_on_bus <= 5, summary
        assert outcome.emulator["commands_applied"] + dropped <= len(outcome.log.topics["/can/tx"])
    assert verify(outcome.log).ok
    figure(
        f"{loss}_run",
        {
            "settle_s": summary["settle_time_s"],
            "dropped": dropped,
            "frames_lost": summary["frames_lost"],
            "plant_missed_periods": missed,
            "coasted_cycles": summary["coasted_cycles"],
            "faults": summary["faults"],
        },
    )
