"""Minimum-time path of the full linear model, motor lag included (docs/design.md §2–3).

Problem: from ``x0 = (θ0, θ̇0, ẋ0, x0)`` reach rest at the origin as early as possible under
``ẋ = A x + B u``, ``|u| ≤ U`` and ``|θ(t)| ≤ θmax`` at all times; afterwards u = 0 keeps the
origin. The input is held over the steps of a grid of step h (default 1 ms, the controller
period), so the answer is a step count N and inputs u_k; the grid optimum converges to the
continuous one as h shrinks (1.7765, 1.777, 1.778, 1.780 s at h = 0.5, 1, 2, 5 ms for the
paper's start with U = 4.5 V).

Method, in three modules:

* ``lag_hold``: the exact zero-order hold in closed form. The motor is one pole a = αβ, then
  θ, then the ball's two integrators; the same formulas give the grid, the responses the LPs
  use, and ``sample``.
* ``lp``: "rest at the origin after n steps" as a sparse linear programme, solved by HiGHS,
  every answer re-simulated exactly before it is believed. It minimises the terminal miss
  rather than demanding it be zero: an infeasible n then still gives a number (the miss,
  smooth and convex in n, so secant steps find the minimal n in few tries) and a shape (the
  closest approach, which shows the true time-optimal arcs: bang at ±U, holds at ±θmax).
* this module: the search over step counts and grids, and the plan.

* Angle between samples: within a step θ is C², so it strays from the chord of its two samples
  by at most θ̈max h²/8 with θ̈max = αU + a·max(|θ̇0|, U/β) (|θ̇| never exceeds that rate).
  The samples k ≥ 1 are therefore held within θmax − δ, δ = θ̈max h²/8: 1.2e-4 rad (0.007°)
  at 1 ms, which costs the paper's start no step (its miss-extrapolated optimum moves by
  0.09 ms). The first step starts from the known state, so it is bounded exactly instead: θ̇
  is monotone over a held input, so θ turns at most once, at an angle given in closed form.
  (The plans found arrive at the limit with θ̇ → 0, so between samples they do not actually
  pass their samples at all; δ is the guarantee, not an observed need.)
* Search: the whole problem is solved only on a coarse grid (at most ``_COARSE_STEPS`` steps
  for the time's lower bound); each grid ``_LEVEL_RATIO`` times finer keeps the inputs of the
  coarser shape and frees only windows around its switches, so the fine LPs have a few
  hundred variables. Only the finest grid needs N feasible and N − 1 not; a coarser one only
  guides the next with a shape and a root, so its search ends at the first infeasible count
  whose miss puts the root within a step (usually the first LP, the start being the coarser
  root), and the coarsest one starts where the same search on a grid twice as coarse (half
  the variables) ends. At h = 1 ms the paper's start takes 7 LPs (3 small ones on the grid of
  step 32 h, 1 each on the 16 h and 4 h grids, 2 on the fine grid). Its plan comes from the
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

import numpy as np

from ballbeam.core.model import LinearModel
from ballbeam.core.planning.lag_hold import _accel_max, _Params, _params, _propagate, _simulate
from ballbeam.core.planning.lp import _Grid, _make_grid, _Solve, _solve_steps
from ballbeam.core.planning.plan import PlanSamples
from ballbeam.errors import ConfigError, PlanningError

__all__ = [
    "TimeOptimalPlan",
    "intersample_margin_rad",
    "plan_time_optimal",
    "plan_time_optimal_from_outside",
]

# The coarsest grid has at most this many steps over the lower bound on the time ...
_COARSE_STEPS = 40
# ... and each finer grid divides the step by this.
_LEVEL_RATIO = 4
# Half-width of the free windows around the coarser shape's switches, in its steps.
_WINDOW = 1.0


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

    The miss falls smoothly and convexly to zero at the minimum (paper's start, 16 h grid:
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


class _Budget:
    """The LPs one plan may solve: past ``limit`` (None: no limit) the plan is given up with
    PlanningError rather than searched on (a caller in a loop needs an answer in bounded time)."""

    def __init__(self, limit: int | None) -> None:
        self.limit = limit
        self.used = 0

    def solve(self, level: _Grid, n: int, free: np.ndarray, fixed_v: np.ndarray) -> _Solve:
        if self.limit is not None and self.used >= self.limit:
            raise PlanningError(
                f"no plan within {self.limit} LP solves on the {level.step_s * 1e3:g} ms grid"
            )
        self.used += 1
        return _solve_steps(level, n, free, fixed_v)


def _whole(level: _Grid, budget: _Budget) -> _Attempt:
    """Attempts on the whole problem: every input free."""
    return lambda n: budget.solve(level, n, np.ones(n, bool), np.zeros(n))


def _windowed(level: _Grid, ref: _Reference, window_s: float, budget: _Budget) -> _Attempt:
    """Attempts with the inputs of ``ref`` except within ``window_s`` of its switches."""
    h = level.step_s
    return lambda n: budget.solve(
        level, n, _window_mask(ref, n, h, window_s), _fixed_inputs(ref, n, h)
    )


def _first_guess(
    grid: _Grid, m: int, t_lo: float, n_max: int, delta: float, budget: _Budget
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
        _whole(pre, budget),
        math.floor(t_lo / pre.step_s),
        None,
        -(-n_max // (2 * m)) + 1,
        confirm=False,
    )
    if found is None or not math.isfinite(found.slope) or not math.isfinite(found.below.miss):
        return start, None
    return max(start, math.floor(2.0 * found.root)), found.slope


def _search(grid: _Grid, t_lo: float, n_max: int, budget: _Budget) -> _Found | None:
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
                return _min_steps(_whole(grid, budget), math.floor(t_lo / h), None, n_max)
            level = coarse
        if found is None or prev is None:
            # a coarse grid may need a step more than the fine horizon allows
            top_max = -(-n_max // m) + (m > 1)
            start, slope = _first_guess(grid, m, t_lo, n_max, delta, budget)
            found = _min_steps(_whole(level, budget), start, slope, top_max, confirm=m == 1)
            if found is None:
                return None  # nothing within the horizon even on the coarse grid
        else:
            ratio = prev.step_s / level.step_s
            if not math.isfinite(found.below.miss):  # no closest approach to refine: no shortcut
                return _min_steps(_whole(grid, budget), math.floor(t_lo / h), None, n_max)
            ref = _reference(prev, found.below)
            start = math.floor(found.root * ratio)
            # the terminal rows are scaled by one step's effect (∝ step): the slope carries over
            refined = None
            for width in (_WINDOW, 4.0 * _WINDOW):
                attempt = _windowed(level, ref, width * prev.step_s, budget)
                refined = _min_steps(
                    attempt, start, found.slope, -(-n_max // m) + (m > 1), confirm=m == 1
                )
                if refined is not None:
                    break
            if refined is None:  # unusual start: no shortcut
                return _min_steps(_whole(grid, budget), math.floor(t_lo / h), None, n_max)
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
    max_lp_solves: int | None = None,
) -> TimeOptimalPlan:
    """The minimum-time path from ``initial_state`` (θ, θ̇, ẋ, x) to rest at the origin.

    Inputs stay within ±(``voltage_limit_v`` − ``voltage_margin_v``) (the paper's setting keeps
    0.5 V back for the tracker: ``plan.voltage_margin_v``), the servo angle within
    ±``theta_max_rad`` at all times. ``verify_minimal`` re-solves the whole fine problem at
    N − 1 steps (one LP over all the inputs, slower than the whole windowed search) and
    continues on it should that be feasible; without it, minimality rests on the windowed
    search. ``max_lp_solves`` bounds the LPs the search may solve (None: unbounded).

    Raises PlanningError when the start is beyond the angle limit, moves too fast to be
    stopped before it, needs longer than ``max_duration_s`` or more than ``max_lp_solves``
    LPs; ConfigError for bad settings.
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
    budget = _Budget(max_lp_solves)
    found = _search(grid, t_lo, n_max, budget)
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
            better = _min_steps(_whole(grid, budget), math.floor(t_lo / step_s), None, n - 1)
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


