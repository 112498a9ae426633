"""The log cannot be written: refused before anything starts, or (disk full mid-run) the run
stops at 0 V and keeps what was written.
"""

from __future__ import annotations

import time
from pathlib import Path

import pytest

from ballbeam.config import DEFAULT_BUS_GROUP
from ballbeam.logs.reader import read_log
from ballbeam.runtime.bus import isolated_group

from ..conftest import PAPER, ballbeam
from .harness import Bench, BusWatch, commands_heard, figure, one_error_line, set_args

# On wall time: alone under pytest -n (tests/conftest.py).
pytestmark = pytest.mark.realtime


@pytest.mark.bus
def test_run_with_an_unusable_log_dir_refuses_before_starting_anything(tmp_path: Path) -> None:
    blocker = tmp_path / "file.txt"
    blocker.write_text("a file, not a directory\n")
    group = isolated_group(DEFAULT_BUS_GROUP)
    watch = BusWatch(group)
    try:
        result = ballbeam(
            "run",
            str(PAPER),
            *set_args(
                [
                    "bus.isolate_runs=false",
                    "bus.interface='udp_multicast'",
                    f"bus.channel='{group}'",
                    f"run.log_dir='{blocker / 'logs'}'",
                ]
            ),
        )
        time.sleep(0.2)
    finally:
        watch.close()
    assert result.returncode == 2
    line = one_error_line(result.stderr)
    assert "cannot create log directory" in line and str(blocker) in line
    assert len(result.stderr.strip().splitlines()) == 1
    assert watch.frames == [], "a node started on the bus anyway"


@pytest.mark.bus
@pytest.mark.parametrize("target", ["/dev/full", "{tmp}/file.txt/run.mcap"])
def test_daemon_refuses_a_log_it_cannot_write_before_touching_the_bus(
    tmp_path: Path, target: str
) -> None:
    (tmp_path / "file.txt").write_text("x")
    path = target.format(tmp=tmp_path)
    group = isolated_group(DEFAULT_BUS_GROUP)
    watch = BusWatch(group)
    try:
        result = ballbeam(
            "daemon", str(PAPER),
            *set_args(["bus.interface='udp_multicast'", f"bus.channel='{group}'"]),
            "--log", path,
        )
        time.sleep(0.2)
    finally:
        watch.close()
    assert result.returncode == 2
    line = one_error_line(result.stderr)
    assert path in line
    # A log is only ever a new file: a device already there is refused as such.
    assert ("exists" in line) if path == "/dev/full" else ("Not a directory" in line)
    assert len(result.stderr.strip().splitlines()) == 1
    assert watch.frames == [], "the daemon sent frames without a log"


@pytest.mark.bus
def test_disk_full_mid_run_stops_the_run_at_0v_and_keeps_what_was_written(tmp_path: Path) -> None:
    """The file may not grow past 192 kB (a full disk, seen as EFBIG): the run must not go on
    unrecorded. The daemon stops at 0 V, exits 2 with one error line; the file is readable
    up to its last complete chunk. (The log's start holds ~90 kB of recorded design, so the
    limit leaves the run about as long to reach it as 96 kB did before the design was kept.)"""
    limit = 192 * 1024
    with Bench(tmp_path, "realtime", 60.0, file_size_limit=limit) as bench:
        assert bench.watch is not None
        bench.wait_cycling()
        daemon_exit = bench.wait_daemon(30.0)  # the run was 60 s long
        time.sleep(0.1)
        assert bench.stop_emulator() == 0
        frames = list(bench.watch.frames)
        daemon_stderr = bench.stderr(bench.daemon)
    assert daemon_exit == 2, daemon_stderr[-2000:]
    line = one_error_line(daemon_stderr)
    assert "File too large" in line and str(bench.log_path) in line
    assert bench.log_path.stat().st_size <= limit
    log = read_log(bench.log_path)
    assert log.truncated and len(log.topics["/command"]) > 0
    commands = commands_heard(frames)
    assert all(c.voltage_v == 0.0 and not c.enable for _, _, c in commands[-3:])
    figure(
        "disk_full_run",
        {"cycles_commanded": len(commands), "recorded": len(log.topics["/command"])},
    )
