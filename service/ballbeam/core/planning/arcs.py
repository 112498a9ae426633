"""Minimum-time paths as arcs of held input, re-solved from any state in about a millisecond.

The continuous minimum-time path of the lag model (θ̈ = −a θ̇ + α u, ẍ = γ θ) under |u| ≤ U and
|θ| ≤ θm is a sequence of **arcs**: full voltage (±U), and **holds** on the angle limit
(θ = ±θm, θ̇ = 0, u = 0), each entered with the servo at rest on the limit. A *structure* (the
arcs' order) with n arcs of which h are holds has n unknown durations and 4 + 2h equations:
rest at the target, and each hold entered at rest on its limit. For a given structure the
durations are the root of a smooth system, found by Newton's method with the Jacobian in closed
form: lengthening arc i moves the state at its end by the flow f(s, u_i) there, and the free
response carries that on (the inputs after it are only shifted in time), so
∂s_k/∂τ_i = Φ(t_k − t_{i+1}) f(s_{i+1}, u_i).

Where the roots come from:

* **warm** (``replan``): a plan being followed, from the state the loop estimates now. Its
  remaining arcs are the guess; a disturbance or a model update moves the root a little and
  Newton follows it in a few steps. Arcs that shrink to nothing are dropped and the rest solved
  again.
* **cold** (``plan_arcs``): the grid planner (``time_optimal``, HiGHS on a coarse grid) gives the
  structure and a guess, which Newton makes exact; where the coarse shape has no root, the
  same on a finer grid, but never finer than ``_FINEST_COLD_STEP_S`` (the LPs of a long path
  on a fine grid are slow, and the step search may fall back to the whole
  problem). A grid may blur the structure (a short hold rounded into a bang, a coast for a
  hold, a short arc for a neighbour's partial step), so where the finest grid's own shape
  has no root either, the structures next to it are tried from its switch times, and the
  shortest valid root no longer than that grid's plan wins. The LPs are bounded per grid,
  so a cold plan ends, found or refused (PlanningError), in bounded time.

Every root is checked before it is believed: durations ≥ 0, and |θ| ≤ θm on every arc in closed
form (θ̇ is monotone over a held input, so θ has at most one extremum an arc).

All the arithmetic is on Python floats and 4×n Jacobians (n ≤ 12): a Newton step costs tens of
microseconds, where numpy's per-call overhead would dominate.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from ballbeam.core.model import LinearModel
from ballbeam.core.planning.lag_hold import _Params, _params, _propagate
from ballbeam.core.planning.plan import PlanSamples
from ballbeam.errors import PlanningError

__all__ = ["ArcPlan", "arcs_from_grid", "plan_arcs", "replan", "solve_arcs"]

State = tuple[float, float, float, float]
# A structure and its durations: (signs, holds, durations), as ``solve_arcs`` takes them.
Guess = tuple[list[int], list[int], list[float]]

# Newton's stopping test, on residuals scaled to the problem's own units (θm, U/β, ...).
_TOLERANCE = 1e-11
_MAX_ITERATIONS = 15
# A cold guess comes from a grid, further from the root than a warm one (a long hold's
# entry blurred over several steps): Newton gets more steps there.
_COLD_ITERATIONS = 60
# An arc this short (s) after convergence is dropped and the rest solved again.
_NEGLIGIBLE_S = 1e-9
# Angle overshoot accepted from rounding (relative to θm).
_THETA_SLACK = 1e-9
# Duration guessed for an arc a re-plan puts in (Newton sizes it).
_SEED_S = 1e-3
# The cold path's grids: the given coarse step, then this one (not finer: the LPs of a long
# path grow with the step count and the search may fall back to the whole problem).
_FINEST_COLD_STEP_S = 2e-3
# LP solves a cold plan may spend on each grid (HiGHS; the step search, see time_optimal).
_COLD_LP_SOLVES_PER_GRID = 24
# An arc at most this many grid steps long may be an artefact of the grid: tried without it.
_SHORT_ARC_STEPS = 2.0
# A grid's coast this close to the limit (fraction of its largest angle) may stand for a hold.
_COAST_HOLD_FRACTION = 0.97
# A servo that turns back within this fraction of θm may belong on the limit for a while.
_NEAR_LIMIT = 0.8


@dataclass(frozen=True)
class Arc:
    """One arc: ``input_v`` held for ``duration_s``; ``hold`` is +1/−1 for a hold on the
    ±θm limit (input 0), 0 for a full-voltage arc."""

    input_v: float
    duration_s: float
    hold: int = 0


def _flow(p: _Params, s: State, u: float) -> State:
    """ds/dt at ``s`` under ``u``."""
    return (s[1], -p.pole_per_s * s[1] + p.alpha * u, p.gamma * s[0], s[2])


def _step(p: _Params, s: State, u: float, tau: float) -> State:
    """Exact state after holding ``u`` for ``tau`` from ``s`` (``lag_hold._propagate`` on
    floats)."""
    a = p.pole_per_s
    theta, rate, speed, pos = s
    e = math.exp(-a * tau)
    phi1 = -math.expm1(-a * tau) / a
    phi2 = (tau - phi1) / a
    phi3 = (0.5 * tau * tau - phi2) / a
    w = u * p.alpha / a
    d = rate - w
    g = p.gamma
    return (
        theta + w * tau + d * phi1,
        w + d * e,
        speed + g * (theta * tau + 0.5 * w * tau * tau + d * phi2),
        pos + speed * tau + g * (0.5 * theta * tau * tau + w * tau**3 / 6.0 + d * phi3),
    )


def _free(p: _Params, v: State, tau: float) -> State:
    """Φ(τ)·v: the free response (no input) carries a perturbation."""
    return _step(p, v, 0.0, tau)


def _theta_extreme(p: _Params, s: State, u: float, tau: float) -> float:
    """Largest |θ| over an arc (θ̇ monotone: at its ends, or where θ̇ crosses 0)."""
    biggest = abs(s[0])
    w = u * p.alpha / p.pole_per_s
    rate = s[1]
    if rate != 0.0 and w != 0.0 and (rate > 0.0) != (w > 0.0):
        t_turn = math.log((rate - w) / -w) / p.pole_per_s
        if 0.0 < t_turn < tau:
            biggest = max(biggest, abs(_step(p, s, u, t_turn)[0]))
    return max(biggest, abs(_step(p, s, u, tau)[0]))


@dataclass(frozen=True)
class _Problem:
    p: _Params
    start: State  # relative to the target: rest is the origin
    voltage_v: float  # U
    theta_max_rad: float
    # residual units: θm, the full-voltage rate, and the ball's speed and travel over the
    # servo's time constant at full angle
    scales: State = field(init=False)

    def __post_init__(self) -> None:
        t = 1.0 / self.p.pole_per_s
        accel = abs(self.p.gamma) * self.theta_max_rad
        rate = self.voltage_v * self.p.alpha / self.p.pole_per_s
        object.__setattr__(self, "scales", (self.theta_max_rad, rate, accel * t, accel * t * t))


def _inputs(problem: _Problem, signs: Sequence[int], holds: Sequence[int]) -> list[float]:
    return [0.0 if h else s * problem.voltage_v for s, h in zip(signs, holds, strict=True)]


def _residuals(
    problem: _Problem, inputs: Sequence[float], holds: Sequence[int], taus: Sequence[float]
) -> tuple[list[float], list[State]]:
    """Scaled residuals (m,) and the states at the arc boundaries."""
    sc = problem.scales
    states: list[State] = [problem.start]
    for u, tau in zip(inputs, taus, strict=True):
        states.append(_step(problem.p, states[-1], u, tau))
    rows: list[float] = []
    for k, hold in enumerate(holds):
        if hold:
            s = states[k]
            rows += [(s[0] - hold * problem.theta_max_rad) / sc[0], s[1] / sc[1]]
    end = states[-1]
    rows += [end[j] / sc[j] for j in range(4)]
    return rows, states


def _jacobian(
    problem: _Problem,
    inputs: Sequence[float],
    holds: Sequence[int],
    taus: Sequence[float],
    states: Sequence[State],
) -> np.ndarray:
    """The residuals' Jacobian (m, n) in the durations, at the arc boundaries ``states``
    (a perturbation of arc i's end carried to each condition by the free response)."""
    p = problem.p
    sc = problem.scales
    n = len(taus)
    # arc boundary times: t_k = Σ_{j<k} τ_j
    times = [0.0]
    for tau in taus:
        times.append(times[-1] + tau)
    flows = [_flow(p, states[i + 1], inputs[i]) for i in range(n)]
    jac: list[list[float]] = []
    for k, hold in enumerate(holds):
        if not hold:
            continue
        r0 = [0.0] * n
        r1 = [0.0] * n
        for i in range(k):
            d = _free(p, flows[i], times[k] - times[i + 1])
            r0[i], r1[i] = d[0] / sc[0], d[1] / sc[1]
        jac += [r0, r1]
    cols = [_free(p, flows[i], times[n] - times[i + 1]) for i in range(n)]
    for j in range(4):
        jac.append([cols[i][j] / sc[j] for i in range(n)])
    return np.array(jac)


@dataclass(frozen=True)
class _Root:
    taus: list[float]
    states: list[State]
    converged: bool


def _newton(
    problem: _Problem,
    inputs: Sequence[float],
    holds: Sequence[int],
    taus: Sequence[float],
    max_iterations: int = _MAX_ITERATIONS,
) -> _Root:
    """Durations ≥ 0 that zero the residuals: Levenberg-Marquardt (Gauss-Newton steps, damped
    where the guess is far: arcs put in by a re-plan start far from their size, and undamped
    steps from there overshoot into negative durations where exp(−aτ) explodes), projected
    onto τ ≥ 0."""
    x = np.maximum(np.array(taus, dtype=float), 0.0)
    r_list, states = _residuals(problem, inputs, holds, x.tolist())
    r = np.array(r_list)
    cost = float(r @ r)
    damping = 1e-6
    for _ in range(max_iterations):
        if max(abs(v) for v in r_list) < _TOLERANCE:
            return _Root(x.tolist(), states, True)
        # the Jacobian where a step is taken from only: most trials of a failing root are
        # rejected, and judged on their residuals alone
        J = _jacobian(problem, inputs, holds, x.tolist(), states)
        H = J.T @ J
        g = J.T @ r
        scale = np.diag(H) + 1e-12
        for _ in range(12):
            try:
                step = np.linalg.solve(H + damping * np.diag(scale), -g)
            except np.linalg.LinAlgError:
                damping *= 10.0
                continue
            trial = np.maximum(x + step, 0.0)
            r_t_list, states_t = _residuals(problem, inputs, holds, trial.tolist())
            r_t = np.array(r_t_list)
            cost_t = float(r_t @ r_t)
            if cost_t < cost:
                damping = max(damping / 10.0, 1e-12)
                break
            damping *= 10.0
        else:
            return _Root(x.tolist(), states, False)
        x, r_list, r, states, cost = trial, r_t_list, r_t, states_t, cost_t
    return _Root(x.tolist(), states, max(abs(v) for v in r_list) < _TOLERANCE)


def _within_limit(problem: _Problem, inputs: Sequence[float], root: _Root) -> bool:
    bound = problem.theta_max_rad * (1.0 + _THETA_SLACK)
    return all(
        _theta_extreme(problem.p, s, u, tau) <= bound
        for s, u, tau in zip(root.states, inputs, root.taus, strict=False)
    )


def _merge(signs: list[int], holds: list[int], taus: list[float]) -> None:
    """Join neighbouring full-voltage arcs of one sign (in place)."""
    i = 0
    while i + 1 < len(signs):
        if not holds[i] and not holds[i + 1] and signs[i] == signs[i + 1]:
            taus[i] += taus.pop(i + 1)
            signs.pop(i + 1)
            holds.pop(i + 1)
        else:
            i += 1


def solve_arcs(
    problem: _Problem,
    signs: Sequence[int],
    holds: Sequence[int],
    taus: Sequence[float],
    max_iterations: int = _MAX_ITERATIONS,
) -> tuple[list[int], list[int], list[float]] | None:
    """The root of a structure from a guess, arcs that vanish dropped: (signs, holds,
    durations), or None when no valid root is found from this guess within
    ``max_iterations`` Newton steps (each time arcs are dropped)."""
    s, h, t = list(signs), list(holds), list(taus)
    for _ in range(len(s) + 1):
        _merge(s, h, t)
        inputs = _inputs(problem, s, h)
        root = _newton(problem, inputs, h, t, max_iterations)
        if not root.converged:
            return None
        t = root.taus
        gone = [i for i, tau in enumerate(t) if tau <= _NEGLIGIBLE_S]
        if not gone:
            return (s, h, t) if _within_limit(problem, inputs, root) else None
        for i in reversed(gone):
            del s[i], h[i], t[i]
        if not s:
            return None
    return None


@dataclass(frozen=True)
class ArcPlan:
    """A minimum-time path as arcs: ``input_v[i]`` held for ``duration_s_each[i]``.

    States are relative to the target: the plan starts at ``start`` (θ, θ̇, ẋ, x − target) and
    rests at the origin from ``duration_s`` on (u = 0). Shaped like the other plans
    (``duration_s``, ``sample``), and exact between any two times.
    """

    input_v: tuple[float, ...]
    duration_s_each: tuple[float, ...]
    holds: tuple[int, ...]
    start: State
    target_m: float
    voltage_limit_v: float
    theta_max_rad: float
    pole_per_s: float
    alpha: float
    gamma: float
    kind: str = field(default="arcs", init=False)

    @property
    def duration_s(self) -> float:
        return math.fsum(self.duration_s_each)

    @property
    def params(self) -> _Params:
        return _Params(self.pole_per_s, self.alpha, self.gamma)

    @property
    def switch_times_s(self) -> np.ndarray:
        """Arc boundaries (n + 1,): 0, the switches, ``duration_s``."""
        return np.concatenate([[0.0], np.cumsum(self.duration_s_each)])

    def sample(self, time_s: np.ndarray) -> PlanSamples:
        """Exact desired states (n, 4) and inputs (n,) at the times (n,); before 0 the start,
        after the end the origin."""
        t = np.atleast_1d(np.asarray(time_s, dtype=float))
        edges = self.switch_times_s
        bounds = np.array(
            [self.start]
            + [
                _replay(
                    self.params, self.start, self.input_v[: i + 1], self.duration_s_each[: i + 1]
                )
                for i in range(len(self.input_v))
            ]
        )
        k = np.searchsorted(edges, t, side="right") - 1
        inside = (k >= 0) & (k < len(self.input_v))
        states = np.zeros((t.size, 4))
        input_v = np.zeros(t.size)
        states[k < 0] = self.start
        if np.any(inside):
            ki = k[inside]
            u = np.asarray(self.input_v)[ki]
            states[inside] = _propagate(self.params, bounds[ki], u, t[inside] - edges[ki])
            input_v[inside] = u
        return PlanSamples(time_s=t, states=states, input_v=input_v)

    def remaining(self, elapsed_s: float) -> tuple[list[float], list[int], list[float]]:
        """The arcs left after ``elapsed_s``: (inputs, holds, durations)."""
        inputs, holds, taus = [], [], []
        t0 = 0.0
        for u, tau, hold in zip(self.input_v, self.duration_s_each, self.holds, strict=True):
            left = min(tau, t0 + tau - elapsed_s)
            t0 += tau
            if left > 0.0:
                inputs.append(u)
                holds.append(hold)
                taus.append(left)
        return inputs, holds, taus

    def shifted(self, elapsed_s: float) -> tuple[list[int], list[int], list[float]]:
        """The arcs left after ``elapsed_s`` as a guess for a re-plan: (signs, holds,
        durations)."""
        inputs, holds, taus = self.remaining(elapsed_s)
        return [int(math.copysign(1.0, u)) if u else 0 for u in inputs], holds, taus


def _replay(p: _Params, s: State, inputs: Sequence[float], taus: Sequence[float]) -> State:
    for u, tau in zip(inputs, taus, strict=True):
        s = _step(p, s, u, tau)
    return s


def _make(
    problem: _Problem, target_m: float, solved: tuple[list[int], list[int], list[float]]
) -> ArcPlan:
    signs, holds, taus = solved
    p = problem.p
    return ArcPlan(
        input_v=tuple(_inputs(problem, signs, holds)),
        duration_s_each=tuple(taus),
        holds=tuple(holds),
        start=problem.start,
        target_m=target_m,
        voltage_limit_v=problem.voltage_v,
        theta_max_rad=problem.theta_max_rad,
        pole_per_s=p.pole_per_s,
        alpha=p.alpha,
        gamma=p.gamma,
    )


def _problem(
    p: _Params,
    state: np.ndarray | Sequence[float],
    target_m: float,
    voltage_v: float,
    theta_max_rad: float,
) -> _Problem:
    theta, rate, speed, pos = (float(v) for v in state)
    if not all(math.isfinite(v) for v in (theta, rate, speed, pos, target_m)):
        raise PlanningError(f"the state and target must be finite, got {state}, {target_m}")
    return _Problem(p, (theta, rate, speed, pos - target_m), voltage_v, theta_max_rad)


def arcs_from_grid(
    input_v: np.ndarray,
    grid_states: np.ndarray,
    step_s: float,
    voltage_v: float,
    theta_max_rad: float,
    coast_hold_fraction: float | None = None,
) -> tuple[list[int], list[int], list[float]]:
    """A structure and guess from a grid plan: steps pinned on the angle limit (with their
    successor) become holds; the others full-voltage arcs as long as their impulse ∫|u| dt / U,
    so a grid's partial steps and coasts (slack within one step) become the nearest bang.
    With ``coast_hold_fraction``, steps of zero input whose samples both lie beyond that
    fraction of the limit, on one side, become holds too: a grid may coast up to the limit
    where the continuous path brakes onto it and holds."""
    theta = grid_states[:, 0]
    # a grid keeps its samples inside θm by its intersample margin: pinned is at its own bound
    # (samples after the start: the start itself may lie beyond that bound)
    pinned = np.abs(theta) >= np.max(np.abs(theta[1:]), initial=0.0) * (1.0 - 1e-6)
    pinned[0] = False
    signs: list[int] = []
    holds: list[int] = []
    taus: list[float] = []
    if coast_hold_fraction is not None:
        near = np.abs(theta) >= coast_hold_fraction * np.max(np.abs(theta[1:]), initial=0.0)
        coast = np.abs(np.asarray(input_v, dtype=float)) <= 1e-9 * voltage_v
        pinned[:-1] |= coast & near[:-1] & near[1:]
        pinned[1:] |= coast & near[:-1] & near[1:]
        pinned[0] = False
    for k, u in enumerate(np.asarray(input_v, dtype=float)):
        if pinned[k] and pinned[k + 1] and np.sign(theta[k]) == np.sign(theta[k + 1]):
            kind, sign, tau = int(np.sign(theta[k])), 0, step_s
        elif abs(u) > 1e-9 * voltage_v:
            kind, sign, tau = 0, int(np.sign(u)), step_s * abs(u) / voltage_v
        else:
            continue
        if taus and holds[-1] == kind and (kind or signs[-1] == sign):
            taus[-1] += tau
        else:
            signs.append(sign)
            holds.append(kind)
            taus.append(tau)
    return _brake_around_holds(signs, holds, taus, step_s)


def _brake_around_holds(
    signs: list[int], holds: list[int], taus: list[float], brake_s: float
) -> tuple[list[int], list[int], list[float]]:
    """A hold on +θm is entered and left by braking at −U (mirrored on −θm): a coarse grid
    coasts onto the limit instead, so such arcs are put in where missing (Newton sizes them)."""
    out_s: list[int] = []
    out_h: list[int] = []
    out_t: list[float] = []
    for i, (sign, hold, tau) in enumerate(zip(signs, holds, taus, strict=True)):
        if hold and out_s and (out_h[-1] or out_s[-1] != -hold):
            out_s.append(-hold)
            out_h.append(0)
            out_t.append(brake_s)
        out_s.append(sign)
        out_h.append(hold)
        out_t.append(tau)
        after = i + 1 < len(signs) and (holds[i + 1] or signs[i + 1] != -hold)
        if hold and after:
            out_s.append(-hold)
            out_h.append(0)
            out_t.append(brake_s)
    return out_s, out_h, out_t


def plan_arcs(
    model: LinearModel,
    state: np.ndarray | Sequence[float],
    *,
    target_m: float = 0.0,
    voltage_limit_v: float = 5.0,
    theta_max_rad: float = math.radians(52.0),
    grid_step_s: float = 0.01,
    max_duration_s: float = 20.0,
) -> ArcPlan:
    """The minimum-time path from ``state`` (θ, θ̇, ẋ, x) to rest at ``target_m`` (cold start):
    the grid planner's shape on a ``grid_step_s`` grid (then on ``_FINEST_COLD_STEP_S``'s; a
    finer ``grid_step_s`` is taken as that), made exact by Newton, or the nearest structure
    that can be. Raises PlanningError where
    the grid planner finds no path within its LP bound or no structure near its shape has a
    valid root no longer than the grid plan."""
    from ballbeam.core.planning.time_optimal import plan_time_optimal

    p = _params(model)
    problem = _problem(p, state, target_m, voltage_limit_v, theta_max_rad)
    if not any(problem.start):
        return _make(problem, target_m, ([], [], []))
    coarse_s = max(grid_step_s, _FINEST_COLD_STEP_S)
    steps_s = (coarse_s, _FINEST_COLD_STEP_S) if coarse_s > _FINEST_COLD_STEP_S else (coarse_s,)
    shapes: list[Guess] = []
    for step_s in steps_s:
        try:
            grid = plan_time_optimal(
                model,
                np.array(problem.start),
                voltage_limit_v=voltage_limit_v,
                theta_max_rad=theta_max_rad,
                step_s=step_s,
                max_duration_s=max_duration_s,
                max_lp_solves=_COLD_LP_SOLVES_PER_GRID,
            )
        except PlanningError:
            if not shapes:
                raise
            break  # the finer grid's search ran out of LPs: the coarser shape must do
        guess = arcs_from_grid(
            grid.input_v, grid.grid_states, grid.step_s, voltage_limit_v, theta_max_rad
        )
        longest_s = grid.duration_s + 1e-9
        found = _valid_roots(problem, [guess], longest_s)
        if found:
            return _make(problem, target_m, found[0])
        coasts = arcs_from_grid(
            grid.input_v,
            grid.grid_states,
            grid.step_s,
            voltage_limit_v,
            theta_max_rad,
            coast_hold_fraction=_COAST_HOLD_FRACTION,
        )
        # the same shape, its holds entered as the continuous path enters them
        shapes = _unique([_braked(problem, guess), _braked(problem, coasts)])
        shape_step_s = step_s
        found = _valid_roots(problem, shapes, longest_s)
        if found:
            return _make(problem, target_m, min(found, key=lambda r: math.fsum(r[2])))
    # the finest grid's shape has no root: the structures next to it, from its switch times
    guesses = [
        _braked(problem, g)
        for shape in shapes
        for g in _alternatives(problem, *shape, shape_step_s)
    ]
    found = _valid_roots(problem, _unique(guesses), longest_s)
    if found:
        return _make(problem, target_m, min(found, key=lambda r: math.fsum(r[2])))
    raise PlanningError(
        f"no exact minimum-time arcs near the grid plans from {problem.start} (θ, θ̇, ẋ, x − target)"
    )


def _unique(guesses: list[Guess]) -> list[Guess]:
    return list({(tuple(g[0]), tuple(g[1]), tuple(g[2])): g for g in guesses}.values())


def _valid_roots(problem: _Problem, guesses: list[Guess], longest_s: float) -> list[Guess]:
    """The valid roots from the guesses that are no longer than ``longest_s`` and have no
    more arcs than conditions (4 for rest, 2 a hold): with more, the roots form a family and
    Newton stops on any member of it, not on the shortest."""
    return [
        r
        for g in guesses
        if (r := solve_arcs(problem, *g, _COLD_ITERATIONS)) is not None
        and math.fsum(r[2]) <= longest_s
        and len(r[0]) <= 4 + 2 * sum(1 for h in r[1] if h)
    ]


def _braked(problem: _Problem, guess: Guess) -> Guess:
    """The guess with each arc that brakes onto a hold at least as long as braking from the
    full-voltage slope to rest takes (ln 2 / a): a grid coasts onto the limit over several
    steps, and counts only the steps it drives."""
    signs, holds, taus = guess
    brake_s = math.log(2.0) / problem.p.pole_per_s
    out = list(taus)
    for i in range(1, len(signs)):
        if holds[i] and not holds[i - 1] and signs[i - 1] == -holds[i]:
            out[i - 1] = max(out[i - 1], brake_s)
    return list(signs), list(holds), out


def _alternatives(
    problem: _Problem, signs: list[int], holds: list[int], taus: list[float], step_s: float
) -> list[Guess]:
    """Structures next to a grid plan's, seeded from its switch times, for when its own has no
    root: each short arc left out (a grid's partial step where the continuous path has no
    arc), each hold left out (a grid pinned on the limit where the path only touches it),
    holds put in where the servo turns back near the limit (a grid that rounded a short hold
    into the bang: one at a time and all at once), and to each of these, arcs added in front
    or at the end (``_repairs``)."""
    out: list[Guess] = []
    n = len(signs)
    for i in range(n):
        if holds[i] or taus[i] <= _SHORT_ARC_STEPS * step_s:
            out.append(
                (signs[:i] + signs[i + 1 :], holds[:i] + holds[i + 1 :], taus[:i] + taus[i + 1 :])
            )
    turns = _turns_near_limit(problem, signs, holds, taus)
    with_holds = [_hold_at(signs, holds, taus, [turn], step_s) for turn in turns]
    if len(turns) > 1:
        with_holds.append(_hold_at(signs, holds, taus, turns, step_s))
    for guess in with_holds:
        out += [guess, *_repairs(*guess)]
    out += _repairs(signs, holds, taus)
    return [g for g in out if g[0]]


def _turns_near_limit(
    problem: _Problem, signs: list[int], holds: list[int], taus: list[float]
) -> list[tuple[int, float]]:
    """Where, inside a full-voltage arc that follows one of the other sign, the servo turns
    back (θ̇ = 0) within ``_NEAR_LIMIT`` of the limit on the first arc's side: (arc, time into
    it)."""
    p = problem.p
    inputs = _inputs(problem, signs, holds)
    found: list[tuple[int, float]] = []
    s = problem.start
    for i, (u, tau) in enumerate(zip(inputs, taus, strict=True)):
        sigma = -signs[i]
        previous_bang = i > 0 and not holds[i - 1] and signs[i - 1] == sigma
        rate = s[1]
        w = u * p.alpha / p.pole_per_s
        if not holds[i] and previous_bang and rate * sigma > 0.0 and w * sigma < 0.0:
            t_turn = math.log((rate - w) / -w) / p.pole_per_s
            theta = _step(p, s, u, t_turn)[0]
            if 0.0 < t_turn < tau and theta * sigma >= _NEAR_LIMIT * problem.theta_max_rad:
                found.append((i, t_turn))
        s = _step(p, s, u, tau)
    return found


def _hold_at(
    signs: list[int],
    holds: list[int],
    taus: list[float],
    turns: list[tuple[int, float]],
    step_s: float,
) -> Guess:
    """The guess with a hold put in at each turn (arc, time into it): the arc is split there,
    braking onto the limit before the hold and leaving it after."""
    at = dict(turns)
    out_s: list[int] = []
    out_h: list[int] = []
    out_t: list[float] = []
    for i, (sign, hold, tau) in enumerate(zip(signs, holds, taus, strict=True)):
        if i in at:
            t_turn = at[i]
            out_s += [sign, 0, sign]
            out_h += [0, -sign, 0]
            out_t += [t_turn, step_s, max(tau - t_turn, step_s)]
        else:
            out_s.append(sign)
            out_h.append(hold)
            out_t.append(tau)
    return out_s, out_h, out_t


def _alternating(first: int, count: int) -> list[int]:
    return [first * (-1) ** k for k in range(count)]


def _repairs(
    signs: list[int], holds: list[int], taus: list[float]
) -> list[tuple[list[int], list[int], list[float]]]:
    """Guesses for a re-plan from a perturbed state, after the remaining arcs themselves. A
    structure that can be optimal has as many arcs as conditions (4 for rest, 2 a hold), and a
    hold is entered at rest after two arcs (σ, then −σ braking); the remaining arcs of a plan
    may have fewer (a start inside a hold, or part-way through its braking arc, or the freedom
    of a finished hold gone). The missing arcs go in front or at the end, alternating."""
    n_holds = sum(1 for h in holds if h)
    first = next((i for i, h in enumerate(holds) if h), None)
    out: list[tuple[list[int], list[int], list[float]]] = []

    def add(front: list[int], back: list[int]) -> None:
        out.append(
            (
                [*front, *signs, *back],
                [0] * len(front) + holds + [0] * len(back),
                [_SEED_S] * len(front) + taus + [_SEED_S] * len(back),
            )
        )

    if first is not None and first < 2:
        sigma = holds[first]
        add([sigma, -sigma][first:], [])
        add([-sigma, sigma, -sigma][first:], [])
    missing = 4 + 2 * n_holds - len(signs)
    if missing > 0 and signs:
        lead = signs[0] or -holds[0]
        tail = signs[-1] or -holds[-1]
        add(_alternating(-lead, missing)[::-1], [])
        add([], _alternating(-tail, missing))
        if missing > 1:
            add(_alternating(-lead, missing - 1)[::-1], [-tail])
    return out


def replan(
    plan: ArcPlan,
    elapsed_s: float,
    state: np.ndarray | Sequence[float],
    *,
    target_m: float | None = None,
    params: _Params | None = None,
    repairs: bool = True,
) -> ArcPlan | None:
    """The minimum-time path from ``state`` at ``elapsed_s`` into ``plan``, warm-started from
    the plan's remaining arcs (optionally to a new target or with a new model). None when
    Newton finds no valid root from those guesses (the caller keeps its plan or plans cold).
    ``repairs``: where the remaining arcs have no root, try the structures with arcs added
    (``_repairs``); False for a caller that would not take a root with more arcs."""
    p = params or plan.params
    target = plan.target_m if target_m is None else target_m
    problem = _problem(p, state, target, plan.voltage_limit_v, plan.theta_max_rad)
    guess = plan.shifted(elapsed_s)
    if not guess[0]:
        guess = ([1, -1, 1, -1], [0, 0, 0, 0], [_SEED_S] * 4)
    solved = solve_arcs(problem, *guess)
    if solved is None:
        if not repairs:
            return None
        found = [r for g in _repairs(*guess) if (r := solve_arcs(problem, *g)) is not None]
        if not found:
            return None
        solved = min(found, key=lambda r: math.fsum(r[2]))
    return _make(problem, target, solved)
