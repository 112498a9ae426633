"""Minimum-time path of the full linear model, motor lag included (docs/design.md §2–3).

Problem: from ``x0 = (θ0, θ̇0, ẋ0, x0)`` reach rest at the origin as early as possible under
``ẋ = A x + B u``, ``|u| ≤ U`` and ``|θ(t)| ≤ θmax`` at all times; afterwards u = 0 keeps the
origin. The input is held over the steps of a grid of step h (default 1 ms, the controller
period), so the answer is a step count N and inputs u_k; the grid optimum converges to the
continuous one as h shrinks (1.7765, 1.777, 1.778, 1.780 s at h = 0.5, 1, 2, 5 ms for the
paper's start with U = 4.5 V).

Method:

* Exact zero-order hold in closed form: the motor is one pole a = αβ, then θ, then the ball's
  two integrators; the same formulas give the grid, the responses the LPs use, and ``sample``.
* Angle between samples: within a step θ is C², so it strays from the chord of its two samples
  by at most θ̈max h²/8 with θ̈max = αU + a·max(|θ̇0|, U/β) (|θ̇| never exceeds that rate).
  The samples k ≥ 1 are therefore held within θmax − δ, δ = θ̈max h²/8: 1.2e-4 rad (0.007°)
  at 1 ms, which costs the paper's start no step (its miss-extrapolated optimum moves by
  0.09 ms). The first step starts from the known state, so it is bounded exactly instead: θ̇
  is monotone over a held input, so θ turns at most once, at an angle given in closed form.
  (The plans found arrive at the limit with θ̇ → 0, so between samples they do not actually
  pass their samples at all; δ is the guarantee, not an observed need.)
* "Rest at the origin after n steps" is a linear programme (HiGHS). Its variables are the free
  inputs and, after each free step, the motor's deviation from the trajectory of the fixed
  inputs (sparse rows, angle limits as variable bounds); the terminal rows are condensed over
  the free inputs, and every answer is re-simulated exactly before it is believed. The LP
  minimises the terminal miss rather than demanding it be zero: an infeasible n then still
  gives a number (the miss, smooth and convex in n, so secant steps find the minimal n in few
  tries) and a shape (the closest approach, which has no slack to spend and so shows the true
  time-optimal arcs: bang at ±U, holds at ±θmax).
* Speed: the whole problem is solved only on a coarse grid (at most ``_COARSE_STEPS`` steps
  for the time's lower bound); each grid ``_LEVEL_RATIO`` times finer keeps the inputs of the
  coarser shape and frees only windows around its switches, so the fine LPs have a few
  hundred variables. A tie-break on the inputs' L1 norm makes holds u = 0 rather than the
  chatter an arbitrary LP vertex would show. Only the finest grid needs N feasible and N − 1
  not; a coarser one only guides the next with a shape and a root, so its search ends at the
  first infeasible count whose miss puts the root within a step (usually the first LP, the
  start being the coarser root), and the coarsest one starts where the same search on a grid
  twice as coarse (half the variables) ends. The paper's start takes 7 LPs (grid steps of
  32 ms: 3 small; 16 and 4 ms: 1 each; 1 ms: 2), each solved by HiGHS through its public
  Python package ``highspy`` with linprog's model and options
  (``_solve_lp``; the tests check that linprog gives the same plan). Its plan comes from the
  same LPs as when every grid confirmed its count, so it is the same to the bit (the golden
  log's replay pins it).
* Minimality of the windowed search is checked against the whole fine problem in the tests
  (paper's start and random starts, independent formulation) and on request at run time
  (``verify_minimal``: the whole fine LP at N − 1).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import highspy
import numpy as np
import scipy.signal
import scipy.sparse

from ballbeam.core.model import LinearModel
from ballbeam.core.plans import PlanSamples
from ballbeam.errors import ConfigError, PlanningError

__all__ = ["TimeOptimalPlan", "intersample_margin_rad", "plan_time_optimal"]

# The coarsest grid has at most this many steps over the lower bound on the time ...
_COARSE_STEPS = 40
# ... and each finer grid divides the step by this.
_LEVEL_RATIO = 4
# Half-width of the free windows around the coarser shape's switches, in its steps.
_WINDOW = 1.0
# Angle kept back in the LPs besides δ, so that solver tolerance cannot break the sample bound.
_SOLVER_MARGIN_RAD = 1e-7
# Terminal miss (L1 over rows scaled to one step's largest effect) that still counts as rest.
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
    if A.shape != (4, 4) or B.shape != (4, 1):
        raise ConfigError("time-optimal planning needs the 4-state ball-and-beam model")
    pattern = np.zeros((4, 4))
    pattern[0, 1], pattern[3, 2] = 1.0, 1.0
    pattern[1, 1], pattern[2, 0] = A[1, 1], A[2, 0]
    b_pattern = np.array([[0.0], [B[1, 0]], [0.0], [0.0]])
    if (
        not np.array_equal(A, pattern)
        or not np.array_equal(B, b_pattern)
        or not A[1, 1] < 0.0
        or not B[1, 0] > 0.0
        or A[2, 0] == 0.0
    ):
        raise ConfigError("time-optimal planning needs the ball-and-beam model structure")
    return _Params(pole_per_s=-float(A[1, 1]), alpha=float(B[1, 0]), gamma=float(A[2, 0]))


def _phis(a: float, tau: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """φ1 = ∫e^{−as}, φ2 = ∫φ1, φ3 = ∫φ2 over [0, τ]: the lag's step, ramp and parabola."""
    phi1 = -np.expm1(-a * tau) / a
    phi2 = (tau - phi1) / a
    phi3 = (0.5 * tau * tau - phi2) / a
    return phi1, phi2, phi3


