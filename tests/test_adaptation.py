"""What the loop learns (core/adaptation.py): the ball's gain and the paced path; the dead zone.

The ball-gain estimate is checked against the true gain of synthetic data and against NumPy's
least squares on the same regression; the paced path against what time scaling promises: a
ball 20 % slower than the model follows the plan's path at pace √0.8 without the overshoot a
tracker on the plan's clock produces. The learnt dead zone is checked against the emulated
motor's true one.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from ballbeam.assembly import run_offline
from ballbeam.config import load_config
from ballbeam.core.adaptation import (
    EMPTY_FIT,
    BallGainAdaptation,
    DeadZoneLearning,
    NoiseAdaptation,
)
from ballbeam.core.control import ControllerState, control_cycle
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
    # On the plan's clock the 0.8 ball overshoots 17.6 mm (below); paced, it stops within 4 mm
    # (the 1.2 ball, whose clock the first arc re-synchronises ahead, overshoots most: 3.8 mm).
    assert overshoot_mm < 4.0


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


def final_state(overrides: list[str]) -> tuple[ControllerState, float | None]:
    """The controller's state at the end of an offline run (replaying its sensor readings
    through the control law) and the run's rest time."""
    config = load_config(PAPER, overrides)
    run = run_offline(config)
    state = ControllerState()
    for angle, position in zip(run.trace.angle_counts, run.trace.position_counts, strict=True):
        state, _ = control_cycle(run.design, state, SensorReading(int(angle), int(position)))
    return state, run.metrics.rest_time_s


def test_a_wide_dead_zone_is_learnt_and_the_ball_rests() -> None:
    state, rest_time_s = final_state(["plant.deadzone_v=0.4"])
    assert state.deadzone_v == pytest.approx(0.4, abs=0.08)
    assert rest_time_s is not None and rest_time_s < 1.6 * 1.746


def test_without_learning_a_wide_dead_zone_never_rests() -> None:
    """The limit cycle the learning removes (so the test above is not vacuous)."""
    _, rest_time_s = final_state(["plant.deadzone_v=0.4", "controller.learn_deadzone=false"])
    # A limit cycle of the ball's size: it may happen to sit in the band at the very end of
    # the 5 s run, never for a second (learnt, the ball rests by 2.8 s).
    assert rest_time_s is None or rest_time_s > 4.0


def resync_law(rate_per_s: float = 20.0) -> BallGainAdaptation:
    law = adaptation()
    return BallGainAdaptation(**{
        **law.__dict__, "resync_rate_per_cycle": rate_per_s * PERIOD_S,
        "resync_max_per_cycle": 0.2, "arc_theta_rad": 0.88,
    })


ARC_THETA_RAD = 0.9  # θ_d held on a limit arc
# The paper model's ball on that arc: ẍ_d = γ·θ_d < 0 (γ < 0), so a ball moving toward −x
# speeds up there, and on the arc at −θ_d it slows down.
ARC_ACCELERATION = DESIGN_GAMMA * ARC_THETA_RAD


@pytest.mark.parametrize("lag_s", [0.025, -0.01])
def test_the_clock_takes_up_a_measured_lag_on_an_accelerating_arc(lag_s: float) -> None:
    """A ball exactly δ behind an arc's parabola (x̂ = X(t − δ)): the clock moves back by
    rate·δ·pace seconds of path this cycle, whatever the pace."""
    law, pace = resync_law(5.0), 0.9
    velocity_d = -0.1  # [m/s] of the plan; speeding up: ẍ_d < 0
    acceleration = pace * pace * ARC_ACCELERATION
    velocity = pace * velocity_d
    position_d = 0.1
    # Where the reference (played at the pace) was δ ago; δ small, so to first order.
    position = position_d - velocity * lag_s
    reference = (ARC_THETA_RAD, 0.0, velocity_d, position_d)
    shift = law.clock_shift_cycles((ARC_THETA_RAD, 0.0, velocity, position), reference, pace)
    assert acceleration * velocity > 0
    assert shift == pytest.approx(-0.005 * lag_s * pace / PERIOD_S, rel=1e-9)


