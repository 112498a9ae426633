"""Issue 27's second candidate (``core/replanning.py``) on the emulated plant, offline: rest
against each plant's own floor, the servo angle at every physics step, the command's total
variation against the plan's, dither, and plots.

    .venv/bin/python bench/replanning_candidate.py --set plant.ball_gain_scale=1.2 --plot x.png
    .venv/bin/python bench/replanning_candidate.py --matrix --draw-seed 11 --seeds 2

A thin driver: the controller and the closed loop are ``ballbeam.core.replanning``; the
floor is ``core.floor`` (via ``assembly.plant_floor``); the figures ``core.metrics``.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
from multiprocessing import Pool
from pathlib import Path
from typing import Any

import numpy as np

from ballbeam.assembly import plant_floor
from ballbeam.config import Config, load_config
from ballbeam.core.metrics import (
    dither_hz,
    first_entry_time,
    input_tv_ratio,
    inside_from,
    outside_rest_band,
)
from ballbeam.core.replanning import ClosedLoopRun, Settings, run_closed_loop
from ballbeam.errors import BallbeamError
from ballbeam.plant_assembly import plant_parameters

REPO = Path(__file__).resolve().parents[1]
PAPER = str(REPO / "configs" / "paper.toml")
EXTRA_S = 8.0


def _after_tap(config: Config, run: ClosedLoopRun, target: float) -> dict[str, Any]:
    """Rest after the run's last tap against the plant's own floor from the state the tap left
    (the true state: the tap is the plant's)."""
    tap_s = max(time_s for time_s, _ in config.plant.disturbances)
    k = int(np.searchsorted(run.time_s, tap_s))
    state = run.states[k]
    floor = plant_floor(
        config.model_copy(update={"initial": config.initial.model_copy(update={
            "theta_deg": math.degrees(state[0]), "theta_rate_deg_s": math.degrees(state[1]),
            "ball_velocity_m_s": float(state[2]), "ball_position_m": float(state[3]),
        })}),
        target,
    )
    outside = outside_rest_band(run.states[k:], target)
    rest = inside_from(run.time_s[k:], outside)
    floor_s = floor.time_s if floor is not None else math.nan
    return {
        "tap_floor_s": floor_s,
        "tap_rest_floor": (rest - tap_s) / floor_s if rest is not None else math.inf,
    }


def one_run(
    overrides: list[str], extra_s: float = EXTRA_S, settings: dict[str, Any] | None = None
) -> tuple[dict[str, Any], ClosedLoopRun]:
    config = load_config(PAPER, overrides)
    target = config.task.target_m
    floor = plant_floor(config, target)
    floor_s = floor.time_s if floor is not None else math.nan
    taps = config.plant.disturbances
    duration_s = max([floor_s, *(time_s for time_s, _ in taps)]) + extra_s
    params = plant_parameters(config)
    run = run_closed_loop(
        params,
        config.initial.state(),
        duration_s,
        seed=config.plant.seed,
        substeps=config.plant.physics_substeps,
        targets=((0.0, target),),
        settings=Settings(
            encoder_step_rad=params.encoder_step_rad,
            adc_step_m=params.adc_step_m,
            **(settings or {}),
        ),
    )
    until = run.time_s < taps[0][0] if taps else np.ones(len(run.time_s), dtype=bool)
    outside = outside_rest_band(run.states[until], target)
    rest_s = inside_from(run.time_s[until], outside)
    entry_s = first_entry_time(run.time_s[until], run.states[until], target)
    c = run.controller
    ident = c.identified
    row = {
        "overrides": overrides,
        "floor_s": floor_s,
        "rest_s": rest_s,
        "rest_floor": rest_s / floor_s if rest_s is not None else math.inf,
        "relapse_ms": (rest_s - entry_s) * 1e3 if rest_s is not None and entry_s else math.inf,
        "theta_deg": math.degrees(float(run.peak_theta_rad.max())),
        "tv": input_tv_ratio(run.command_v, run.feedforward_v),
        "dither_hz": dither_hz(run.time_s, run.command_v),
        "alpha_ratio": ident.alpha / params.alpha,
        "gamma_ratio": ident.gamma / params.gamma,
        "deadzone_v": ident.deadzone_v,
        "deadzone_true_v": params.deadzone_v,
        "deadzone_std_v": ident.deadzone_std_v,
        "replans": c.replans,
        "missed": c.missed,
        "kept": c.kept_plans,
        "cold": c.cold_plans,
        "near": c.near_plans,
        "jumps": c.jumps,
        "drive_limit_v": c.design.drive_limit_v,
    }
    if taps:
        row.update(_after_tap(config, run, target))
    return row, run


def plot(run: ClosedLoopRun, path: str, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(4, 1, figsize=(11, 10), sharex=True)
    t = run.time_s
    axes[0].plot(t, np.degrees(run.states[:, 0]), label="θ")
    axes[0].plot(t, np.degrees(run.reference[:, 0]), "--", label="plan")
    axes[0].set_ylabel("servo angle [deg]")
    axes[0].legend()
    axes[1].plot(t, 1e3 * (run.states[:, 3] - run.target_m))
    axes[1].plot(t, 1e3 * (run.reference[:, 3] - run.target_m), "--")
    axes[1].set_ylabel("x − target [mm]")
    axes[1].set_ylim(-5, 5)
    axes[2].plot(t, run.command_v, label="command")
    axes[2].plot(t, run.feedforward_v, "--", label="plan")
    axes[2].set_ylabel("[V]")
    axes[2].legend()
    axes[3].plot(t, run.command_v)
    axes[3].set_ylim(-1, 1)
    axes[3].set_ylabel("command, zoom [V]")
    axes[3].set_xlabel("time [s]")
    axes[0].set_title(title)
    fig.tight_layout()
    fig.savefig(path, dpi=70)


def _row(args: tuple[list[str], dict[str, Any]]) -> dict[str, Any]:
    overrides, settings = args
    try:
        return one_run(overrides, settings=settings)[0]
    except BallbeamError as error:
        return {"overrides": overrides, "error": str(error), "rest_floor": math.inf}


def parse_settings(items: list[str]) -> dict[str, Any]:
    """``name=value`` pairs for core.replanning.Settings (values as JSON)."""
    known = set(Settings.__dataclass_fields__)
    parsed: dict[str, Any] = {}
    for item in items:
        name, _, value = item.partition("=")
        if name not in known:
            raise BallbeamError(f"--setting {item!r}: no such setting")
        try:
            parsed[name] = json.loads(value)
        except json.JSONDecodeError as error:
            raise BallbeamError(f"--setting {item!r}: the value is not JSON") from error
        if isinstance(parsed[name], list):
            parsed[name] = tuple(parsed[name])
    return parsed


def print_row(row: dict[str, Any]) -> None:
    case = " ".join(o for o in row["overrides"] if "seed" not in o)
    if "error" in row:
        print(f"ERROR {row['error']}  {case}")
        return
    tap = f" tap {row['tap_rest_floor']:.3f}" if "tap_rest_floor" in row else ""
    print(
        f"{row['rest_floor']:7.3f} {row['floor_s']:6.3f} {row['relapse_ms']:7.0f} "
        f"{row['theta_deg']:7.3f} {row['tv']:5.2f} {row['dither_hz']:5.1f} "
        f"α {row['alpha_ratio']:.3f} γ {row['gamma_ratio']:.3f} "
        f"d {row['deadzone_v']:.3f}±{row['deadzone_std_v']:.3f} ({row['deadzone_true_v']}) "
        f"U {row['drive_limit_v']:.2f} plans {row['replans']}/{row['missed']}/{row['kept']}/"
        f"{row['cold']}/{row['near']} jumps {row['jumps']}{tap}  {case}"
    )


HEADER = (
    "rest/fl floor s relapse  max|θ|    TV  dith  identified (α, γ as true ratios; d ± σ "
    "(true)); plan drive; re-plans/missed/kept/cold/near; speed jumps found"
)


def _start(rng: np.random.Generator, kind: str) -> list[str]:
    if kind == "paper":
        return []
    short = "short" in kind
    theta = rng.uniform(-25, 25) if short else rng.uniform(-50, 50)
    position = rng.uniform(-0.04, 0.04) if short else rng.uniform(-0.18, 0.18)
    speed = rng.choice((-1, 1)) * rng.uniform(0.05, 0.12) if "rolling" in kind else 0.0
    return [
        f"initial.theta_deg={theta:.3f}", f"initial.ball_position_m={position:.4f}",
        f"initial.ball_velocity_m_s={speed:.4f}",
    ]


def matrix(draw_seed: int, seeds: int) -> list[list[str]]:
    """An untuned subset of issue 27's item 3: starts drawn with ``draw_seed`` (short, rolling,
    both, any; the paper's) on plants across the ranges, other targets and a tap, ``seeds``
    noise seeds each."""
    rng = np.random.default_rng(draw_seed)
    b, m, d = "plant.ball_gain_scale", "plant.motor_gain_scale", "plant.deadzone_v"
    plants = [
        [], [f"{b}=0.7"], [f"{b}=0.85"], [f"{b}=1.15"], [f"{b}=1.3"],
        [f"{m}=0.8"], [f"{m}=0.9"], [f"{m}=1.1"], [f"{m}=1.2"],
        [f"{d}=0.0"], [f"{d}=0.25"], [f"{d}=0.4"],
        ["plant.nonlinear_ball=true", f"{b}=1.1"], ["plant.position_noise_m=1e-3"],
        [f"{b}=1.2", f"{m}=0.85", f"{d}=0.3"], [f"{b}=1.3", f"{m}=0.8", f"{d}=0.4"],
        [f"{b}=0.7", f"{m}=1.2", f"{d}=0.0"],
    ]
    kinds = ("paper", "short", "rolling", "short rolling", "any")
    cases = [[*_start(rng, kinds[i % 5]), *plant] for i, plant in enumerate(plants)]
    for kind in ("any", "short", "paper"):
        cases.append([*_start(rng, kind), f"task.target_m={rng.uniform(-0.15, 0.15):.4f}"])
    for kind in ("paper", "short"):
        tap_s = rng.uniform(2.5, 3.5)
        speed = rng.choice((-1, 1)) * rng.uniform(0.02, 0.08)
        cases.append([*_start(rng, kind), f"plant.disturbances=[[{tap_s:.3f}, {speed:.4f}]]"])
    return [
        [*case, f"plant.seed={seed + 100 * draw_seed}"]
        for case in cases
        for seed in range(1, seeds + 1)
    ]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--set", action="append", default=[])
    parser.add_argument("--plot")
    parser.add_argument("--matrix", action="store_true")
    parser.add_argument("--draw-seed", type=int, default=1)
    parser.add_argument("--seeds", type=int, default=2)
    parser.add_argument("--processes", type=int, default=2)
    parser.add_argument("--setting", action="append", default=[],
                        help="a controller setting, name=JSON value (core.replanning.Settings)")
    args = parser.parse_args(argv)
    try:
        settings = parse_settings(args.setting)
    except BallbeamError as error:
        print(f"replanning_candidate: {error}", file=sys.stderr)
        return 2
    print(HEADER)
    if not args.matrix:
        try:
            row, run = one_run(args.set, settings=settings)
        except BallbeamError as error:
            print(f"replanning_candidate: {error}", file=sys.stderr)
            return 2
        print_row(row)
        if args.plot:
            plot(run, args.plot, " ".join(args.set) or "nominal")
        return 0
    cases = matrix(args.draw_seed, args.seeds)
    with Pool(args.processes) as pool:
        rows = []
        for row in pool.imap(_row, [(case, settings) for case in cases]):
            print_row(row)
            rows.append(row)
    ratios = [r["rest_floor"] for r in rows]
    finite = [r for r in rows if "error" not in r]
    taps = [r["tap_rest_floor"] for r in finite if "tap_rest_floor" in r]
    if taps:
        listed = ", ".join(f"{x:.3f}" for x in taps)
        print(f"after the taps: rest / floor from the state the tap left: {listed}")
    print(
        f"runs {len(rows)}: rest/floor median {statistics.median(ratios):.3f} worst "
        f"{max(ratios):.3f}; max|θ| {max(r['theta_deg'] for r in finite):.3f}°; TV worst "
        f"{max(r['tv'] for r in finite):.2f}; dither worst "
        f"{max(r['dither_hz'] for r in finite):.1f} Hz; relapse worst "
        f"{max(r['relapse_ms'] for r in finite):.0f} ms; over 1.10: "
        f"{sum(x > 1.10 for x in ratios)}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
