"""Full-model minimum-time path: bounds, minimality against an independent LP, consistency.

The independent checks here share nothing with the planner but the model: the grid matrices
come from the model's own expm-based ``discretize``, the minimality LP keeps every state of
every step as a variable (the planner condenses and windows), the continuous check integrates
the model with ``solve_ivp``, and the lower bounds come from closed forms and from Ruckig.
"""

from __future__ import annotations

import itertools
import math
import re
from typing import Any

import numpy as np
import pytest
import ruckig
import scipy.sparse
from numpy.testing import assert_allclose
from scipy.integrate import solve_ivp
from scipy.optimize import linprog

from ballbeam.core.model import (
    BALL_POSITION,
    BALL_VELOCITY,
    THETA,
    THETA_RATE,
    LinearModel,
    PhysicalConstants,
    zoh_propagate,
)
from ballbeam.core.planning.plan import at_time
from ballbeam.core.planning.time_optimal import (
    TimeOptimalPlan,
    intersample_margin_rad,
    plan_time_optimal,
)
from ballbeam.errors import ConfigError, PlanningError

CONSTANTS = PhysicalConstants()
MODEL = LinearModel.from_constants(CONSTANTS)
ALPHA = CONSTANTS.alpha
BETA = CONSTANTS.beta
GAMMA = CONSTANTS.gamma
MOTOR_TIME_CONSTANT_S = 1.0 / (ALPHA * BETA)  # ≈ 17 ms
THETA_MAX_RAD = math.radians(52.0)
V_MAX = 5.0
PAPER_START = np.array([math.radians(-52.0), 0.0, 0.0, 0.195])
STEP_S = 1e-3

# Continuous integration against the closed form: DOP853 at rtol 1e-12 agrees to 1e-13 rad,
# 1e-11 rad/s, 1e-14 m/s and m; these tolerances leave a factor of 100 or more.
STATE_ATOL = np.array([1e-9, 1e-8, 1e-10, 1e-10])  # rad, rad/s, m/s, m
# The LP solver's tolerance (1e-9 on scaled rows) leaves the end this close to the origin.
END_ATOL = np.array([1e-8, 1e-7, 1e-9, 1e-9])


def assert_states_close(actual: np.ndarray, expected: np.ndarray, atol: np.ndarray) -> None:
    """assert_allclose per state component, each with its own absolute tolerance."""
    actual, expected = np.atleast_2d(actual), np.atleast_2d(expected)
    for i, name in enumerate(("theta", "theta_rate", "ball_velocity", "ball_position")):
        assert_allclose(actual[:, i], expected[:, i], rtol=0, atol=atol[i], err_msg=name)


def paper_plan(margin_v: float, step_s: float = STEP_S) -> TimeOptimalPlan:
    return plan_time_optimal(
        MODEL,
        PAPER_START,
        voltage_limit_v=V_MAX,
        voltage_margin_v=margin_v,
        theta_max_rad=THETA_MAX_RAD,
        step_s=step_s,
    )


@pytest.fixture(scope="module")
def plan_margin() -> TimeOptimalPlan:
    return paper_plan(0.5)


@pytest.fixture(scope="module")
def plan_physical() -> TimeOptimalPlan:
    return paper_plan(0.0)


# ---------------------------------------------------------------- independent references


def sample_margin_rad(voltage_v: float, step_s: float, rate0: float = 0.0) -> float:
    """δ = θ̈max h²/8 with θ̈max = αU + αβ·max(|θ̇0|, U/β), written out from the constants."""
    rate_max = max(abs(rate0), voltage_v / BETA)
    return (ALPHA * voltage_v + ALPHA * BETA * rate_max) * step_s**2 / 8.0


def ball_only_time_s(position_m: float) -> float:
    """Bang-bang time of the ball from rest with an instantaneous servo: 2·sqrt(x0/(|γ|θmax))."""
    return 2.0 * math.sqrt(position_m / (abs(GAMMA) * THETA_MAX_RAD))