def _propagate(p: _Params, states: np.ndarray, input_v: np.ndarray, tau: np.ndarray) -> np.ndarray:
    """Exact states (n, 4) after holding ``input_v`` (n,) for ``tau`` (n,) from ``states``."""
    theta, rate, speed, pos = states.T
    phi1, phi2, phi3 = _phis(p.pole_per_s, tau)
    w = input_v / p.beta  # the steady servo rate under this voltage
    d = rate - w
    out = np.empty_like(states)
    out[:, 0] = theta + w * tau + d * phi1
    out[:, 1] = w + d * np.exp(-p.pole_per_s * tau)
    out[:, 2] = speed + p.gamma * (theta * tau + 0.5 * w * tau**2 + d * phi2)
    out[:, 3] = pos + speed * tau + p.gamma * (0.5 * theta * tau**2 + w * tau**3 / 6.0 + d * phi3)
    return out


def _simulate(p: _Params, step_s: float, x0: np.ndarray, input_v: np.ndarray) -> np.ndarray:
    """Grid states (N+1, 4) under the held inputs (N,); O(N) as a chain of filters."""
    n = input_v.shape[0]
    h = step_s
    E = math.exp(-p.pole_per_s * h)
    phi1, phi2, phi3 = (float(v) for v in _phis(p.pole_per_s, np.array(h)))
    w = input_v / p.beta
    rate = np.empty(n + 1)
    rate[0] = x0[1]
    if n:  # θ̇_{k+1} = E θ̇_k + (1 − E) w_k
        rate[1:] = scipy.signal.lfilter([1.0 - E], [1.0, -E], w, zi=[E * x0[1]])[0]
    r = rate[:-1]
    theta = np.empty(n + 1)
    theta[0] = x0[0]
    np.cumsum(phi1 * r + (h - phi1) * w, out=theta[1:])
    theta[1:] += x0[0]
    t = theta[:-1]
    speed = np.empty(n + 1)
    speed[0] = x0[2]
    np.cumsum(p.gamma * (t * h + 0.5 * w * h * h + (r - w) * phi2), out=speed[1:])
    speed[1:] += x0[2]
    pos = np.empty(n + 1)
    pos[0] = x0[3]
    np.cumsum(
        speed[:-1] * h + p.gamma * (0.5 * t * h * h + w * h**3 / 6.0 + (r - w) * phi3),
        out=pos[1:],
    )
    pos[1:] += x0[3]
    return np.column_stack([theta, rate, speed, pos])


def _accel_max(p: _Params, voltage_v: float, initial_rate_rad_s: float) -> float:
    """Bound on |θ̈| = |αu − αβθ̇|: under |u| ≤ U, |θ̇| never exceeds max(|θ̇0|, U/β)."""
    return p.alpha * voltage_v + p.pole_per_s * max(abs(initial_rate_rad_s), voltage_v / p.beta)


def intersample_margin_rad(
    model: LinearModel, voltage_v: float, step_s: float, initial_rate_rad_s: float = 0.0
) -> float:
    """δ = θ̈max h²/8: how far θ can pass the larger of two neighbouring samples within a step
    (θ is C² there, and a C² function strays from its chord by at most max|f''|·h²/8)."""
    return _accel_max(_params(model), voltage_v, initial_rate_rad_s) * step_s**2 / 8.0


def _ball_only_time_s(position_m: float, speed_m_s: float, accel_max: float) -> float:
    """Bang-bang time of a double integrator to rest at 0 under |ẍ| ≤ accel_max."""
    x, v = position_m, speed_m_s
    stop = x + v * abs(v) / (2.0 * accel_max)
    if stop > 0.0:
        return (v + 2.0 * math.sqrt(accel_max * x + 0.5 * v * v)) / accel_max
    if stop < 0.0:
        return (-v + 2.0 * math.sqrt(-accel_max * x + 0.5 * v * v)) / accel_max
    return abs(v) / accel_max


def _turn_angle(p: _Params, theta0: float, rate0: float, w: float) -> float:
    """The angle where θ turns, rate0 > 0 braked by the steady rate w < 0 held from t = 0:
    θ̇ = w + (rate0 − w) e^{−at} vanishes at t*, and θ(t*) = θ0 + w t* + rate0/a."""
    t_turn = math.log((rate0 - w) / -w) / p.pole_per_s
    return theta0 + w * t_turn + rate0 / p.pole_per_s