def plan_time_optimal_from_outside(
    model: LinearModel,
    initial_state: np.ndarray,
    *,
    voltage_limit_v: float,
    theta_max_rad: float,
    step_s: float = 1e-3,
    max_duration_s: float = 20.0,
) -> TimeOptimalPlan:
    """``plan_time_optimal``, also from a start beyond ±``theta_max_rad`` (but at rest or
    turning back): full voltage away from the limit until the path's bound is reached, then
    the minimum-time path from there.

    A path that keeps a margin off the angle limit cannot hold a start on the limit (the
    paper's −52°); riding the start's angle instead would leave the tracker no room there. The
    lead-in is the time-optimal start whenever the optimum leaves the limit at once (the
    paper's start does: it swings to the other side first), and costs a few steps otherwise.
    """
    p = _params(model)
    x0 = np.asarray(initial_state, dtype=float).reshape(4)
    side = math.copysign(1.0, x0[0])
    if abs(x0[0]) <= theta_max_rad:
        return plan_time_optimal(
            model,
            x0,
            voltage_limit_v=voltage_limit_v,
            theta_max_rad=theta_max_rad,
            step_s=step_s,
            max_duration_s=max_duration_s,
        )
    if side * x0[1] > 0.0:
        raise PlanningError(
            f"the start {math.degrees(x0[0]):.2f}° is beyond the "
            f"±{math.degrees(theta_max_rad):.2f}° path bound and moving further out"
        )
    # the lead-in's samples must end within the bound less the planner's intersample margin
    inside = theta_max_rad - _accel_max(p, voltage_limit_v, x0[1]) * step_s**2 / 8.0
    lead_v: list[float] = []
    state = x0[None, :]
    one_step = np.array([step_s])
    while abs(state[0, 0]) > inside:
        if len(lead_v) * step_s > max_duration_s:
            raise PlanningError("the start does not leave the limit")  # pragma: no cover
        lead_v.append(-side * voltage_limit_v)
        state = _propagate(p, state, np.array([lead_v[-1]]), one_step)
    rest = plan_time_optimal(
        model,
        state[0],
        voltage_limit_v=voltage_limit_v,
        theta_max_rad=theta_max_rad,
        step_s=step_s,
        max_duration_s=max_duration_s - len(lead_v) * step_s,
    )
    input_v = np.concatenate([np.array(lead_v), rest.input_v])
    return TimeOptimalPlan(
        step_s=step_s,
        input_v=input_v,
        grid_states=_simulate(p, step_s, x0, input_v),
        voltage_limit_v=rest.voltage_limit_v,
        theta_max_rad=theta_max_rad,  # from the end of the lead-in on
        verified_minimal=False,
        pole_per_s=p.pole_per_s,
        alpha=p.alpha,
        gamma=p.gamma,
    )
