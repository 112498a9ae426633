"""How long a minimum-time re-plan takes (issue 27, item 2: p99 ≤ 5 ms), side by side with
the grid planner, on the paper's task.

    .venv/bin/python bench/replan.py              # about a minute
    .venv/bin/python bench/replan.py --json out.json
    .venv/bin/python bench/replan.py --cold-draws 200 --seed 7 --before --slice 0:50 --json a.json
    .venv/bin/python bench/replan.py --summarise a.json b.json ...

- ``cold``: ``plan_arcs`` from the paper's start (grid LP, then Newton), against
  ``plan_time_optimal`` at 1 ms (what every run pays today).
- ``warm on path``: ``replan`` every 5 ms along the plan from the plan's own state (the loop's
  case when the estimate follows the plan).
- ``warm perturbed``: the same, the state disturbed by noise of the estimate's size (σ: 0.1 mrad,
  2.5 mrad/s, 0.1 mm/s, 0.05 mm); a perturbation can change the optimal structure (an arc
  more at the end), which the warm start may not find: those are counted as misses (the loop
  keeps its plan and plans cold in the background). ``as the law``: without the structures
  with arcs added, which the law tries only for a detour or a new model.
- ``warm tap``: a 5 cm/s tap on the ball part-way: the same, larger.
- ``the law's …``: every request the re-planning law made in two 3 s runs from the paper's
  start (nominal plant), solved again and timed by its answer: cold, near, a warm re-plan
  taken, missed, or not taken because the plan in force ends in the terminal set (that
  answer tracks the plan to its end: the costliest).

``--cold-draws N --seed S``: cold ``plan_arcs`` from N seeded random starts on random plants
(issue 27's ranges: ball gain 0.7–1.3, motor gain 0.8–1.2; θ within ±45°, |θ̇| ≤ 0.5 rad/s,
|ẋ| ≤ 0.15 m/s, |x| ≤ 0.2 m, every other start short: |x| ≤ 5 cm, |ẋ| ≤ 7.5 cm/s), planned as
the controller plans (52° less its 0.3° margin, a drive of ``--voltage-v``, 4.5 V by default;
its first plans, with the model still uncertain, may have far less): time per plan p50/p99/max, the
LP solves it took, and how many were found. ``--before`` adds the cold path as it was (grid
LPs at 10, 2 and 0.5 ms until the grid's own shape has a root, no bound on the LPs), on the
same draws, side by side; a stall there is stopped after ``--before-cap`` LP solves on one
grid and counted as such (its time is then a lower bound). ``--slice a:b`` runs draws a..b−1
of the same sequence (runs of a minute or less on a shared machine), ``--summarise`` prints
the figures of several such runs' ``--json`` files together.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

import numpy as np

import ballbeam.core.planning.time_optimal as time_optimal
from ballbeam.core.model import LinearModel, PhysicalConstants
from ballbeam.core.planning.arcs import (
    ArcPlan,
    _problem,
    arcs_from_grid,
    plan_arcs,
    replan,
    solve_arcs,
)
from ballbeam.core.planning.lag_hold import _params
from ballbeam.core.planning.time_optimal import plan_time_optimal
from ballbeam.errors import PlanningError

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
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


def law_requests(seeds: int = 2) -> dict[str, dict[str, float]]:
    """The law's own re-plans: every plan request of closed-loop runs from the paper's start
    on the nominal plant (``seeds`` noise seeds), solved again here and timed, split by what
    the answer was (a later-ending re-plan not taken needs the plan in force tracked to its
    end: the costliest answer)."""
    from ballbeam.config import load_config
    from ballbeam.core import replanning
    from ballbeam.plant_assembly import plant_parameters

    requests: list[replanning.PlanRequest] = []
    solve = replanning.solve_plan_request

    def recording(request: replanning.PlanRequest) -> replanning.PlanAnswer:
        requests.append(request)
        return solve(request)

    config = load_config(os.path.join(REPO, "configs", "paper.toml"))
    replanning.solve_plan_request = recording
    try:
        for seed in range(1, seeds + 1):
            replanning.run_closed_loop(
                plant_parameters(config), config.initial.state(), 3.0, seed=seed
            )
    finally:
        replanning.solve_plan_request = solve
    by_answer: dict[str, list[float]] = {}
    for request in requests:
        t0 = time.perf_counter()
        answer = solve(request)
        elapsed = time.perf_counter() - t0
        kind = request.kind if request.kind != "warm" else (
            "warm, kept" if "kept" in answer.counts else "warm, re-planned"
            if answer.plan is not None else "warm, missed"
        )
        by_answer.setdefault(kind, []).append(elapsed)
    by_answer["every request"] = [t for times in by_answer.values() for t in times]
    return {f"the law's {kind}": percentiles(times) for kind, times in by_answer.items()}


def warm(
    plan: ArcPlan, sigma: np.ndarray, seed: int, repairs: bool = True
) -> dict[str, float]:
    rng = np.random.default_rng(seed)
    times: list[float] = []
    misses = 0
    for elapsed_s in np.arange(0.0, plan.duration_s - 0.005, 0.005):
        state = plan.sample(np.array([elapsed_s])).states[0] + sigma * rng.normal(size=4)
        # a state beyond the limit cannot be planned from: keep the angle inside it
        state[0] = float(np.clip(state[0], -THETA_MAX, THETA_MAX))
        t0 = time.perf_counter()
        result = replan(plan, float(elapsed_s), state, repairs=repairs)
        times.append(time.perf_counter() - t0)
        misses += result is None
    return {**percentiles(times), "misses": misses}


COLD_VOLTAGE_V = 4.5
COLD_THETA_MAX = math.radians(52.0 - 0.3)


def cold_draws(seed: int, count: int) -> list[tuple[float, float, list[float]]]:
    """(ball gain, motor gain, start) for ``count`` seeded draws; every other start short."""
    rng = np.random.default_rng(seed)
    draws = []
    for i in range(count):
        ball, motor = rng.uniform(0.7, 1.3), rng.uniform(0.8, 1.2)
        short = i % 2 == 0
        reach_m, speed_m_s = (0.05, 0.075) if short else (0.2, 0.15)
        start = [
            math.radians(rng.uniform(-45.0, 45.0)),
            rng.uniform(-0.5, 0.5),
            rng.uniform(-speed_m_s, speed_m_s),
            rng.uniform(-reach_m, reach_m),
        ]
        draws.append((ball, motor, start))
    return draws


@contextmanager
def counted_lps(log: list[float]) -> Iterator[None]:
    """Every LP the grid planner solves, its grid step appended to ``log``."""
    solve = time_optimal._solve_steps

    def counted(grid: Any, *args: Any, **kwargs: Any) -> Any:
        log.append(grid.step_s)
        return solve(grid, *args, **kwargs)

    time_optimal._solve_steps = counted
    try:
        yield
    finally:
        time_optimal._solve_steps = solve


def plan_arcs_before(
    model: LinearModel, start: list[float], voltage_v: float, theta_max_rad: float, cap: int
) -> float:
    """The cold path as it was: the grid LP at 10, then 2, then 0.5 ms until the grid's own
    shape has a root (15 Newton steps); ``cap`` LPs a grid only to end a stall. Its duration."""
    problem = _problem(_params(model), start, 0.0, voltage_v, theta_max_rad)
    for step_s in (0.01, 0.002, 0.0005):
        grid = plan_time_optimal(
            model,
            np.array(problem.start),
            voltage_limit_v=voltage_v,
            theta_max_rad=theta_max_rad,
            step_s=step_s,
            max_lp_solves=cap,
        )
        guess = arcs_from_grid(
            grid.input_v, grid.grid_states, grid.step_s, voltage_v, theta_max_rad
        )
        solved = solve_arcs(problem, *guess)
        if solved is not None and math.fsum(solved[2]) <= grid.duration_s + 1e-9:
            return math.fsum(solved[2])
    raise PlanningError("no exact arcs near the grid plans")


Planner = Callable[[LinearModel, list[float]], float]


def cold_records(
    planners: dict[str, Planner],
    draws: list[tuple[float, float, list[float]]],
    first: int,
    cap: int,
) -> dict[str, list[dict[str, Any]]]:
    """One record per planner and draw: time, LP solves (and the finest grid), outcome. The
    planners take turns draw by draw, in alternating order, so that a shared machine's load
    falls on them alike."""
    records: dict[str, list[dict[str, Any]]] = {name: [] for name in planners}
    for index, (ball, motor, start) in enumerate(draws):
        model = LinearModel.from_constants(
            PhysicalConstants(), ball_gain_scale=ball, motor_gain_scale=motor
        )
        names = list(planners)
        for name in names if index % 2 == 0 else names[::-1]:
            lps: list[float] = []
            with counted_lps(lps):
                t0 = time.perf_counter()
                try:
                    duration_s: float | None = planners[name](model, start)
                    outcome = "ok"
                except PlanningError:
                    duration_s = None
                    # a stall stopped by the cap, or a refusal
                    most = max((lps.count(step) for step in set(lps)), default=0)
                    outcome = "stalled" if name == "before" and most >= cap else "failed"
                elapsed_s = time.perf_counter() - t0
            records[name].append(
                {
                    "draw": first + index,
                    "time_s": elapsed_s,
                    "lp_solves": len(lps),
                    "finest_lp_step_s": min(lps, default=math.nan),
                    "outcome": outcome,
                    "duration_s": duration_s,
                }
            )
    return records


def cold_summary(name: str, records: list[dict[str, Any]]) -> str:
    ms = np.array([r["time_s"] for r in records]) * 1e3
    lps = np.array([r["lp_solves"] for r in records])
    outcomes = [r["outcome"] for r in records]
    fine = sum(1 for r in records if r["finest_lp_step_s"] < 0.002 - 1e-12)
    return (
        f"{name:8} {ms.size:5d} {outcomes.count('ok'):5d} {outcomes.count('failed'):6d} "
        f"{outcomes.count('stalled'):7d} {np.percentile(ms, 50):8.1f} {np.percentile(ms, 99):8.1f} "
        f"{np.max(ms):8.1f} {int(np.median(lps)):6d} {int(np.max(lps)):6d} {fine:8d}"
    )


def cold_report(results: dict[str, list[dict[str, Any]]]) -> None:
    print(
        f"{'path':8} {'draws':>5} {'found':>5} {'failed':>6} {'stalled':>7} {'p50 ms':>8} "
        f"{'p99 ms':>8} {'max ms':>8} {'LPs p50':>6} {'LPs max':>6} {'<2 ms LP':>8}"
    )
    for name, records in results.items():
        print(cold_summary(name, records))
    if "before" in results and "after" in results:
        before = {r["draw"]: r for r in results["before"]}
        both = [
            (before[r["draw"]]["duration_s"], r["duration_s"])
            for r in results["after"]
            if r["draw"] in before
            and r["duration_s"] is not None
            and before[r["draw"]]["duration_s"] is not None
        ]
        if both:
            diff_ms = np.array([a - b for b, a in both]) * 1e3
            print(
                f"where both found a plan ({len(both)}): after − before duration "
                f"min {diff_ms.min():+.3f} ms, max {diff_ms.max():+.3f} ms"
            )


def positive(text: str) -> float:
    """A positive finite number (argparse reports a bad one in one line and exits 2)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not 0.0 < value < math.inf:
        raise argparse.ArgumentTypeError(f"expected a positive number, got {text!r}")
    return value


