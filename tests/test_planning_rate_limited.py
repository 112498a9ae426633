"""Servo-rate-limited minimum-time path, checked against Ruckig as an independent solver."""

from __future__ import annotations

import math

import numpy as np
import pytest
import ruckig
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.testing import assert_allclose
from scipy.integrate import solve_ivp

from ballbeam.core.model import BALL_POSITION, BALL_VELOCITY, THETA, THETA_RATE, PhysicalConstants
from ballbeam.core.planning.rate_limited import (
    RateLimitedPlan,
    plan_rate_limited,
    solve_jerk_profile,
)
from ballbeam.errors import PlanningError

CONSTANTS = PhysicalConstants()
GAMMA = CONSTANTS.gamma
THETA_MAX_RAD = math.radians(52.0)
ACCEL_MAX = abs(GAMMA) * THETA_MAX_RAD
PAPER_START = np.array([math.radians(-52.0), 0.0, 0.0, 0.195])
# Both solvers are exact up to rounding; observed agreement is ~1e-12 s.
DURATION_ATOL_S = 1e-9
POSITION_ATOL_M = 1e-9


def ruckig_trajectory(
    position_m: float, velocity_m_s: float, accel_m_s2: float, accel_max: float, jerk_max: float
) -> ruckig.Trajectory:
    inp = ruckig.InputParameter(1)
    inp.current_position = [position_m]
    inp.current_velocity = [velocity_m_s]
    inp.current_acceleration = [accel_m_s2]
    inp.target_position = [0.0]
    inp.target_velocity = [0.0]
    inp.target_acceleration = [0.0]
    inp.max_velocity = [1e3]  # effectively unbounded, as in our problem
    inp.max_acceleration = [accel_max]
    inp.max_jerk = [jerk_max]
    trajectory = ruckig.Trajectory(1)
    result = ruckig.Ruckig(1).calculate(inp, trajectory)
    assert result in (ruckig.Result.Working, ruckig.Result.Finished)
    return trajectory


def compare_with_ruckig(start: np.ndarray, theta_rate_max_rad_s: float) -> float:
    """Check duration and path against Ruckig; return the duration difference."""
    plan = plan_rate_limited(CONSTANTS, THETA_MAX_RAD, theta_rate_max_rad_s, start)
    reference = ruckig_trajectory(
        start[BALL_POSITION],
        start[BALL_VELOCITY],
        GAMMA * start[THETA],
        ACCEL_MAX,
        abs(GAMMA) * theta_rate_max_rad_s,
    )
    difference = plan.duration_s - float(reference.duration)
    assert abs(difference) <= DURATION_ATOL_S
    t = np.linspace(0.0, min(plan.duration_s, reference.duration), 9)
    ours = plan.sample(t).states
    theirs = np.array([[values[0] for values in reference.at_time(ti)] for ti in t])
    assert_allclose(ours[:, BALL_POSITION], theirs[:, 0], atol=POSITION_ATOL_M)
    assert_allclose(ours[:, BALL_VELOCITY], theirs[:, 1], atol=1e-8)
    assert_allclose(ours[:, THETA] * GAMMA, theirs[:, 2], atol=1e-8)
    return difference


@pytest.mark.parametrize("theta_rate_max_rad_s", [9.325, 8.0])
def test_paper_cases_match_ruckig(theta_rate_max_rad_s: float) -> None:
    compare_with_ruckig(PAPER_START, theta_rate_max_rad_s)
    plan = plan_rate_limited(CONSTANTS, THETA_MAX_RAD, theta_rate_max_rad_s, PAPER_START)
    # Longer than the bang-bang 1.444 s and than the paper's own (suboptimal-shape) figures,
    # because the servo first has to swing from −52° through to the other side.
    assert plan.duration_s > 1.444
    assert plan.kind == "rate_limited"


def test_paper_case_durations() -> None:
    fast = plan_rate_limited(CONSTANTS, THETA_MAX_RAD, 9.325, PAPER_START)
    slow = plan_rate_limited(CONSTANTS, THETA_MAX_RAD, 8.0, PAPER_START)
    assert_allclose(fast.duration_s, 1.699815, atol=1e-6)
    assert_allclose(slow.duration_s, 1.744578, atol=1e-6)
    # Servo at −52° pushes the ball the wrong way: the first bang swings it up at full rate.
    assert fast.segments[0].jerk_m_s3 < 0.0
    assert_allclose(abs(fast.segments[0].jerk_m_s3), abs(GAMMA) * 9.325, rtol=1e-12)