def jerk_limited_time_s(start: np.ndarray, voltage_v: float) -> float:
    """Ruckig's time-optimal motion of the ball with |ẍ| ≤ |γ|θmax and |x⃛| ≤ |γ|U/β.

    Any plan of ours is such a motion (|θ̇| ≤ U/β holds for all t once |θ̇0| ≤ U/β, and ẍ = γθ),
    so this is a lower bound on its duration; the motor lag only adds to it.
    """
    inp = ruckig.InputParameter(1)
    inp.current_position = [start[BALL_POSITION]]
    inp.current_velocity = [start[BALL_VELOCITY]]
    inp.current_acceleration = [GAMMA * start[THETA]]
    inp.target_position = [0.0]
    inp.target_velocity = [0.0]
    inp.target_acceleration = [0.0]
    inp.max_velocity = [1e3]
    inp.max_acceleration = [abs(GAMMA) * THETA_MAX_RAD]
    inp.max_jerk = [abs(GAMMA) * voltage_v / BETA]
    trajectory = ruckig.Trajectory(1)
    result = ruckig.Ruckig(1).calculate(inp, trajectory)
    assert result in (ruckig.Result.Working, ruckig.Result.Finished)
    return float(trajectory.duration)


def whole_problem_status(start: np.ndarray, n: int, voltage_v: float, step_s: float) -> int:
    """HiGHS status (0 feasible, 2 infeasible) of reaching rest in n steps on the grid.

    Formulated independently of the planner: every state of every step is a variable (scaled),
    linked by x_{k+1} = Ad x_k + Bd u_k with Ad, Bd from the model's expm discretisation;
    |u_k| ≤ U; |θ_k| ≤ θmax − δ at the samples 1..n−1 (the planner's rule, δ from the
    constants); x_n = 0. The planner's exact first-step interval for u_0 is left out, which
    only makes this problem easier: infeasible here means infeasible there.
    """
    d = MODEL.discretize(step_s)
    scale = np.array([THETA_MAX_RAD, voltage_v / BETA, abs(GAMMA) * THETA_MAX_RAD, 0.2])
    Ad = d.Ad * scale[None, :] / scale[:, None]
    Bd = d.Bd[:, 0] * voltage_v / scale
    x0 = start / scale
    n_var = n + 4 * n  # u_0..u_{n−1}, then x_1..x_n
    rows, cols, vals = [], [], []
    b = np.zeros(4 * n)
    for k in range(n):
        for i in range(4):
            r = 4 * k + i
            rows += [r, r]
            cols += [n + 4 * k + i, k]
            vals += [1.0, -Bd[i]]
            for j in range(4):
                if Ad[i, j] == 0.0:
                    continue
                if k == 0:
                    b[r] += Ad[i, j] * x0[j]
                else:
                    rows.append(r)
                    cols.append(n + 4 * (k - 1) + j)
                    vals.append(-Ad[i, j])
    A_eq = scipy.sparse.csr_array((vals, (rows, cols)), shape=(4 * n, n_var))
    bounds = np.full((n_var, 2), [-np.inf, np.inf])
    bounds[:n] = [-1.0, 1.0]
    delta = sample_margin_rad(voltage_v, step_s, start[THETA_RATE])
    theta_bound = (THETA_MAX_RAD - delta) / scale[0]
    bounds[n + 4 * np.arange(n - 1)] = [-theta_bound, theta_bound]
    bounds[n + 4 * (n - 1) :] = [0.0, 0.0]
    result = linprog(np.zeros(n_var), A_eq=A_eq, b_eq=b, bounds=bounds, method="highs-ipm")
    return int(result.status)


