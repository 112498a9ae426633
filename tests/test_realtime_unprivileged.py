"""Real time as a user the system refuses real-time scheduling: one line says what to grant and
how, the run goes on at normal priority with the angle guard's latency allowance raised to the
lateness the daemon measured, and the servo stays within 52.0°.

Run as root, the test takes the privilege away the way a normal login lacks it: no
capabilities (CAP_SYS_NICE among them) and an rtprio limit of 0 (``setpriv``, util-linux).
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from ballbeam.logs.reader import read_log

from .conftest import REPO, import_bench

# On wall time: alone under pytest -n (tests/conftest.py).
pytestmark = pytest.mark.realtime

REFUSED = "real-time scheduling refused"
THETA_LIMIT_DEG = 52.0
TRUTH_RESOLUTION_DEG = 1e-3  # the truth frame's 1e-5 rad, with room to spare


def unprivileged_prefix() -> list[str]:
    """The command prefix that drops the privilege (bench/realtime_load.py's, which measures the
    same runs under load)."""
    prefix = import_bench("realtime_load").unprivileged_prefix()
    if prefix is None:
        pytest.skip("needs setpriv and prlimit (Debian: apt-get install util-linux) to drop "
                    "the real-time privilege")
    return list(prefix)


@pytest.mark.bus
def test_a_realtime_run_without_the_privilege_says_how_to_grant_it_and_holds_52(
    tmp_path: Path,
) -> None:
    command = [
        *unprivileged_prefix(), sys.executable, "-m", "ballbeam", "run",
        "--set", "run.mode='realtime'", "--set", "run.duration_s=3.0",
        "--set", f"run.log_dir='{tmp_path}'", "--json",
    ]
    done = subprocess.run(command, capture_output=True, text=True, timeout=120, cwd=REPO,
                          check=False)
    assert done.returncode == 0, done.stderr[-3000:]
    refusals = [line for line in done.stderr.splitlines() if REFUSED in line]
    assert len(refusals) == 1, done.stderr
    assert "rtprio" in refusals[0] and "limits.conf" in refusals[0]
    summary = json.loads(done.stdout)
    assert summary["end_reason"] == "completed"
    assert summary["max_abs_theta_deg"] <= THETA_LIMIT_DEG + TRUTH_RESOLUTION_DEG
    # The daemon recorded what it got and what it measured.
    run = read_log(summary["log_path"]).metadata["run"]
    assert run["scheduling_realtime_priority"].startswith("refused")
    # The probe's worst starts the guard's lateness watch (recorded in the config it ran).
    probe_us = int(run["scheduling_lateness_probe_max_us"])
    assert int(run["scheduling_start_lateness_us"]) == min(probe_us, 30_000)
    config = json.loads(read_log(summary["log_path"]).metadata["config"]["json"])
    assert config["controller"]["start_lateness_us"] == min(probe_us, 30_000)
    assert run["scheduling_fair_slice"] == "100 us"


SLICE_PROBE = (
    "from ballbeam.runtime.process import request_fair_slice\n"
    "from ballbeam.runtime.ticker import spin_ns_for_this_process\n"
    "print(request_fair_slice(100), spin_ns_for_this_process(200))\n"
    "print(next(line for line in open('/proc/self/sched') if line.startswith('se.slice')))\n"
)


def test_at_normal_priority_the_loop_asks_for_a_short_slice_and_does_not_spin() -> None:
    """Any user may shorten its fair-scheduler slice; the kernel's own account of the process
    (/proc/self/sched, Linux 6.12+) shows it. And a loop that is not SCHED_FIFO does not
    spin before its deadlines (it would spend the CPU share that keeps it on time)."""
    done = subprocess.run([*unprivileged_prefix(), sys.executable, "-c", SLICE_PROBE],
                          capture_output=True, text=True, timeout=60, cwd=REPO, check=False)
    assert done.returncode == 0, done.stderr
    answer, kernel_line = done.stdout.splitlines()[:2]
    assert answer == "100 us 0"
    assert int(kernel_line.split(":")[1]) == 100_000  # ns
