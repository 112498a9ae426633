"""Control at each true plant's own limit (issue 27, item 3): rest against the plant's own floor,
chatter, the servo angle at every physics step and relapse, over seeded starts and plants.

    .venv/bin/python bench/control_quality.py                  # the whole matrix (about an hour)
    .venv/bin/python bench/control_quality.py --quick          # a representative subset
    .venv/bin/python bench/control_quality.py --draw-seed 7    # starts the controller never saw
    .venv/bin/python bench/control_quality.py --only nominal,deadzone:0.25 --json out.json
    .venv/bin/python bench/control_quality.py --config my.toml --set tracker.r=0.1
    .venv/bin/python bench/control_quality.py --target 0.0 --target -0.1   # needs [task]

Sets: ``nominal`` (the drawn starts on the design plant) and one set per plant in range:
``ball_gain:K`` (0.7–1.3), ``motor_gain:K`` (0.8–1.2), ``deadzone:V`` (0–0.4 V),
``nonlinear:K`` (the nonlinear ball at ball gain 0.9–1.1), ``noise_5x`` and ``corners:...``
(the range's corners, where a guard sized for the design plant is weakest). ``--only`` takes
set names or families. Every run lasts T* + 8 s (T* the design model's minimum time).

The starts are drawn with ``--draw-seed`` and stratified: a fifth each short (T* < 0.7 s) at
rest, rolling (0.05 ≤ |v0| ≤ 0.15 m/s) and both, the rest anywhere at rest; the paper's start
comes first in every plant set. Each run's floor is the true plant's own minimum time
(ballbeam.core.floor: its α, γ, 5 V less its dead zone, zero margins; for the nonlinear ball
the linear model with the chord gain γ·sin 52°/52°, see that module for why).

Runs offline (``run_offline`` with designs shared between runs that share them), or over the
bus in lock-step with ``--bus`` (a run's two processes each; much slower).
"""

from __future__ import annotations

import argparse
import json
import math
import multiprocessing
import statistics
import sys
import tempfile
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import asdict, dataclass, replace
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from ballbeam.assembly import (
    controller_design,
    design_key,
    plant_floor,
    run_offline_with,
)
from ballbeam.config import Config, load_config
from ballbeam.core.floor import own_floor
from ballbeam.core.metrics import first_entry_time, inside_from, outside_rest_band
from ballbeam.errors import BallbeamError
from ballbeam.plant_assembly import design_model

REPO = Path(__file__).resolve().parents[1]
PAPER = str(REPO / "configs" / "paper.toml")
EXTRA_S = 8.0  # each run lasts T* + this: long enough to show a relapse
SHORT_T_STAR_S = 0.7
ROLLING_SPEED_M_S = (0.05, 0.15)
STRATUM_SHARE = 0.2  # of the drawn starts: short, rolling, short and rolling; the rest "any"
DRAW_BATCH = 12  # candidates drawn at once for a stratum (T* decides which are kept)
MAX_DRAWS = 400
GROUP_RUNS = 10  # runs that share a design go to a worker in batches of at most this

# Issue 27, item 3.
BOUNDS = {
    "rest_median": 1.03,  # rest / own floor, median over a set
    "rest_worst": 1.10,  # ... and worst
    "tv": 3.0,  # Σ|Δu| / Σ|Δu_d|
    "dither_hz": 5.0,  # sign changes of u a second, last second
    "step_v": 2.0,  # largest one-period |Δu| off the plan's own switches
    "theta_deg": 52.0,  # |θ| at every physics step
    "relapse_s": 0.05,  # rest less the first entry into the rest band
}


@dataclass(frozen=True)
class Start:
    kind: str  # paper | any | short | rolling | short rolling
    theta_deg: float
    position_m: float
    velocity_m_s: float
    t_star_s: float  # the design model's minimum time to the target (the run's length)

    def overrides(self) -> list[str]:
        return [
            f"initial.theta_deg={self.theta_deg!r}",
            f"initial.ball_position_m={self.position_m!r}",
            f"initial.ball_velocity_m_s={self.velocity_m_s!r}",
        ]


