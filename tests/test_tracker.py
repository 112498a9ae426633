"""Tracker synthesis against independent answers: the algebraic Riccati solvers, quadrature,
the analytic feedforward of a consistent path, and a brute-force quadratic program."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest
import scipy.linalg
from numpy.testing import assert_allclose

from ballbeam.core.model import LinearModel, PhysicalConstants
from ballbeam.core.planning.plan import PlanSamples
from ballbeam.core.tracker import (
    continuous_tracker,
    discrete_tracker,
    sampled_cost,
    stationary_gain,
    synthesize_discrete,
    tracker_input,
)
from ballbeam.errors import ConfigError

MODEL = LinearModel.from_constants(PhysicalConstants())
Q = np.diag([50.0, 0.0, 20.0, 2000.0])
R = np.array([[0.05]])
ALPHA = float(MODEL.B[1, 0])
ALPHA_BETA = float(-MODEL.A[1, 1])
GAMMA = float(MODEL.A[2, 0])


@dataclass(frozen=True)
class RestPlan:
    """Rest at the origin throughout."""

    kind: str = "rest"
    duration_s: float = 0.0

    def sample(self, time_s: np.ndarray) -> PlanSamples:
        time_s = np.asarray(time_s, dtype=float)
        return PlanSamples(time_s, np.zeros((time_s.size, 4)), np.zeros(time_s.size))


@dataclass(frozen=True)
class SmoothPlan:
    """A path the model follows exactly, built from the flat output x (ball position).

    x(t) = x0 (1 − s(t/T)) with s the degree-9 smooth step (derivatives 1..4 vanish at both
    ends); then θ = ẍ/γ, θ̇ = x⃛/γ and u = (θ̈ + αβ θ̇)/α, so ẋ_d = A x_d + B u_d.
    """

    start_m: float = 0.15
    duration_s: float = 2.0
    kind: str = "smooth"

    def sample(self, time_s: np.ndarray) -> PlanSamples:
        time_s = np.asarray(time_s, dtype=float)
        T = self.duration_s
        tau = np.clip(time_s / T, 0.0, 1.0)
        step = np.polynomial.Polynomial([0, 0, 0, 0, 0, 126, -420, 540, -315, 70])
        position = np.polynomial.Polynomial([self.start_m]) - self.start_m * step
        derivs = [position.deriv(i)(tau) / T**i for i in range(5)]
        inside = (time_s >= 0.0) & (time_s <= T)
        for i in range(1, 5):
            derivs[i] = np.where(inside, derivs[i], 0.0)
        derivs[0] = np.where(time_s >= T, 0.0, derivs[0])
        theta = derivs[2] / GAMMA
        theta_rate = derivs[3] / GAMMA
        theta_accel = derivs[4] / GAMMA
        states = np.stack([theta, theta_rate, derivs[1], derivs[0]], axis=1)
        input_v = (theta_accel + ALPHA_BETA * theta_rate) / ALPHA
        return PlanSamples(time_s, states, input_v)


def test_smooth_plan_obeys_the_model() -> None:
    plan = SmoothPlan()
    t = np.linspace(0.0, plan.duration_s, 401)
    samples = plan.sample(t)
    # Compare the derivative of x_d (finite differences) with A x_d + B u_d.
    rhs = samples.states @ MODEL.A.T + np.outer(samples.input_v, MODEL.B[:, 0])
    derivative = np.gradient(samples.states, t, axis=0, edge_order=2)
    assert_allclose(derivative[5:-5], rhs[5:-5], atol=2e-3 * np.abs(rhs).max())
    assert_allclose(plan.sample(np.array([plan.duration_s + 1.0])).states, 0.0, atol=1e-15)


# --------------------------------------------------------------------------------------------
# Sampled cost (Van Loan) against quadrature


@pytest.mark.parametrize("period_s", [1e-3, 0.02])
def test_sampled_cost_matches_quadrature(period_s: float) -> None:
    cost = sampled_cost(MODEL, Q, R, period_s)
    # Gauss-Legendre on [0, h] of [e^{Aτ} Γ(τ)]ᵀ Q [e^{Aτ} Γ(τ)] + diag(0, R): the integrand
    # is analytic, so 30 nodes are exact to rounding.
    nodes, weights = np.polynomial.legendre.leggauss(30)
    nodes = 0.5 * period_s * (nodes + 1.0)
    weights = 0.5 * period_s * weights
    block = np.zeros((5, 5))
    block[:4, :4] = MODEL.A
    block[:4, 4] = MODEL.B[:, 0]
    total = np.zeros((5, 5))
    for tau, weight in zip(nodes, weights, strict=True):
        response = scipy.linalg.expm(block * tau)[:4, :]  # [e^{Aτ}, Γ(τ)]
        total += weight * (response.T @ Q @ response)
    total[4, 4] += R[0, 0] * period_s
    assert_allclose(cost.Qd, total[:4, :4], rtol=1e-10, atol=1e-12 * np.abs(total).max())
    assert_allclose(cost.Nd, total[:4, 4:], rtol=1e-10, atol=1e-12 * np.abs(total).max())
    assert_allclose(cost.Rd, total[4:, 4:], rtol=1e-10)
    assert_allclose(cost.Rh, R * period_s, rtol=1e-15)


# --------------------------------------------------------------------------------------------
# Long horizons converge to the stationary solutions


def test_continuous_zero_terminal_converges_to_care() -> None:
    tracker = continuous_tracker(
        MODEL,
        RestPlan(),
        Q=Q,
        R=R,
        horizon_s=15.0,
        terminal="zero",
        time_s=np.array([0.0, 14.0, 15.0]),
    )
    care = scipy.linalg.solve_continuous_are(MODEL.A, MODEL.B, Q, R)
    assert_allclose(tracker.S[0], care, rtol=1e-7, atol=1e-9 * np.abs(care).max())
    assert_allclose(tracker.S[-1], 0.0, atol=1e-15)
    assert_allclose(tracker.K[0], np.linalg.solve(R, MODEL.B.T @ care), rtol=1e-7)


def test_discrete_zero_terminal_converges_to_dare() -> None:
    period_s = 0.01
    N = 2000  # 20 s: the slowest closed-loop mode (~1.1 /s) has long died out
    tracker = discrete_tracker(
        MODEL, np.zeros((N + 1, 4)), np.zeros(N), Q=Q, R=R, period_s=period_s, terminal="zero"
    )
    discrete = MODEL.discretize(period_s)
    cost = sampled_cost(MODEL, Q, R, period_s)
    dare = scipy.linalg.solve_discrete_are(discrete.Ad, discrete.Bd, cost.Qd, cost.Rd, s=cost.Nd)
    assert_allclose(tracker.S[0], dare, rtol=1e-9, atol=1e-11 * np.abs(dare).max())
    assert_allclose(tracker.S[N], 0.0, atol=0.0)
    K_dare = np.linalg.solve(
        cost.Rd + discrete.Bd.T @ dare @ discrete.Bd, discrete.Bd.T @ dare @ discrete.Ad + cost.Nd.T
    )
    assert_allclose(tracker.K[0], K_dare, rtol=1e-9)
    assert_allclose(tracker.K_final, K_dare, rtol=1e-9)


def _riccati_by_loop(period_s: float, S_N: np.ndarray, N: int) -> tuple[np.ndarray, np.ndarray]:
    """The textbook backward recursion, one step at a time: S (N + 1, 4, 4), K (N, 4)."""
    discrete = MODEL.discretize(period_s)
    Ad, Bd = discrete.Ad, discrete.Bd
    cost = sampled_cost(MODEL, Q, R, period_s)
    S = np.empty((N + 1, 4, 4))
    K = np.empty((N, 4))
    S[N] = S_N
    for k in range(N - 1, -1, -1):
        G = cost.Rd + Bd.T @ S[k + 1] @ Bd
        H = Bd.T @ S[k + 1] @ Ad + cost.Nd.T
        K[k] = np.linalg.solve(G, H)[0]
        S[k] = cost.Qd + Ad.T @ S[k + 1] @ Ad - H.T @ np.linalg.solve(G, H)
    return S, K


def test_zero_terminal_gain_schedule_matches_step_by_step_recursion() -> None:
    period_s, N = 1e-3, 1500
    tracker = discrete_tracker(
        MODEL, np.zeros((N + 1, 4)), np.zeros(N), Q=Q, R=R, period_s=period_s, terminal="zero"
    )
    S, K = _riccati_by_loop(period_s, np.zeros((4, 4)), N)
    scale = np.abs(S).max()
    assert_allclose(tracker.S, S, rtol=1e-9, atol=1e-11 * scale)
    assert_allclose(tracker.K[:, 0], K, rtol=1e-8, atol=1e-10 * np.abs(K).max())
    # The gains collapse towards the end of the horizon.
    assert np.abs(tracker.K[-1]).max() < 0.01 * np.abs(tracker.K[0]).max()


# --------------------------------------------------------------------------------------------
# Continuous and sampled-data solutions agree as the period shrinks


def test_discrete_gains_converge_to_continuous_linearly_in_period() -> None:
    horizon_s = 1.0
    grid = np.arange(2001) * 5e-4  # holds every k·h below
    continuous = continuous_tracker(
        MODEL, RestPlan(), Q=Q, R=R, horizon_s=horizon_s, terminal="zero", time_s=grid
    )
    scale = np.abs(continuous.K).max()
    errors = []
    for period_s in (4e-3, 2e-3, 1e-3, 5e-4):
        N = round(horizon_s / period_s)
        discrete = discrete_tracker(
            MODEL, np.zeros((N + 1, 4)), np.zeros(N), Q=Q, R=R, period_s=period_s, terminal="zero"
        )
        stride = round(period_s / 5e-4)
        K_continuous = continuous.K[: N * stride : stride]
        errors.append(np.abs(discrete.K - K_continuous).max() / scale)
    ratios = np.array(errors[:-1]) / np.array(errors[1:])
    assert errors[-1] < 0.02
    assert np.all((ratios > 1.7) & (ratios < 2.3)), (errors, ratios)


@pytest.mark.parametrize(
    ("terminal", "input_reference"), [("zero", "zero"), ("stationary", "feedforward")]
)
def test_discrete_offsets_converge_to_continuous_linearly_in_period(
    terminal: str, input_reference: str
) -> None:
    plan = SmoothPlan()
    horizon_s = 3.0
    grid = np.arange(6001) * 5e-4
    continuous = continuous_tracker(
        MODEL,
        plan,
        Q=Q,
        R=R,
        horizon_s=horizon_s,
        terminal=terminal,  # type: ignore[arg-type]
        input_reference=input_reference,  # type: ignore[arg-type]
        time_s=grid,
    )
    scale = np.abs(continuous.offset_v).max()
    errors = []
    for period_s in (4e-3, 2e-3, 1e-3, 5e-4):
        discrete = synthesize_discrete(
            MODEL,
            plan,
            Q=Q,
            R=R,
            period_s=period_s,
            horizon_s=horizon_s,
            terminal=terminal,  # type: ignore[arg-type]
            input_reference=input_reference,  # type: ignore[arg-type]
        )
        stride = round(period_s / 5e-4)
        expected = continuous.offset_v[: discrete.n_steps * stride : stride]
        errors.append(np.abs(discrete.offset_v - expected).max() / scale)
    ratios = np.array(errors[:-1]) / np.array(errors[1:])
    assert errors[-1] < 0.02
    assert np.all((ratios > 1.7) & (ratios < 2.3)), (errors, ratios)


# --------------------------------------------------------------------------------------------
# Feedforward along a path the model can follow


@pytest.mark.parametrize("terminal", ["stationary", "zero"])
def test_continuous_feedforward_on_consistent_path_is_S_times_reference(terminal: str) -> None:
    plan = SmoothPlan()
    horizon_s = 3.0
    grid = np.linspace(0.0, horizon_s, 301)
    tracker = continuous_tracker(
        MODEL,
        plan,
        Q=Q,
        R=R,
        horizon_s=horizon_s,
        terminal=terminal,  # type: ignore[arg-type]
        input_reference="feedforward",
        time_s=grid,
    )
    samples = plan.sample(grid)
    expected_v = np.einsum("kij,kj->ki", tracker.S, samples.states)
    assert_allclose(tracker.v, expected_v, atol=1e-7 * np.abs(expected_v).max())
    # u = u_d − K (x − x_d): offset = u_d + K x_d.
    expected_offset = samples.input_v + np.einsum("kij,kj->k", tracker.K, samples.states)
    assert_allclose(tracker.offset_v, expected_offset, atol=1e-7 * np.abs(expected_offset).max())
    assert_allclose(tracker.u_ref, samples.input_v, rtol=0, atol=0)


def _zoh_reference(period_s: float, N: int) -> tuple[np.ndarray, np.ndarray]:
    """A reference made by holding a smooth input over each period: exactly consistent."""
    discrete = MODEL.discretize(period_s)
    t = np.arange(N) * period_s
    u_bar = 0.2 * np.sin(2.0 * np.pi * t / (N * period_s)) ** 3 + 0.3 * np.sin(9.0 * t)
    r = np.empty((N + 1, 4))
    r[0] = (np.radians(-5.0), 0.0, 0.05, 0.12)
    for k in range(N):
        r[k + 1] = discrete.Ad @ r[k] + discrete.Bd[:, 0] * u_bar[k]
    return r, u_bar


@pytest.mark.parametrize("terminal", ["stationary", "zero"])
def test_discrete_closed_loop_stays_on_zoh_consistent_reference(terminal: str) -> None:
    period_s, N = 1e-3, 3000
    r, u_bar = _zoh_reference(period_s, N)
    tracker = discrete_tracker(
        MODEL,
        r,
        u_bar,
        Q=Q,
        R=R,
        period_s=period_s,
        terminal=terminal,  # type: ignore[arg-type]
        input_reference="feedforward",
    )
    assert_allclose(
        tracker.v, np.einsum("kij,kj->ki", tracker.S, r), atol=1e-9 * np.abs(tracker.v).max()
    )
    discrete = MODEL.discretize(period_s)
    x = r[0].copy()
    errors = np.empty((N, 4))
    for k in range(N):
        u = tracker_input(tracker, k, x)
        assert u == pytest.approx(u_bar[k], abs=1e-9)
        x = discrete.Ad @ x + discrete.Bd[:, 0] * u
        errors[k] = x - r[k + 1]
    # Relative to each state's range along the path.
    relative = np.abs(errors).max(axis=0) / np.abs(r).max(axis=0)
    assert relative.max() < 3e-9, relative


def test_synthesize_from_plan_tracks_smooth_path_closely() -> None:
    plan = SmoothPlan()
    period_s = 1e-3
    tracker = synthesize_discrete(
        MODEL, plan, Q=Q, R=R, period_s=period_s, horizon_s=3.0, terminal="stationary"
    )
    assert tracker.K.shape == (3000, 1, 4)
    assert tracker.offset_v.shape == (3000,)
    assert tracker.n_steps == 3000
    discrete = MODEL.discretize(period_s)
    reference = plan.sample(np.arange(3001) * period_s).states
    x = reference[0].copy()
    errors = []
    for k in range(3000):
        x = discrete.Ad @ x + discrete.Bd[:, 0] * tracker_input(tracker, k, x)
        errors.append(np.abs(x - reference[k + 1])[3])
    # The plan's input is not held between samples: only an O(h²) residual remains.
    assert max(errors) < 1e-5


# --------------------------------------------------------------------------------------------
# The paper's cost (u_ref = 0) and the feedforward one against a brute-force least squares


def _matrix_sqrt(M: np.ndarray) -> np.ndarray:
    values, vectors = np.linalg.eigh(0.5 * (M + M.T))
    result: np.ndarray = (vectors * np.sqrt(np.clip(values, 0.0, None))) @ vectors.T
    return result


@pytest.mark.parametrize("input_reference", ["zero", "feedforward"])
@pytest.mark.parametrize("terminal", ["zero", "stationary"])
def test_recursion_matches_least_squares_over_input_sequence(
    terminal: str, input_reference: str
) -> None:
    period_s, N = 0.01, 30
    rng = np.random.default_rng(7)
    r = rng.normal(scale=[0.3, 2.0, 0.05, 0.1], size=(N + 1, 4))
    u_bar = rng.normal(scale=1.0, size=N)
    x0 = rng.normal(scale=[0.3, 2.0, 0.05, 0.1])
    discrete = MODEL.discretize(period_s)
    Ad, Bd = discrete.Ad, discrete.Bd
    cost = sampled_cost(MODEL, Q, R, period_s)
    if terminal == "zero":
        S_N = np.zeros((4, 4))
    else:
        S_N = scipy.linalg.solve_discrete_are(Ad, Bd, cost.Qd, cost.Rd, s=cost.Nd)
    u_ref = u_bar if input_reference == "feedforward" else np.zeros(N)

    # x_k = F_k x0 + E_k u  (E_k: (4, N)); stack every residual as an affine function of u.
    tracking = _matrix_sqrt(np.block([[cost.Qd, cost.Nd], [cost.Nd.T, cost.Rd - cost.Rh]]))
    input_weight = np.sqrt(cost.Rh[0, 0])
    rows_A, rows_b = [], []
    F, E = np.eye(4), np.zeros((4, N))
    for k in range(N):
        unit = np.zeros((1, N))
        unit[0, k] = 1.0
        # Residual tracking @ [x_k − r_k; u_k − ū_k].
        z_u = np.vstack([E, unit])
        z_0 = np.concatenate([F @ x0 - r[k], [-u_bar[k]]])
        rows_A.append(tracking @ z_u)
        rows_b.append(-(tracking @ z_0))
        rows_A.append(input_weight * unit)
        rows_b.append(np.array([input_weight * u_ref[k]]))
        F, E = Ad @ F, Ad @ E + Bd @ unit
    terminal_root = _matrix_sqrt(S_N)
    rows_A.append(terminal_root @ E)
    rows_b.append(-(terminal_root @ (F @ x0 - r[N])))
    u_best = np.linalg.lstsq(np.vstack(rows_A), np.concatenate(rows_b), rcond=None)[0]

    tracker = discrete_tracker(
        MODEL,
        r,
        u_bar,
        Q=Q,
        R=R,
        period_s=period_s,
        terminal=terminal,  # type: ignore[arg-type]
        input_reference=input_reference,  # type: ignore[arg-type]
    )
    x = x0.copy()
    u_recursion = np.empty(N)
    for k in range(N):
        u_recursion[k] = tracker_input(tracker, k, x)
        x = Ad @ x + Bd[:, 0] * u_recursion[k]
    assert_allclose(u_recursion, u_best, rtol=1e-7, atol=1e-8 * np.abs(u_best).max())


# --------------------------------------------------------------------------------------------
# Stability, the hand-over after the horizon, and argument checks


@pytest.mark.parametrize("period_s", [1e-2, 1e-3, 2e-4])
def test_stationary_closed_loop_is_stable(period_s: float) -> None:
    K, P = stationary_gain(MODEL, Q, R, period_s)
    discrete = MODEL.discretize(period_s)
    assert np.abs(np.linalg.eigvals(discrete.Ad - discrete.Bd @ K)).max() < 1.0
    assert np.linalg.eigvalsh(P).min() > 0.0
    tracker = discrete_tracker(
        MODEL, np.zeros((11, 4)), np.zeros(10), Q=Q, R=R, period_s=period_s, terminal="stationary"
    )
    assert_allclose(tracker.K_final, K, rtol=1e-12)
    assert_allclose(tracker.K[:, 0], np.broadcast_to(K, (10, 4)), rtol=1e-12)


def test_after_horizon_tracker_regulates_to_origin() -> None:
    tracker = synthesize_discrete(
        MODEL, SmoothPlan(duration_s=0.5), Q=Q, R=R, period_s=1e-3, horizon_s=1.0
    )
    x = np.array([0.1, -0.2, 0.01, 0.05])
    assert tracker_input(tracker, 1000, x) == pytest.approx(float(-(tracker.K_final @ x)[0]))
    assert tracker_input(tracker, 5000, x) == tracker_input(tracker, 1000, x)
    with pytest.raises(ValueError):
        tracker_input(tracker, -1, x)


def test_results_are_read_only() -> None:
    tracker = synthesize_discrete(
        MODEL, SmoothPlan(duration_s=0.5), Q=Q, R=R, period_s=1e-3, horizon_s=1.0, terminal="zero"
    )
    for array in (tracker.K, tracker.offset_v, tracker.K_final, tracker.S, tracker.v):
        assert not array.flags.writeable


def test_bad_arguments_are_config_errors() -> None:
    plan = SmoothPlan(duration_s=2.0)
    with pytest.raises(ConfigError, match="ends before the plan"):
        synthesize_discrete(MODEL, plan, Q=Q, R=R, period_s=1e-3, horizon_s=1.0)
    with pytest.raises(ConfigError, match="period"):
        synthesize_discrete(MODEL, plan, Q=Q, R=R, period_s=0.0, horizon_s=3.0)
    with pytest.raises(ConfigError, match="R must be"):
        synthesize_discrete(MODEL, plan, Q=Q, R=np.array([[0.0]]), period_s=1e-3, horizon_s=3.0)
    with pytest.raises(ConfigError, match="Q must be"):
        synthesize_discrete(MODEL, plan, Q=-Q, R=R, period_s=1e-3, horizon_s=3.0)
    with pytest.raises(ConfigError, match="terminal"):
        synthesize_discrete(
            MODEL,
            plan,
            Q=Q,
            R=R,
            period_s=1e-3,
            horizon_s=3.0,
            terminal="free",  # type: ignore[arg-type]
        )
    with pytest.raises(ConfigError, match="references"):
        discrete_tracker(MODEL, np.zeros((10, 4)), np.zeros(10), Q=Q, R=R, period_s=1e-3)
