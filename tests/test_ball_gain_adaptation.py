"""The ball-gain estimate and the paced path (core/control.py, BallGainAdaptation).

The estimate is checked against the true gain of synthetic data and against NumPy's least
squares on the same regression; the paced path against what time scaling promises: a ball 20 %
slower than the model follows the plan's path at pace √0.8 without the overshoot a tracker on
the plan's clock produces.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from ballbeam.assembly import run_offline
from ballbeam.config import load_config
from ballbeam.core.control import (
    EMPTY_FIT,
    BallGainAdaptation,
    ControllerState,
    control_cycle,
)
from ballbeam.core.plant import SensorReading

from .conftest import PAPER

PERIOD_S = 1e-3
DESIGN_GAMMA = -0.41218487  # the paper model's ẍ per rad of servo angle


def adaptation(confidence: float = 0.01) -> BallGainAdaptation:
    return BallGainAdaptation(
        design_gamma=DESIGN_GAMMA,
        position_noise_m=2e-4,
        confidence=confidence,
        min_ratio=0.5,
        max_ratio=1.5,
        period_s=PERIOD_S,
        until_cycle=10**9,
        back_emf_v_s_per_rad=0.54,
        pace_step_per_cycle=1e-3,
    )


def synthetic_run(gamma: float, noise_m: float, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """A servo angle held piecewise constant over each period (as a ZOH plant sees it) and the
    ball's exact response x(t) = x0 + v0·t + γ·∬θ, sampled at the period starts, plus noise."""
    rng = np.random.default_rng(seed)
    n = 1500  # 1.5 s
    t = np.arange(n) * PERIOD_S
    theta = 0.9 * np.sin(2 * np.pi * t / 1.2) + 0.05 * rng.standard_normal(n)
    x0, v0 = 0.195, 0.01
    x = np.empty(n)
    position, velocity = x0, v0
    for k in range(n):
        x[k] = position
        position += velocity * PERIOD_S + 0.5 * gamma * theta[k] * PERIOD_S**2
        velocity += gamma * theta[k] * PERIOD_S
    return theta, x + noise_m * rng.standard_normal(n)


def test_lost_samples_keep_the_time_base() -> None:
    """Periods without a measurement still advance t and G (here every third sample lost)."""
    law = adaptation()
    theta, x = synthetic_run(0.8 * DESIGN_GAMMA, noise_m=2e-4, seed=4)
    sums = EMPTY_FIT
    for k, (angle, position) in enumerate(zip(theta, x, strict=True)):
        if k % 3:
            sums = law.add_sample(sums, float(position))
        sums = law.advance(sums, float(angle))
    assert law.ratio(sums) == pytest.approx(0.8, rel=0.015)


@pytest.mark.parametrize("scale", [0.8, 1.0, 1.2])
def test_estimate_finds_the_true_gain(scale: float) -> None:
    law = adaptation()
    theta, x = synthetic_run(scale * DESIGN_GAMMA, noise_m=2e-4, seed=3)
    sums = EMPTY_FIT
    for angle, position in zip(theta, x, strict=True):
        sums = law.advance(law.add_sample(sums, float(position)), float(angle))
    assert law.ratio(sums) == pytest.approx(scale, rel=0.01)


def test_estimate_is_numpys_least_squares() -> None:
    """The normal-equation sums and Cramer's rule give what lstsq gives on the same regressors
    (the double integral built independently, by cumulative sums)."""
    law = adaptation(confidence=1.0)
    theta, x = synthetic_run(0.9 * DESIGN_GAMMA, noise_m=2e-4, seed=5)
    sums = EMPTY_FIT
    for angle, position in zip(theta, x, strict=True):
        sums = law.advance(law.add_sample(sums, float(position)), float(angle))
    n = theta.size
    t = np.arange(n) * PERIOD_S
    velocity_part = np.concatenate(([0.0], np.cumsum(theta * PERIOD_S)[:-1]))
    step = velocity_part * PERIOD_S + 0.5 * theta * PERIOD_S**2
    double_integral = np.concatenate(([0.0], np.cumsum(step)[:-1]))
    regressors = np.column_stack([np.ones(n), t, double_integral])
    (_, _, gamma), *_ = np.linalg.lstsq(regressors, x, rcond=None)
    assert law.ratio(sums) == pytest.approx(gamma / DESIGN_GAMMA, rel=1e-8)


def test_estimate_waits_for_confidence() -> None:
    """A few samples with the servo barely moving say little about γ: the ratio stays 1."""
    law = adaptation()
    theta, x = synthetic_run(0.7 * DESIGN_GAMMA, noise_m=2e-4, seed=1)
    sums = EMPTY_FIT
    for angle, position in zip(theta[:40], x[:40], strict=True):
        sums = law.advance(law.add_sample(sums, float(position)), float(angle))
    assert law.ratio(sums) == 1.0


def estimated_ratio_at_plan_end(overrides: list[str]) -> tuple[float, float]:
    """(γ̂/γ at the plan's end, overshoot [mm]) of an offline run, the ratio from replaying
    the run's own sensor readings through the control law."""
    config = load_config(PAPER, overrides)
    run = run_offline(config)
    design = run.design
    assert design.adaptation is not None
    state = ControllerState()
    for angle, position in zip(run.trace.angle_counts, run.trace.position_counts, strict=True):
        state, _ = control_cycle(design, state, SensorReading(int(angle), int(position)))
        if state.path_position >= design.adaptation.until_cycle:
            break
    return state.ball_gain_ratio, run.metrics.overshoot_mm


@pytest.mark.parametrize("scale", [0.8, 1.2])
def test_a_mismatched_ball_is_estimated_and_followed(scale: float) -> None:
    ratio, overshoot_mm = estimated_ratio_at_plan_end([f"plant.ball_gain_scale={scale}"])
    assert ratio == pytest.approx(scale, rel=0.02)
    # On the plan's clock the 0.8 ball overshoots 17.6 mm (below); paced, it stops within 3 mm.
    assert overshoot_mm < 3.0


def test_the_plans_clock_overshoots_a_slow_ball() -> None:
    """The failure the pacing removes, so the test above is not vacuous."""
    config = load_config(
        PAPER, ["plant.ball_gain_scale=0.8", "tracker.adapt_ball_gain=false"]
    )
    assert run_offline(config).metrics.overshoot_mm > 10.0


def test_the_nominal_ball_keeps_the_plans_pace() -> None:
    ratio, _ = estimated_ratio_at_plan_end([])
    assert math.sqrt(ratio) == pytest.approx(1.0, abs=0.01)


def test_the_pace_changes_by_bounded_steps() -> None:
    law = adaptation()
    assert law.pace(0.64, 1.0) == pytest.approx(0.999)
    assert law.pace(0.64, 0.8005) == pytest.approx(0.8)
    assert law.pace(1.0, 1.0) == 1.0
