"""Study throughput (issue 14, item 4): offline and bus runs a minute through the sweep engine
on an embedded Dask LocalCluster with 1 and 2 workers, and the per-run start-up cost a run in
a fresh process pays, side by side in one run.

    .venv/bin/python bench/throughput.py               # about 3 minutes
    .venv/bin/python bench/throughput.py --quick       # fewer points
    .venv/bin/python bench/throughput.py --json throughput.json

Offline points are 4 s runs of the paper start over ball/motor gain draws and noise seeds
(plant-only keys: every point shares one designed controller, built once per worker); the
"own design" row gives every point a plan margin of its own (plan + synthesis + T* per point).
Bus points are 4 s lock-step runs, two processes each on a private ff11:: group. A rate
counts from the first point submitted to the last result (the cluster's start is its own row;
workers import before the clock starts). The machine is shared: read the ratios.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from ballbeam.studies.cluster import dask_client
from ballbeam.studies.engine import run_points, tasks_for
from ballbeam.studies.points import PointOutcome
from ballbeam.studies.spec import spec_from_mapping

REPO = Path(__file__).resolve().parents[1]
PAPER = str(REPO / "configs" / "paper.toml")
RUN_S = 4.0


def _spec(runner: str, samples: int, own_design: bool = False) -> Any:
    random: dict[str, Any] = {
        "plant.ball_gain_scale": {"uniform": [0.8, 1.2]},
        "plant.motor_gain_scale": {"uniform": [0.9, 1.1]},
    }
    if own_design:  # a margin of its own: nothing to share between points
        random["plan.theta_margin_deg"] = {"uniform": [0.3, 0.7]}
    return spec_from_mapping(
        {
            "sweep": {"base": PAPER, "set": [f"run.duration_s={RUN_S}"], "run": runner,
                      "samples": samples, "sample_seed": int(time.time_ns() % 1_000_000)},
            "random": random,
        },
        REPO / "bench" / f"throughput_{runner}.toml",
    )


def rate(client: Any, runner: str, points: int, own_design: bool = False) -> dict[str, Any]:
    spec = _spec(runner, points, own_design)
    with tempfile.TemporaryDirectory(prefix="ballbeam-throughput-") as output:
        tasks = [task for task, _ in tasks_for(spec, spec.points(), Path(output))]
        outcomes: list[PointOutcome] = []
        client.run(lambda: None)
        started = time.perf_counter()
        run_points(client, tasks, runner, outcomes.append, progress=False)
        elapsed_s = time.perf_counter() - started
    failed = [outcome.error for outcome in outcomes if outcome.error]
    if failed:
        raise SystemExit(f"{len(failed)} {runner} points failed, first: {failed[0]}")
    return {
        "points": len(outcomes),
        "elapsed_s": elapsed_s,
        "runs_per_min": 60.0 * len(outcomes) / elapsed_s,
        "point_wall_median_s": statistics.median(outcome.wall_time_s for outcome in outcomes),
        # What a point costs the worker, whatever else the shared machine runs meanwhile.
        "point_cpu_median_s": statistics.median(outcome.cpu_time_s for outcome in outcomes),
    }


def process_wall_s(argv: list[str], repeats: int) -> float:
    """Median wall time of a command in a fresh process."""
    times = []
    for _ in range(repeats):
        started = time.perf_counter()
        subprocess.run(argv, check=True, capture_output=True, cwd=REPO)
        times.append(time.perf_counter() - started)
    return statistics.median(times)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer points")
    parser.add_argument("--json", metavar="PATH", help="also write the figures as JSON")
    args = parser.parse_args(argv)
    offline_points = 120 if args.quick else 400
    own_points = 16 if args.quick else 40
    bus_points = 4 if args.quick else 8
    repeats = 3 if args.quick else 5
    python = sys.executable
    results: dict[str, Any] = {}

    imports = [python, "-c", "import ballbeam.cli, ballbeam.assembly, "
               "ballbeam.core.planning.time_optimal"]
    results["startup"] = {
        "python_bare_s": process_wall_s([python, "-c", "pass"], repeats),
        "imports_s": process_wall_s(imports, repeats),
        "plan_s": process_wall_s([python, "-m", "ballbeam", "plan", "--json"], repeats),
        "simulate_4s_s": process_wall_s(
            [python, "-m", "ballbeam", "simulate", "--set", f"run.duration_s={RUN_S}", "--json"],
            repeats,
        ),
    }
    for workers in (1, 2):
        started = time.perf_counter()
        with dask_client(None, workers) as client:
            cluster_start_s = time.perf_counter() - started
            row: dict[str, Any] = {"cluster_start_s": cluster_start_s}
            row["offline_shared_design"] = rate(client, "offline", offline_points)
            row["offline_own_design"] = rate(client, "offline", own_points, own_design=True)
            row["lockstep"] = rate(client, "lockstep", bus_points)
        results[f"workers_{workers}"] = row
        print(f"{workers} worker(s): done", file=sys.stderr)

    startup = results["startup"]
    print(f"start-up in a fresh process (median of {repeats}): python "
          f"{startup['python_bare_s']:.3f} s, imports {startup['imports_s']:.3f} s, "
          f"`ballbeam plan` {startup['plan_s']:.3f} s, "
          f"`ballbeam simulate` (4 s run) {startup['simulate_4s_s']:.3f} s "
          f"= {60 / startup['simulate_4s_s']:.0f} runs/min one process at a time")
    print()
    print("| runs (4 s each) | 1 worker: runs/min | 2 workers: runs/min | point wall, median "
          "(1 / 2 workers) | worker CPU a point, median (1 / 2 workers) |")
    print("| --- | --- | --- | --- | --- |")
    for key, label in (("offline_shared_design", "offline, one shared design"),
                       ("offline_own_design", "offline, a design per point"),
                       ("lockstep", "bus, lock-step")):
        one, two = results["workers_1"][key], results["workers_2"][key]
        print(f"| {label} ({one['points']}/{two['points']} points) | {one['runs_per_min']:.0f} | "
              f"{two['runs_per_min']:.0f} | {one['point_wall_median_s']:.3f} / "
              f"{two['point_wall_median_s']:.3f} s | {one['point_cpu_median_s']:.3f} / "
              f"{two['point_cpu_median_s']:.3f} s |")
    print(f"| cluster start | {results['workers_1']['cluster_start_s']:.2f} s | "
          f"{results['workers_2']['cluster_start_s']:.2f} s | | |")
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