def integrate_plan(plan: TimeOptimalPlan, times_s: np.ndarray) -> np.ndarray:
    """solve_ivp through the plan's held inputs, one arc of constant input at a time, carrying
    the integrated state across arcs (never reset to the plan's states)."""
    A, B = MODEL.A, MODEL.B[:, 0]
    u = plan.input_v
    switches = np.flatnonzero(np.diff(u) != 0.0) + 1
    edges = np.concatenate([[0], switches, [u.size]])
    state = plan.grid_states[0].copy()
    out = np.empty((times_s.size, 4))
    for a, b in itertools.pairwise(edges):
        t0, t1 = a * plan.step_s, b * plan.step_s
        inside = (times_s >= t0) & (times_s < t1)
        voltage = u[a]
        sol = solve_ivp(
            lambda _t, x, v=voltage: A @ x + B * v,
            (t0, t1),
            state,
            method="DOP853",
            t_eval=times_s[inside],
            rtol=1e-12,
            atol=1e-14,
        )
        out[inside] = sol.y.T
        state = solve_ivp(
            lambda _t, x, v=voltage: A @ x + B * v,
            (t0, t1),
            state,
            method="DOP853",
            rtol=1e-12,
            atol=1e-14,
        ).y[:, -1]
    out[times_s >= plan.duration_s] = state
    return out


def check_plan(plan: TimeOptimalPlan, start: np.ndarray, voltage_v: float) -> None:
    """Invariants every plan must satisfy."""
    n = plan.n_steps
    assert plan.kind == "time_optimal"
    assert plan.input_v.shape == (n,)
    assert plan.grid_states.shape == (n + 1, 4)
    assert plan.duration_s == pytest.approx(n * plan.step_s, abs=1e-12)
    assert_allclose(plan.grid_states[0], start, rtol=0, atol=0)
    # inputs within the limit
    assert np.max(np.abs(plan.input_v)) <= voltage_v + 1e-12
    # grid states are the exact zero-order-hold states (model's expm discretisation)
    d = MODEL.discretize(plan.step_s)
    x = start.copy()
    expected = [x]
    for k in range(n):
        x = d.Ad @ x + d.Bd[:, 0] * plan.input_v[k]
        expected.append(x)
    assert_states_close(plan.grid_states, np.array(expected), STATE_ATOL)
    # ends at rest at the origin
    assert_states_close(plan.grid_states[-1], np.zeros(4), END_ATOL)
    # the angle stays within the limit at all times (16 points per step)
    t = np.arange(16 * n + 1) * plan.step_s / 16.0
    assert np.max(np.abs(plan.sample(t).states[:, THETA])) <= THETA_MAX_RAD


# ---------------------------------------------------------------- the paper's start


@pytest.mark.parametrize("margin_v", [0.5, 0.0])
def test_paper_duration_between_independent_bounds(margin_v: float) -> None:
    plan = paper_plan(margin_v)
    voltage = V_MAX - margin_v
    ball_only = ball_only_time_s(0.195)
    assert ball_only == pytest.approx(1.44398, abs=1e-5)
    jerk_limited = jerk_limited_time_s(PAPER_START, voltage)
    assert plan.duration_s >= ball_only
    assert plan.duration_s >= jerk_limited
    # The lag costs each of the three servo swings (−52° → +52° → −52° → 0) at most about one
    # time constant when it starts and one when it stops, compared with an instant change of
    # rate: within 6τ ≈ 0.10 s. Observed: 0.047 s (margin 0.5 V) and 0.046 s (no margin).
    assert plan.duration_s - jerk_limited <= 6.0 * MOTOR_TIME_CONSTANT_S


def test_paper_durations(plan_margin: TimeOptimalPlan, plan_physical: TimeOptimalPlan) -> None:
    # recorded for the report; minimality is the next test's business
    assert plan_margin.n_steps == 1777
    assert plan_physical.n_steps == 1746
    assert plan_physical.duration_s < plan_margin.duration_s