def test_the_clock_stays_off_arcs_and_on_decelerating_ones() -> None:
    law = resync_law()
    behind = (0.0, 0.0, -0.1, 0.102)
    # Decelerating arc: θ_d of the other sign, so ẍ_d opposes the velocity.
    decelerating = (-ARC_THETA_RAD, 0.0, -0.1, 0.1)
    assert law.clock_shift_cycles(behind, decelerating, 1.0) == 0.0
    swinging = (0.5, 3.0, -0.1, 0.1)  # θ_d moving: not an arc
    assert law.clock_shift_cycles(behind, swinging, 1.0) == 0.0
    assert resync_law(0.0).clock_shift_cycles(
        behind, (ARC_THETA_RAD, 0.0, -0.1, 0.1), 1.0
    ) == 0.0


def test_the_clock_shift_is_bounded() -> None:
    law = resync_law(1000.0)
    far_behind = (0.0, 0.0, -0.1, 0.2)
    reference = (ARC_THETA_RAD, 0.0, -0.1, 0.1)
    shift = law.clock_shift_cycles(far_behind, reference, 1.0)
    assert shift == pytest.approx(-0.2)


def test_resynchronising_the_clock_brings_a_slow_ball_to_rest_sooner() -> None:
    """Ball gain 0.8: the lag the first 0.35 s leave (before the estimate is confident) costs
    the paced path ~0.67 s of endgame; taken up on the first arc, the ball rests near the
    plan's end stretched by 1/√0.8."""
    t_star_s = 1.746
    overrides = ["plant.ball_gain_scale=0.8", "run.duration_s=4.75"]
    resynced = run_offline(load_config(PAPER, overrides)).metrics.rest_time_s
    plain = run_offline(
        load_config(PAPER, [*overrides, "tracker.clock_resync_per_s=0"])
    ).metrics.rest_time_s
    assert resynced is not None and resynced < 1.2 * t_star_s
    assert plain is not None and plain > 1.4 * t_star_s


@pytest.mark.parametrize("overrides", [[], ["plant.motor_gain_scale=0.9"]])
def test_the_modelled_dead_zone_stays_put(overrides: list[str]) -> None:
    """The emulated motor's 0.1 V is what the design models: the estimate stays near it, also
    with a motor 10 % weaker (full-scale moves do not teach the dead zone)."""
    state, _ = final_state(overrides)
    assert state.deadzone_v == pytest.approx(0.1, abs=0.05)


SERVO_ROWS = (1.0, 1e-3, 0.0, 0.94, 5e-5, 0.1)  # a servo over 1 ms: θ̇ += 0.1·drive, decay 0.94


def run_window(learning: DeadZoneLearning, sent_v: float, true_deadzone_v: float) -> float:
    """Hold ``sent_v`` for 300 cycles on a servo with the given dead zone (the same model as
    the learning's, so only the dead zone differs), then reverse it: the learnt dead zone."""
    believed_v = 0.1
    window = None
    theta, rate = 0.0, 0.0
    a00, a01, a10, a11, b0, b1 = SERVO_ROWS
    for command_v in [sent_v] * 300 + [-sent_v]:
        drive_true = max(abs(command_v) - true_deadzone_v, 0.0) * (1 if command_v > 0 else -1)
        drive_model = max(abs(command_v) - believed_v, 0.0) * (1 if command_v > 0 else -1)
        believed_v, window = learning.step(
            believed_v, window, command_v, drive_model, theta, rate, SERVO_ROWS
        )
        theta, rate = a00 * theta + a01 * rate + b0 * drive_true, (
            a10 * theta + a11 * rate + b1 * drive_true
        )
    return believed_v


def test_one_window_moves_the_estimate_towards_the_true_dead_zone() -> None:
    learning = DeadZoneLearning(
        min_motion_rad=0.006, judge_motion_rad=1e9, rate=1.0, below_v=1.5, max_v=1.0
    )
    # rate 1: one judged window gives the dead zone that explains the motion, exactly for a
    # servo that matches the model.
    assert run_window(learning, 0.8, 0.4) == pytest.approx(0.4, abs=1e-9)
    assert run_window(learning, 0.8, 0.1) == pytest.approx(0.1, abs=1e-9)