def draw_slice(text: str) -> tuple[int, int]:
    """``a:b`` with 0 ≤ a < b (argparse reports a bad one in one line and exits 2)."""
    try:
        first, stop = (int(v) for v in text.split(":"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a:b, got {text!r}") from None
    if not 0 <= first < stop:
        raise argparse.ArgumentTypeError(f"expected 0 <= a < b, got {text!r}")
    return first, stop


def cold_main(args: argparse.Namespace) -> None:
    draws = cold_draws(args.seed, args.cold_draws)
    first, stop = args.slice or (0, len(draws))
    draws = draws[first:stop]
    planners: dict[str, Planner] = {}
    voltage_v = args.voltage_v
    if args.before:
        planners["before"] = lambda model, start: plan_arcs_before(
            model, start, voltage_v, COLD_THETA_MAX, args.before_cap
        )
    planners["after"] = lambda model, start: (
        plan_arcs(model, start, voltage_limit_v=voltage_v, theta_max_rad=COLD_THETA_MAX).duration_s
    )
    results = cold_records(planners, draws, first, args.before_cap)
    print(
        f"cold plans, draw seed {args.seed}, draws {first}..{first + len(draws) - 1}, "
        f"drive {voltage_v} V, load average {os.getloadavg()[0]:.1f} (2 cores)"
    )
    cold_report(results)
    if args.json:
        with open(args.json, "x", encoding="utf-8") as out:
            json.dump(results, out, indent=1)


def summarise(paths: list[str]) -> None:
    results: dict[str, list[dict[str, Any]]] = {}
    for path in paths:
        with open(path, encoding="utf-8") as source:
            for name, records in json.load(source).items():
                results.setdefault(name, []).extend(records)
    print(f"cold plans, {len(paths)} runs together")
    cold_report(results)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--json", help="write the figures to this file")
    parser.add_argument("--repeat", type=int, default=5, help="cold plans to time")
    parser.add_argument("--cold-draws", type=int, help="cold plans from this many random draws")
    parser.add_argument("--seed", type=int, default=1, help="draw seed for --cold-draws")
    parser.add_argument("--slice", type=draw_slice, help="a:b, the draws of the sequence to run")
    parser.add_argument("--before", action="store_true", help="also the cold path as it was")
    parser.add_argument(
        "--voltage-v", type=positive, default=COLD_VOLTAGE_V, help="the plans' drive limit"
    )
    parser.add_argument("--before-cap", type=int, default=30, help="LPs a grid, before")
    parser.add_argument("--summarise", nargs="+", help="--json files of cold runs")
    args = parser.parse_args()
    if args.json and os.path.exists(args.json):
        parser.error(f"--json {args.json} exists (it would not be overwritten)")
    if args.summarise:
        try:
            summarise(args.summarise)
        except (OSError, ValueError, KeyError, TypeError) as error:
            print(f"replan: --summarise: not the --json of a cold run: {error}", file=sys.stderr)
            sys.exit(2)
        return
    if args.cold_draws:
        if args.cold_draws < 1:
            parser.error("--cold-draws must be at least 1")
        cold_main(args)
        return
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
        # the law's re-plan while the ball is near its plan: no structure with arcs added
        # (it would not take one), a miss keeps the plan
        "warm perturbed, as the law": warm(
            plan, np.array([1e-4, 2.5e-3, 1e-4, 5e-5]), 2, repairs=False
        ),
        "warm tap": warm(plan, np.array([0.0, 0.0, 0.05, 0.0]), 3),
        **law_requests(),
    }
    print(f"paper start: arcs {plan.duration_s:.6f} s")
    print(f"{'case':34} {'n':>5} {'p50 ms':>9} {'p99 ms':>9} {'max ms':>9} {'misses':>7}")
    for name, row in figures.items():
        print(
            f"{name:34} {row['n']:5d} {row['p50_ms']:9.3f} {row['p99_ms']:9.3f} "
            f"{row['max_ms']:9.3f} {row.get('misses', 0):7d}"
        )
    if args.json:
        with open(args.json, "x", encoding="utf-8") as out:
            json.dump(figures, out, indent=2)


if __name__ == "__main__":
    main()