@dataclass(frozen=True)
class Case:
    set_name: str
    start_index: int  # in the draw; -1 for the paper's start
    start: Start
    seed: int
    target_m: float
    overrides: tuple[str, ...]  # the run's whole --set list past the base config


def plant_sets() -> dict[str, list[str]]:
    """Every plant of the matrix: its set name and its overrides."""
    sets: dict[str, list[str]] = {"nominal": []}
    for k in (0.7, 0.8, 0.9, 1.1, 1.2, 1.3):
        sets[f"ball_gain:{k}"] = [f"plant.ball_gain_scale={k}"]
    for k in (0.8, 0.85, 0.9, 1.1, 1.15, 1.2):
        sets[f"motor_gain:{k}"] = [f"plant.motor_gain_scale={k}"]
    for v in (0.0, 0.2, 0.25, 0.3, 0.4):
        sets[f"deadzone:{v}"] = [f"plant.deadzone_v={v}"]
    for k in (0.9, 1.0, 1.1):
        sets[f"nonlinear:{k}"] = ["plant.nonlinear_ball=true", f"plant.ball_gain_scale={k}"]
    sets["noise_5x"] = ["plant.position_noise_m=1e-3"]
    corners = [(b, m, d) for b in (0.7, 1.3) for m in (0.8, 1.2) for d in (0.0, 0.4)]
    for b, m, d in [*corners, (1.2, 0.85, 0.3)]:  # the last: issue 27's 52.006° plant
        sets[f"corners:b{b}m{m}d{d}"] = [
            f"plant.ball_gain_scale={b}", f"plant.motor_gain_scale={m}", f"plant.deadzone_v={d}"
        ]
    return sets


def selected(name: str, only: set[str] | None) -> bool:
    return only is None or name in only or name.split(":")[0] in only


# --- starts ---------------------------------------------------------------------------------


def design_t_star_s(config: Config, target_m: float) -> float | None:
    """T*: the design model's minimum time to rest at the target, full limits, no dead zone
    (equal to ``assembly.minimum_time_s`` at target 0)."""
    try:
        return own_floor(
            design_model(config),
            config.initial.state(),
            voltage_limit_v=config.limits.voltage_v,
            deadzone_v=0.0,
            theta_max_rad=config.limits.theta_rad,
            step_s=config.controller.period_s,
            target_m=target_m,
        ).time_s
    except BallbeamError:
        return None


def _candidate_t_star(args: tuple[str, tuple[str, ...], Start, float]) -> float | None:
    config_path, extra, start, target_m = args
    return design_t_star_s(load_config(config_path, [*extra, *start.overrides()]), target_m)


def _draw(rng: np.random.Generator, kind: str) -> Start:
    short = "short" in kind
    theta_deg = rng.uniform(-25.0, 25.0) if short else rng.uniform(-52.0, 52.0)
    position_m = rng.uniform(-0.04, 0.04) if short else rng.uniform(-0.2, 0.2)
    velocity_m_s = 0.0
    if "rolling" in kind:
        velocity_m_s = rng.choice((-1.0, 1.0)) * rng.uniform(*ROLLING_SPEED_M_S)
    return Start(
        kind,
        round(float(theta_deg), 3),
        round(float(position_m), 4),
        round(float(velocity_m_s), 4),
        math.nan,
    )