def test_dead_zone_windows_that_cannot_teach_are_ignored() -> None:
    learning = DeadZoneLearning(
        min_motion_rad=0.006, judge_motion_rad=1e9, rate=1.0, below_v=1.5, max_v=1.0
    )
    assert run_window(learning, 2.0, 0.4) == 0.1  # a large command: a gain error would mislead
    strict = DeadZoneLearning(
        min_motion_rad=10.0, judge_motion_rad=1e9, rate=1.0, below_v=1.5, max_v=1.0
    )
    assert run_window(strict, 0.8, 0.4) == 0.1  # the model moved less than the minimum
    capped = DeadZoneLearning(
        min_motion_rad=0.006, judge_motion_rad=1e9, rate=1.0, below_v=1.5, max_v=0.3
    )
    assert run_window(capped, 0.8, 0.4) == 0.3  # never above the largest believed


def test_coarse_counts_are_not_taken_for_a_dead_zone() -> None:
    """A 1024-count encoder hides sub-count motion; the learning must not read it as a dead
    zone (an innovation-correlation rule did: 0.1 → 0.79 V, and the ball never rested)."""
    state, rest_time_s = final_state(["sensors.encoder_counts_per_rev=1024", "sensors.adc_bits=12"])
    assert state.deadzone_v == pytest.approx(0.1, abs=0.05)
    assert rest_time_s is not None


def noise_law(levels: tuple[float, ...] = (1.0, 2.0, 4.0)) -> NoiseAdaptation:
    pole = 0.285  # 200 Hz first-order noise sampled at 1 kHz
    gains = tuple(
        tuple((float(level * row), float(-level * row)) for row in range(4))
        for level in levels
    )
    return NoiseAdaptation(
        levels=levels,
        tracking_gains=gains,  # type: ignore[arg-type]
        rest_gains=None,
        expected_square=(6.0 - 8.0 * pole + 2.0 * pole * pole),  # σ = 1 unit
        smoothing_per_cycle=1e-3 / 0.3,
    )


@pytest.mark.parametrize("true_level", [0.5, 1.0, 3.0, 5.0])
def test_the_noise_level_is_measured_from_the_second_difference(true_level: float) -> None:
    """First-order band-limited noise of std = true_level (the design assumes 1), plus a ball
    moving on a parabola (its second difference is not noise): the measured level is the true
    one within 10 % (never below 1, the design's own)."""
    law = noise_law((1.0, 2.0, 4.0, 8.0))
    rng = np.random.default_rng(2)
    pole = 0.285
    noise = true_level * rng.standard_normal()
    mean_square = law.expected_square
    positions: list[float] = []
    for k in range(4000):
        noise = pole * noise + math.sqrt(1 - pole * pole) * true_level * rng.standard_normal()
        positions.append(noise + 0.5 * 0.37e-6 * k * k * 100)  # 0.37 m/s², measurement units
        if len(positions) >= 3:
            second = positions[-1] - 2 * positions[-2] + positions[-3]
            mean_square = law.smoothed(mean_square, second)
    assert law.level(mean_square) == pytest.approx(max(true_level, 1.0), rel=0.1)


def test_the_filter_gain_is_interpolated_between_the_designed_levels() -> None:
    law = noise_law()
    assert law.gain(2.0, rest=False) == law.tracking_gains[1]
    assert law.gain(1.0, rest=True) == law.tracking_gains[0]  # no rest table: the tracking one
    midway = law.gain(3.0, rest=False)
    for row, (a, b) in enumerate(midway):
        assert a == pytest.approx(3.0 * row) and b == pytest.approx(-3.0 * row)
    assert law.gain(99.0, rest=False) == law.tracking_gains[-1]  # clamped to the table


def test_a_noisy_sensor_is_filtered_for_its_noise() -> None:
    """5× the position noise: with the filter chosen for the measured level the ball rests
    within 10 % of the minimum time and the input varies far less; with the design's filter it
    rests at 1.76 T* (issue 12 asks for 1.4 at most)."""
    adapted = run_offline(load_config(PAPER, ["plant.position_noise_m=1e-3"])).metrics
    fixed = run_offline(
        load_config(PAPER, ["plant.position_noise_m=1e-3", "observer.adapt_noise=false"])
    ).metrics
    assert adapted.input_tv_ratio is not None and fixed.input_tv_ratio is not None
    assert adapted.rest_ratio is not None and fixed.rest_ratio is not None
    assert adapted.rest_ratio <= 1.1 and fixed.rest_ratio > 1.4
    assert adapted.input_tv_ratio < 0.8 * fixed.input_tv_ratio
