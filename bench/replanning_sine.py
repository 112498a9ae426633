"""The re-planning law on sines it was not tuned on: drawn sines, starts, plants and noise.

    nice -n 5 .venv/bin/python bench/replanning_sine.py [--draw-seed 777] [--runs 8]
        [--processes 2]

Each run is offline (``run_offline``, the law's own in-process planner) for two periods or
12 s, whichever is longer. Drawn per run: a sine (period 2, 4 or 10 s; amplitude 1–3 cm at
2 s, 2–8 cm otherwise; offset ±5 cm), a start (θ ±40°, x ±18 cm, ẋ ±0.15 m/s), a plant (ball
gain 0.7–1.3, motor gain 0.8–1.2, dead zone 0–0.4 V, a noise seed), 5× the position noise and
the nonlinear ball each with probability 1/4. Printed per run, from the plant's truth against
the sine itself: RMS and largest |x − x_r| over the second half, when |x − x_r| last came
within 1 mm to stay, the largest |θ| at any physics step, and over the second half the largest
|u|, the largest one-period |Δu| and sign changes of u a second.
"""

from __future__ import annotations

import argparse
import json
import math
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from ballbeam.assembly import run_offline
from ballbeam.config import load_config

PAPER = str(Path(__file__).resolve().parents[1] / "configs" / "paper.toml")
JOINED_M = 1e-3


def one(overrides: list[str]) -> dict[str, Any]:
    config = load_config(PAPER, ["controller.kind='replanning'", *overrides])
    sine = config.task.sine
    assert sine is not None
    trace = run_offline(config).trace
    time_s = trace.time_s
    error_m = trace.true_states[:, 3] - (
        sine.offset_m + sine.amplitude_m * np.sin(2.0 * math.pi / sine.period_s * time_s)
    )
    half = time_s >= time_s[-1] / 2
    away = np.flatnonzero(np.abs(error_m) > JOINED_M)
    joined_s = None if away.size and away[-1] == len(time_s) - 1 else (
        float(time_s[away[-1] + 1]) if away.size else 0.0
    )
    voltage_v = trace.voltage_v[half]
    return {
        "set": " ".join(overrides),
        "rms_mm": round(1e3 * float(np.sqrt(np.mean(error_m[half] ** 2))), 3),
        "max_mm": round(1e3 * float(np.max(np.abs(error_m[half]))), 3),
        "joined_s": joined_s,
        "max_theta_deg": round(math.degrees(float(np.max(trace.peak_abs_theta_rad))), 4),
        "max_u_v": round(float(np.max(np.abs(voltage_v))), 3),
        "largest_step_v": round(float(np.max(np.abs(np.diff(voltage_v)))), 3),
        "sign_changes_per_s": round(
            float(np.count_nonzero(np.diff(np.sign(voltage_v)) != 0)) / float(time_s[-1] / 2), 1
        ),
    }


def draws(seed: int, runs: int) -> list[list[str]]:
    rng = np.random.default_rng(seed)
    cases = []
    for _ in range(runs):
        period = float(rng.choice([2.0, 4.0, 10.0]))
        amplitude = rng.uniform(0.02, 0.08) if period >= 4 else rng.uniform(0.01, 0.03)
        cases.append([
            f"task.sine={{amplitude_m={amplitude:.4f}, period_s={period}, "
            f"offset_m={rng.uniform(-0.05, 0.05):.4f}}}",
            f"run.duration_s={max(2 * period, 12.0)}",
            f"initial.theta_deg={rng.uniform(-40, 40):.2f}",
            f"initial.ball_position_m={rng.uniform(-0.18, 0.18):.4f}",
            f"initial.ball_velocity_m_s={rng.uniform(-0.15, 0.15):.4f}",
            f"plant.ball_gain_scale={rng.uniform(0.7, 1.3):.3f}",
            f"plant.motor_gain_scale={rng.uniform(0.8, 1.2):.3f}",
            f"plant.deadzone_v={rng.uniform(0, 0.4):.3f}",
            f"plant.seed={int(rng.integers(1000, 9999))}",
            *(["plant.position_noise_m=1e-3"] if rng.uniform() < 0.25 else []),
            *(["plant.nonlinear_ball=true"] if rng.uniform() < 0.25 else []),
        ])
    return cases


def main() -> int:
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--draw-seed", type=int, default=777)
    parser.add_argument("--runs", type=int, default=8)
    parser.add_argument("--processes", type=int, default=2)
    args = parser.parse_args()
    with ProcessPoolExecutor(args.processes) as pool:
        for row in pool.map(one, draws(args.draw_seed, args.runs)):
            print(json.dumps(row))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