def draw_starts(
    count: int, draw_seed: int, config_path: str, extra: Sequence[str], target_m: float, pool: Any
) -> list[Start]:
    """``count`` seeded starts in strata; which candidates are kept depends on their T* only,
    so the draw is the same whatever the pool."""
    rng = np.random.default_rng(draw_seed)
    per_stratum = max(1, round(STRATUM_SHARE * count)) if count >= 4 else 0
    wanted = {"short": per_stratum, "rolling": per_stratum, "short rolling": per_stratum}
    wanted["any"] = count - 3 * per_stratum
    starts: list[Start] = []
    for kind, n in wanted.items():
        kept: list[Start] = []
        drawn = 0
        while len(kept) < n:
            if drawn >= MAX_DRAWS:
                raise BallbeamError(f"could not draw {n} {kind!r} starts in {MAX_DRAWS} tries")
            batch = [_draw(rng, kind) for _ in range(DRAW_BATCH)]
            drawn += len(batch)
            t_stars = pool.map(
                _candidate_t_star, [(config_path, tuple(extra), s, target_m) for s in batch]
            )
            for start, t_star in zip(batch, t_stars, strict=True):
                if t_star is None or len(kept) == n:
                    continue
                if "short" in kind and t_star >= SHORT_T_STAR_S:
                    continue
                kept.append(replace(start, t_star_s=t_star))
        starts += kept
    return starts


# --- runs -----------------------------------------------------------------------------------


def rest_figures(time_s: np.ndarray, states: np.ndarray, target_m: float) -> dict[str, Any]:
    """Rest, first entry into the rest band and the relapse between them, about the target."""
    rest_s = inside_from(time_s, outside_rest_band(states, target_m))
    entry_s = first_entry_time(time_s, states, target_m)
    relapse = None if rest_s is None or entry_s is None else rest_s - entry_s
    return {"rest_s": rest_s, "first_entry_s": entry_s, "relapse_s": relapse}


def _floor_row(config: Config, target_m: float) -> dict[str, Any]:
    floor = plant_floor(config, target_m)
    if floor is None:
        return {"floor_s": None}
    return {
        "floor_s": floor.time_s,
        "floor_method": floor.method,
        "floor_gamma": floor.gamma,
        "floor_alpha": floor.alpha,
        "floor_drive_v": floor.drive_limit_v,
    }


def _finish(case: Case, row: dict[str, Any], metrics: dict[str, Any]) -> dict[str, Any]:
    floor_s, rest_s = row.get("floor_s"), row["rest_s"]
    row["rest_floor"] = rest_s / floor_s if rest_s is not None and floor_s else math.inf
    row["rest_t_star"] = rest_s / case.start.t_star_s if rest_s is not None else math.inf
    row["relapse_s"] = math.inf if row["relapse_s"] is None else row["relapse_s"]
    for key, name in (
        ("tv", "input_tv_ratio"), ("dither_hz", "dither_hz"), ("step_v", "largest_step_v"),
        ("theta_deg", "max_abs_theta_deg"),
    ):
        value = metrics.get(name)
        row[key] = math.inf if value is None else float(value)
    return row


def _case_row(case: Case) -> dict[str, Any]:
    return {
        "set": case.set_name, "start_index": case.start_index, "start": asdict(case.start),
        "seed": case.seed, "target_m": case.target_m, "overrides": list(case.overrides),
    }


def _error_row(case: Case, error: Exception) -> dict[str, Any]:
    return {
        **_case_row(case), "error": f"{type(error).__name__}: {error}", "rest_s": None,
        "rest_floor": math.inf, "rest_t_star": math.inf, "relapse_s": math.inf, "tv": math.inf,
        "dither_hz": math.inf, "step_v": math.inf, "theta_deg": math.inf, "floor_s": None,
    }


def run_group(cases: Sequence[Case], config_path: str) -> list[dict[str, Any]]:
    """Offline runs that share one controller design (made once)."""
    rows = []
    design = None
    for case in cases:
        try:
            config = load_config(config_path, list(case.overrides))
            if design is None:
                design = controller_design(config)
            row = {**_case_row(case), **_floor_row(config, case.target_m)}
            result = run_offline_with(config, design, case.start.t_star_s)
            row.update(
                rest_figures(result.trace.time_s, result.trace.true_states, case.target_m)
            )
            rows.append(_finish(case, row, result.metrics.as_dict()))
        except BallbeamError as error:
            rows.append(_error_row(case, error))
    return rows


