"""Bus noise: a flood of foreign traffic on the bench's bus, while the daemon cycles and
while it starts up, is rejected, counted and recorded, and the loop keeps its rate.

A foreign frame that carries a *valid* E2E CRC for one of our standard ids is spoofing, which
a CRC-16 does not defend against; the flood (tests/helpers/flood.py) therefore makes its bad
CRCs bad on purpose.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import can
import numpy as np
import pytest

from ballbeam.config import DEFAULT_BUS_GROUP, BusSection
from ballbeam.evaluation.replay import verify
from ballbeam.runtime.bus import isolated_group, open_bus

from ..conftest import REPO
from .harness import (
    DEFAULTS,
    START_TIMEOUT_S,
    Bench,
    BusWatch,
    Outcome,
    assert_settles_like,
    assert_watchdog_tripped_only_when_the_daemon_was_silent,
    faults,
    figure,
    finish_flood,
    run_to_end,
    summary_meta,
)

# On wall time: alone under pytest -n (tests/conftest.py).
pytestmark = pytest.mark.realtime

FLOOD = Path(__file__).resolve().parents[1] / "helpers" / "flood.py"


@pytest.mark.bus
def test_private_groups_on_one_port_do_not_hear_each_other() -> None:
    """What every test here (and ``ballbeam run``'s bus.isolate_runs) relies on. Linux by
    default hands a datagram to every socket on the port once the host joined its group."""
    port = DEFAULTS.bus.port
    group, other = isolated_group(DEFAULT_BUS_GROUP), isolated_group(DEFAULT_BUS_GROUP)
    sender = open_bus(BusSection(channel=group, port=port))
    same = open_bus(BusSection(channel=group, port=port))
    elsewhere = open_bus(BusSection(channel=other, port=port))
    watch = BusWatch(other, port)
    try:
        sender.send(can.Message(arbitration_id=0x7AB, data=b"hello", is_extended_id=False))
        heard = same.recv(timeout=1.0)
        assert heard is not None and bytes(heard.data) == b"hello"
        assert elsewhere.recv(timeout=0.3) is None
        time.sleep(0.05)
    finally:
        for bus in (sender, same, elsewhere):
            bus.shutdown()
        watch.close()
    assert watch.frames == []


def run_with_flood(
    tmp: Path, start_on: str, duration_s: float, seed: int, raw_weight: int = 4
) -> tuple[Outcome, dict[str, Any]]:
    with Bench(tmp, "realtime", duration_s, watch=False) as bench:
        flood = subprocess.Popen(
            [
                sys.executable,
                str(FLOOD),
                "--channel",
                bench.group,
                "--port",
                str(bench.port),
                "--seed",
                str(seed),
                "--rate-hz",
                "3000",
                "--max-frames",
                "20000",
                "--max-seconds",
                "3",
                "--start-on",
                start_on,
                "--wait",
                str(START_TIMEOUT_S),
                "--raw-weight",
                str(raw_weight),
            ],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            cwd=REPO,
        )
        flood_out, flood_err = finish_flood(flood)
        outcome = run_to_end(bench)
    # The flood stopped by itself (exit 0: it was not killed above), bounded in count by its
    # own limit. How long it took depends on the machine's load, which is not what this test
    # is about: no wall-clock bound (its elapsed time is among the figures).
    assert flood.returncode == 0, flood_err
    sent: dict[str, Any] = json.loads(flood_out)
    assert 0 < sent["sent"] <= 20_000, sent
    assert outcome.daemon_exit == 0, outcome.daemon_stderr[-2000:]
    assert "Traceback" not in outcome.daemon_stderr + outcome.emulator_stderr
    assert outcome.summary["end_reason"] == "completed" and not outcome.summary["truncated"]
    return outcome, sent


# Not a speed target: the loop stays on wall time and runs most of its periods under the flood,
# and its control holds (the angle bound, the rest; below). How many periods it skips is the
# machine's: daemon, emulator and flood share two cores, and on these shared hosts the figure
# ranged from 0.3 % to 17 % within an hour, and CI's machine skipped 11 % (docs/decisions.md).
# That figure is a benchmark's (bench/secoc_attack.py prints it for clean and attacked runs
# side by side); here only a loop the flood held down fails: a quarter of its periods gone.
MAX_SKIPPED_FRACTION = 0.25


@pytest.mark.bus
def test_a_flood_of_foreign_frames_is_rejected_and_counted_while_the_loop_holds_its_rate(
    tmp_path: Path, clean_realtime: Outcome
) -> None:
    outcome, sent = run_with_flood(tmp_path, "command", 4.0, seed=7)
    by_kind = sent["by_kind"]
    summary, meta = outcome.summary, summary_meta(outcome.log)
    # Counted, by reason, and recorded as /faults events (capped per reason).
    rejected = {
        k.removeprefix("rejected_"): int(v)
        for k, v in meta.items()
        if k.startswith("rejected_") and k != "rejected_total"
    }
    assert int(meta["rejected_total"]) == sum(rejected.values()) > 0
    for reason in ("unknown_id", "crc", "length", "foreign", "malformed"):
        assert rejected.get(reason, 0) > 0, (reason, rejected)
    assert rejected["malformed"] <= by_kind["raw_datagram"]
    kinds = {m["kind"] for m in faults(outcome.log)}
    assert {
        "rejected_unknown_id",
        "rejected_crc",
        "rejected_length",
        "rejected_foreign",
        "rejected_malformed",
    } <= kinds
    # No noise got through: no full-scale spoofed reading was used, the plant never saw a
    # spoofed command (it applied at most what the daemon sent) and its watchdog never tripped
    # while the daemon was sending.
    sensor = outcome.log.topics["/sensor"].values
    taken = sensor["fresh"] >= 1  # on time or late
    assert np.abs(sensor["angle_counts"][taken]).max() < 32767
    assert np.abs(sensor["position_counts"][taken]).max() < 32767
    assert outcome.emulator["commands_applied"] <= len(outcome.log.topics["/can/tx"])
    # (a trip only where the daemon itself sent nothing for the watchdog's time: this host
    # stalls processes for that long at times, flood or none; docs/decisions.md)
    assert_watchdog_tripped_only_when_the_daemon_was_silent(outcome)
    assert outcome.emulator["rejected"] > 0 and outcome.emulator["own_or_foreign"] > 0
    assert verify(outcome.log).ok
    # The loop held its rate: 4000 periods on wall time, nearly all of them run.
    timing = outcome.log.topics["/timing"].values
    executed = len(timing)
    skipped = int(meta["skipped_periods"])
    assert executed + skipped == 4000
    assert skipped <= MAX_SKIPPED_FRACTION * 4000, meta
    span_s = (int(timing["start_ns"][-1]) - int(timing["start_ns"][0])) * 1e-9
    assert abs(span_s - 3.999) < 0.01, span_s
    # And the servo stayed within its limit (what failed in CI: under the flood a daemon
    # short of CPU coasted, commanded 0 V, and the servo reached its end stop at 56°).
    bound_deg = DEFAULTS.limits.theta_deg + DEFAULTS.controller.bound_tolerance_deg
    assert summary["max_abs_theta_deg"] <= bound_deg, summary
    starved = faults(outcome.log, "sensor_timeout")
    if not starved:
        assert_settles_like(outcome, clean_realtime)
    else:
        # The flood and the other process took the CPU long enough that no sensor frame was
        # read for 3 periods: the daemon commanded 0 V by design (a fault, counted), and the
        # run is not comparable with the clean one. It must still come to rest.
        assert summary["settle_time_s"] is not None, summary
        figure("flood_starved_settle_s", summary["settle_time_s"])
    figure("flood_frames", sent)
    figure(
        "flood_loop",
        {
            "executed_cycles": executed,
            "skipped_periods": skipped,
            "overruns": int(meta["overruns"]),
            "cycle_rate_hz": round((executed - 1) / span_s, 1),
            "lateness_p99_us": round(summary["lateness_p99_us"], 1),
            "lateness_max_us": round(summary["lateness_max_us"], 1),
            "sensor_timeouts": len(faults(outcome.log, "sensor_timeout")),
            "settle_s": summary["settle_time_s"],
            "rejected": rejected,
        },
    )


@pytest.mark.bus
def test_a_flood_while_the_daemon_starts_up_does_not_stop_it(tmp_path: Path) -> None:
    """The flood starts with the plant's first sample: the daemon meets it while it plans,
    waits for the plant and probes the sensor phase (a window of ~20 ms), not only once it
    is cycling. A third of it is raw datagrams, so that the short windows do get some."""
    outcome, sent = run_with_flood(tmp_path, "sensor", 2.0, seed=8, raw_weight=48)
    meta = summary_meta(outcome.log)
    assert int(meta["rejected_total"]) > 0
    assert int(meta.get("rejected_malformed", 0)) > 0
    figure(
        "startup_flood",
        {
            "sent": sent["sent"],
            "rejected_total": meta["rejected_total"],
            "cycles": outcome.summary["cycles"],
        },
    )