@pytest.mark.parametrize("margin_v", [0.5, 0.0])
def test_paper_one_step_less_is_infeasible(margin_v: float) -> None:
    plan = paper_plan(margin_v)
    voltage = V_MAX - margin_v
    assert whole_problem_status(PAPER_START, plan.n_steps, voltage, STEP_S) == 0
    assert whole_problem_status(PAPER_START, plan.n_steps - 1, voltage, STEP_S) == 2


def test_finer_grid_is_not_materially_faster(plan_margin: TimeOptimalPlan) -> None:
    durations = {h: paper_plan(0.5, h).duration_s for h in (5e-3, 2e-3, 0.5e-3)}
    durations[STEP_S] = plan_margin.duration_s
    # refining the grid only lets the switching times move by less than a step
    assert durations[5e-3] >= durations[2e-3] >= durations[STEP_S] >= durations[0.5e-3]
    assert durations[STEP_S] - durations[0.5e-3] <= STEP_S
    assert durations[5e-3] - durations[0.5e-3] <= 5e-3


def test_paper_plan_invariants(
    plan_margin: TimeOptimalPlan, plan_physical: TimeOptimalPlan
) -> None:
    check_plan(plan_margin, PAPER_START, 4.5)
    check_plan(plan_physical, PAPER_START, 5.0)
    assert plan_margin.voltage_limit_v == pytest.approx(4.5)
    assert plan_margin.theta_max_rad == THETA_MAX_RAD


def test_paper_plan_matches_continuous_integration(plan_margin: TimeOptimalPlan) -> None:
    plan = plan_margin
    rng = np.random.default_rng(7)
    grid_times = np.arange(plan.n_steps + 1) * plan.step_s
    inner = rng.uniform(0.0, plan.duration_s, 400)
    times = np.sort(np.concatenate([grid_times, inner, [plan.duration_s + 0.05]]))
    integrated = integrate_plan(plan, times)
    assert_states_close(plan.sample(times).states, integrated, STATE_ATOL)
    assert_states_close(integrated[-1], np.zeros(4), END_ATOL)


def test_paper_plan_holds_are_clean(plan_margin: TimeOptimalPlan) -> None:
    """Bang arcs at ±U, holds at u = 0; only the few steps that land an arc are partial."""
    u = plan_margin.input_v / plan_margin.voltage_limit_v
    at_level = np.isclose(np.abs(u), 1.0, atol=1e-9) | np.isclose(u, 0.0, atol=1e-9)
    assert np.count_nonzero(~at_level) <= 12
    assert np.count_nonzero(np.abs(np.diff(u)) > 1e-9) <= 30


def test_angle_between_samples_stays_within_sample_margin(plan_margin: TimeOptimalPlan) -> None:
    """The samples k ≥ 1 keep δ back; between samples θ gains less than that."""
    plan = plan_margin
    delta = sample_margin_rad(4.5, STEP_S)
    assert intersample_margin_rad(MODEL, 4.5, STEP_S) == pytest.approx(delta, rel=1e-12)
    assert np.max(np.abs(plan.grid_states[1:, THETA])) <= THETA_MAX_RAD - delta
    t = np.arange(64 * plan.n_steps + 1) * plan.step_s / 64.0
    assert np.max(np.abs(plan.sample(t).states[:, THETA])) <= THETA_MAX_RAD


# ---------------------------------------------------------------- seeded random starts

RNG = np.random.default_rng(20240601)
RANDOM_STARTS = [
    np.array(
        [
            math.radians(RNG.uniform(-50.0, 50.0)),
            RNG.uniform(-0.5, 0.5),
            RNG.uniform(-0.05, 0.05),
            RNG.uniform(-0.2, 0.2),
        ]
    )
    for _ in range(20)
]


@pytest.mark.parametrize("start", RANDOM_STARTS, ids=[f"start{i}" for i in range(20)])
def test_random_start(start: np.ndarray) -> None:
    plan = plan_time_optimal(MODEL, start, voltage_limit_v=V_MAX, voltage_margin_v=0.5)
    check_plan(plan, start, 4.5)
    assert plan.duration_s >= jerk_limited_time_s(start, 4.5)
    assert whole_problem_status(start, plan.n_steps - 1, 4.5, STEP_S) == 2


