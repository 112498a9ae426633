"""Control quality over the sets of issue 12, offline: rest against the true minimum time,
chatter (input total variation, one-period steps, dither) and the servo angle at every
physics step.

    .venv/bin/python bench/control_quality.py                 # all sets (a few minutes)
    .venv/bin/python bench/control_quality.py --quick         # fewer seeds
    .venv/bin/python bench/control_quality.py --config configs/paths/rate_limited_9325.toml
    .venv/bin/python bench/control_quality.py --set tracker.r=0.1 --only paper --json out.json
    .venv/bin/python bench/control_quality.py --bus --processes 1   # over the bus (~25 min)

Sets: the paper start over 20 noise seeds; 30 seeded random starts (|θ0| <= 52°, |x0| <= 0.2 m);
starts on both angle limits; robustness (ball gain 0.8/1.2, motor gain 0.9/1.1, dead zone
0.4 V, nonlinear ball, 5x noise). Every run lasts T* + 3 s, T* the minimum time from its start.
Besides the issue's dither (the last second), "settle sc" counts sign changes of u a second in
the 1.5 s after the plan, while the ball is caught, against the same 5 Hz bound.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
import tempfile
import time
from dataclasses import dataclass
from functools import cache, partial
from multiprocessing import Pool
from pathlib import Path
from typing import Any

import numpy as np

from ballbeam.assembly import minimum_time_s, run_offline
from ballbeam.config import Config, load_config
from ballbeam.core.metrics import sign_changes

REPO = Path(__file__).resolve().parents[1]
PAPER = str(REPO / "configs" / "paper.toml")
EXTRA_S = 3.0  # each run lasts T* + this
SETTLE_WINDOW_S = 1.5  # "settle sc": sign changes of u a second in this window after the plan
RANDOM_STARTS_SEED = 12
LIMIT_START_POSITION_M = 0.195

# Targets of issue 12 (nominal sets; robustness: rest_ratio <= 1.4 and no chatter).
TARGET_MEDIAN_REST = 1.05
TARGET_WORST_REST = 1.10
TARGET_ROBUST_REST = 1.4
TARGET_TV = 3.0
TARGET_STEP_V = 2.0
TARGET_DITHER_HZ = 5.0
THETA_LIMIT_DEG = 52.0

ROBUSTNESS = {
    "ball_gain_0.8": ["plant.ball_gain_scale=0.8"],
    "ball_gain_1.2": ["plant.ball_gain_scale=1.2"],
    "motor_gain_0.9": ["plant.motor_gain_scale=0.9"],
    "motor_gain_1.1": ["plant.motor_gain_scale=1.1"],
    "deadzone_0.4": ["plant.deadzone_v=0.4"],
    "nonlinear_ball": ["plant.nonlinear_ball=true"],
    "noise_5x": ["plant.position_noise_m=1e-3"],
}


@dataclass(frozen=True)
class Case:
    group: str  # the set the run belongs to
    label: str
    config: str
    overrides: tuple[str, ...]
    start: tuple[float, float]  # θ0 [deg], x0 [m]
    seed: int


def start_overrides(theta_deg: float, position_m: float) -> list[str]:
    return [f"initial.theta_deg={theta_deg!r}", f"initial.ball_position_m={position_m!r}"]


@cache
def cached_minimum_time_s(config: str, start: tuple[float, float]) -> float | None:
    """T* per start (the base config's model and limits; plant variations do not change it)."""
    return minimum_time_s(load_config(config, start_overrides(*start)))


def random_starts(count: int) -> list[tuple[float, float]]:
    rng = np.random.default_rng(RANDOM_STARTS_SEED)
    return [
        (round(float(rng.uniform(-52.0, 52.0)), 3), round(float(rng.uniform(-0.2, 0.2)), 4))
        for _ in range(count)
    ]


def build_cases(config: str, extra: list[str], quick: bool, only: set[str] | None) -> list[Case]:
    paper = (-52.0, 0.195)
    cases: list[Case] = []

    def add(group: str, label: str, start: tuple[float, float], seed: int, more: list[str]) -> None:
        if only is None or group in only or group.split(":")[0] in only:
            cases.append(Case(group, label, config, tuple(extra + more), start, seed))

    for seed in range(1, 6 if quick else 21):
        add("paper", f"seed {seed}", paper, seed, [])
    for index, start in enumerate(random_starts(10 if quick else 30)):
        add("random", f"start {index}", start, 100 + index, [])
    limit_starts = [(theta, x) for theta in (-52.0, 52.0) for x in (-0.195, 0.195)]
    for start in limit_starts:
        for seed in range(1, 2 if quick else 4):
            add("limits", f"{start}", start, seed, [])
    for name, more in ROBUSTNESS.items():
        for seed in range(1, 3 if quick else 6):
            add(f"robust:{name}", f"seed {seed}", paper, seed, more)
    return cases


@dataclass(frozen=True)
class CaseRun:
    """What one run gives the bench, offline or over the bus."""

    metrics: dict[str, Any]  # the run's summary metrics (rest_ratio, input_tv_ratio, ...)
    time_s: np.ndarray  # command instants
    voltage_v: np.ndarray  # the commands
    plan_end_s: float


def run_case_offline(config: Config) -> CaseRun:
    result = run_offline(config)
    return CaseRun(
        result.metrics.as_dict(), result.trace.time_s, result.trace.voltage_v,
        result.design.plan_duration_s,
    )


def run_case_bus(config_path: str, overrides: list[str]) -> CaseRun:
    """``ballbeam run`` in lock-step (two processes on a private ff11:: group), its log read
    back; the plan's end from the design the run recorded."""
    from ballbeam.evaluation.summary import run_series, summarise
    from ballbeam.logs import design_record
    from ballbeam.logs.reader import read_log
    from ballbeam.runtime.launcher import launch_run

    with tempfile.TemporaryDirectory(prefix="control-quality-") as directory:
        result = launch_run(
            config_path, [*overrides, "run.mode='lockstep'", f"run.log_dir='{directory}'"]
        )
        run_log = read_log(result.log_path)
    series = run_series(run_log)
    design = design_record.decode_design(
        run_log.attachments[design_record.ATTACHMENT_NAME], str(result.log_path)
    )
    return CaseRun(
        summarise(run_log), series.cycle_time_s, series.voltage_v, design.plan_duration_s
    )


def run_case(case: Case, bus: bool = False) -> dict[str, Any]:
    t_star = cached_minimum_time_s(case.config, case.start)
    duration_s = (t_star if t_star is not None else 2.0) + EXTRA_S
    overrides = [
        *start_overrides(*case.start),
        f"plant.seed={case.seed}",
        f"run.duration_s={duration_s:.3f}",
        *case.overrides,
    ]
    run = (
        run_case_bus(case.config, overrides) if bus
        else run_case_offline(load_config(case.config, overrides))
    )
    metrics = run.metrics
    # Dither while the plan runs (the dither_hz only looks at the last second): on the
    # limit arcs u_d is 0 and any sign flip of u is the loop's own.
    during_plan = run.time_s < run.plan_end_s
    plan_sign_changes_hz = sign_changes(run.voltage_v[during_plan]) / max(run.plan_end_s, 1e-3)
    # ... and in the 1.5 s after it, while the ball is caught (the firm rest gains fade there).
    after_plan = (run.time_s >= run.plan_end_s) & (
        run.time_s < run.plan_end_s + SETTLE_WINDOW_S
    )
    settle_sign_changes_hz = sign_changes(run.voltage_v[after_plan]) / SETTLE_WINDOW_S
    rest_ratio = metrics["rest_ratio"]
    return {
        "settle_sign_changes_hz": settle_sign_changes_hz,
        "plan_sign_changes_hz": plan_sign_changes_hz,
        "group": case.group,
        "label": case.label,
        "start": case.start,
        "seed": case.seed,
        "t_star_s": t_star,
        "plan_s": run.plan_end_s,
        "rest_time_s": metrics["rest_time_s"],
        "rest_ratio": rest_ratio if rest_ratio is not None else math.inf,
        "input_tv_ratio": metrics["input_tv_ratio"],
        "dither_hz": metrics["dither_hz"],
        "largest_step_v": metrics["largest_step_v"],
        "max_abs_theta_deg": metrics["max_abs_theta_deg"],
        "settle_time_s": metrics["settle_time_s"],
        "frames_rejected": metrics.get("frames_rejected", 0),
    }


def summarise_group(rows: list[dict[str, Any]]) -> dict[str, Any]:
    def worst(key: str) -> dict[str, Any]:
        return max(rows, key=lambda row: row[key])

    rest = [row["rest_ratio"] for row in rows]
    return {
        "runs": len(rows),
        "rest_median": statistics.median(rest),
        "rest_worst": max(rest),
        "rest_worst_case": worst("rest_ratio")["label"],
        "tv_worst": worst("input_tv_ratio")["input_tv_ratio"],
        "tv_median": statistics.median(row["input_tv_ratio"] for row in rows),
        "dither_worst_hz": worst("dither_hz")["dither_hz"],
        "plan_sc_worst_hz": worst("plan_sign_changes_hz")["plan_sign_changes_hz"],
        "settle_sc_worst_hz": worst("settle_sign_changes_hz")["settle_sign_changes_hz"],
        "step_worst_v": worst("largest_step_v")["largest_step_v"],
        "theta_max_deg": worst("max_abs_theta_deg")["max_abs_theta_deg"],
        "theta_max_case": worst("max_abs_theta_deg")["label"],
    }


def verdict(group: str, summary: dict[str, Any]) -> str:
    failures = []
    if group.startswith("robust"):
        if summary["rest_worst"] > TARGET_ROBUST_REST:
            failures.append("rest")
    else:
        if summary["rest_median"] > TARGET_MEDIAN_REST or summary["rest_worst"] > TARGET_WORST_REST:
            failures.append("rest")
    if summary["tv_worst"] > TARGET_TV:
        failures.append("tv")
    if summary["step_worst_v"] > TARGET_STEP_V:
        failures.append("step")
    if summary["dither_worst_hz"] > TARGET_DITHER_HZ:
        failures.append("dither")
    if summary["settle_sc_worst_hz"] > TARGET_DITHER_HZ:
        failures.append("settle dither")
    if summary["theta_max_deg"] > THETA_LIMIT_DEG + 1e-9:
        failures.append("theta")
    return "ok" if not failures else "FAIL " + ",".join(failures)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", default=PAPER)
    parser.add_argument("--set", dest="overrides", action="append", default=[])
    parser.add_argument("--quick", action="store_true", help="fewer seeds and starts")
    parser.add_argument("--only", help="comma-separated sets: paper,random,limits,robust")
    parser.add_argument("--json", type=Path, help="write every run's figures here")
    parser.add_argument("--processes", type=int, default=2)
    parser.add_argument(
        "--bus", action="store_true",
        help="each run over the bus in lock-step (ballbeam run: two processes a run)",
    )
    args = parser.parse_args(argv)
    only = set(args.only.split(",")) if args.only else None
    cases = build_cases(args.config, args.overrides, args.quick, only)
    started = time.perf_counter()
    with Pool(args.processes) as pool:
        rows = pool.map(partial(run_case, bus=args.bus), cases, chunksize=1)
    groups: dict[str, list[dict[str, Any]]] = {}
    for row in rows:
        groups.setdefault(row["group"], []).append(row)
    header = (
        f"{'set':<22}{'runs':>5}{'rest med':>10}{'rest max':>10}{'TV med':>8}{'TV max':>8}"
        f"{'dither':>8}{'plan sc':>8}{'settle sc':>10}{'step V':>8}{'|θ| max':>9}"
        "  verdict / worst rest"
    )
    where = "over the bus, lock-step" if args.bus else "offline"
    print(f"config {args.config} {' '.join(args.overrides)} ({where})")
    print(header)
    summaries = {}
    for group, group_rows in groups.items():
        s = summarise_group(group_rows)
        summaries[group] = s
        print(
            f"{group:<22}{s['runs']:>5}{s['rest_median']:>10.3f}{s['rest_worst']:>10.3f}"
            f"{s['tv_median']:>8.2f}{s['tv_worst']:>8.2f}{s['dither_worst_hz']:>8.1f}"
            f"{s['plan_sc_worst_hz']:>8.1f}{s['settle_sc_worst_hz']:>10.1f}"
            f"{s['step_worst_v']:>8.2f}{s['theta_max_deg']:>9.3f}  {verdict(group, s)}"
            f" / {s['rest_worst_case']}"
        )
    print(f"({len(rows)} runs in {time.perf_counter() - started:.0f} s)")
    if args.json is not None:
        args.json.write_text(json.dumps({"summary": summaries, "runs": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