def run_bus(case: Case, config_path: str) -> list[dict[str, Any]]:
    """``ballbeam run`` in lock-step (two processes on a private ff11:: group), its log read
    back: the figures from its /truth and /command."""
    from ballbeam.evaluation.summary import run_series, summarise
    from ballbeam.logs.reader import read_log
    from ballbeam.runtime.launcher import launch_run

    try:
        config = load_config(config_path, list(case.overrides))
        row = {**_case_row(case), **_floor_row(config, case.target_m)}
        with tempfile.TemporaryDirectory(prefix="control-quality-") as directory:
            result = launch_run(
                config_path,
                [*case.overrides, "run.mode='lockstep'", f"run.log_dir='{directory}'"],
            )
            run_log = read_log(result.log_path)
        series = run_series(run_log)
        row.update(rest_figures(series.truth_time_s, series.truth_states, case.target_m))
        return [_finish(case, row, summarise(run_log))]
    except BallbeamError as error:
        return [_error_row(case, error)]


def build_cases(
    starts: Sequence[Start],
    sets: dict[str, list[str]],
    extra: Sequence[str],
    seeds: int,
    plant_starts: int,
    plant_seeds: int,
    targets: Sequence[float],
    target_overrides: dict[float, list[str]],
) -> list[Case]:
    """Nominal: every drawn start × ``seeds`` noise seeds. Every other plant: the paper's
    start and ``plant_starts`` − 1 drawn ones (rotating through the draw from set to set, so
    together the sets see every stratum) × ``plant_seeds``."""
    cases = []
    paper = starts[0]
    drawn = list(enumerate(starts[1:]))
    for set_index, (name, more) in enumerate(sets.items()):
        set_seeds = seeds
        if name == "nominal":
            chosen = drawn
        else:
            set_seeds = plant_seeds
            k = min(plant_starts - 1, len(drawn))
            offset = set_index * k
            chosen = [(-1, paper)] + [drawn[(offset + j) % len(drawn)] for j in range(k)]
        for target in targets:
            for index, start in chosen:
                duration_s = start.t_star_s + EXTRA_S  # T* to this target: see main
                for seed in range(1, set_seeds + 1):
                    overrides = (
                        *extra, *start.overrides(), f"plant.seed={seed}",
                        f"run.duration_s={duration_s:.3f}", *more, *target_overrides[target],
                    )
                    cases.append(Case(name, index, start, seed, target, tuple(overrides)))
    return cases


def grouped(cases: Iterable[Case], config_path: str) -> list[list[Case]]:
    """Cases by controller design, in batches of at most GROUP_RUNS."""
    by_design: dict[str, list[Case]] = {}
    for case in cases:
        key = design_key(load_config(config_path, list(case.overrides)))
        by_design.setdefault(key, []).append(case)
    batches = []
    for group in by_design.values():
        batches += [group[i : i + GROUP_RUNS] for i in range(0, len(group), GROUP_RUNS)]
    return batches


# --- report ---------------------------------------------------------------------------------


def summarise_set(rows: list[dict[str, Any]]) -> dict[str, Any]:
    ratios = [row["rest_floor"] for row in rows]
    floors = [row["floor_s"] for row in rows if row.get("floor_s")]
    s = {
        "runs": len(rows),
        "errors": sum("error" in row for row in rows),
        "rest_median": statistics.median(ratios),
        "rest_worst": max(ratios),
        "rest_t_star_median": statistics.median(row["rest_t_star"] for row in rows),
        "tv": max(row["tv"] for row in rows),
        "dither_hz": max(row["dither_hz"] for row in rows),
        "step_v": max(row["step_v"] for row in rows),
        "theta_deg": max(row["theta_deg"] for row in rows),
        "relapse_s": max(row["relapse_s"] for row in rows),
        "floor_min_s": min(floors, default=None),
        "floor_max_s": max(floors, default=None),
        "floor_methods": sorted({row["floor_method"] for row in rows if "floor_method" in row}),
    }
    s["failed"] = [key for key, bound in BOUNDS.items() if not s[key] <= bound]
    return s