def _first_step_interval(
    p: _Params, x0: np.ndarray, voltage_v: float, theta_max: float, step_s: float
) -> tuple[float, float] | None:
    """Inputs u_0 that keep |θ| ≤ θmax over the first step, or None if even full braking from
    the start carries θ past the limit (then no input can keep it).

    Over a held input θ̇ is monotone, so θ turns at most once. Moving toward a limit (mirrored
    here to θ̇0 > 0, limit +θmax), θ peaks inside the step only when u_0 brakes hard enough to
    reverse before h; that peak grows with u_0, so the inputs that keep it within the limit
    form u_0 ≤ u_p (found by bisection on the closed form). Otherwise the largest angle of the
    step is a sample, bounded by the LP.
    """
    a, h = p.pole_per_s, step_s
    E = math.exp(-a * h)
    lo, hi = -voltage_v, voltage_v
    w_min = -voltage_v / p.beta
    for side in (1.0, -1.0):
        theta0, rate0 = side * x0[0], side * x0[1]
        if rate0 <= 0.0:
            continue
        if _turn_angle(p, theta0, rate0, w_min) > theta_max:
            return None
        w_rev = -rate0 * E / (1.0 - E)  # turns exactly at t = h
        theta_h = theta0 + w_rev * h + (rate0 - w_rev) * (1.0 - E) / a
        if w_rev <= w_min or theta_h <= theta_max:
            continue  # no turn inside the step, or every turn inside it is below θ(h; w_rev)
        w_lo, w_hi = w_min, w_rev  # turn angle rises with w from ≤ θmax to > θmax
        for _ in range(60):
            mid = 0.5 * (w_lo + w_hi)
            if _turn_angle(p, theta0, rate0, mid) <= theta_max:
                w_lo = mid
            else:
                w_hi = mid
        if side > 0.0:
            hi = min(hi, w_lo * p.beta)
        else:
            lo = max(lo, -w_lo * p.beta)
    return (lo, hi) if lo <= hi else None