def test_random_starts_match_ruckig() -> None:
    rng = np.random.default_rng(20040601)
    differences = []
    for index in range(300):
        theta0 = rng.uniform(-THETA_MAX_RAD, THETA_MAX_RAD)
        if index % 5 == 0:  # starts on the angle bound, as in the paper
            theta0 = float(rng.choice([-THETA_MAX_RAD, THETA_MAX_RAD]))
        velocity = 0.0 if index % 7 == 0 else rng.uniform(-0.5, 0.5)
        start = np.array([theta0, 0.0, velocity, rng.uniform(-0.25, 0.25)])
        differences.append(compare_with_ruckig(start, rng.uniform(2.0, 12.0)))
    assert max(abs(d) for d in differences) <= DURATION_ATOL_S


def test_ball_only_profile_matches_ruckig_on_edge_starts() -> None:
    jerk_max = abs(GAMMA) * 9.325
    brake_velocity = ACCEL_MAX**2 / (2.0 * jerk_max)  # a = −A brought to 0 stops exactly here
    starts = [
        (0.0, 0.0, ACCEL_MAX),
        (0.0, 0.0, -0.1),
        (0.0, brake_velocity, -ACCEL_MAX),
        (0.01, brake_velocity, -ACCEL_MAX),
        (-0.01, brake_velocity, -ACCEL_MAX),
        (0.2, 0.3, -ACCEL_MAX),
        (5.0, 2.0, 0.1),
    ]
    for p0, v0, a0 in starts:
        profile = solve_jerk_profile(p0, v0, a0, ACCEL_MAX, jerk_max)
        reference = ruckig_trajectory(p0, v0, a0, ACCEL_MAX, jerk_max)
        assert abs(profile.duration_s - reference.duration) <= DURATION_ATOL_S
        assert_allclose(profile.knot_states[-1], 0.0, atol=1e-12)


def integrate_jerk_model(
    plan: RateLimitedPlan, start: np.ndarray, t_eval: np.ndarray
) -> np.ndarray:
    """θ̇_d → θ → ẋ → x by an adaptive ODE solver, from the start; rows (θ, ẋ, x)."""

    def rhs(time_s: float, y: np.ndarray) -> np.ndarray:
        theta_rate = plan.sample(np.array([time_s])).states[0, THETA_RATE]
        return np.array([theta_rate, GAMMA * y[0], y[1]])

    solution = solve_ivp(
        rhs,
        (0.0, plan.duration_s),
        [start[THETA], start[BALL_VELOCITY], start[BALL_POSITION]],
        t_eval=t_eval,
        rtol=1e-11,
        atol=1e-13,
        max_step=0.01,
    )
    assert solution.success
    result: np.ndarray = solution.y
    return result


@pytest.mark.parametrize(
    ("start", "theta_rate_max_rad_s"),
    [
        (PAPER_START, 9.325),
        (PAPER_START, 8.0),
        (np.array([0.3, 0.0, 0.4, -0.1]), 3.0),
        (np.array([-0.5, 0.0, -0.3, 0.2]), 11.0),
    ],
    ids=["paper-9.325", "paper-8", "moving-away", "braking"],
)
def test_path_is_dynamically_consistent(start: np.ndarray, theta_rate_max_rad_s: float) -> None:
    plan = plan_rate_limited(CONSTANTS, THETA_MAX_RAD, theta_rate_max_rad_s, start)
    t_eval = np.linspace(0.0, plan.duration_s, 201)
    integrated = integrate_jerk_model(plan, start, t_eval)
    states = plan.sample(t_eval).states
    assert_allclose(integrated[0], states[:, THETA], atol=1e-7)
    assert_allclose(integrated[1], states[:, BALL_VELOCITY], atol=1e-7)
    assert_allclose(integrated[2], states[:, BALL_POSITION], atol=1e-7)
    assert_allclose(integrated[:, -1], 0.0, atol=1e-7)


