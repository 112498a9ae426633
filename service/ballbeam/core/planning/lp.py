"""The linear programmes of the time-optimal planner, and HiGHS (docs/design.md §2–3).

"Rest at the origin after n steps" is a linear programme. Its variables are the free inputs
and, after each free step, the motor's deviation from the trajectory of the fixed inputs
(sparse rows, angle limits as variable bounds); the terminal rows are condensed over the free
inputs, and every answer is re-simulated exactly before it is believed (``_solve_steps``).
The LP minimises the terminal miss rather than demanding it be zero: an infeasible n then
still gives a number (the miss, smooth and convex in n) and a shape (the closest approach,
which has no slack to spend and so shows the true time-optimal arcs: bang at ±U, holds at
±θmax). A tie-break on the inputs' L1 norm makes holds u = 0 rather than the chatter an
arbitrary LP vertex would show. ``_Grid`` is one discretisation as the LPs see it: its
step, its limits and the impulse response.

Each LP is solved by HiGHS through its public Python package ``highspy`` with linprog's model
and options (``_solve_lp``, ``_highs_solve``; the tests check that linprog gives the same
plan).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import highspy
import numpy as np
import scipy.sparse

from ballbeam.core.planning.lag_hold import (
    _first_step_interval,
    _Params,
    _phis,
    _propagate,
    _simulate,
)

# Angle kept back in the LPs besides δ, so that solver tolerance cannot break the sample bound.
_SOLVER_MARGIN_RAD = 1e-7
# Terminal miss (L1 over rows scaled to one step's largest effect) that still counts as rest.
_MISS_TOL = 1e-8
# Weight of the inputs' L1 norm next to the miss: breaks ties (clean holds) without trading
# miss for it (a unit of input moves a scaled terminal row by far more than this).
_TIE_WEIGHT = 1e-6
_HIGHS_OPTIONS = {"primal_feasibility_tolerance": 1e-9, "dual_feasibility_tolerance": 1e-9}


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