# ---------------------------------------------------------------- edges and errors


def test_margin_shortens_nothing_but_the_voltage(
    plan_margin: TimeOptimalPlan, plan_physical: TimeOptimalPlan
) -> None:
    assert plan_physical.duration_s < plan_margin.duration_s
    assert np.max(np.abs(plan_physical.input_v)) == pytest.approx(5.0)
    assert np.max(np.abs(plan_margin.input_v)) == pytest.approx(4.5)


def test_sample_outside_and_at_grid_times(plan_margin: TimeOptimalPlan) -> None:
    plan = plan_margin
    before = plan.sample(np.array([-1.0, -1e-3]))
    assert_allclose(before.states, np.tile(PAPER_START, (2, 1)))
    assert_allclose(before.input_v, 0.0)
    after = plan.sample(np.array([plan.duration_s, plan.duration_s + 3.0]))
    assert_allclose(after.states, 0.0)
    assert_allclose(after.input_v, 0.0)
    # grid times as a caller computes them (k · period), rounding included
    k = np.arange(plan.n_steps)
    on_grid = plan.sample(k * plan.step_s)
    assert_allclose(on_grid.states, plan.grid_states[:-1], rtol=0, atol=1e-12)
    assert_allclose(on_grid.input_v, plan.input_v, rtol=0, atol=0)
    state, input_v = at_time(plan, 0.5)
    assert state.shape == (4,)
    assert input_v == plan.input_v[500]


def test_sample_within_steps_matches_expm(plan_margin: TimeOptimalPlan) -> None:
    plan = plan_margin
    rng = np.random.default_rng(3)
    k = rng.integers(0, plan.n_steps, 50)
    tau = rng.uniform(0.0, plan.step_s, 50)
    got = plan.sample(k * plan.step_s + tau).states
    expected = [
        zoh_propagate(MODEL.A, MODEL.B, plan.grid_states[i], plan.input_v[i], t)
        for i, t in zip(k, tau, strict=True)
    ]
    assert_allclose(got, np.array(expected), rtol=0, atol=1e-12)


def test_sample_many_points(plan_margin: TimeOptimalPlan) -> None:
    t = np.linspace(-0.1, plan_margin.duration_s + 0.1, 8000)
    samples = plan_margin.sample(t)
    assert samples.states.shape == (8000, 4)
    assert samples.input_v.shape == (8000,)
    assert np.all(np.isfinite(samples.states))


def test_plan_is_immutable(plan_margin: TimeOptimalPlan) -> None:
    with pytest.raises(ValueError):
        plan_margin.input_v[0] = 0.0
    with pytest.raises(ValueError):
        plan_margin.grid_states[0, 0] = 0.0
    with pytest.raises(AttributeError):
        plan_margin.step_s = 2.0  # type: ignore[misc]


def test_short_move_is_verified_minimal() -> None:
    start = np.array([0.0, 0.0, 0.0, 0.01])
    plan = plan_time_optimal(MODEL, start, voltage_margin_v=0.5, verify_minimal=True)
    assert plan.verified_minimal
    check_plan(plan, start, 4.5)
    assert whole_problem_status(start, plan.n_steps - 1, 4.5, STEP_S) == 2


def test_start_at_rest_needs_no_time() -> None:
    plan = plan_time_optimal(MODEL, np.zeros(4))
    assert plan.n_steps == 0
    assert plan.duration_s == 0.0
    assert_allclose(plan.sample(np.array([0.0, 1.0])).states, 0.0)


def test_start_beyond_angle_limit_raises() -> None:
    start = np.array([math.radians(53.0), 0.0, 0.0, 0.1])
    with pytest.raises(PlanningError, match=re.escape("beyond the ±52.00° limit")):
        plan_time_optimal(MODEL, start)