@dataclass(frozen=True)
class _Grid:
    """One discretisation: step, limits, and the impulse response the LPs use."""

    p: _Params
    step_s: float
    x0: np.ndarray
    voltage_v: float  # U
    theta_max_rad: float
    theta_sample_rad: float  # bound on the samples k ≥ 1: θmax − δ
    first_input_v: tuple[float, float]  # interval for u_0
    # the impulse response (n, 4), Ad^i Bd, as far as computed: a cache, grown by ``impulse``
    _impulse: list[np.ndarray] = field(default_factory=list, compare=False, repr=False)

    @property
    def theta_lp_rad(self) -> float:
        return self.theta_sample_rad - _SOLVER_MARGIN_RAD

    def impulse(self, n: int) -> np.ndarray:
        """The impulse response Ad^i Bd for at least i < n, shape (≥ n, 4); computed once for
        all the attempts on this grid (doubling as they ask for more)."""
        known = self._impulse[0] if self._impulse else np.zeros((0, 4))
        if n > known.shape[0]:
            n_new = max(n, 2 * known.shape[0])
            Bd = _propagate(self.p, np.zeros((1, 4)), np.ones(1), np.array([self.step_s]))[0]
            known = _simulate(self.p, self.step_s, Bd, np.zeros(n_new - 1))
            self._impulse[:] = [known]
        return known

    def bounds_v(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        lo = np.full(n, -self.voltage_v)
        hi = np.full(n, self.voltage_v)
        lo[0], hi[0] = self.first_input_v
        return lo, hi


def _make_grid(
    p: _Params, x0: np.ndarray, voltage_v: float, theta_max: float, step_s: float, delta: float
) -> _Grid | None:
    interval = _first_step_interval(p, x0, voltage_v, theta_max, step_s)
    if interval is None:
        return None
    return _Grid(p, step_s, x0, voltage_v, theta_max, theta_max - delta, interval)


def _highs_solve(
    c: np.ndarray,
    A_eq: scipy.sparse.csc_array,
    b_eq: np.ndarray,
    bounds: np.ndarray,
    options: dict[str, Any],
) -> tuple[bool | None, np.ndarray]:
    """One HiGHS run on min c·x, A_eq x = b_eq, bounds (n, 2), with linprog's model and
    settings (column-wise matrix, dual simplex strategy, ``presolve`` a bool): (True, x) when
    optimal, (False, _) when infeasible, (None, _) when HiGHS gives up."""
    n_col, n_row = c.size, b_eq.size
    lp = highspy.HighsLp()
    lp.num_col_, lp.num_row_ = n_col, n_row
    lp.col_cost_ = c
    lp.col_lower_ = np.maximum(bounds[:, 0], -highspy.kHighsInf)
    lp.col_upper_ = np.minimum(bounds[:, 1], highspy.kHighsInf)
    lp.row_lower_ = lp.row_upper_ = b_eq
    matrix = lp.a_matrix_
    matrix.format_ = highspy.MatrixFormat.kColwise
    matrix.num_col_, matrix.num_row_ = n_col, n_row
    matrix.start_ = A_eq.indptr
    matrix.index_ = A_eq.indices
    matrix.value_ = A_eq.data
    solver = highspy.Highs()  # type: ignore[no-untyped-call]  # (its __init__ is unannotated)
    solver.setOptionValue("output_flag", False)
    solver.setOptionValue("log_to_console", False)
    solver.setOptionValue("simplex_strategy", 1)  # dual simplex, as linprog sets it
    for key, value in options.items():
        if key == "presolve":  # linprog's bool; HiGHS's own default is "choose"
            value = "on" if value else "off"
        solver.setOptionValue(key, value)
    solver.passModel(lp)
    solver.run()
    status = solver.getModelStatus()
    if status == highspy.HighsModelStatus.kOptimal:
        return True, np.array(solver.getSolution().col_value)
    infeasible = status in (
        highspy.HighsModelStatus.kInfeasible,
        highspy.HighsModelStatus.kModelError,
    )
    return (False if infeasible else None), np.zeros(0)


def _solve_lp(
    c: np.ndarray,
    A_eq: scipy.sparse.csc_array,
    b_eq: np.ndarray,
    bounds: np.ndarray,
    method: str,
) -> np.ndarray | None:
    """argmin c·x subject to A_eq x = b_eq within the bounds (n, 2), or None if the LP is
    infeasible or HiGHS gives up on every try. ``method`` is linprog's name for the solver:
    "highs" (HiGHS chooses, dual simplex here) or "highs-ipm" (interior point).

    The LPs go to HiGHS directly (``highspy``) rather than through ``scipy.optimize.linprog``:
    linprog's checks and conversions take longer than most of these small LPs take to solve.
    The model and options are linprog's, so the answers are those linprog gives (the tests
    compare the two).
    """
    # HiGHS now and then gives up ("model status unknown") on these near-degenerate LPs, most
    # often right at the minimal count; without presolve, or by interior point, it answers.
    tries: list[dict[str, Any]] = [{}, {"presolve": False}, {"solver": "ipm"}]
    for extra in tries:
        options: dict[str, Any] = {"presolve": True, **_HIGHS_OPTIONS, **extra}
        if method == "highs-ipm":
            options["solver"] = "ipm"
        elif method != "highs":
            raise ValueError(f"unknown LP method {method!r}")
        optimal, x = _highs_solve(c, A_eq, b_eq, bounds, options)
        if optimal is not None:
            return x if optimal else None
    return None


@dataclass(frozen=True)
class _Solve:
    """One attempt: inputs (n,), their exactly simulated grid states (n+1, 4), and the
    terminal miss of those states (L1 over rows scaled to one step's largest effect)."""

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
    exact_end: bool = False,
    method: str = "highs",
) -> _Solve:
    """Come as close to the origin in n steps as the limits allow, the inputs outside
    ``free_mask`` held at ``fixed_v``; feasible when the miss is negligible.

    Minimising the miss keeps the LP feasible whenever the angle limits are, so an infeasible n
    still yields the closest approach. ``exact_end``: demand rest instead (no tie-break; used to
    verify). Answers are re-simulated exactly; a sample inside a fixed stretch that passes the
    limit gets its own bound and the LP is solved again, one before the first free input frees
    the inputs before it.
    """
    p, h = grid.p, grid.step_s
    lo, hi = grid.bounds_v(n)
    fixed_v = np.clip(fixed_v, lo, hi)
    mask = free_mask.copy()
    extra = np.zeros(0, dtype=np.int64)

    def fail() -> _Solve:
        return _Solve(False, fixed_v, _simulate(p, h, grid.x0, fixed_v))

    for _ in range(12):
        fixed = np.where(mask, 0.0, fixed_v)
        base = _simulate(p, h, grid.x0, fixed)
        cols = np.flatnonzero(mask)
        if cols.size == 0:
            return fail()
        # θ is monotone over a held zero input (holds) and turns at most once over any held
        # input: bounding the last sample of each fixed stretch covers holds; turns come lazily
        samples = np.union1d(cols[1:][np.diff(cols) > 1], extra)
        free_v = _shooting_lp(grid, n, cols, base, samples, exact_end=exact_end, method=method)
        if free_v is None:
            return fail()
        u = fixed.copy()
        u[cols] = free_v
        states = _simulate(p, h, grid.x0, u)
        over = np.flatnonzero(np.abs(states[1:n, 0]) > grid.theta_sample_rad) + 1
        if over.size == 0:
            missed = float(np.sum(np.abs(states[-1]) / _terminal_rows(grid, n, cols)[1]))
            return _Solve(missed <= _MISS_TOL, u, states, missed)
        early = over[over <= cols[0]]
        if early.size:  # only fixed inputs reach these samples: free the inputs before them
            mask[max(0, int(early[0]) - 8) : int(early[-1])] = True
            continue
        near = (over[:, None] + np.arange(-1, 2)[None, :]).ravel()
        added = np.union1d(extra, near[(near >= 1) & (near < n)])
        if np.union1d(samples, added).size == samples.size:  # bounded already: tolerance
            return fail()
        extra = added
    return fail()


