"""The task's references (core/task.py) against analytic answers."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.testing import assert_allclose, assert_array_equal

from ballbeam.assembly import make_task
from ballbeam.config import load_config
from ballbeam.core.task import (
    FixedTarget,
    SineWave,
    SquareWave,
    StepSchedule,
    flat_feedforward,
)
from ballbeam.errors import ConfigError


def test_the_default_task_is_the_papers_fixed_target_at_zero() -> None:
    task = make_task(load_config(None))
    assert task == FixedTarget(0.0)
    assert task.kind == "fixed"
    assert task.target_at(3.0) == 0.0
    assert task.change_times_s(0.0, 100.0).size == 0
    assert task.next_change_after(0.0) is None
    flat = task.reference_at(np.array([0.0, 1.0]))
    assert_array_equal(flat.velocity_m_s, [0.0, 0.0])


def test_a_step_schedule_holds_each_target_from_its_instant() -> None:
    task = StepSchedule(times_s=(0.0, 4.0, 6.5), targets_m=(0.0, -0.1, 0.05))
    times = np.array([-1.0, 0.0, 3.999, 4.0, 6.4, 6.5, 100.0])
    assert_array_equal(task.target_at(times), [0.0, 0.0, 0.0, -0.1, -0.1, 0.05, 0.05])
    assert task.target_at(4.0) == -0.1
    assert_array_equal(task.change_times_s(0.0, 10.0), [4.0, 6.5])
    assert_array_equal(task.change_times_s(4.0, 6.5), [6.5])  # (start, end]
    assert task.next_change_after(0.0) == 4.0
    assert task.next_change_after(4.0) == 6.5
    assert task.next_change_after(6.5) is None
    assert task.kind == "steps"


def test_a_step_schedule_must_ascend_from_zero() -> None:
    with pytest.raises(ConfigError):
        StepSchedule(times_s=(1.0,), targets_m=(0.0,))
    with pytest.raises(ConfigError):
        StepSchedule(times_s=(0.0, 2.0, 2.0), targets_m=(0.0, 0.1, 0.2))


@settings(max_examples=60, deadline=None)
@given(
    amplitude_m=st.floats(0.001, 0.1),
    period_s=st.floats(0.1, 20.0),
    offset_m=st.floats(-0.1, 0.1),
    fractions=st.lists(st.floats(0.0, 1.0), min_size=1, max_size=20),
)
def test_a_square_wave_is_the_step_schedule_it_expands_to(
    amplitude_m: float, period_s: float, offset_m: float, fractions: list[float]
) -> None:
    until_s = 7.3 * period_s
    square = SquareWave(amplitude_m, period_s, offset_m)
    steps = square.as_steps(until_s)
    # +A for the first half period, then −A, and so on (Quanser's and Berkeley's phase).
    assert steps.times_s[:3] == (0.0, 0.5 * period_s, period_s)
    assert steps.targets_m[:2] == (offset_m + amplitude_m, offset_m - amplitude_m)
    times = np.array([f * until_s for f in fractions] + list(steps.times_s))
    assert_array_equal(square.target_at(times), steps.target_at(times))
    assert_array_equal(square.change_times_s(0.0, until_s), steps.change_times_s(0.0, until_s))
    for time_s in times:
        assert square.next_change_after(float(time_s)) == pytest.approx(
            (math.floor(time_s / (0.5 * period_s) + 1e-9) + 1) * 0.5 * period_s, rel=1e-12
        )


def test_a_square_wave_changes_at_its_own_instants_exactly() -> None:
    square = SquareWave(0.04, 10.0)
    changes = square.change_times_s(0.0, 30.0)
    assert_array_equal(changes, [5.0, 10.0, 15.0, 20.0, 25.0, 30.0])
    assert_array_equal(square.target_at(changes), [-0.04, 0.04, -0.04, 0.04, -0.04, 0.04])
    assert_array_equal(square.target_at(changes - 1e-9), [0.04, -0.04, 0.04, -0.04, 0.04, -0.04])
    assert square.next_change_after(5.0) == 10.0


def test_a_sines_flat_outputs_are_its_derivatives() -> None:
    amplitude_m, period_s, offset_m = 0.04, 10.0, 0.01
    sine = SineWave(amplitude_m, period_s, offset_m)
    times = np.linspace(0.0, 20.0, 401)
    w = 2.0 * math.pi / period_s
    flat = sine.reference_at(times)
    assert_allclose(flat.position_m, offset_m + amplitude_m * np.sin(w * times), atol=1e-15)
    assert_allclose(flat.velocity_m_s, amplitude_m * w * np.cos(w * times), atol=1e-15)
    assert_allclose(flat.acceleration_m_s2, -amplitude_m * w**2 * np.sin(w * times), atol=1e-15)
    assert_allclose(flat.jerk_m_s3, -amplitude_m * w**3 * np.cos(w * times), atol=1e-15)
    assert_allclose(flat.snap_m_s4, amplitude_m * w**4 * np.sin(w * times), atol=1e-15)
    # And each is the time derivative of the one before (central differences).
    h = 1e-4
    for lower, higher in (("position_m", "velocity_m_s"), ("velocity_m_s", "acceleration_m_s2"),
                          ("acceleration_m_s2", "jerk_m_s3"), ("jerk_m_s3", "snap_m_s4")):
        slope = (getattr(sine.reference_at(times + h), lower)
                 - getattr(sine.reference_at(times - h), lower)) / (2 * h)
        assert_allclose(slope, getattr(flat, higher), rtol=1e-6, atol=1e-9)
    assert sine.kind == "sine" and sine.next_change_after(0.0) is None
    assert sine.target_at(2.5) == pytest.approx(offset_m + amplitude_m)


def test_flat_feedforward_keeps_the_linear_model_on_the_sine() -> None:
    # ẍ = γθ and θ̈ = α u − αβ θ̇: the feedforward's state and input satisfy both.
    gamma, alpha, alpha_beta = -0.4122, 108.9, 58.47
    sine = SineWave(0.04, 10.0)
    times = np.linspace(0.0, 10.0, 101)
    states, input_v = flat_feedforward(sine.reference_at(times), gamma, alpha, alpha_beta)
    assert states.shape == (101, 4) and input_v.shape == (101,)
    flat = sine.reference_at(times)
    assert_allclose(gamma * states[:, 0], flat.acceleration_m_s2, rtol=1e-12)
    assert_allclose(gamma * states[:, 1], flat.jerk_m_s3, rtol=1e-12)
    assert_allclose(states[:, 2], flat.velocity_m_s)
    assert_allclose(states[:, 3], flat.position_m)
    theta_accel = flat.snap_m_s4 / gamma
    assert_allclose(alpha * input_v - alpha_beta * states[:, 1], theta_accel, atol=1e-12)
    # Berkeley's 4 cm, 10 s sine asks for a small angle: |θ| = A ω² / |γ| ≈ 0.22°.
    assert math.degrees(np.max(np.abs(states[:, 0]))) == pytest.approx(
        math.degrees(0.04 * (2 * math.pi / 10) ** 2 / 0.4122), rel=1e-3
    )


def test_make_task_builds_each_shape_from_the_config() -> None:
    assert make_task(load_config(None, ["task.target_m=-0.05"])) == FixedTarget(-0.05)
    assert make_task(load_config(None, ["task.setpoints=[[0.0, 0.0], [4.0, -0.1]]"])) == (
        StepSchedule(times_s=(0.0, 4.0), targets_m=(0.0, -0.1))
    )
    assert make_task(
        load_config(None, ["task.square.amplitude_m=0.05", "task.square.period_s=4"])
    ) == SquareWave(0.05, 4.0, 0.0)
    assert make_task(
        load_config(None, ["task.sine={amplitude_m=0.04, period_s=10, offset_m=0.01}"])
    ) == SineWave(0.04, 10.0, 0.01)
