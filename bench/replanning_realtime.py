"""The re-planning law in real time beside the tracker: the same command, side by side.

Runs ``ballbeam run`` on the paper's start in real time twice — ``controller.kind`` "tracker"
and "replanning" — and prints, from each log: overruns and skipped periods, p99 lateness and
the cycle's own duration (/timing), whether and when the ball came to rest, the largest |θ|
(/truth), and for the re-planning law its planner's answers (/plans): how many, and the wall
time from sending each request to reading its answer, p50 and p99.

    nice -n 19 .venv/bin/python bench/replanning_realtime.py [--duration 4] [--set KEY=VALUE]
        [--log-dir DIR]
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

from ballbeam.logs.plan_record import PLANS
from ballbeam.logs.reader import read_log

REPO = Path(__file__).resolve().parents[1]
REST_BAND_M = 5e-4
REST_BAND_RAD = math.radians(0.5)


def run(kind: str, duration_s: float, log_dir: Path, extra: list[str]) -> dict[str, object]:
    sets = [f"controller.kind='{kind}'", "run.mode='realtime'", f"run.duration_s={duration_s}",
            f"run.log_dir='{log_dir}'", *extra]
    argv = [sys.executable, "-m", "ballbeam", "run", str(REPO / "configs" / "paper.toml"),
            *[item for value in sets for item in ("--set", value)], "--json"]
    result = subprocess.run(argv, capture_output=True, text=True, check=False, cwd=REPO)
    logs = sorted(log_dir.glob("*.mcap"), key=lambda path: path.stat().st_mtime)
    if not logs:
        return {"kind": kind, "error": result.stderr.strip()}
    run_log = read_log(logs[-1])
    timing = run_log.topics["/timing"].values
    lateness_us = np.asarray(timing["lateness_ns"]) / 1e3
    duration_us = (np.asarray(timing["end_ns"]) - np.asarray(timing["start_ns"])) / 1e3
    skipped = np.asarray(timing["skipped"])
    truth = run_log.topics["/truth"].values
    time_s = np.asarray(truth["plant_time_s"])
    outside = (np.abs(np.asarray(truth["ball_position_m"])) > REST_BAND_M) | (
        np.abs(np.asarray(truth["theta_rad"])) > REST_BAND_RAD
    )
    rest_s = None
    if not outside[-1]:
        last = np.flatnonzero(outside)
        rest_s = float(time_s[last[-1] + 1]) if last.size else 0.0
    figures: dict[str, object] = {
        "kind": kind,
        "exit": result.returncode,
        "end_reason": run_log.metadata.get("summary", {}).get("end_reason"),
        "overruns": int(np.count_nonzero(skipped)),
        "skipped_periods": int(skipped.sum()),
        "lateness_p99_us": round(float(np.percentile(lateness_us, 99)), 1),
        "cycle_p50_us": round(float(np.percentile(duration_us, 50)), 1),
        "cycle_p99_us": round(float(np.percentile(duration_us, 99)), 1),
        "rest_s": rest_s,
        "max_abs_theta_deg": round(float(np.degrees(np.max(np.abs(truth["theta_rad"])))), 3),
    }
    figures["cycle_p50_us_where_an_answer_was_taken"] = None
    plans = run_log.json_topics.get(PLANS)
    if plans is not None:
        waits_ms = np.array(
            [m["wait_ns"] for m in plans.messages if m.get("wait_ns", -1) >= 0]
        ) / 1e6
        figures["answers_taken"] = len(plans.messages)
        figures["plans_taken"] = sum(m["plan"] is not None for m in plans.messages)
        if waits_ms.size:
            figures["answer_wait_p50_ms"] = round(float(np.percentile(waits_ms, 50)), 2)
            figures["answer_wait_p99_ms"] = round(float(np.percentile(waits_ms, 99)), 2)
        taken = np.isin(np.asarray(timing["cycle"]), [m["cycle"] for m in plans.messages])
        if taken.any():
            figures["cycle_p50_us_where_an_answer_was_taken"] = round(
                float(np.percentile(duration_us[taken], 50)), 1
            )
        figures["fewest_cycles_request_to_effect"] = min(
            (m["cycle"] - m["request_cycle"] for m in plans.messages if m["cycle"] > 0),
            default=None,
        )
    figures["log"] = str(logs[-1])
    return figures


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=4.0)
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE")
    parser.add_argument("--log-dir", type=Path, help="keep the logs here (default: discarded)")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as scratch:
        base = args.log_dir or Path(scratch)
        rows = [
            run(kind, args.duration, base / kind, args.set) for kind in ("tracker", "replanning")
        ]
        for row in rows:
            if args.log_dir is None:
                row.pop("log", None)
        print(json.dumps(rows, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