def _terminal_rows(grid: _Grid, n: int, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The end state's response to the free inputs v = u/U (4, m), rows scaled to a largest
    entry of 1, and those scales (4,): the units of the miss."""
    T = grid.impulse(n)[n - 1 - cols].T * grid.voltage_v
    scale = np.max(np.abs(T), axis=1)
    scale[scale == 0.0] = 1.0
    return T / scale[:, None], scale


def _shooting_lp(
    grid: _Grid,
    n: int,
    cols: np.ndarray,
    base: np.ndarray,
    samples: np.ndarray,
    *,
    exact_end: bool,
    method: str,
) -> np.ndarray | None:
    """The free inputs [V] of the sparse multiple-shooting LP, or None if it is infeasible.

    Variables: v = u/U at the free steps (split v⁺ − v⁻ for the L1 tie-break); after each free
    step the motor's deviation from the fixed-input trajectory ``base`` (P = δθ/θlp,
    Q = δθ̇/(U/β)); one per bounded sample inside a fixed stretch (S); the terminal miss e±.
    Between free steps the deviation evolves freely, in closed form over any gap g:
    δθ += (1 − E^g)/a · δθ̇, δθ̇ *= E^g, so every row but the four terminal ones (condensed over
    the free inputs, exact) has at most five entries and the angle limits are variable bounds.
    """
    p, h, U = grid.p, grid.step_s, grid.voltage_v
    a = p.pole_per_s
    E = math.exp(-a * h)
    phi1 = float(_phis(a, np.array(h))[0])
    rate = U / p.beta
    m = cols.size
    th = grid.theta_lp_rad - 2e-9 * m  # solver error adds up along the chain
    c1 = (h - phi1) * rate / th  # P after one step from rest at v = 1
    c2 = 1.0 - E  # Q after one step from rest at v = 1
    # bounded samples k inside fixed stretches, after free step i: θ_k = base_k + th·(P_i + q Q_i)
    i_of = np.searchsorted(cols, samples - 1, side="right") - 1
    keep = (i_of >= 0) & (cols[np.clip(i_of, 0, None)] + 1 < samples)
    ks, iks = samples[keep], i_of[keep]
    nk = ks.size
    tie = not exact_end
    nv = 2 * m if tie else m
    iP, iQ = nv + np.arange(m), nv + m + np.arange(m)
    iS = nv + 2 * m + np.arange(nk)
    iE = nv + 2 * m + nk + np.arange(0 if exact_end else 8)
    n_var = nv + 2 * m + nk + iE.size
    r = np.arange(m)
    prev = r > 0
    lag = (1.0 - E ** np.diff(cols, prepend=cols[0]).astype(float)) / a * rate / th
    decay = E ** np.diff(cols, prepend=cols[0]).astype(float)
    q = (1.0 - E ** (ks - cols[iks] - 1).astype(float)) / a * rate / th
    T, scale = _terminal_rows(grid, n, cols)
    rk = 2 * m + 4 + np.arange(nk)
    terminal = np.repeat(2 * m + np.arange(4), m)
    # rows: P_i − P_{i−1} − lag_i Q_{i−1} − c1 v_i = 0;  Q_i − decay_i Q_{i−1} − c2 v_i = 0;
    #       Σ_j T_j v_j − e⁺ + e⁻ = −base_n/scale;     S_k − P_i − q_k Q_i = 0
    parts = [
        (r, iP, np.ones(m)),
        (r[prev], iP[prev] - 1, -np.ones(m - 1)),
        (r[prev], iQ[prev] - 1, -lag[prev]),
        (r, r, np.full(m, -c1)),
        (m + r, iQ, np.ones(m)),
        (m + r[prev], iQ[prev] - 1, -decay[prev]),
        (m + r, r, np.full(m, -c2)),
        (terminal, np.tile(r, 4), T.ravel()),
        (rk, iS, np.ones(nk)),
        (rk, iP[iks], -np.ones(nk)),
        (rk, iQ[iks], -q),
    ]
    if tie:  # v = v⁺ − v⁻; the miss variables
        parts += [
            (r, m + r, np.full(m, c1)),
            (m + r, m + r, np.full(m, c2)),
            (terminal, np.tile(m + r, 4), -T.ravel()),
            (2 * m + np.arange(4), iE[:4], -np.ones(4)),
            (2 * m + np.arange(4), iE[4:], np.ones(4)),
        ]
    R, C, V = (np.concatenate(z) for z in zip(*parts, strict=True))
    A_eq = scipy.sparse.csc_array((V, (R, C)), shape=(2 * m + 4 + nk, n_var))
    b_eq = np.zeros(2 * m + 4 + nk)
    b_eq[2 * m : 2 * m + 4] = -base[-1] / scale
    lo, hi = grid.bounds_v(n)
    v_lo, v_hi = lo[cols] / U, hi[cols] / U
    bounds = np.empty((n_var, 2))
    if tie:
        bounds[:m] = np.column_stack([np.maximum(v_lo, 0.0), np.maximum(v_hi, 0.0)])
        bounds[m:nv] = np.column_stack([np.maximum(-v_hi, 0.0), np.maximum(-v_lo, 0.0)])
    else:
        bounds[:m] = np.column_stack([v_lo, v_hi])
    after = cols + 1  # the sample after each free step; the last one is pinned by the end rows
    inner = after < n
    bounds[iP, 0] = np.where(inner, (-th - base[after, 0]) / th, -np.inf)
    bounds[iP, 1] = np.where(inner, (th - base[after, 0]) / th, np.inf)
    bounds[iQ] = (-np.inf, np.inf)
    bounds[iS, 0] = (-th - base[ks, 0]) / th
    bounds[iS, 1] = (th - base[ks, 0]) / th
    bounds[iE] = (0.0, np.inf)
    cost = np.zeros(n_var)
    cost[:nv] = _TIE_WEIGHT if tie else 0.0
    cost[iE] = 1.0
    x = _solve_lp(cost, A_eq, b_eq, bounds, method)
    if x is None:
        return None
    v = x[:m] - x[m:nv] if tie else x[:m]
    return np.asarray(np.clip(v * U, lo[cols], hi[cols]), dtype=float)


@dataclass(frozen=True)
class _Found:
    """Result of a step-count search on one grid."""

    n: int  # smallest step count that reached rest (predicted when ``solution`` is None)
    solution: _Solve | None  # that solution; None when n was predicted, not tried
    below: _Solve  # the closest approach with n − 1 steps: the shape without slack
    root: float  # where the miss, extrapolated, reaches zero [steps]
    slope: float  # miss decrease per step there


_Attempt = Callable[[int], _Solve]


def _min_steps(
    attempt: _Attempt, n_start: int, slope: float | None, n_max: int, *, confirm: bool = True
) -> _Found | None:
    """Smallest n ≤ n_max with ``attempt(n).feasible``: safeguarded secant steps on the miss.

    The miss falls smoothly and convexly to zero at the minimum (paper's start, 16 ms grid:
    1.48 at 90 steps, 0.17 at 108, 0.0097 at 111, zero from 112 on), so the secant through the
    two largest infeasible counts lands on or just below it. A secant step that does not
    halve the miss doubles the next; once bracketed, such a step is followed by bisection.
    Ends when n is feasible and n − 1 has been tried and is not. Without ``confirm`` (a
    coarser grid, which only guides the next) it ends as soon as an infeasible n puts the
    root within a step: the next grid needs that shape and the root, not a feasible count.
    """
    tried: dict[int, _Solve] = {}
    lo, hi = 0, n_max + 1  # largest infeasible count tried (0: none); smallest feasible
    n = min(max(n_start, 1), n_max)
    gallop, last_step, secant_failed = 1, 0, False
    for _ in range(64):
        sol = tried[n] = attempt(n)
        if sol.feasible:
            hi = min(hi, n)
        else:
            # a secant step falls short of a convex miss's root, but should at least halve it
            secant_failed = last_step > 0 and n > lo and sol.miss > 0.5 * tried[lo].miss
            lo = max(lo, n)
        if hi <= n_max and hi - lo == 1 and (lo in tried or lo == 0):
            below = tried.get(lo, tried[hi])
            known = lo in tried and bool(slope)
            root = lo + min(1.0, below.miss / slope) if known and slope else lo + 0.5
            out_slope = slope or (2.0 * below.miss if lo in tried else 0.0)
            return _Found(hi, tried[hi], below, root, out_slope)
        if lo >= n_max:
            return None
        failed = sorted(k for k, v in tried.items() if not v.feasible)
        if len(failed) >= 2:
            k1, k2 = failed[-2:]
            secant = (tried[k1].miss - tried[k2].miss) / (k2 - k1)
            if 0.0 < secant < math.inf:
                slope = secant
        # (a slope of ∞ comes from a miss the LP could not give: it predicts nothing)
        if not confirm and lo in tried and lo < n_max and slope and slope < math.inf:
            below = tried[lo]
            if below.miss <= slope:
                return _Found(lo + 1, None, below, lo + below.miss / slope, slope)
        if lo == 0:  # nothing infeasible yet: walk down from the feasible count
            n = max(1, hi - gallop)
            gallop *= 2
            last_step = 0
            continue
        miss = tried[lo].miss
        if slope and miss < math.inf:
            # to confirm, step onto the predicted root; else to just short of it, where an
            # infeasible count ends the search
            step = math.ceil(miss / slope - 1e-9) if confirm else math.floor(miss / slope)
        else:
            step = max(2, lo // 5)
        step = max(step, 1, 2 * last_step if secant_failed else 0)
        if hi <= n_max and (secant_failed or lo + step >= hi or not slope):
            n, last_step = (lo + hi) // 2, 0
        else:
            n, last_step = min(lo + step, n_max), step
    return None


@dataclass(frozen=True)
class _Reference:
    """A shape on a coarser grid: its inputs (N,), holds set to 0."""

    step_s: float
    input_v: np.ndarray

    @property
    def duration_s(self) -> float:
        return self.step_s * int(self.input_v.shape[0])


def _reference(level: _Grid, sol: _Solve) -> _Reference:
    """The shape to refine. On a grid an arc along the angle limit may ring (inputs alternating
    in sign, the samples pinned at the limit: the sampled bound allows it); its continuous
    counterpart is u = 0 at θ̇ = 0, which is what the finer grid is given."""
    theta = sol.states[:, 0]
    pinned = np.abs(theta) >= level.theta_lp_rad * (1.0 - 1e-6)
    hold = pinned[:-1] & pinned[1:] & (np.sign(theta[:-1]) == np.sign(theta[1:]))
    return _Reference(level.step_s, np.where(hold, 0.0, sol.input_v))


def _window_mask(ref: _Reference, n: int, step_s: float, window_s: float) -> np.ndarray:
    """Fine steps left free: those within ``window_s`` of a switch of the reference (a change
    of input, or a step at neither 0 nor ±U), its time stretched onto the n steps."""
    stretch = n * step_s / ref.duration_s
    u = ref.input_v
    U = float(np.max(np.abs(u)))
    tol = 1e-6 * max(U, 1e-12)
    partial = np.flatnonzero((np.abs(u) > tol) & (np.abs(np.abs(u) - U) > tol))
    change = np.flatnonzero(np.abs(np.diff(u)) > tol) + 1
    edges = np.unique(np.concatenate([change, partial, partial + 1, [0, u.size]]))
    times = edges * ref.step_s * stretch
    centers = (np.arange(n) + 0.5) * step_s
    pos = np.searchsorted(times, centers)
    left = np.abs(centers - times[np.clip(pos - 1, 0, None)])
    right = np.abs(times[np.clip(pos, None, times.size - 1)] - centers)
    return np.asarray(np.minimum(left, right) <= window_s)


def _fixed_inputs(ref: _Reference, n: int, step_s: float) -> np.ndarray:
    """The reference's input at each fine step, by the same stretch as ``_window_mask``."""
    stretch = n * step_s / ref.duration_s
    t_ref = (np.arange(n) + 0.5) * step_s / stretch
    idx = np.clip((t_ref / ref.step_s).astype(int), 0, ref.input_v.size - 1)
    return np.asarray(ref.input_v[idx])