def over_bounds(row: dict[str, Any]) -> list[tuple[float, str]]:
    """The run's figures over their bound, as (figure / bound, name), largest first."""
    scored = [
        (row["rest_floor"] / BOUNDS["rest_worst"], "rest/floor"),
        *((row[key] / BOUNDS[key], key) for key in ("tv", "dither_hz", "step_v", "theta_deg")),
        (row["relapse_s"] / BOUNDS["relapse_s"], "relapse_s"),
    ]
    return sorted((item for item in scored if item[0] > 1.0), reverse=True)


def worst_order(row: dict[str, Any]) -> tuple[int, float]:
    """Runs over any bound first, then by rest / own floor."""
    return (len(over_bounds(row)) > 0, row["rest_floor"])


def rerun_command(config_path: str, row: dict[str, Any], rank: int) -> str:
    sets = " ".join(f"--set '{o}'" for o in row["overrides"])
    return f"ballbeam simulate {config_path} {sets} --plot worst{rank}.png"


def _f(value: float | None, width: int, digits: int) -> str:
    if value is None:
        return f"{'—':>{width}}"
    return f"{value:>{width}.{digits}f}"


def print_report(
    config_path: str, extra: Sequence[str], rows: list[dict[str, Any]], args: argparse.Namespace,
    summaries: dict[str, dict[str, Any]], notes: list[str], elapsed_s: float,
) -> None:
    where = "over the bus, lock-step" if args.bus else "offline"
    print(f"config {config_path} {' '.join(extra)} ({where}); draw seed {args.draw_seed}, "
          f"noise seeds a start {args.seeds} (other plants {args.plant_seeds}), runs of T* + "
          f"{EXTRA_S:.0f} s")
    b = BOUNDS
    header = (
        f"{'set':<24}{'runs':>5}{'rest/floor':>11}{'':>9}{'TV':>6}{'dither':>7}{'step':>6}"
        f"{'|θ|':>8}{'relapse':>9}{'rest/T*':>8}  {'floor s':<12} verdict"
    )
    print(header)
    print(
        f"{'  (bound)':<24}{'':>5}{'med≤' + str(b['rest_median']):>11}"
        f"{'max≤' + str(b['rest_worst']):>9}{'≤' + str(b['tv']):>6}{'≤' + str(b['dither_hz']):>7}"
        f"{'≤' + str(b['step_v']):>6}{'≤' + str(b['theta_deg']):>8}"
        f"{'≤' + str(int(b['relapse_s'] * 1000)) + 'ms':>9}"
    )
    for name, s in summaries.items():
        floors = (
            f"{s['floor_min_s']:.3f}–{s['floor_max_s']:.3f}" if s["floor_min_s"] is not None
            else "—"
        )
        verdict = "PASS" if not s["failed"] else "FAIL " + ",".join(s["failed"])
        if s["errors"]:
            verdict += f" ({s['errors']} errors)"
        print(
            f"{name:<24}{s['runs']:>5}{_f(s['rest_median'], 11, 3)}{_f(s['rest_worst'], 9, 3)}"
            f"{_f(s['tv'], 6, 2)}{_f(s['dither_hz'], 7, 1)}{_f(s['step_v'], 6, 2)}"
            f"{_f(s['theta_deg'], 8, 3)}{_f(s['relapse_s'] * 1000, 7, 0)}ms"
            f"{_f(s['rest_t_star_median'], 8, 3)}  {floors:<12} {verdict}"
        )
    methods = sorted({m for s in summaries.values() for m in s["floor_methods"]})
    print("floors: " + "; ".join(methods))
    for note in notes:
        print(f"note: {note}")
    passed = sum(not s["failed"] for s in summaries.values())
    print(f"{passed} of {len(summaries)} sets pass ({len(rows)} runs in {elapsed_s:.0f} s)")
    worst = sorted(rows, key=worst_order, reverse=True)[: args.worst]
    print(f"\nthe {len(worst)} worst runs (over a bound first, then by rest/floor), to re-run:")
    for rank, row in enumerate(worst, 1):
        over = ", ".join(f"{name} {score:.2f}× its bound" for score, name in over_bounds(row))
        start = row["start"]
        print(
            f"{rank}. {row['set']} start {row['start_index']} ({start['kind']}, T* "
            f"{start['t_star_s']:.3f} s) seed {row['seed']} target {row['target_m']}: rest/floor "
            f"{row['rest_floor']:.3f}, floor {_f(row.get('floor_s'), 0, 3)} s, relapse "
            f"{_f(row['relapse_s'] * 1000, 0, 0)} ms, |θ| {_f(row['theta_deg'], 0, 3)}°"
            + (f"; over: {over}" if over else "")
            + (f"; {row['error']}" if "error" in row else "")
        )
        print(f"   {rerun_command(config_path, row, rank)}")
    if args.runs:
        print("\nevery run: set, start, seed, target, floor s (how), rest s, rest/floor, relapse")
        for row in rows:
            print(
                f"{row['set']:<24}{row['start_index']:>4} {row['start']['kind']:<14}"
                f"{row['seed']:>3}{row['target_m']:>7.3f}{_f(row.get('floor_s'), 8, 3)} "
                f"({'chord γ' if 'nonlinear' in row.get('floor_method', '') else 'linear'})"
                f"{_f(row['rest_s'], 8, 3)}{_f(row['rest_floor'], 8, 3)}"
                f"{_f(row['relapse_s'] * 1000, 7, 0)}ms"
            )


