"""How long a minimum-time re-plan takes (issue 27, item 2: p99 ≤ 5 ms), side by side with
the grid planner, on the paper's task.

    .venv/bin/python bench/replan.py              # about a minute
    .venv/bin/python bench/replan.py --json out.json

- ``cold``: ``plan_arcs`` from the paper's start (grid LP, then Newton), against
  ``plan_time_optimal`` at 1 ms (what every run pays today).
- ``warm on path``: ``replan`` every 5 ms along the plan from the plan's own state (the loop's
  case when the estimate follows the plan).
- ``warm perturbed``: the same, the state disturbed by noise of the estimate's size (σ: 0.1 mrad,
  2.5 mrad/s, 0.1 mm/s, 0.05 mm); a perturbation can change the optimal structure (an arc
  more at the end), which the warm start may not find: those are counted as misses (the loop
  keeps its plan and plans cold in the background).
- ``warm tap``: a 5 cm/s tap on the ball part-way: the same, larger.
"""

from __future__ import annotations

import argparse
import json
import math
import time

import numpy as np

from ballbeam.core.model import LinearModel, PhysicalConstants
from ballbeam.core.planning.arcs import ArcPlan, plan_arcs, replan
from ballbeam.core.planning.time_optimal import plan_time_optimal

THETA_MAX = math.radians(52.0)
START = np.array([-THETA_MAX, 0.0, 0.0, 0.195])


def percentiles(times_s: list[float]) -> dict[str, float]:
    ms = np.array(times_s) * 1e3
    return {
        "n": int(ms.size),
        "p50_ms": float(np.percentile(ms, 50)) if ms.size else math.nan,
        "p99_ms": float(np.percentile(ms, 99)) if ms.size else math.nan,
        "max_ms": float(np.max(ms)) if ms.size else math.nan,
    }


def warm(plan: ArcPlan, sigma: np.ndarray, seed: int) -> dict[str, float]:
    rng = np.random.default_rng(seed)
    times: list[float] = []
    misses = 0
    for elapsed_s in np.arange(0.0, plan.duration_s - 0.005, 0.005):
        state = plan.sample(np.array([elapsed_s])).states[0] + sigma * rng.normal(size=4)
        # a state beyond the limit cannot be planned from: keep the angle inside it
        state[0] = float(np.clip(state[0], -THETA_MAX, THETA_MAX))
        t0 = time.perf_counter()
        result = replan(plan, float(elapsed_s), state)
        times.append(time.perf_counter() - t0)
        misses += result is None
    return {**percentiles(times), "misses": misses}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--json", help="write the figures to this file")
    parser.add_argument("--repeat", type=int, default=5, help="cold plans to time")
    args = parser.parse_args()
    model = LinearModel.from_constants(PhysicalConstants())
    cold, grid = [], []
    for _ in range(args.repeat):
        t0 = time.perf_counter()
        plan = plan_arcs(model, START)
        cold.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        plan_time_optimal(model, START, voltage_limit_v=5.0, theta_max_rad=THETA_MAX)
        grid.append(time.perf_counter() - t0)
    figures = {
        "cold plan_arcs": percentiles(cold),
        "grid plan_time_optimal 1 ms": percentiles(grid),
        "warm on path": warm(plan, np.zeros(4), 1),
        "warm perturbed": warm(plan, np.array([1e-4, 2.5e-3, 1e-4, 5e-5]), 2),
        "warm tap": warm(plan, np.array([0.0, 0.0, 0.05, 0.0]), 3),
    }
    print(f"paper start: arcs {plan.duration_s:.6f} s")
    print(f"{'case':30} {'n':>5} {'p50 ms':>9} {'p99 ms':>9} {'max ms':>9} {'misses':>7}")
    for name, row in figures.items():
        print(
            f"{name:30} {row['n']:5d} {row['p50_ms']:9.3f} {row['p99_ms']:9.3f} "
            f"{row['max_ms']:9.3f} {row.get('misses', 0):7d}"
        )
    if args.json:
        with open(args.json, "x", encoding="utf-8") as out:
            json.dump(figures, out, indent=2)


if __name__ == "__main__":
    main()
