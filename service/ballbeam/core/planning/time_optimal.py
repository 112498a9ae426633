"""Minimum-time path of the full linear model (motor lag included).

Problem: from ``x0 = (θ0, θ̇0, ẋ0, x0)`` reach rest at the origin as early as possible under
``ẋ = A x + B u``, ``|u| ≤ U = V_max − margin`` and ``|θ(t)| ≤ θ_max`` for all t; after the end
``u = 0`` keeps the origin. The input is held constant over the steps of a grid of step h
(default 1 ms, the controller period), so the answer is a step count N and inputs u_k.

Method (every claim checked numerically, not assumed):

* Exact zero-order hold. The model has closed-form solutions (motor pole a = αβ, then two
  integrators), used for the grid, the condensed responses and ``sample``.
* Angle between samples: θ is C² within a step, so |θ(t)| ≤ max(|θ_k|, |θ_k+1|) + θ̈_max h²/8
  with θ̈_max = αU + a·max(|θ̇0|, U/β). The samples k ≥ 1 are therefore bounded by θ_max − δ,
  δ = θ̈_max h²/8 (1.2e-4 rad at 1 ms); the first step, whose start is known, is instead bounded
  exactly: θ(τ) on [0, h] is linear in u_0, giving an interval for u_0.
* Feasibility of "rest at the origin after N steps" is a linear programme in the inputs
  (states condensed, so sampled angles are exact, not accumulated by a recurrence). Minimal N:
  bisection of that LP (HiGHS) on a coarse grid (about 80 steps), then the fine grid with the
  inputs fixed to the coarse solution's bang arcs (±U) and holds (0) except in windows around
  its switches. A window LP is small, so each try costs a few milliseconds.
* Optimality is certified, not presumed: a relaxation of the fine problem at N − 1 (all inputs
  free; angle limits kept at the hold ends, and over each hold only as two weighted sums) is
  solved, and its dual multipliers are turned into an explicit Lagrangian lower bound on the
  terminal miss, evaluated here over every input. A positive bound proves that no input
  sequence on the grid reaches the origin in N − 1 steps (``proven_optimal``).
* Among the inputs reaching the origin in N steps the L1-smallest is chosen: holds get u = 0
  instead of the chattering an arbitrary LP vertex would give.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import scipy.signal
import scipy.sparse
from scipy.optimize import OptimizeWarning, linprog

from ballbeam.core.model import LinearModel
from ballbeam.core.plans import PlanSamples
from ballbeam.errors import ConfigError, PlanningError

__all__ = [
    "TimeOptimalPlan",
    "intersample_margin_rad",
    "plan_time_optimal",
]

# Extra angle kept back in the LPs so that solver tolerance can never break the sample bound.
_SOLVER_MARGIN_RAD = 1e-7
# Terminal miss (row-scaled, L1) above which a relaxation proves infeasibility.
_CERTIFICATE_TOL = 1e-8
# The coarsest grid has at most this many steps over the lower bound on the time ...
_COARSE_STEPS = 40
# ... and each finer grid divides the step by this.
_LEVEL_RATIO = 4
# Half-width of the free windows around the coarser answer's switches, in its steps.
_WINDOW = 1.5
# Terminal miss (row-scaled L1) still counted as reaching the origin.
_MISS_TOL = 1e-8
# Weight of the inputs' L1 norm next to the miss: breaks ties (clean holds) without trading
# miss for it (a unit of input moves a scaled terminal row by far more than this).
_TIE_WEIGHT = 1e-6
_HIGHS_OPTIONS = {"primal_feasibility_tolerance": 1e-9, "dual_feasibility_tolerance": 1e-9}


@dataclass(frozen=True)
class _Params:
    """The structured model: θ̈ = −a θ̇ + α u, ẍ = γ θ."""

    pole_per_s: float  # a = αβ
    alpha: float
    gamma: float

    @property
    def beta(self) -> float:
        return self.pole_per_s / self.alpha


def _params(model: LinearModel) -> _Params:
    A, B = np.asarray(model.A, float), np.asarray(model.B, float)
    pattern = np.zeros((4, 4))
    pattern[0, 1], pattern[3, 2] = 1.0, 1.0
    pattern[1, 1], pattern[2, 0] = A[1, 1], A[2, 0]
    b_pattern = np.array([[0.0], [B[1, 0]], [0.0], [0.0]])
    if (
        A.shape != (4, 4)
        or B.shape != (4, 1)
        or not np.array_equal(A, pattern)
        or not np.array_equal(B, b_pattern)
        or not A[1, 1] < 0.0
        or not B[1, 0] > 0.0
        or A[2, 0] == 0.0
    ):
        raise ConfigError("time-optimal planning needs the ball-and-beam model structure")
    return _Params(pole_per_s=-float(A[1, 1]), alpha=float(B[1, 0]), gamma=float(A[2, 0]))


def _phis(a: float, tau: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """φ1 = ∫e^{−as}, φ2 = ∫φ1, φ3 = ∫φ2 over [0, τ] (the lag's step, ramp and parabola)."""
    phi1 = -np.expm1(-a * tau) / a
    phi2 = (tau - phi1) / a
    phi3 = (0.5 * tau * tau - phi2) / a
    return phi1, phi2, phi3


def _propagate(p: _Params, states: np.ndarray, input_v: np.ndarray, tau: np.ndarray) -> np.ndarray:
    """Exact state after holding ``input_v`` for ``tau`` from ``states``; all rows at once."""
    theta, rate, speed, pos = states.T
    phi1, phi2, phi3 = _phis(p.pole_per_s, tau)
    w = input_v / p.beta  # steady servo rate under this voltage
    d = rate - w
    out = np.empty_like(states)
    out[:, 0] = theta + w * tau + d * phi1
    out[:, 1] = w + d * np.exp(-p.pole_per_s * tau)
    out[:, 2] = speed + p.gamma * (theta * tau + 0.5 * w * tau**2 + d * phi2)
    out[:, 3] = pos + speed * tau + p.gamma * (0.5 * theta * tau**2 + w * tau**3 / 6.0 + d * phi3)
    return out


def _simulate(p: _Params, step_s: float, x0: np.ndarray, input_v: np.ndarray) -> np.ndarray:
    """Grid states (N+1, 4) under zero-order hold, vectorised (the model is a chain of filters)."""
    n = input_v.shape[0]
    h = step_s
    E = math.exp(-p.pole_per_s * h)
    phi1, phi2, phi3 = (float(v) for v in _phis(p.pole_per_s, np.array(h)))
    w = input_v / p.beta
    rate = np.empty(n + 1)
    rate[0] = x0[1]
    if n:
        rate[1:] = scipy.signal.lfilter([1.0 - E], [1.0, -E], w, zi=[E * x0[1]])[0]
    r, wk = rate[:-1], w
    theta = np.empty(n + 1)
    theta[0] = x0[0]
    np.cumsum(phi1 * r + (h - phi1) * wk, out=theta[1:])
    theta[1:] += x0[0]
    t = theta[:-1]
    speed = np.empty(n + 1)
    speed[0] = x0[2]
    np.cumsum(p.gamma * (t * h + 0.5 * wk * h * h + (r - wk) * phi2), out=speed[1:])
    speed[1:] += x0[2]
    pos = np.empty(n + 1)
    pos[0] = x0[3]
    np.cumsum(
        speed[:-1] * h + p.gamma * (0.5 * t * h * h + wk * h**3 / 6.0 + (r - wk) * phi3),
        out=pos[1:],
    )
    pos[1:] += x0[3]
    return np.column_stack([theta, rate, speed, pos])


def _accel_max(p: _Params, voltage_v: float, initial_rate_rad_s: float) -> float:
    """Bound on |θ̈| = |αu − αβθ̇|: |θ̇| never exceeds max(|θ̇0|, U/β) under |u| ≤ U."""
    return p.alpha * voltage_v + p.pole_per_s * max(abs(initial_rate_rad_s), voltage_v / p.beta)


def intersample_margin_rad(
    model: LinearModel, voltage_v: float, step_s: float, initial_rate_rad_s: float = 0.0
) -> float:
    """δ = θ̈_max h²/8: how far θ can pass the larger of two neighbouring samples within a step
    (θ is C² within a step, and a C² function departs from its chord by at most max|f''|h²/8)."""
    return _accel_max(_params(model), voltage_v, initial_rate_rad_s) * step_s**2 / 8.0


def _ball_only_time_s(position_m: float, speed_m_s: float, accel_max: float) -> float:
    """Bang-bang time of a double integrator to rest at 0 with |ẍ| ≤ accel_max (a lower bound)."""
    x, v = position_m, speed_m_s
    stop = x + v * abs(v) / (2.0 * accel_max)
    if stop > 0.0:
        return (v + 2.0 * math.sqrt(accel_max * x + 0.5 * v * v)) / accel_max
    if stop < 0.0:
        return (-v + 2.0 * math.sqrt(-accel_max * x + 0.5 * v * v)) / accel_max
    return abs(v) / accel_max


@dataclass(frozen=True)
class _Grid:
    """One discretisation of the problem: step, limits, and the condensed responses."""

    p: _Params
    step_s: float
    x0: np.ndarray
    voltage_v: float  # U
    angle_max_rad: float  # θ_max
    theta_sample_rad: float  # bound on the samples k ≥ 1: θ_max − δ
    first_input_v: tuple[float, float]  # interval for u_0 from the exact first step
    impulse: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))  # (n, 4): Ad^i Bd

    @property
    def theta_lp_rad(self) -> float:
        """The bound imposed in the LPs: kept back so solver tolerance cannot break it."""
        return self.theta_sample_rad - _SOLVER_MARGIN_RAD

    def responses(self, n: int) -> _Grid:
        """This grid with the impulse response known for at least n steps."""
        if n <= self.impulse.shape[0]:
            return self
        n_new = max(n, 2 * self.impulse.shape[0])
        Bd = _propagate(self.p, np.zeros((1, 4)), np.ones(1), np.array([self.step_s]))[0]
        return replace(self, impulse=_simulate(self.p, self.step_s, Bd, np.zeros(n_new - 1)))

    def bounds_v(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        lo = np.full(n, -self.voltage_v)
        hi = np.full(n, self.voltage_v)
        lo[0], hi[0] = self.first_input_v
        return lo, hi


def _make_grid(
    p: _Params,
    x0: np.ndarray,
    voltage_v: float,
    angle_max_rad: float,
    step_s: float,
    accel_max: float,
    delta_rad: float | None = None,
) -> _Grid | None:
    """The grid, or None when no u_0 keeps the first step within the angle limit.

    The first step starts from the known state, so instead of δ its bound is exact: θ(τ) on
    [0, h] is θ0 + θ̇0 φ1(τ) + (u/β)(τ − φ1(τ)), linear in u_0, imposed on 64 sub-steps (between
    them θ can pass by at most θ̈_max (h/64)²/8, kept back).
    """
    h = step_s
    delta = accel_max * h * h / 8.0 if delta_rad is None else delta_rad
    tau = h * np.arange(1, 65) / 64.0
    phi1 = -np.expm1(-p.pole_per_s * tau) / p.pole_per_s
    slope = (tau - phi1) / p.beta  # > 0
    base = x0[0] + x0[1] * phi1
    limit = angle_max_rad - accel_max * (h / 64.0) ** 2 / 8.0
    hi = min(voltage_v, float(np.min((limit - base) / slope)))
    lo = max(-voltage_v, float(np.max((-limit - base) / slope)))
    if lo > hi:
        return None
    return _Grid(p, h, x0, voltage_v, angle_max_rad, angle_max_rad - delta, (lo, hi))


def _linprog(**kwargs: Any) -> Any:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", OptimizeWarning)
        return linprog(**kwargs)


@dataclass(frozen=True)
class _Solve:
    """Outcome of one LP: inputs (N,), their exactly simulated grid states (N+1, 4), and the
    smallest terminal miss found (row-scaled L1; 0 when solved with an exact end)."""

    feasible: bool
    input_v: np.ndarray
    states: np.ndarray
    miss: float = math.inf


def _solve_steps(
    grid: _Grid,
    n: int,
    free_mask: np.ndarray,
    fixed_v: np.ndarray,
    *,
    miss: bool = False,
    smallest: bool = True,
    method: str = "highs",
) -> _Solve:
    """Reach the origin in n steps with the inputs outside ``free_mask`` held at ``fixed_v``.

    ``miss``: minimise the terminal miss instead of demanding an exact end (the LP is then
    feasible whenever the angle limits are, and an infeasible n still yields the inputs that
    come closest: the time-optimal shape without slack). The answer is checked on the exactly
    simulated states. A sample inside a fixed stretch that passes the angle limit gets its own
    row (with its neighbours) and the LP is solved again; one before the first free input frees
    the inputs before it.
    """
    p, h = grid.p, grid.step_s
    grid = grid.responses(n + 1)
    lo, hi = grid.bounds_v(n)
    mask = free_mask.copy()
    extra = np.zeros(0, dtype=np.int64)
    fail = _Solve(
        False, np.clip(fixed_v, lo, hi), _simulate(p, h, grid.x0, np.clip(fixed_v, lo, hi))
    )
    for _ in range(12):
        fixed = np.where(mask, 0.0, np.clip(fixed_v, lo, hi))
        base = _simulate(p, h, grid.x0, fixed)
        cols = np.flatnonzero(mask)
        if cols.size == 0:
            ok = bool(np.all(np.abs(base[-1]) <= 1e-12))
            return _Solve(ok, fixed, base, 0.0 if ok else math.inf)
        # θ is monotone over a held zero input (holds) and has at most one turn over any held
        # input: bounding the last sample of each fixed stretch covers holds; turns come lazily
        ends = cols[1:][np.diff(cols) > 1]
        samples = np.union1d(ends, extra)
        free_v = _shooting_lp(
            grid, n, cols, base, lo, hi, samples, miss=miss, smallest=smallest, method=method
        )
        if free_v is None:
            return fail
        u = fixed.copy()
        u[cols] = free_v
        states = _simulate(p, h, grid.x0, u)
        over = np.flatnonzero(np.abs(states[1:n, 0]) > grid.theta_sample_rad) + 1
        if over.size == 0:
            # the miss of the exactly simulated end, in the LP's units
            missed = float(np.sum(np.abs(states[-1]) / _terminal_rows(grid, n, cols)[1]))
            return _Solve(missed <= _MISS_TOL, u, states, missed)
        early = over[over <= cols[0]]
        if early.size:  # only fixed inputs reach these samples: free the inputs before them
            mask[max(0, int(early[0]) - 8) : int(early[-1])] = True
            continue
        near = (over[:, None] + np.arange(-1, 2)[None, :]).ravel()
        added = np.union1d(extra, near[(near >= 1) & (near < n)])
        if np.union1d(samples, added).size == samples.size:  # bounded already: tolerance
            return fail
        extra = added
    return fail


def _terminal_rows(grid: _Grid, n: int, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The terminal state's response to the free inputs v = u/U, rows scaled to a largest
    entry of 1 (4, m), and those scales (4,): the units of the miss."""
    T = grid.impulse[n - 1 - cols].T * grid.voltage_v
    scale = np.max(np.abs(T), axis=1)
    scale[scale == 0.0] = 1.0
    return T / scale[:, None], scale


def _shooting_lp(
    grid: _Grid,
    n: int,
    cols: np.ndarray,
    base: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
    samples: np.ndarray,
    *,
    miss: bool,
    smallest: bool,
    method: str,
) -> np.ndarray | None:
    """The free inputs [V] of the sparse multiple-shooting LP, or None if it is infeasible.

    Variables: the free inputs v = u/U and, after each free step, the motor state's deviation
    from the fixed-input trajectory ``base`` (P = δθ/θ_lp, Q = δθ̇/(U/β)). Between free steps
    the deviation evolves freely, in closed form over any gap g: δθ += (1 − E^g)/a · δθ̇,
    δθ̇ *= E^g. So the angle limits at the samples after free steps are variable bounds, those
    at ``samples`` inside fixed stretches bounds on one more variable each (a row of three
    entries), and everything stays sparse but the four terminal rows, condensed over the free
    inputs (exact). ``miss``: minimise the terminal miss (L1, rows scaled) rather than demand
    an exact end; ``smallest``: also minimise the inputs' L1 norm (a tie-break under ``miss``).
    """
    p, h, U = grid.p, grid.step_s, grid.voltage_v
    m = cols.size
    a = p.pole_per_s
    E = math.exp(-a * h)
    phi1 = float(_phis(a, np.array(h))[0])
    rate = U / p.beta
    # solver error adds up along the chain: keep that much more angle back
    th = grid.theta_lp_rad - 2e-9 * m
    c1 = (h - phi1) * rate / th  # P after one step from rest at v = 1
    c2 = 1.0 - E  # Q after one step from rest at v = 1
    # samples inside fixed stretches: θ_k = base_k + th (P_i + (1 − E^g)/a · rate/th · Q_i)
    i_of = np.searchsorted(cols, samples - 1, side="right") - 1
    keep = (i_of >= 0) & (cols[np.clip(i_of, 0, None)] + 1 < samples)
    ks, iks = samples[keep], i_of[keep]
    nk = ks.size
    nv = 2 * m if smallest else m
    iP, iQ = nv + np.arange(m), nv + m + np.arange(m)
    iS = nv + 2 * m + np.arange(nk)
    iE = nv + 2 * m + nk + np.arange(8 if miss else 0)
    n_var = iE[-1] + 1 if miss else nv + 2 * m + nk
    r = np.arange(m)
    prev = r > 0
    gap = np.diff(cols, prepend=cols[0]).astype(float)
    Eg = E**gap
    T, scale = _terminal_rows(grid, n, cols)
    # rows: [P chain (m) | Q chain (m) | terminal (4) | samples (nk)]
    # P_i − P_{i−1} − (1 − E^g)/a · rate/th · Q_{i−1} − c1 v_i = 0
    # Q_i − E^g Q_{i−1} − c2 v_i = 0
    # Σ_j T_j v_j (− e⁺ + e⁻) = −base_n / scale
    # S − P_i − (1 − E^g)/a · rate/th · Q_i = 0
    g = (ks - cols[iks] - 1).astype(float)
    parts = [
        (r, iP, np.ones(m)),
        (r[prev], iP[prev] - 1, -np.ones(m - 1)),
        (r[prev], iQ[prev] - 1, -((1.0 - Eg) / a * rate / th)[prev]),
        (r, r, np.full(m, -c1)),
        (m + r, iQ, np.ones(m)),
        (m + r[prev], iQ[prev] - 1, -Eg[prev]),
        (m + r, r, np.full(m, -c2)),
        (np.repeat(2 * m + np.arange(4), m), np.tile(r, 4), T.ravel()),
        (2 * m + 4 + np.arange(nk), iS, np.ones(nk)),
        (2 * m + 4 + np.arange(nk), iP[iks], -np.ones(nk)),
        (2 * m + 4 + np.arange(nk), iQ[iks], -(1.0 - E**g) / a * rate / th),
    ]
    if smallest:  # v = v⁺ − v⁻
        parts += [
            (r, m + r, np.full(m, c1)),
            (m + r, m + r, np.full(m, c2)),
            (np.repeat(2 * m + np.arange(4), m), np.tile(m + r, 4), -T.ravel()),
        ]
    if miss:
        parts += [
            (2 * m + np.arange(4), iE[:4], -np.ones(4)),
            (2 * m + np.arange(4), iE[4:], np.ones(4)),
        ]
    R, C, V = (np.concatenate(z) for z in zip(*parts, strict=True))
    A_eq = scipy.sparse.csc_array((V, (R, C)), shape=(2 * m + 4 + nk, n_var))
    b_eq = np.zeros(2 * m + 4 + nk)
    b_eq[2 * m : 2 * m + 4] = -base[-1] / scale
    bounds = np.empty((n_var, 2))
    v_lo, v_hi = lo[cols] / U, hi[cols] / U
    if smallest:
        bounds[:m] = np.column_stack([np.maximum(v_lo, 0.0), np.maximum(v_hi, 0.0)])
        bounds[m:nv] = np.column_stack([np.maximum(-v_hi, 0.0), np.maximum(-v_lo, 0.0)])
    else:
        bounds[:m] = np.column_stack([v_lo, v_hi])
    after = cols + 1  # the sample after each free step; the last one is fixed by the end rows
    inner = after < n
    bounds[iP, 0] = np.where(inner, (-th - base[after, 0]) / th, -np.inf)
    bounds[iP, 1] = np.where(inner, (th - base[after, 0]) / th, np.inf)
    bounds[iQ] = (-np.inf, np.inf)
    bounds[iS, 0] = (-th - base[ks, 0]) / th
    bounds[iS, 1] = (th - base[ks, 0]) / th
    bounds[iE] = (0.0, np.inf)
    cost = np.zeros(n_var)
    if smallest:
        cost[:nv] = _TIE_WEIGHT if miss else 1.0
    cost[iE] = 1.0
    res = _linprog(
        c=cost, A_eq=A_eq, b_eq=b_eq, bounds=bounds, method=method, options=_HIGHS_OPTIONS
    )
    if res.status != 0:
        return None
    v = res.x[:m] - res.x[m:nv] if smallest else res.x[:m]
    return np.asarray(np.clip(v * U, lo[cols], hi[cols]), dtype=float)


@dataclass(frozen=True)
class _Found:
    """Result of a step-count search on one grid."""

    n: int  # smallest step count that reached the origin
    solution: _Solve  # that solution
    below: _Solve  # the attempt with n − 1 steps: the slack-free time-optimal shape
    root: float  # where the miss, extrapolated, reaches zero [steps]
    slope: float  # miss decrease per step there


def _min_steps(
    attempt: Callable[[int], _Solve], n_start: int, slope: float | None, n_max: int
) -> _Found | None:
    """Smallest n ≤ n_max with ``attempt(n).feasible``: safeguarded secant steps on the miss.

    The miss falls smoothly and convexly to zero as n approaches the minimum (on the paper's
    case within 6 % of linear over the last 20 % of the range), so the secant through the two
    largest infeasible counts lands on or just below the minimum. Safeguards: a secant step
    that stays infeasible doubles the next step; once bracketed, a secant step that fails is
    followed by bisection. Ends when n is feasible and n − 1 is not (both tried).
    """
    tried: dict[int, _Solve] = {}
    lo, hi = 0, n_max + 1  # lo: largest infeasible count tried (0: none); hi: smallest feasible
    n = min(max(n_start, 1), n_max)
    gallop, last_step, secant_failed = 1, 0, False
    for _ in range(64):
        sol = tried[n] = attempt(n)
        if sol.feasible:
            hi = min(hi, n)
        else:
            secant_failed = last_step > 0 and n > lo
            lo = max(lo, n)
        if hi - lo == 1 and (lo in tried or lo == 0):
            below = tried.get(lo, tried[hi])
            root = lo + min(1.0, below.miss / slope) if lo in tried and slope else lo + 0.5
            out_slope = slope or (2.0 * below.miss if lo in tried else 0.0)
            return _Found(hi, tried[hi], below, root, out_slope)
        if lo >= n_max:
            return None
        failed = sorted(k for k, v in tried.items() if not v.feasible)
        if len(failed) >= 2:
            k1, k2 = failed[-2:]
            secant = (tried[k1].miss - tried[k2].miss) / (k2 - k1)
            if secant > 0.0:
                slope = secant
        if lo == 0:  # nothing infeasible yet: walk down from the feasible count
            n = max(1, hi - gallop)
            gallop *= 2
            last_step = 0
            continue
        step = math.ceil(tried[lo].miss / slope - 1e-9) if slope else max(2, lo // 5)
        step = max(step, 1, 2 * last_step if secant_failed else 0)
        if hi <= n_max and (secant_failed or lo + step >= hi or not slope):
            n, last_step = (lo + hi) // 2, 0
        else:
            n, last_step = min(lo + step, n_max), step
    return None


@dataclass(frozen=True)
class _Reference:
    """An answer on a coarser grid, used to fix most of the finer grid's inputs."""

    step_s: float
    input_v: np.ndarray  # (N,)

    @property
    def duration_s(self) -> float:
        return self.step_s * self.input_v.shape[0]


def _reference(level: _Grid, sol: _Solve) -> _Reference:
    """The shape to refine: ``sol``'s inputs with its holds set to 0. On a grid, an arc along
    the angle limit may ring (inputs alternating in sign with the samples pinned at the limit:
    the sampled bound allows it); its continuous counterpart is u = 0 at θ̇ = 0."""
    theta = sol.states[:, 0]
    pinned = np.abs(theta) >= level.theta_lp_rad * (1.0 - 1e-6)
    hold = pinned[:-1] & pinned[1:] & (np.sign(theta[:-1]) == np.sign(theta[1:]))
    return _Reference(level.step_s, np.where(hold, 0.0, sol.input_v))


def _window_mask(ref: _Reference, n: int, step_s: float, window_s: float) -> np.ndarray:
    """Fine steps left free: within ``window_s`` of the reference's switches, which are mapped
    by the uniform stretch of the reference duration onto n steps."""
    stretch = n * step_s / ref.duration_s
    u = ref.input_v
    U = float(np.max(np.abs(u))) if u.size else 1.0
    tol = 1e-6 * max(U, 1e-12)
    fractional = np.flatnonzero((np.abs(u) > tol) & (np.abs(np.abs(u) - U) > tol))
    change = np.flatnonzero(np.abs(np.diff(u)) > tol) + 1
    edges = np.unique(np.concatenate([change, fractional, fractional + 1, [0, u.size]]))
    times = edges * ref.step_s * stretch
    centers = (np.arange(n) + 0.5) * step_s
    pos = np.searchsorted(times, centers)
    left = np.abs(centers - times[np.clip(pos - 1, 0, None)])
    right = np.abs(times[np.clip(pos, None, times.size - 1)] - centers)
    return np.asarray(np.minimum(left, right) <= window_s)


def _fixed_inputs(ref: _Reference, n: int, step_s: float) -> np.ndarray:
    """The reference input at each fine step, by the same stretch as ``_window_mask``."""
    stretch = n * step_s / ref.duration_s
    t_ref = (np.arange(n) + 0.5) * step_s / stretch
    idx = np.clip((t_ref / ref.step_s).astype(int), 0, ref.input_v.size - 1)
    return np.asarray(ref.input_v[idx])


@dataclass(frozen=True)
class TimeOptimalPlan:
    """Minimum-time path on a zero-order-hold grid.

    ``input_v`` (N,) is held over each step of ``step_s``; ``grid_states`` (N+1, 4) are the exact
    states at the grid times (the last is the origin up to solver tolerance). ``sample`` is exact
    between grid points too. Before 0 the plan holds the start with u = 0; after ``duration_s``
    it rests at the origin with u = 0.
    """

    step_s: float
    input_v: np.ndarray
    grid_states: np.ndarray
    voltage_limit_v: float  # the U used: V_max − margin
    angle_limit_rad: float  # θ_max: |θ(t)| stays within it at all times
    verified_minimal: bool  # N − 1 steps shown infeasible by the LP of the whole problem
    pole_per_s: float  # αβ
    alpha: float
    gamma: float
    kind: str = field(default="time_optimal", init=False)

    def __post_init__(self) -> None:
        for array in (self.input_v, self.grid_states):
            array.setflags(write=False)

    @property
    def n_steps(self) -> int:
        return int(self.input_v.shape[0])

    @property
    def duration_s(self) -> float:
        return self.n_steps * self.step_s

    def sample(self, time_s: np.ndarray) -> PlanSamples:
        """Exact desired states (n, 4) and inputs (n,) at any times (n,)."""
        t = np.atleast_1d(np.asarray(time_s, dtype=float))
        n = self.n_steps
        states = np.zeros((t.size, 4))
        input_v = np.zeros(t.size)
        states[t < 0.0] = self.grid_states[0]
        inside = (t >= 0.0) & (t < self.duration_s)
        if n and np.any(inside):
            k = np.clip((t[inside] / self.step_s).astype(np.int64), 0, n - 1)
            tau = t[inside] - k * self.step_s
            p = _Params(self.pole_per_s, self.alpha, self.gamma)
            states[inside] = _propagate(p, self.grid_states[k], self.input_v[k], tau)
            input_v[inside] = self.input_v[k]
        return PlanSamples(time_s=t, states=states, input_v=input_v)


def plan_time_optimal(
    model: LinearModel,
    initial_state: np.ndarray,
    *,
    voltage_limit_v: float = 5.0,
    angle_limit_rad: float = math.radians(52.0),
    voltage_margin_v: float = 0.5,
    step_s: float = 1e-3,
    max_duration_s: float = 20.0,
    verify_minimal: bool = False,
) -> TimeOptimalPlan:
    """The minimum-time path to rest at the origin under |u| ≤ V_max − margin, |θ| ≤ θ_max.

    ``initial_state`` is (θ, θ̇, ẋ, x). ``verify_minimal`` re-solves the whole fine problem
    at N − 1 steps (about 0.15 s for the paper's start) and, should it be feasible, continues
    the search on the whole problem; without it the minimality of N rests on the window
    search (checked against the whole problem in the tests).

    Raises PlanningError when the start violates the angle limit, cannot be kept within it,
    or needs longer than ``max_duration_s``.
    """
    p = _params(model)
    x0 = np.asarray(initial_state, dtype=float).reshape(4)
    U = voltage_limit_v - voltage_margin_v
    if not step_s > 0.0:
        raise ConfigError(f"step_s must be positive, got {step_s}")
    if not U > 0.0:
        raise ConfigError(
            f"voltage margin {voltage_margin_v} V leaves no input under the "
            f"{voltage_limit_v} V limit"
        )
    if not np.all(np.isfinite(x0)):
        raise PlanningError(f"initial state must be finite, got {x0.tolist()}")
    if abs(x0[0]) > angle_limit_rad:
        raise PlanningError(
            f"initial servo angle {math.degrees(x0[0]):.2f}° is beyond the "
            f"±{math.degrees(angle_limit_rad):.2f}° limit; start inside it or raise the limit"
        )
    grid = _make_grid(p, x0, U, angle_limit_rad, step_s, _accel_max(p, U, x0[1]))
    if grid is None:
        raise _overrun(x0, angle_limit_rad, U)
    if not np.any(x0):
        return _plan(grid, np.zeros(0), verified=True)
    n_max = math.floor(max_duration_s / step_s + 1e-9)
    # lower bounds on the time: the ball alone under an instantaneous servo; the servo's rate
    t_lo = max(
        _ball_only_time_s(x0[3], x0[2], abs(p.gamma) * angle_limit_rad),
        abs(x0[0]) / max(abs(x0[1]), U / p.beta),
    )
    found = _search(grid, t_lo, n_max)
    if found is None:
        raise _too_long(max_duration_s, x0)
    n, sol = found
    verified = False
    if verify_minimal:
        whole = _solve_steps(
            grid, n - 1, np.ones(n - 1, bool), np.zeros(n - 1), smallest=False, method="highs-ipm"
        )
        if whole.feasible:  # the windows were too narrow: finish on the whole problem
            better = _whole_search(grid, t_lo, n - 1)
            if better is not None:
                n, sol = better
        verified = True
    return _plan(grid, sol.input_v, verified=verified)


_Attempt = Callable[[int], _Solve]  # steps -> closest approach to the origin


def _whole(level: _Grid) -> _Attempt:
    """Attempts on the whole problem: every input free."""

    def attempt(n: int) -> _Solve:
        return _solve_steps(level, n, np.ones(n, bool), np.zeros(n), miss=True)

    return attempt


def _windowed(level: _Grid, ref: _Reference, window_s: float) -> _Attempt:
    """Attempts with the inputs fixed to ``ref`` except within ``window_s`` of its switches."""

    def attempt(n: int) -> _Solve:
        h = level.step_s
        mask, fixed = _window_mask(ref, n, h, window_s), _fixed_inputs(ref, n, h)
        return _solve_steps(level, n, mask, fixed, miss=True)

    return attempt


def _search(grid: _Grid, t_lo: float, n_max: int) -> tuple[int, _Solve] | None:
    """Minimal step count and clean inputs: the whole problem on a coarse grid of at most
    ``_COARSE_STEPS`` steps over the lower bound ``t_lo``, then on grids ``_LEVEL_RATIO`` times
    finer in turn, each with the inputs fixed to the coarser grid's time-optimal shape (bang
    arcs at ±U, holds at 0: its closest attempt one step short, which has no slack to spend)
    except in windows around its switches."""
    h = grid.step_s
    multiples = [1]
    while multiples[-1] * _LEVEL_RATIO * h * _COARSE_STEPS <= t_lo:
        multiples.append(multiples[-1] * _LEVEL_RATIO)
    # the coarser grids only guess the shape: they keep the fine grid's sample bound
    delta = grid.angle_max_rad - grid.theta_sample_rad
    accel = delta * 8.0 / (h * h)
    found: _Found | None = None
    prev: _Grid | None = None
    attempt: _Attempt | None = None
    for m in reversed(multiples):
        level = (
            grid
            if m == 1
            else _make_grid(
                grid.p, grid.x0, grid.voltage_v, grid.angle_max_rad, m * h, accel, delta
            )
        )
        if level is None:
            break
        if found is None or prev is None:
            attempt = _whole(level)
            found = _min_steps(attempt, math.floor(t_lo / level.step_s), None, n_max // m)
        else:
            ratio = prev.step_s / level.step_s
            ref = _reference(prev, found.below)
            attempt = _windowed(level, ref, _WINDOW * prev.step_s)
            start = math.floor(found.root * ratio)
            # terminal rows are scaled by one step's effect (∝ step): the slope carries over
            found = _min_steps(attempt, start, found.slope, n_max // m)
        if found is None:
            break
        prev = level
    else:
        if found is not None and attempt is not None:
            return found.n, found.solution
    return _whole_search(grid, t_lo, n_max)  # unusual start: no shortcut


def _whole_search(grid: _Grid, t_lo: float, n_max: int) -> tuple[int, _Solve] | None:
    """The step-count search on the whole fine problem (slow for long horizons)."""
    attempt = _whole(grid)
    found = _min_steps(attempt, math.floor(t_lo / grid.step_s), None, n_max)
    return None if found is None else (found.n, found.solution)


def _too_long(max_duration_s: float, x0: np.ndarray) -> PlanningError:
    return PlanningError(
        f"no path to rest within {max_duration_s} s from state {np.round(x0, 4).tolist()}; "
        "raise the maximum duration or start closer to rest"
    )


def _overrun(x0: np.ndarray, angle_limit_rad: float, voltage_v: float) -> PlanningError:
    return PlanningError(
        f"servo rate {x0[1]:.3f} rad/s at {math.degrees(x0[0]):.2f}° carries the servo past "
        f"±{math.degrees(angle_limit_rad):.2f}° within the first step even at {voltage_v:.2f} V; "
        "start slower or further from the limit"
    )


def _plan(grid: _Grid, input_v: np.ndarray, *, verified: bool) -> TimeOptimalPlan:
    p = grid.p
    return TimeOptimalPlan(
        step_s=grid.step_s,
        input_v=np.array(input_v, dtype=float),
        grid_states=_simulate(p, grid.step_s, grid.x0, input_v),
        voltage_limit_v=grid.voltage_v,
        angle_limit_rad=grid.angle_max_rad,
        verified_minimal=verified,
        pole_per_s=p.pole_per_s,
        alpha=p.alpha,
        gamma=p.gamma,
    )