def test_start_too_fast_to_stop_raises() -> None:
    start = np.array([math.radians(50.0), 8.0, 0.0, 0.1])
    with pytest.raises(PlanningError, match="braking carries it past"):
        plan_time_optimal(MODEL, start, voltage_margin_v=0.5)


def test_start_beyond_recovery_within_horizon_raises() -> None:
    with pytest.raises(PlanningError, match=re.escape("no path to rest within 1.0 s")):
        plan_time_optimal(MODEL, PAPER_START, voltage_margin_v=0.5, max_duration_s=1.0)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"voltage_margin_v": 5.0}, "leaves no input"),
        ({"step_s": 0.0}, "step_s must be positive"),
        ({"theta_max_rad": 0.0}, "theta_max_rad must be positive"),
    ],
)
def test_bad_settings_raise(kwargs: dict[str, Any], match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        plan_time_optimal(MODEL, PAPER_START, **kwargs)


def test_other_model_structures_are_refused() -> None:
    A = np.array(MODEL.A, copy=True)
    A[0, 0] = -1.0
    with pytest.raises(ConfigError, match="structure"):
        plan_time_optimal(LinearModel(A=A, B=MODEL.B, C=MODEL.C), PAPER_START)


def test_highspy_gives_what_linprog_gives(
    plan_margin: TimeOptimalPlan, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The planner hands its LPs to HiGHS through ``highspy``; the same model and options
    through SciPy's public linprog must give the same plan, bit for bit."""
    import ballbeam.core.planning.lp as lp

    calls = 0

    def through_linprog(
        c: np.ndarray, A_eq: Any, b_eq: np.ndarray, bounds: np.ndarray, options: dict[str, Any]
    ) -> tuple[bool | None, np.ndarray]:
        nonlocal calls
        calls += 1
        options = dict(options)
        method = "highs-ipm" if options.pop("solver", None) == "ipm" else "highs"
        res = linprog(c, A_eq=A_eq, b_eq=b_eq, bounds=bounds, method=method, options=options)
        if res.status == 0:
            return True, np.asarray(res.x)
        return (False if res.status == 2 else None), np.zeros(0)

    monkeypatch.setattr(lp, "_highs_solve", through_linprog)
    by_linprog = paper_plan(0.5)
    assert calls > 0
    assert by_linprog.n_steps == plan_margin.n_steps
    assert np.array_equal(by_linprog.input_v, plan_margin.input_v)


def test_a_start_beyond_the_path_bound_leaves_it_at_full_voltage_first() -> None:
    """The paper's −52° start with a path inside ±51.5°: a lead-in at +U, then the minimum-time
    path from where it ends; the whole plan comes to rest and stays within ±52° throughout."""
    from ballbeam.config import load_config
    from ballbeam.core.planning.time_optimal import plan_time_optimal_from_outside
    from ballbeam.plant_assembly import design_model

    model = design_model(load_config(None))
    start = np.array([math.radians(-52.0), 0.0, 0.0, 0.195])
    bound = math.radians(51.5)
    plan = plan_time_optimal_from_outside(model, start, voltage_limit_v=4.75, theta_max_rad=bound)
    lead = int(np.argmax(plan.input_v != 4.75))
    assert lead > 0 and np.all(plan.input_v[:lead] == 4.75)
    assert np.all(np.abs(plan.input_v) <= 4.75 + 1e-9)
    samples = plan.sample(np.arange(0.0, plan.duration_s, 1e-4))
    assert np.all(np.abs(samples.states[:, 0]) <= math.radians(52.0) + 1e-12)
    after = samples.time_s >= lead * plan.step_s
    assert np.all(np.abs(samples.states[after, 0]) <= bound + 1e-9)
    np.testing.assert_allclose(plan.grid_states[-1], 0.0, atol=1e-7)
    # it costs little: the paper's start is 1.746 s at the full 5 V and 52°
    assert plan.duration_s < 1.746 * 1.015
