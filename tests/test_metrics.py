"""Run metrics on hand-built traces with known answers."""

from __future__ import annotations

import math

import numpy as np
import pytest

from ballbeam.core.metrics import (
    compute_metrics,
    dither_hz,
    first_entry_time,
    input_tv_ratio,
    largest_step_v,
    relapse_s,
    rest_time,
    settle_time,
    sign_changes,
)


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
