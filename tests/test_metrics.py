"""Run metrics on hand-built traces with known answers."""

from __future__ import annotations

import math

import numpy as np
import pytest

from ballbeam.core.metrics import (
    SegmentRest,
    compute_metrics,
    dither_hz,
    first_entry_time,
    input_tv_ratio,
    largest_step_v,
    relapse_s,
    rest_time,
    segment_rest_times,
    settle_time,
    sign_changes,
)
from ballbeam.core.task import FixedTarget, SquareWave, StepSchedule


def _states(theta: np.ndarray, position: np.ndarray) -> np.ndarray:
    states = np.zeros((len(position), 4))
    states[:, 0] = theta
    states[:, 3] = position
    return states


def test_settle_time_is_the_first_time_after_which_the_ball_stays_in_band() -> None:
    t = np.arange(10) * 0.5
    x = np.array([0.1, 0.05, 0.001, 0.003, 0.0015, -0.001, 0.0, 0.0, 0.0, 0.0])
    # Leaves the band at index 3 (3 mm), back inside from index 4 on: settles at t[4] = 2.0 s.
    assert settle_time(t, x, 0.002) == 2.0
    assert settle_time(t, np.full(10, 0.01), 0.002) is None
    assert settle_time(t, np.zeros(10), 0.002) == 0.0
    # Outside at the very last sample: never settled.
    assert settle_time(t, np.r_[np.zeros(9), 0.01], 0.002) is None


def test_metrics_on_a_known_trace() -> None:
    t = np.arange(5) * 0.001
    theta = np.radians([-52.0, 53.0, 54.0, 10.0, 0.0])
    x = np.array([0.195, 0.1, -0.004, -0.001, 0.0])
    ref = np.array([0.195, 0.1, 0.0, 0.0, 0.0])
    u = np.array([5.0, -5.0, 4.0, 0.0, -6.0])
    metrics = compute_metrics(t, _states(theta, x), u, ref, math.radians(52))
    assert metrics.settle_time_s == pytest.approx(0.003)
    assert metrics.overshoot_mm == pytest.approx(4.0)
    assert metrics.max_abs_theta_deg == pytest.approx(54.0)
    assert metrics.theta_violation_s == pytest.approx(0.002)
    assert metrics.max_abs_u_v == 6.0
    assert metrics.tracking_rms_mm == pytest.approx(1e3 * math.sqrt((0.004**2 + 0.001**2) / 5))


def test_overshoot_is_measured_past_zero_on_the_far_side_of_the_start() -> None:
    t = np.arange(4) * 0.01
    from_left = compute_metrics(
        t, _states(np.zeros(4), np.array([-0.1, 0.0, 0.003, 0.0])), np.zeros(4), np.zeros(4), 1.0
    )
    assert from_left.overshoot_mm == pytest.approx(3.0)
    no_overshoot = compute_metrics(
        t, _states(np.zeros(4), np.array([0.1, 0.05, 0.01, 0.0])), np.zeros(4), np.zeros(4), 1.0
    )
    assert no_overshoot.overshoot_mm == 0.0


def test_rest_needs_both_bands_to_the_end() -> None:
    t = np.arange(6) * 0.1
    x = np.array([0.01, 0.0004, 0.0006, 0.0001, 0.0, 0.0])
    theta = np.radians([0.0, 0.0, 0.0, 0.6, 0.2, 0.0])
    # x leaves 0.5 mm at index 2, θ leaves 0.5° at index 3: at rest from index 4
    assert rest_time(t, _states(theta, x)) == pytest.approx(0.4)
    assert rest_time(t, _states(np.zeros(6), np.full(6, 0.001))) is None
    metrics = compute_metrics(
        t, _states(theta, x), np.zeros(6), np.zeros(6), 1.0, minimum_time_s=0.2
    )
    assert metrics.rest_ratio == pytest.approx(2.0)


