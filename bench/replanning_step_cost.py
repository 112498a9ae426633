"""The re-planning law's step, offline: its cost per cycle and its closed loop, this tree's
against the law as it was at a git revision (``--before``, default: before its cycle was
written in plain floats), side by side in one run.

    nice -n 19 .venv/bin/python bench/replanning_step_cost.py
    nice -n 19 .venv/bin/python bench/replanning_step_cost.py --before cd1daf0 --starts 3

Each law runs ``run_closed_loop`` on the emulated plant from the paper's start for
``--duration-s`` deferred, its steps timed with ``perf_counter_ns`` (the requests answered
between steps: a solve is the planner's, not the step's), then it runs ``run_closed_loop``
from there and from ``--starts`` more starts (drawn with
``--draw-seed``) for the closed-loop comparison: rest (truth, 0.5 mm / 0.5°), the largest
|θ| at every physics step, and the largest command difference between the two.
"""

from __future__ import annotations

import argparse
import importlib.util
import math
import subprocess
import sys
import time
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np

from ballbeam.config import load_config
from ballbeam.core import replanning as after
from ballbeam.core.metrics import inside_from, outside_rest_band
from ballbeam.core.plant import (
    PlantPhysics,
    command_as_received,
    initial_noise,
    next_noise,
    read_sensors,
)
from ballbeam.plant_assembly import plant_parameters

REPO = Path(__file__).resolve().parents[1]
PAPER = str(REPO / "configs" / "paper.toml")
MODULE = "service/ballbeam/core/replanning.py"
BEFORE = "cd1daf01567da5b016de5a744a189e9d6e3bf36b"  # main before the plain-float cycle


def load_before(revision: str) -> ModuleType:
    """``core/replanning.py`` as it was at ``revision``, as its own module (the rest of the
    package is this tree's)."""
    source = subprocess.run(
        ["git", "-C", str(REPO), "show", f"{revision}:{MODULE}"],
        capture_output=True, text=True, check=True,
    ).stdout
    spec = importlib.util.spec_from_loader("replanning_before", loader=None)
    assert spec is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses resolve their module by name
    exec(compile(source, f"{revision}:{MODULE}", "exec"), module.__dict__)
    return module


def run(module: ModuleType, overrides: list[str], duration_s: float) -> tuple[Any, float]:
    """The synchronous closed loop (``run_closed_loop``), its target."""
    config = load_config(PAPER, overrides)
    params = plant_parameters(config)
    result = module.run_closed_loop(
        params, config.initial.state(), duration_s, seed=config.plant.seed,
        substeps=config.plant.physics_substeps, targets=((0.0, config.task.target_m),),
        settings=module.Settings(
            encoder_step_rad=params.encoder_step_rad, adc_step_m=params.adc_step_m
        ),
    )
    return result, config.task.target_m


def step_times_ns(module: ModuleType, duration_s: float) -> list[int]:
    """The law's steps from the paper's start, timed; its requests answered between steps (as
    the planner would: the solves are not the step's), each taken at the next step."""
    config = load_config(PAPER, [])
    plant = plant_parameters(config)
    s = module.Settings(encoder_step_rad=plant.encoder_step_rad, adc_step_m=plant.adc_step_m)
    rng = np.random.default_rng(config.plant.seed)
    physics = PlantPhysics(plant)
    state = np.array(config.initial.state(), dtype=float)
    noise = initial_noise(plant, rng)
    controller = module.ReplanningController(s, state.copy(), target_m=config.task.target_m)
    controller.deferred = True
    controller.request_plan(controller.initial_state)
    controller.adopt(module.solve_plan_request(controller.outstanding))
    controller.issued = None
    substeps = config.plant.physics_substeps
    times: list[int] = []
    for k in range(round(duration_s / s.period_s)):
        reading = read_sensors(plant, state, noise)
        theta_rad = reading.angle_counts * plant.encoder_step_rad
        position_m = reading.position_counts * plant.adc_step_m
        start = time.perf_counter_ns()
        record = controller.step(theta_rad, position_m)
        times.append(time.perf_counter_ns() - start)
        if controller.design_issued is not None:
            controller.adopt_design(module.solve_design_request(controller.design_issued))
        if controller.issued is not None:
            controller.adopt(module.solve_plan_request(controller.issued))
        controller.issued = controller.design_issued = None
        state = physics.advance(state, command_as_received(record.command_v), substeps,
                                from_step=k * substeps)
        noise = next_noise(plant, noise, rng)
    return times


def closed_loop(result: Any, target_m: float) -> tuple[float | None, float]:
    rest = inside_from(result.time_s, outside_rest_band(result.states, target_m))
    return rest, math.degrees(float(result.peak_theta_rad.max()))


def starts(draw_seed: int, count: int) -> list[list[str]]:
    rng = np.random.default_rng(draw_seed)
    return [
        [
            f"initial.theta_deg={rng.uniform(-40, 40):.3f}",
            f"initial.ball_position_m={rng.uniform(-0.15, 0.15):.4f}",
            f"initial.ball_velocity_m_s={rng.uniform(-0.1, 0.1):.4f}",
        ]
        for _ in range(count)
    ]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--before", default=BEFORE)
    parser.add_argument("--duration-s", type=float, default=4.0)
    parser.add_argument("--starts", type=int, default=3)
    parser.add_argument("--draw-seed", type=int, default=27)
    args = parser.parse_args(argv)
    before = load_before(args.before)
    laws = (("before", before), ("after", after))
    print(f"step cost, paper start, {args.duration_s:g} s ({args.before[:10]} vs this tree)")
    print(f"{'':8}{'p50 µs':>10}{'p99 µs':>10}{'max µs':>10}{'mean µs':>10}")
    for name, module in laws:
        step_times_ns(module, 0.2)  # warm: imports, first design, caches
        us = np.array(step_times_ns(module, args.duration_s)) / 1e3
        print(f"{name:8}{np.percentile(us, 50):10.1f}{np.percentile(us, 99):10.1f}"
              f"{us.max():10.1f}{us.mean():10.1f}")
    print("\nclosed loop, before → after (rest s; max |θ| deg; max |Δ command| V, and the "
          "fraction of cycles over 1e-9 V)")
    for overrides in [[], *starts(args.draw_seed, args.starts)]:
        (old, target_m), (new, _) = [run(module, overrides, args.duration_s) for _, module in laws]
        rest = [closed_loop(r, target_m) for r in (old, new)]
        diff = np.abs(old.command_v - new.command_v)
        print(f"{' '.join(overrides) or 'paper start':70}  rest {rest[0][0]} → {rest[1][0]}; "
              f"|θ| {rest[0][1]:.9f} → {rest[1][1]:.9f}; Δu {diff.max():.2e} V, "
              f"{np.mean(diff > 1e-9):.3%} over 1e-9")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