def _usage_error(message: str) -> int:
    print(f"control_quality: {message}", file=sys.stderr)
    return 2


class _InlinePool:
    """One process: the runs in this one (no fork of a process that may hold threads)."""

    def __enter__(self) -> _InlinePool:
        return self

    def __exit__(self, *_: object) -> None:
        return None

    @staticmethod
    def map(function: Callable[[Any], Any], items: Iterable[Any]) -> list[Any]:
        return [function(item) for item in items]

    @staticmethod
    def imap_unordered(
        function: Callable[[Any], Any], items: Iterable[Any], chunksize: int = 1
    ) -> Iterator[Any]:
        return (function(item) for item in items)


def _pool(processes: int) -> Any:
    """Workers started fresh (spawn): forking a process that runs threads (a test runner, a
    Dask client) can copy a held lock into the child, which then waits forever."""
    if processes == 1:
        return _InlinePool()
    return multiprocessing.get_context("spawn").Pool(processes)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--config", default=PAPER)
    parser.add_argument("--set", dest="overrides", action="append", default=[])
    parser.add_argument("--quick", action="store_true",
                        help="8 starts, 2 seeds nominal; other plants: 2 starts, 1 seed")
    parser.add_argument("--only", help="comma-separated sets or families (nominal,deadzone,...)")
    parser.add_argument("--starts", type=int, help="drawn starts (default 40; quick 8)")
    parser.add_argument("--seeds", type=int, help="noise seeds a start (default 5; quick 2)")
    parser.add_argument("--plant-starts", type=int,
                        help="starts a non-nominal plant is run from (default 6; quick 2)")
    parser.add_argument("--plant-seeds", type=int,
                        help="noise seeds a start, other plants (default: --seeds; quick 1)")
    parser.add_argument("--draw-seed", type=int, default=27, help="seed of the starts' draw")
    parser.add_argument("--target", type=float, action="append", help="target x [m] (default 0)")
    parser.add_argument("--json", type=Path, help="write every run's figures here")
    parser.add_argument("--processes", type=int, default=2)
    parser.add_argument("--worst", type=int, default=5, help="worst runs listed")
    parser.add_argument("--runs", action="store_true", help="print every run and its floor")
    parser.add_argument("--bus", action="store_true",
                        help="each run over the bus in lock-step (ballbeam run: two processes)")
    args = parser.parse_args(argv)
    quick = args.quick
    args.starts = args.starts if args.starts is not None else (8 if quick else 40)
    args.seeds = args.seeds if args.seeds is not None else (2 if quick else 5)
    args.plant_starts = (
        args.plant_starts if args.plant_starts is not None else (2 if quick else 6)
    )
    args.plant_seeds = (
        args.plant_seeds if args.plant_seeds is not None else (1 if quick else args.seeds)
    )
    counts = (args.starts, args.seeds, args.plant_starts, args.plant_seeds, args.processes)
    if min(counts) < 1:
        return _usage_error(
            "--starts, --seeds, --plant-starts, --plant-seeds and --processes must be ≥ 1"
        )
    targets = args.target or [0.0]
    if any(abs(target) > 0.2 for target in targets):
        return _usage_error("targets must lie within ±0.2 m")
    only = set(args.only.split(",")) if args.only else None
    sets = {name: more for name, more in plant_sets().items() if selected(name, only)}
    if not sets:
        return _usage_error(f"--only {args.only}: no such set (families: "
                            f"{', '.join(sorted({n.split(':')[0] for n in plant_sets()}))})")
    try:
        base = load_config(args.config, args.overrides)
    except BallbeamError as error:
        return _usage_error(str(error))
    notes: list[str] = []
    target_overrides: dict[float, list[str]] = {}
    for target in targets:
        more = [] if target == 0.0 else [f"task.target_m={target!r}"]
        try:
            load_config(args.config, [*args.overrides, *more])
        except BallbeamError as error:
            notes.append(f"target {target} m skipped: the config refuses it ({error})")
            continue
        target_overrides[target] = more
    if not target_overrides:
        return _usage_error("no target the config accepts; " + "; ".join(notes))
    started = time.perf_counter()
    with _pool(args.processes) as pool:
        rows: list[dict[str, Any]] = []
        for target in target_overrides:
            paper_t_star = design_t_star_s(base, target)
            if paper_t_star is None:
                return _usage_error("the config's own start has no path to rest")
            paper = Start(
                "paper", base.initial.theta_deg, base.initial.ball_position_m,
                base.initial.ball_velocity_m_s, paper_t_star,
            )
            drawn = draw_starts(
                args.starts, args.draw_seed, args.config, args.overrides, target, pool
            )
            cases = build_cases(
                [paper, *drawn], sets, args.overrides, args.seeds, args.plant_starts,
                args.plant_seeds, [target], target_overrides,
            )
            if args.bus:
                work = pool.imap_unordered(
                    partial(run_bus, config_path=args.config), cases, chunksize=1
                )
            else:
                work = pool.imap_unordered(
                    partial(run_group, config_path=args.config), grouped(cases, args.config)
                )
            for batch in work:
                rows += batch
    order = list(sets)
    rows.sort(key=lambda r: (order.index(r["set"]), r["target_m"], r["start_index"], r["seed"]))
    summaries: dict[str, dict[str, Any]] = {}
    for name in order:
        for target in target_overrides:
            set_rows = [r for r in rows if r["set"] == name and r["target_m"] == target]
            if set_rows:
                label = name if len(target_overrides) == 1 else f"{name}@{target:+.3f}"
                summaries[label] = summarise_set(set_rows)
    print_report(args.config, args.overrides, rows, args, summaries, notes,
                 time.perf_counter() - started)
    if args.json is not None:
        payload = {"bounds": BOUNDS, "args": vars(args) | {"json": str(args.json)},
                   "notes": notes, "summary": summaries, "runs": rows}
        try:
            args.json.write_text(json.dumps(payload, indent=1, default=str))
        except OSError as error:
            return _usage_error(f"cannot write {args.json}: {error.strerror}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