def test_chatter_figures() -> None:
    plan = np.array([5.0, 5.0, 5.0, -5.0, -5.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    command = plan + np.array([0, 0.1, 0, 0, 0, 0.3, -0.3, 0.3, 0, 0])
    assert input_tv_ratio(command, plan) == pytest.approx(np.abs(np.diff(command)).sum() / 15.0)
    # the plan switches at steps 2 (2→3) and 4 (4→5): steps 0..6 are within two periods of
    # them (the 0.6 V flips at 5 and 6 among them); step 7 (0.3 V back to 0) is the largest left
    assert largest_step_v(command, plan) == pytest.approx(0.3)
    assert sign_changes(np.array([0.2, 0.0, -0.1, -0.2, 0.0, 0.3])) == 2  # zeros are skipped
    t = np.arange(3000) * 1e-3
    u = np.where(np.arange(3000) % 100 < 50, 0.2, -0.2)  # 10 Hz square wave
    assert dither_hz(t, u) == pytest.approx(20.0, abs=1.0)


# -- a task's target ------------------------------------------------------------------------


def test_rest_settle_and_overshoot_are_measured_from_the_target() -> None:
    t = np.arange(8) * 0.5
    # From 0.15 m to a target of 0.05 m: passes it by 1 mm on the far side, then rests.
    x = np.array([0.15, 0.1, 0.049, 0.0493, 0.0496, 0.0504, 0.05, 0.05])
    theta = np.zeros(8)
    states = _states(theta, x)
    m = compute_metrics(t, states, np.zeros(8), np.full(8, 0.05), math.radians(52),
                        target_m=0.05)
    assert m.rest_time_s == 2.0  # |x − 0.05| <= 0.5 mm from 0.0496 m on
    assert m.settle_time_s == 1.0
    assert m.overshoot_mm == pytest.approx(1.0)
    assert m.tracking_rms_mm == pytest.approx(
        1e3 * math.sqrt(np.mean((x - 0.05) ** 2)))
    # At the paper's target 0 the same trace never rests.
    assert compute_metrics(t, states, np.zeros(8), x, math.radians(52)).rest_time_s is None
    # A target per sample (a schedule's x_r(t)).
    target = np.where(t < 1.0, 0.15, 0.05)
    assert rest_time(t, states, target_m=target) == 2.0


def _schedule_trace() -> tuple[np.ndarray, np.ndarray]:
    """1 ms samples over 6 s: the ball at 0 until 2 s, then it moves to −0.1 m, resting there
    from 2.8 s, and at 4 s it goes to 0.05 m, resting from 4.5 s; θ tilts 1° while it moves."""
    t = np.arange(6000) * 1e-3
    x = np.zeros_like(t)
    theta = np.zeros_like(t)
    first = (t >= 2.0) & (t < 2.8)
    x[first] = -0.1 * (t[first] - 2.0) / 0.8
    theta[first] = math.radians(1.0)
    x[(t >= 2.8) & (t < 4.0)] = -0.1
    second = (t >= 4.0) & (t < 4.5)
    x[second] = -0.1 + 0.15 * (t[second] - 4.0) / 0.5
    x[t >= 4.5] = 0.05
    return t, _states(theta, x)


def test_each_segment_of_a_schedule_has_its_own_rest() -> None:
    t, states = _schedule_trace()
    task = StepSchedule(times_s=(0.0, 2.0, 4.0), targets_m=(0.0, -0.1, 0.05))
    segments = segment_rest_times(t, states, task)
    assert [s.start_s for s in segments] == [0.0, 2.0, 4.0]
    assert [s.target_m for s in segments] == [0.0, -0.1, 0.05]
    assert segments[0].rest_after_s == 0.0
    # The ramp reaches −0.1 m within 0.5 mm before 2.8 s, but θ is 1° until then.
    assert segments[1].rest_after_s == pytest.approx(0.8, abs=1e-9)
    # The ramp to 0.05 m reaches 0.0495 m at 4.5 s − 0.5 mm / (0.3 m/s): rest from there.
    assert segments[2].rest_after_s == pytest.approx(0.5 - 0.0005 / 0.3, abs=1.5e-3)


def test_a_segment_that_never_rests_says_so() -> None:
    t, states = _schedule_trace()
    states[(t >= 3.0) & (t < 3.5), 3] = -0.09  # knocked out of the band within segment 2
    task = StepSchedule(times_s=(0.0, 2.0, 4.0), targets_m=(0.0, -0.1, 0.04))
    segments = segment_rest_times(t, states, task)
    assert segments[1].rest_after_s == pytest.approx(1.5, abs=1e-9)
    assert segments[2].rest_after_s is None  # 0.05 m is 10 mm off the 0.04 m target


def test_a_square_waves_segments_are_its_half_periods() -> None:
    t = np.arange(4000) * 1e-3
    square = SquareWave(amplitude_m=0.05, period_s=2.0)
    states = _states(np.zeros_like(t), square.target_at(t))  # a ball exactly on the wave
    segments = segment_rest_times(t, states, square)
    assert [s.start_s for s in segments] == [0.0, 1.0, 2.0, 3.0]
    assert [s.target_m for s in segments] == [0.05, -0.05, 0.05, -0.05]
    assert all(s.rest_after_s == 0.0 for s in segments)
    # A fixed target is one segment, the whole run.
    assert segment_rest_times(t, states, FixedTarget(0.0)) == (SegmentRest(0.0, 0.0, None),)


def test_relapse_is_rest_less_the_first_entry_into_the_rest_band() -> None:
    t = np.arange(12) * 0.1
    level = np.zeros(12)
    # In the band from t = 0.3 s and stays: no relapse.
    x = np.array([0.01, 0.004, 0.001, 0.0004, 0.0, -0.0003, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    assert first_entry_time(t, _states(level, x)) == pytest.approx(0.3)
    assert relapse_s(t, _states(level, x)) == 0.0
    # Enters at 0.3 s, drifts out to 0.7 mm at 0.6 s, back in from 0.8 s: 0.5 s lost.
    x_out = x.copy()
    x_out[6:8] = [0.0007, -0.0006]
    assert first_entry_time(t, _states(level, x_out)) == pytest.approx(0.3)
    assert rest_time(t, _states(level, x_out)) == pytest.approx(0.8)
    assert relapse_s(t, _states(level, x_out)) == pytest.approx(0.5)
    # The ball sits in its band but the servo creeps out past 0.5° and back: a relapse too.
    creeping = np.zeros(12)
    creeping[5] = math.radians(0.6)
    assert relapse_s(t, _states(creeping, x)) == pytest.approx(0.3)
    # Never in the band, or out at the end (a limit cycle the run cuts off): no rest, no figure.
    assert first_entry_time(t, _states(level, np.full(12, 0.01))) is None
    assert relapse_s(t, _states(level, np.full(12, 0.01))) is None
    x_end = x.copy()
    x_end[-1] = 0.001
    assert first_entry_time(t, _states(level, x_end)) == pytest.approx(0.3)
    assert relapse_s(t, _states(level, x_end)) is None


def test_relapse_about_a_target() -> None:
    t = np.arange(6) * 0.1
    target_m = -0.1
    x = target_m + np.array([0.05, 0.0004, 0.0008, 0.0, 0.0001, 0.0])
    states = _states(np.zeros(6), x)
    assert first_entry_time(t, states, target_m) == pytest.approx(0.1)
    assert relapse_s(t, states, target_m) == pytest.approx(0.2)
    assert first_entry_time(t, states) is None  # about 0 the ball is never in the band