@pytest.mark.parametrize("theta_rate_max_rad_s", [9.325, 8.0, 2.0])
def test_bounds_end_state_and_input(theta_rate_max_rad_s: float) -> None:
    plan = plan_rate_limited(CONSTANTS, THETA_MAX_RAD, theta_rate_max_rad_s, PAPER_START)
    t = np.linspace(-0.5, plan.duration_s + 0.5, 20001)
    samples = plan.sample(t)
    states = samples.states
    assert np.all(np.abs(states[:, THETA]) <= THETA_MAX_RAD + 1e-9)
    assert np.all(np.abs(states[:, THETA_RATE]) <= theta_rate_max_rad_s + 1e-9)
    assert_allclose(samples.input_v, CONSTANTS.beta * states[:, THETA_RATE], rtol=1e-15)
    after = t >= plan.duration_s
    assert np.all(states[after] == 0.0) and np.all(samples.input_v[after] == 0.0)
    before = t < 0.0
    assert_allclose(states[before], np.tile(PAPER_START, (before.sum(), 1)), atol=0)
    assert np.all(samples.input_v[before] == 0.0)
    # Continuity of (θ, ẋ, x) across every knot and into the rest at T.
    knots = plan.profile.knot_time_s
    left = plan.sample(knots - 1e-10).states[:, [THETA, BALL_VELOCITY, BALL_POSITION]]
    right = plan.sample(knots).states[:, [THETA, BALL_VELOCITY, BALL_POSITION]]
    assert_allclose(left[1:], right[1:], atol=1e-8)


def test_start_at_rest_at_origin_is_an_empty_plan() -> None:
    plan = plan_rate_limited(CONSTANTS, THETA_MAX_RAD, 9.325, np.array([0.0, 0.0, 0.0, 0.0]))
    assert plan.duration_s == 0.0
    assert plan.segments == ()
    assert np.all(plan.sample(np.array([-1.0, 0.0, 1.0])).states == 0.0)


@pytest.mark.parametrize(
    ("theta_max_rad", "theta_rate_max_rad_s", "start"),
    [
        (THETA_MAX_RAD, 0.0, PAPER_START),
        (THETA_MAX_RAD, -9.0, PAPER_START),
        (0.0, 9.325, np.zeros(4)),
        (-THETA_MAX_RAD, 9.325, PAPER_START),
        (THETA_MAX_RAD, 9.325, np.array([math.radians(53.0), 0.0, 0.0, 0.1])),
        (THETA_MAX_RAD, 9.325, np.array([0.0, 0.0, 0.1])),
    ],
    ids=["zero-rate", "negative-rate", "zero-angle", "negative-angle", "start-beyond", "shape"],
)
def test_refuses_infeasible_requests(
    theta_max_rad: float, theta_rate_max_rad_s: float, start: np.ndarray
) -> None:
    with pytest.raises(PlanningError):
        plan_rate_limited(CONSTANTS, theta_max_rad, theta_rate_max_rad_s, start)


def test_ball_only_profile_refuses_bad_limits() -> None:
    with pytest.raises(ValueError, match="beyond the bound"):
        solve_jerk_profile(0.1, 0.0, 1.0, 0.5, 1.0)
    with pytest.raises(PlanningError):
        solve_jerk_profile(0.1, 0.0, 0.0, 0.5, math.inf)


@settings(max_examples=300, deadline=None)
@given(
    position=st.floats(-0.5, 0.5),
    velocity=st.floats(-1.0, 1.0),
    theta_fraction=st.floats(-1.0, 1.0),
    theta_rate_max_rad_s=st.floats(0.5, 50.0),
)
def test_property_ends_at_rest_within_bounds(
    position: float, velocity: float, theta_fraction: float, theta_rate_max_rad_s: float
) -> None:
    start = np.array([theta_fraction * THETA_MAX_RAD, 0.0, velocity, position])
    plan = plan_rate_limited(CONSTANTS, THETA_MAX_RAD, theta_rate_max_rad_s, start)
    profile = plan.profile
    scale = max(1.0, plan.duration_s) ** 2
    assert_allclose(profile.knot_states[-1], 0.0, atol=1e-10 * scale)
    assert np.all(np.diff(profile.knot_time_s) > 0.0)
    jerk_max = abs(GAMMA) * theta_rate_max_rad_s
    for segment in plan.segments:
        assert segment.jerk_m_s3 in (0.0, jerk_max, -jerk_max)
    t = np.linspace(0.0, plan.duration_s, 257)
    states = plan.sample(np.append(t, plan.duration_s + 1.0)).states
    assert np.all(np.abs(states[:, THETA]) <= THETA_MAX_RAD + 1e-9)
    assert np.all(np.abs(states[:, THETA_RATE]) <= theta_rate_max_rad_s + 1e-9)
    assert np.all(states[-2:] == 0.0)
