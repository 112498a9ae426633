"""Runs under attack against clean runs: forged, replayed and random frames at 5 kHz from a
separate process (tests/helpers/flood.py --attack, 15,000 frames, stops by itself) on the run's
private interface-local group, during ``ballbeam run``.

    .venv/bin/python bench/secoc_attack.py --mode realtime --pairs 5
    .venv/bin/python bench/secoc_attack.py --mode lockstep --pairs 1

Clean and attacked runs alternate (the machine's load then falls on both alike). Prints per run
the rest time, the periods the loop skipped, the daemon's rejections by reason, the plant
emulator's and what the flood sent, then the accepted count (valid commands the plant applied
beyond those the daemon sent, and second-writer frames: both must be 0), the spread of rest
times and the periods skipped, clean and attacked.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

from ballbeam.config import DEFAULT_BUS_GROUP
from ballbeam.evaluation.summary import summarise
from ballbeam.logs.reader import read_log
from ballbeam.runtime.bus import free_udp_port, isolated_group
from ballbeam.runtime.launcher import launch_run

REPO = Path(__file__).resolve().parents[1]
FLOOD = REPO / "tests" / "helpers" / "flood.py"
PAPER = REPO / "configs" / "paper.toml"


def one_run(
    mode: str, attacked: bool, seed: int, log_dir: Path, keep: bool = False
) -> dict[str, Any]:
    group, port = isolated_group(DEFAULT_BUS_GROUP), free_udp_port()
    overrides = [f"run.mode='{mode}'", "run.duration_s=4.0", "bus.isolate_runs=false",
                 "bus.interface='udp_multicast'",
                 f"bus.channel='{group}'", f"bus.port={port}", f"run.log_dir='{log_dir}'"]
    flood: subprocess.Popen[str] | None = None
    if attacked:
        flood = subprocess.Popen(
            [sys.executable, str(FLOOD), "--attack", "--channel", group, "--port", str(port),
             "--seed", str(seed), "--rate-hz", "5000", "--max-frames", "15000",
             "--max-seconds", "3", "--start-on", "command", "--wait", "60"],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO,
        )
    try:
        result = launch_run(str(PAPER), overrides)
    finally:
        if flood is not None and flood.poll() is None:
            try:
                flood.wait(timeout=70)
            except subprocess.TimeoutExpired:
                flood.kill()
    log = read_log(result.log_path)
    summary = summarise(log)
    meta = dict(log.metadata.get("summary", {}))
    row: dict[str, Any] = {
        "attacked": attacked,
        "late_samples": summary.get("late_samples"),
        "daemon_exit": result.daemon_exit,
        "end_reason": summary["end_reason"],
        "rest_time_s": summary["rest_time_s"],
        "overruns": int(meta.get("overruns", 0)),
        "skipped_periods": int(meta.get("skipped_periods", 0)),
        "plant_missed_periods": summary.get("plant_missed_periods"),
        "lateness_max_us": summary.get("lateness_max_us"),
        "frames_lost": summary.get("frames_lost"),
        "sensor_timeouts": sum(1 for m in log.json_topics["/faults"].messages
                               if m.get("kind") == "sensor_timeout")
        if "/faults" in log.json_topics else 0,
        "second_writer_frames": int(meta.get("second_writer_frames", 0)),
        "rejected": {k.removeprefix("rejected_"): int(v) for k, v in meta.items()
                     if k.startswith("rejected_") and k != "rejected_total"},
    }
    if flood is not None:
        out, _ = flood.communicate()
        flood_report = json.loads(out) if out.strip() else {}
        row["flood_sent"] = flood_report.get("sent")
        row["flood_elapsed_s"] = flood_report.get("elapsed_s")
    if keep:
        row["log_path"] = str(result.log_path)
    else:
        result.log_path.unlink()
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--mode", choices=("realtime", "lockstep"), default="realtime")
    parser.add_argument("--pairs", type=int, default=3)
    parser.add_argument("--log-dir", type=Path, help="keep the runs' logs here (default: a "
                        "temporary directory, removed at the end)")
    args = parser.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as tmp_dir:
        tmp = args.log_dir or tmp_dir
        for pair in range(args.pairs):
            for attacked in (False, True):
                row = one_run(args.mode, attacked, 100 + pair, Path(tmp), args.log_dir is not None)
                print(json.dumps(row), flush=True)
                rows.append(row)
    clean = [r["rest_time_s"] for r in rows if not r["attacked"]]
    attacked_rest = [r["rest_time_s"] for r in rows if r["attacked"]]
    print(json.dumps({
        "mode": args.mode,
        "clean_rest_s": clean,
        "attacked_rest_s": attacked_rest,
        "pair_differences_ms": [
            round((a - c) * 1e3, 1) for a, c in zip(attacked_rest, clean, strict=True)
        ],
        "clean_spread_ms": round((max(clean) - min(clean)) * 1e3, 1),
        "median_difference_ms": round((statistics.median(attacked_rest)
                                       - statistics.median(clean)) * 1e3, 1),
        "skipped_periods_clean": [r["skipped_periods"] for r in rows if not r["attacked"]],
        "skipped_periods_attacked": [r["skipped_periods"] for r in rows if r["attacked"]],
        "second_writer_frames": sum(r["second_writer_frames"] for r in rows),
    }, indent=1))


if __name__ == "__main__":
    main()