def _whole(level: _Grid) -> _Attempt:
    """Attempts on the whole problem: every input free."""
    return lambda n: _solve_steps(level, n, np.ones(n, bool), np.zeros(n))


def _windowed(level: _Grid, ref: _Reference, window_s: float) -> _Attempt:
    """Attempts with the inputs of ``ref`` except within ``window_s`` of its switches."""
    h = level.step_s
    return lambda n: _solve_steps(
        level, n, _window_mask(ref, n, h, window_s), _fixed_inputs(ref, n, h)
    )


def _first_guess(
    grid: _Grid, m: int, t_lo: float, n_max: int, delta: float
) -> tuple[int, float | None]:
    """Where to start the whole problem on the coarsest grid (step m·h), and the miss's slope.

    From the lower bound on the time the secant steps take a few LPs to reach the root; they
    are taken on a grid twice as coarse instead, whose LPs have half the variables, and its
    root (a little late: the coarser grid is slower) starts the coarsest grid's search.
    """
    start = math.floor(t_lo / (m * grid.step_s))
    pre = _make_grid(
        grid.p, grid.x0, grid.voltage_v, grid.theta_max_rad, 2 * m * grid.step_s, delta
    )
    if pre is None:
        return start, None
    found = _min_steps(
        _whole(pre), math.floor(t_lo / pre.step_s), None, -(-n_max // (2 * m)) + 1, confirm=False
    )
    if found is None or not math.isfinite(found.slope) or not math.isfinite(found.below.miss):
        return start, None
    return max(start, math.floor(2.0 * found.root)), found.slope


def _search(grid: _Grid, t_lo: float, n_max: int) -> _Found | None:
    """The minimal step count: the whole problem on the coarsest grid, then each finer grid
    around the coarser shape (see the module notes)."""
    h = grid.step_s
    multiples = [1]
    while multiples[-1] * _LEVEL_RATIO * h * _COARSE_STEPS <= t_lo:
        multiples.append(multiples[-1] * _LEVEL_RATIO)
    # the coarser grids only guess the shape: they keep the fine grid's sample bound
    delta = grid.theta_max_rad - grid.theta_sample_rad
    found: _Found | None = None
    prev: _Grid | None = None
    for m in reversed(multiples):
        level = grid
        if m > 1:
            coarse = _make_grid(grid.p, grid.x0, grid.voltage_v, grid.theta_max_rad, m * h, delta)
            if coarse is None:
                return _min_steps(_whole(grid), math.floor(t_lo / h), None, n_max)
            level = coarse
        if found is None or prev is None:
            # a coarse grid may need a step more than the fine horizon allows
            top_max = -(-n_max // m) + (m > 1)
            start, slope = _first_guess(grid, m, t_lo, n_max, delta)
            found = _min_steps(_whole(level), start, slope, top_max, confirm=m == 1)
            if found is None:
                return None  # nothing within the horizon even on the coarse grid
        else:
            ratio = prev.step_s / level.step_s
            if not math.isfinite(found.below.miss):  # no closest approach to refine: no shortcut
                return _min_steps(_whole(grid), math.floor(t_lo / h), None, n_max)
            ref = _reference(prev, found.below)
            start = math.floor(found.root * ratio)
            # the terminal rows are scaled by one step's effect (∝ step): the slope carries over
            refined = None
            for width in (_WINDOW, 4.0 * _WINDOW):
                attempt = _windowed(level, ref, width * prev.step_s)
                refined = _min_steps(
                    attempt, start, found.slope, -(-n_max // m) + (m > 1), confirm=m == 1
                )
                if refined is not None:
                    break
            if refined is None:  # unusual start: no shortcut
                return _min_steps(_whole(grid), math.floor(t_lo / h), None, n_max)
            found = refined
        prev = level
    return found


@dataclass(frozen=True)
class TimeOptimalPlan:
    """Minimum-time path on a zero-order-hold grid.

    ``input_v`` (N,) is held over each step of ``step_s``; ``grid_states`` (N+1, 4) are the exact
    states at the grid times, the last one the origin up to solver tolerance (~1e-10). ``sample``
    is exact between grid times too. Before 0 the plan holds the start with u = 0; from
    ``duration_s`` on it rests at the origin with u = 0.
    """

    step_s: float
    input_v: np.ndarray
    grid_states: np.ndarray
    voltage_limit_v: float  # U, the bound the inputs respect
    theta_max_rad: float  # |θ(t)| stays within it at all times
    verified_minimal: bool  # N − 1 steps found infeasible on the whole fine problem
    pole_per_s: float  # αβ of the model planned with
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
        """Exact desired states (n, 4) and inputs (n,) at the times (n,)."""
        t = np.atleast_1d(np.asarray(time_s, dtype=float))
        # a time a rounding error short of a grid time belongs to that grid time
        k = np.floor(t / self.step_s + 1e-9).astype(np.int64)
        inside = (k >= 0) & (k < self.n_steps)
        states = np.zeros((t.size, 4))
        input_v = np.zeros(t.size)
        states[k < 0] = self.grid_states[0]
        if np.any(inside):
            ki = k[inside]
            tau = np.maximum(t[inside] - ki * self.step_s, 0.0)
            p = _Params(self.pole_per_s, self.alpha, self.gamma)
            states[inside] = _propagate(p, self.grid_states[ki], self.input_v[ki], tau)
            input_v[inside] = self.input_v[ki]
        return PlanSamples(time_s=t, states=states, input_v=input_v)


def plan_time_optimal(
    model: LinearModel,
    initial_state: np.ndarray,
    *,
    voltage_limit_v: float = 5.0,
    theta_max_rad: float = math.radians(52.0),
    voltage_margin_v: float = 0.0,
    step_s: float = 1e-3,
    max_duration_s: float = 20.0,
    verify_minimal: bool = False,
) -> TimeOptimalPlan:
    """The minimum-time path from ``initial_state`` (θ, θ̇, ẋ, x) to rest at the origin.

    Inputs stay within ±(``voltage_limit_v`` − ``voltage_margin_v``) (the paper's setting keeps
    0.5 V back for the tracker: ``plan.voltage_margin_v``), the servo angle within
    ±``theta_max_rad`` at all times. ``verify_minimal`` re-solves the whole fine problem at
    N − 1 steps (one LP over all the inputs, slower than the whole windowed search) and
    continues on it should that be feasible; without it, minimality rests on the windowed
    search.

    Raises PlanningError when the start is beyond the angle limit, moves too fast to be
    stopped before it, or needs longer than ``max_duration_s``; ConfigError for bad settings.
    """
    p = _params(model)
    x0 = np.asarray(initial_state, dtype=float).reshape(4)
    U = voltage_limit_v - voltage_margin_v
    if not step_s > 0.0:
        raise ConfigError(f"step_s must be positive, got {step_s}")
    if not U > 0.0:
        raise ConfigError(
            f"a voltage margin of {voltage_margin_v} V leaves no input under the "
            f"{voltage_limit_v} V limit"
        )
    if not theta_max_rad > 0.0:
        raise ConfigError(f"theta_max_rad must be positive, got {theta_max_rad}")
    if not np.all(np.isfinite(x0)):
        raise PlanningError(f"the initial state must be finite, got {x0.tolist()}")
    limit_deg = math.degrees(theta_max_rad)
    if abs(x0[0]) > theta_max_rad:
        raise PlanningError(
            f"the initial servo angle {math.degrees(x0[0]):.2f}° is beyond the ±{limit_deg:.2f}° "
            "limit; start inside it or widen the limit"
        )
    delta = _accel_max(p, U, x0[1]) * step_s**2 / 8.0
    grid = _make_grid(p, x0, U, theta_max_rad, step_s, delta)
    if grid is None:
        raise PlanningError(
            f"the servo turns at {x0[1]:.3f} rad/s at {math.degrees(x0[0]):.2f}°: even "
            f"{U:.2f} V of braking carries it past ±{limit_deg:.2f}°; start slower or further "
            "from the limit"
        )
    if not np.any(x0):
        return _plan(grid, np.zeros(0), verified=True)
    n_max = math.floor(max_duration_s / step_s + 1e-9)
    # lower bounds on the time: the ball alone under an instantaneous servo; the servo's rate
    t_lo = max(
        _ball_only_time_s(x0[3], x0[2], abs(p.gamma) * theta_max_rad),
        abs(x0[0]) / max(abs(x0[1]), U / p.beta),
    )
    found = _search(grid, t_lo, n_max)
    if found is None or found.solution is None:  # (the finest grid always confirms its count)
        raise PlanningError(
            f"no path to rest within {max_duration_s} s from {np.round(x0, 4).tolist()} "
            f"(θ, θ̇, ẋ, x) under ±{U:.2f} V and ±{limit_deg:.2f}°; allow a longer duration "
            "or start closer to rest"
        )
    n, sol = found.n, found.solution
    verified = False
    if verify_minimal and n == 1:
        verified = True  # zero steps reach rest only from rest
    elif verify_minimal:
        whole = _solve_steps(
            grid, n - 1, np.ones(n - 1, bool), np.zeros(n - 1), exact_end=True, method="highs-ipm"
        )
        if whole.feasible:  # the windows missed a faster path: search the whole problem below n
            better = _min_steps(_whole(grid), math.floor(t_lo / step_s), None, n - 1)
            if better is not None and better.solution is not None:
                n, sol = better.n, better.solution
        verified = True
    return _plan(grid, sol.input_v, verified=verified)


def _plan(grid: _Grid, input_v: np.ndarray, *, verified: bool) -> TimeOptimalPlan:
    p = grid.p
    return TimeOptimalPlan(
        step_s=grid.step_s,
        input_v=np.array(input_v, dtype=float),
        grid_states=_simulate(p, grid.step_s, grid.x0, input_v),
        voltage_limit_v=grid.voltage_v,
        theta_max_rad=grid.theta_max_rad,
        verified_minimal=verified,
        pole_per_s=p.pole_per_s,
        alpha=p.alpha,
        gamma=p.gamma,
    )
