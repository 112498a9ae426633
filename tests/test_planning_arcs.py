"""The arc planner: exact continuous minimum-time paths, checked against the grid LP (an
independent formulation: HiGHS on a 1 kHz grid) and by integrating the ODE numerically."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from ballbeam.core.model import LinearModel, PhysicalConstants
from ballbeam.core.planning.arcs import ArcPlan, plan_arcs, replan
from ballbeam.core.planning.time_optimal import plan_time_optimal
from ballbeam.errors import PlanningError

MODEL = LinearModel.from_constants(PhysicalConstants())
THETA_MAX = math.radians(52.0)
PAPER_START = np.array([-THETA_MAX, 0.0, 0.0, 0.195])


def integrate(plan: ArcPlan, start: np.ndarray) -> tuple[np.ndarray, float]:
    """End state and largest |θ| of the plan's inputs applied to ẋ = Ax + Bu by RK45."""
    A, B = MODEL.A, MODEL.B[:, 0]
    state = np.array(start, dtype=float)
    biggest = abs(state[0])
    for u, tau in zip(plan.input_v, plan.duration_s_each, strict=True):
        if tau <= 0.0:
            continue
        sol = solve_ivp(
            lambda _t, x, u=u: A @ x + B * u,
            (0.0, tau),
            state,
            rtol=1e-11,
            atol=1e-13,
            dense_output=True,
        )
        inside = sol.sol(np.linspace(0.0, tau, 200))
        biggest = max(biggest, float(np.max(np.abs(inside[0]))))
        state = sol.y[:, -1]
    return state, biggest


def test_paper_start_is_the_continuous_optimum_of_the_fine_grid() -> None:
    plan = plan_arcs(MODEL, PAPER_START)
    grid = plan_time_optimal(
        MODEL, PAPER_START, voltage_limit_v=5.0, theta_max_rad=THETA_MAX, step_s=5e-4
    )
    # the grid holds inputs over whole steps: its optimum is at most a step slower
    assert 0.0 <= grid.duration_s - plan.duration_s <= 5e-4 + 2e-4
    # full voltage and holds, two of them: up to +52°, across to −52°, back to rest
    assert plan.holds == (0, 0, 1, 0, 0, -1, 0, 0)
    assert {abs(u) for u in plan.input_v} == {0.0, 5.0}


def test_arcs_reach_rest_within_the_limit_by_numerical_integration() -> None:
    plan = plan_arcs(MODEL, PAPER_START, target_m=0.05)
    end, biggest = integrate(plan, PAPER_START - np.array([0.0, 0.0, 0.0, 0.05]))
    np.testing.assert_allclose(end, 0.0, atol=1e-7)
    assert biggest <= THETA_MAX * (1.0 + 1e-7)


def test_sample_is_continuous_and_ends_at_rest() -> None:
    plan = plan_arcs(MODEL, PAPER_START)
    t = np.linspace(0.0, plan.duration_s + 0.1, 4001)
    states = plan.sample(t).states
    assert np.max(np.abs(np.diff(states[:, 0]))) < 0.01  # no jumps in the angle
    np.testing.assert_allclose(states[-1], 0.0, atol=1e-9)
    np.testing.assert_allclose(states[0], PAPER_START, atol=0.0)


def test_a_target_is_a_shift_of_the_ball_position() -> None:
    start = np.array([0.2, 0.0, 0.0, 0.1])
    to_target = plan_arcs(MODEL, start, target_m=-0.08)
    shifted = plan_arcs(MODEL, start + np.array([0.0, 0.0, 0.0, 0.08]))
    assert to_target.duration_s == pytest.approx(shifted.duration_s, abs=1e-9)


@pytest.mark.parametrize("seed", range(6))
def test_random_starts_agree_with_the_grid_planner(seed: int) -> None:
    rng = np.random.default_rng(seed)
    start = np.array(
        [
            rng.uniform(-0.9, 0.9) * THETA_MAX,
            rng.uniform(-3.0, 3.0),
            rng.uniform(-0.15, 0.15),
            rng.uniform(-0.2, 0.2),
        ]
    )
    grid = plan_time_optimal(MODEL, start, voltage_limit_v=5.0, theta_max_rad=THETA_MAX)
    try:
        plan = plan_arcs(MODEL, start)
    except PlanningError:
        pytest.fail(f"no exact arcs from {start.tolist()} (grid plan: {grid.duration_s} s)")
    # 1 ms grid, and its samples kept inside the limit by its intersample margin
    assert -1e-9 <= grid.duration_s - plan.duration_s <= 1.5e-3
    end, biggest = integrate(plan, start)
    np.testing.assert_allclose(end, 0.0, atol=1e-7)
    assert biggest <= THETA_MAX * (1.0 + 1e-7)


def test_replan_on_the_path_keeps_the_rest_of_the_plan() -> None:
    plan = plan_arcs(MODEL, PAPER_START)
    for elapsed_s in (0.05, 0.5, 1.0, 1.65, plan.duration_s - 0.005):
        state = plan.sample(np.array([elapsed_s])).states[0]
        again = replan(plan, elapsed_s, state)
        assert again is not None
        assert again.duration_s == pytest.approx(plan.duration_s - elapsed_s, abs=1e-9)


def test_replan_follows_a_model_update() -> None:
    """A ball 5 % stronger, identified part-way: the warm start finds the new optimum, which
    the grid planner on the new model confirms."""
    plan = plan_arcs(MODEL, PAPER_START)
    stronger = LinearModel.from_constants(PhysicalConstants(), ball_gain_scale=1.05)
    elapsed_s = 0.3
    state = plan.sample(np.array([elapsed_s])).states[0]
    from ballbeam.core.planning.lag_hold import _params

    again = replan(plan, elapsed_s, state, params=_params(stronger))
    assert again is not None
    grid = plan_time_optimal(stronger, state, voltage_limit_v=5.0, theta_max_rad=THETA_MAX)
    assert -1e-9 <= grid.duration_s - again.duration_s <= 1.5e-3
