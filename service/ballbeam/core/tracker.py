"""Time-varying linear-quadratic tracker (paper, sections 3–4), continuous and sampled-data.

Cost, with ``u_ref = u_d`` (``input_reference="feedforward"``) or ``u_ref = 0`` (``"zero"``,
the paper's ``uᵀRu``)::

    J = ∫₀ᵀ (x − x_d)ᵀQ(x − x_d) + (u − u_ref)ᵀR(u − u_ref) dt + e(T)ᵀ S_T e(T),  e = x − x_d

with ``S_T`` the stationary Riccati solution (``terminal="stationary"``: the tracker hands over
smoothly to the constant LQR used after the horizon) or 0 (``"zero"``: the paper's ``S(T) = 0``,
whose gains collapse near ``T``).

Continuous solution. Writing the value function as ``V(t, x) = xᵀS x − 2vᵀx + c`` and minimising
the Hamiltonian over ``u = u_ref + w`` gives ``w = −R⁻¹Bᵀ(S x − v)``, i.e.::

    u  = u_ref − K x + R⁻¹Bᵀ v,            K = R⁻¹BᵀS
    −Ṡ = AᵀS + S A − S B R⁻¹BᵀS + Q,        S(T) = S_T
    −v̇ = (A − B K)ᵀ v + Q x_d − S B u_ref,  v(T) = S_T x_d(T)

(the ``x``-linear terms of the HJB equation give the ``v`` equation; ``u_ref`` enters through
``2(S x − v)ᵀB u_ref``). With ``u_ref = 0`` and ``S_T = 0`` these are exactly the paper's (5)–(7).
For a reference that obeys the model, ``ẋ_d = A x_d + B u_d``, and ``u_ref = u_d``, the solution
is ``v = S x_d``, so ``u = u_d − K (x − x_d)``.

Sampled-data solution (what the controller runs at period ``h``, input held over each period).
The plant is discretised exactly (zero-order hold) and so is the cost: between samples the
state is ``x(kh + τ) = e^{Aτ} x_k + Γ(τ) u_k`` and the reference is taken as the plan's own
held-input motion ``x_d(kh + τ) ≈ e^{Aτ} r_k + Γ(τ) ū_k`` (exact for a plan that is itself
zero-order-hold consistent, second order in ``h`` otherwise), ``r_k = x_d(kh)``,
``ū_k = u_d(kh)``. The integral of the stage cost over one period is then the quadratic form
of ``(x_k − r_k, u_k − ū_k)`` with the Van Loan matrices

    [[Qd, Nd], [Ndᵀ, Rd − R h]] = ∫₀ʰ [e^{Aτ} Γ(τ)]ᵀ Q [e^{Aτ} Γ(τ)] dτ,

read off ``expm([[−Fᵀ, diag(Q, 0)], [0, F]] h)`` with ``F = [[A, B], [0, 0]]`` (Van Loan, 1978),
plus the input term ``(u_k − u_ref,k)ᵀ R h (u_k − u_ref,k)``. With ``V_k(x) = xᵀS_k x − 2v_kᵀx``
and stage linear terms ``a_k = Qd r_k + Nd ū_k``, ``b_k = Ndᵀ r_k + (Rd − R h) ū_k + R h u_ref,k``
the backward recursion is

    G_k = Rd + BdᵀS_{k+1}Bd,        K_k = G_k⁻¹ (BdᵀS_{k+1}Ad + Ndᵀ)
    S_k = Qd + AdᵀS_{k+1}Ad − K_kᵀ G_k K_k
    v_k = a_k − K_kᵀ b_k + (Ad − Bd K_k)ᵀ v_{k+1},   offset_k = G_k⁻¹ (b_k + Bdᵀv_{k+1})
    u_k = −K_k x_k + offset_k,      S_N = S_T, v_N = S_T r_N.

It is evaluated without a Python loop over the horizon (8000 steps at 1 kHz must synthesise in
milliseconds): with ``S_T = P`` (the DARE solution) ``S_k = P`` for all k and the ``v``
recursion is linear time-invariant, solved by a Schur decomposition and first-order filters;
with ``S_T = 0`` the deviation from the stationary problem has a closed form (see
:func:`_finite_horizon_deviation`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
import scipy.linalg

from ballbeam.core.model import LinearModel, zoh_generator
from ballbeam.core.planning.plan import Plan, PlanSamples
from ballbeam.core.recursion import first_order_response
from ballbeam.errors import ConfigError

Terminal = Literal["stationary", "zero"]
InputReference = Literal["feedforward", "zero"]

_POWER_BLOCK = 64  # Φ^j is built as Φ^(64 i) Φ^r: two short loops and one batched product


@dataclass(frozen=True)
class SampledCost:
    """The continuous cost integrated exactly over one held-input period ``h`` (Van Loan).

    Per period the cost is ``[δx; δu]ᵀ [[Qd, Nd], [Ndᵀ, Rd − Rh]] [δx; δu] + (u − u_ref)ᵀ Rh
    (u − u_ref)`` with ``δx = x_k − r_k``, ``δu = u_k − ū_k``. Qd (4, 4), Nd (4, 1),
    Rd (1, 1) (state part plus ``Rh``), Rh (1, 1) = R·h. Ad (4, 4), Bd (4, 1): the plant over
    the same period, read from the same exponential (``model.discretize`` to rounding).
    """

    Qd: np.ndarray
    Nd: np.ndarray
    Rd: np.ndarray
    Rh: np.ndarray
    Ad: np.ndarray
    Bd: np.ndarray


@dataclass(frozen=True)
class ContinuousTracker:
    """The continuous solution on a time grid: u(t) = −K(t) x + offset_v(t).

    time_s (N,), S (N, 4, 4), v (N, 4), K (N, 1, 4), u_ref (N,), offset_v (N,) = u_ref + R⁻¹Bᵀv.
    """

    time_s: np.ndarray
    S: np.ndarray
    v: np.ndarray
    K: np.ndarray
    u_ref: np.ndarray
    offset_v: np.ndarray


@dataclass(frozen=True)
class DiscreteTracker:
    """Gain schedule for the sampled-data tracker: ``u_k = −K[k] x_k + offset_v[k]`` for
    ``k < N``, then ``u = −K_final x`` (the stationary LQR, regulating to the origin).

    K (N, 1, 4), offset_v (N,), K_final (1, 4); S (N + 1, 4, 4) and v (N + 1, 4) are the value
    function ``V_k(x) = xᵀS_k x − 2v_kᵀx`` (k = N is the terminal weight).
    """

    period_s: float
    K: np.ndarray
    offset_v: np.ndarray
    K_final: np.ndarray
    S: np.ndarray
    v: np.ndarray

    @property
    def n_steps(self) -> int:
        return int(self.offset_v.shape[0])


def sampled_cost(model: LinearModel, Q: np.ndarray, R: np.ndarray, period_s: float) -> SampledCost:
    """Van Loan's exact integral of the stage cost over one zero-order-hold period."""
    if not period_s > 0.0:
        raise ConfigError(f"sampling period must be positive, got {period_s} s")
    n, m = model.B.shape
    F = zoh_generator(model.A, model.B)
    block = np.zeros((2 * (n + m), 2 * (n + m)))
    block[: n + m, : n + m] = -F.T
    block[:n, n + m : 2 * n + m] = Q
    block[n + m :, n + m :] = F
    transition = scipy.linalg.expm(block * period_s)
    # expm = [[e^{−Fᵀh}, e^{−Fᵀh}·W], [0, e^{Fh}]] with W the wanted integral.
    plant = transition[n + m :, n + m :]  # e^{Fh} = [[Ad, Bd], [0, I]]
    W = plant.T @ transition[: n + m, n + m :]
    W = 0.5 * (W + W.T)
    Rh = np.atleast_2d(np.asarray(R, dtype=float)) * period_s
    return SampledCost(
        Qd=W[:n, :n],
        Nd=W[:n, n:],
        Rd=W[n:, n:] + Rh,
        Rh=Rh,
        Ad=plant[:n, :n].copy(),
        Bd=plant[:n, n:].copy(),
    )


def _check_weights(Q: np.ndarray, R: np.ndarray, n: int, m: int) -> tuple[np.ndarray, np.ndarray]:
    Q = np.asarray(Q, dtype=float)
    R = np.atleast_2d(np.asarray(R, dtype=float))
    if Q.shape != (n, n) or R.shape != (m, m):
        raise ConfigError(f"Q must be ({n}, {n}) and R ({m}, {m}), got {Q.shape} and {R.shape}")
    if not np.allclose(Q, Q.T) or np.linalg.eigvalsh(Q).min() < -1e-12 * max(1.0, abs(Q).max()):
        raise ConfigError("Q must be symmetric positive semi-definite")
    if not np.allclose(R, R.T) or np.linalg.eigvalsh(R).min() <= 0.0:
        raise ConfigError("R must be symmetric positive definite")
    return Q, R


def _check_choices(terminal: str, input_reference: str) -> None:
    if terminal not in ("stationary", "zero"):
        raise ConfigError(f"terminal must be 'stationary' or 'zero', got {terminal!r}")
    if input_reference not in ("feedforward", "zero"):
        raise ConfigError(
            f"input_reference must be 'feedforward' or 'zero', got {input_reference!r}"
        )


# ----------------------------------------------------------------------------------------------
# Continuous time (reference solution; the controller runs the sampled-data one)


def continuous_tracker(
    model: LinearModel,
    plan: Plan,
    *,
    Q: np.ndarray,
    R: np.ndarray,
    horizon_s: float,
    terminal: Terminal = "stationary",
    input_reference: InputReference = "feedforward",
    time_s: np.ndarray | None = None,
    rtol: float = 1e-10,
    atol: float = 1e-10,
) -> ContinuousTracker:
    """Integrate the Riccati and feedforward equations backward from ``horizon_s`` to 0.

    ``time_s`` (N,) in [0, horizon_s] is the output grid (default: every 1 ms). The plan is
    sampled wherever the integrator needs it.
    """
    n, m = model.B.shape
    Q, R = _check_weights(Q, R, n, m)
    _check_choices(terminal, input_reference)
    if m != 1:
        raise ConfigError(f"the tracker is written for a single-input model, got {m} inputs")
    if not horizon_s > 0.0:
        raise ConfigError(f"horizon must be positive, got {horizon_s} s")
    if time_s is None:
        time_s = np.linspace(0.0, horizon_s, max(2, round(horizon_s / 1e-3) + 1))
    time_s = np.array(time_s, dtype=float)  # a copy: it is frozen into the result
    if time_s.ndim != 1 or np.any(np.diff(time_s) <= 0) or time_s[0] < 0 or time_s[-1] > horizon_s:
        raise ConfigError("time_s must increase strictly within [0, horizon_s]")
    A, B = model.A, model.B
    R_inv_Bt = np.linalg.solve(R, B.T)  # (m, n)
    BR_inv_Bt = B @ R_inv_Bt
    use_feedforward = input_reference == "feedforward"

    def reference(t: float) -> tuple[np.ndarray, np.ndarray]:
        samples = plan.sample(np.array([t]))
        u_ref = samples.input_v[:1] if use_feedforward else np.zeros(m)
        return samples.states[0], u_ref

    x_T = reference(horizon_s)[0]
    if terminal == "stationary":
        S_T = scipy.linalg.solve_continuous_are(A, B, Q, R)
        S_T = 0.5 * (S_T + S_T.T)
        closed_T = (A - BR_inv_Bt @ S_T).T
        S_T_B = S_T @ B

        # S stays at the stationary solution: only v moves.
        def rhs(t: float, y: np.ndarray) -> np.ndarray:
            x_d, u_ref = reference(t)
            result: np.ndarray = -(closed_T @ y + Q @ x_d - S_T_B @ u_ref)
            return result

        y_T = S_T @ x_T
    else:
        S_T = np.zeros((n, n))

        def rhs(t: float, y: np.ndarray) -> np.ndarray:
            S = y[: n * n].reshape(n, n)
            S = 0.5 * (S + S.T)
            v = y[n * n :]
            x_d, u_ref = reference(t)
            SA = S @ A
            S_dot = -(SA + SA.T - S @ BR_inv_Bt @ S + Q)
            v_dot = -((A - BR_inv_Bt @ S).T @ v + Q @ x_d - S @ B @ u_ref)
            return np.concatenate([S_dot.ravel(), v_dot])

        y_T = np.concatenate([S_T.ravel(), S_T @ x_T])
    # Imported here: only this path integrates, and the import costs every process.
    from scipy.integrate import solve_ivp

    solution = solve_ivp(
        rhs,
        (horizon_s, float(time_s[0])),
        y_T,
        method="DOP853",
        t_eval=time_s[::-1],
        rtol=rtol,
        atol=atol,
    )
    if not solution.success:
        raise ConfigError(f"continuous Riccati integration failed: {solution.message}")
    y = solution.y[:, ::-1].T  # (N, len(y)) in increasing time
    N = time_s.shape[0]
    if terminal == "stationary":
        S_all = np.broadcast_to(S_T, (N, n, n)).copy()
        v_all = y
    else:
        S_all = y[:, : n * n].reshape(N, n, n)
        S_all = 0.5 * (S_all + S_all.transpose(0, 2, 1))
        v_all = y[:, n * n :]
    K_all = np.einsum("ij,kjl->kil", R_inv_Bt, S_all)
    samples = plan.sample(time_s)
    u_ref_all = samples.input_v.astype(float) if use_feedforward else np.zeros(N)
    offset = u_ref_all + v_all @ R_inv_Bt[0]
    return ContinuousTracker(
        time_s=_frozen(time_s),
        S=_frozen(S_all),
        v=_frozen(v_all),
        K=_frozen(K_all),
        u_ref=_frozen(u_ref_all),
        offset_v=_frozen(offset),
    )


# ----------------------------------------------------------------------------------------------
# Sampled data (what the controller runs)


def stationary_gain(
    model: LinearModel, Q: np.ndarray, R: np.ndarray, period_s: float
) -> tuple[np.ndarray, np.ndarray]:
    """The sampled-data LQR: ``K`` (1, 4) and the DARE solution ``P`` (4, 4)."""
    n, m = model.B.shape
    Q, R = _check_weights(Q, R, n, m)
    cost = sampled_cost(model, Q, R, period_s)
    P = _dare(cost)
    Bd = cost.Bd
    K = np.linalg.solve(cost.Rd + Bd.T @ P @ Bd, Bd.T @ P @ cost.Ad + cost.Nd.T)
    return K, P


def _dare(cost: SampledCost) -> np.ndarray:
    try:
        P = scipy.linalg.solve_discrete_are(cost.Ad, cost.Bd, cost.Qd, cost.Rd, s=cost.Nd)
    except (np.linalg.LinAlgError, ValueError) as error:
        raise ConfigError(
            f"no stabilising stationary tracker for these weights: {error}"
        ) from error
    result: np.ndarray = 0.5 * (P + P.T)
    return result


@dataclass(frozen=True)
class StationaryTracker:
    """The part of the sampled-data tracker no plan changes (the stationary problem, S_N = P):
    the period's cost, the DARE solution P (4, 4), the constant gain K_P (4,) with its
    ``G_P = Rd + BdᵀP Bd``, the closed loop Φ = Ad − Bd K_P (4, 4) and the complex Schur form
    ``Φᵀ = U T Uᴴ`` (schur_t = T, schur_u = U, (4, 4)) the feedforward recursion runs in.
    Read-only arrays: one may serve many syntheses (the assembly keeps one per model, weights
    and period)."""

    cost: SampledCost
    P: np.ndarray
    K_P: np.ndarray
    G_P: float
    Phi: np.ndarray
    schur_t: np.ndarray
    schur_u: np.ndarray


def stationary_tracker(
    model: LinearModel, *, Q: np.ndarray, R: np.ndarray, period_s: float
) -> StationaryTracker:
    """The plan-independent part of :func:`discrete_tracker` for these weights and period."""
    n, m = model.B.shape
    Q, R = _check_weights(Q, R, n, m)
    cost = sampled_cost(model, Q, R, period_s)
    Ad, bd = cost.Ad, cost.Bd[:, 0]
    nd = cost.Nd[:, 0]
    rd = float(cost.Rd[0, 0])
    P = _dare(cost)
    Pb = P @ bd
    G_P = rd + bd @ Pb
    K_P = (Pb @ Ad + nd) / G_P
    Phi = Ad - np.outer(bd, K_P)
    T, U = scipy.linalg.schur(Phi.T, output="complex")
    for array in (P, K_P, Phi, T, U, *vars(cost).values()):
        array.setflags(write=False)
    return StationaryTracker(cost, P, K_P, float(G_P), Phi, T, U)


def discrete_tracker(
    model: LinearModel,
    reference_states: np.ndarray,
    reference_input_v: np.ndarray,
    *,
    Q: np.ndarray,
    R: np.ndarray,
    period_s: float,
    terminal: Terminal = "stationary",
    input_reference: InputReference = "feedforward",
    stationary: StationaryTracker | None = None,
) -> DiscreteTracker:
    """Synthesise the sampled-data tracker from references at the sample instants.

    reference_states (N + 1, 4): r_k = x_d(k h) for k = 0..N (r_N enters the terminal cost);
    reference_input_v (N,): ū_k = u_d(k h). ``stationary``: ``stationary_tracker(model, Q=Q,
    R=R, period_s=period_s)`` if already at hand (computed here otherwise).
    """
    n, m = model.B.shape
    _check_choices(terminal, input_reference)
    r = np.asarray(reference_states, dtype=float)
    u_bar = np.asarray(reference_input_v, dtype=float)
    N = u_bar.shape[0]
    if m != 1 or u_bar.ndim != 1 or N < 1 or r.shape != (N + 1, n):
        raise ConfigError(
            f"references must be states (N + 1, {n}) and inputs (N,) with N >= 1 for a "
            f"single-input model, got {r.shape} and {u_bar.shape}"
        )
    if stationary is None:
        stationary = stationary_tracker(model, Q=Q, R=R, period_s=period_s)
    cost = stationary.cost
    Ad, bd = cost.Ad, cost.Bd[:, 0]
    nd = cost.Nd[:, 0]
    rd, rh = float(cost.Rd[0, 0]), float(cost.Rh[0, 0])
    P, K_P, G_P, Phi = stationary.P, stationary.K_P, stationary.G_P, stationary.Phi

    # Stage linear terms a_k (N, 4) and b_k (N,).
    u_ref = u_bar if input_reference == "feedforward" else np.zeros(N)
    a = _rows(r[:N], cost.Qd.T) + np.multiply.outer(u_bar, nd)
    b = _rows(r[:N], nd[:, None])[:, 0] + (rd - rh) * u_bar + rh * u_ref

    # The stationary problem (S_N = P): constant gain, LTI feedforward recursion.
    v_P = _backward_lti(
        (stationary.schur_t, stationary.schur_u), a - np.multiply.outer(b, K_P), P @ r[N]
    )
    if terminal == "stationary":
        S = np.broadcast_to(P, (N + 1, n, n))
        v = v_P
        K = np.broadcast_to(K_P, (N, 1, n))
        G: np.ndarray | float = G_P
    else:
        S, v = _finite_horizon_deviation(Phi, bd, G_P, P, -P, v_P, b, r[N])
        S_next_b = np.einsum("kij,j->ki", S[1:], bd)  # S_{k+1} Bd (S symmetric)
        G = rd + _rows(S_next_b, bd[:, None])[:, 0]
        K = ((_rows(S_next_b, Ad) + nd) / G[:, None]).reshape(N, 1, n)
    offset = (b + _rows(v[1:], bd[:, None])[:, 0]) / G
    return DiscreteTracker(
        period_s=float(period_s),
        K=_frozen(K),
        offset_v=_frozen(offset),
        K_final=_frozen(K_P.reshape(1, n)),
        S=_frozen(S),
        v=_frozen(v),
    )


def synthesize_discrete(
    model: LinearModel,
    plan: Plan,
    *,
    Q: np.ndarray,
    R: np.ndarray,
    period_s: float,
    horizon_s: float,
    terminal: Terminal = "stationary",
    input_reference: InputReference = "feedforward",
    stationary: StationaryTracker | None = None,
    samples: PlanSamples | None = None,
) -> DiscreteTracker:
    """The controller's tracker for ``plan``: N = round(horizon_s / period_s) periods
    (``stationary``: as :func:`discrete_tracker`; ``samples``: ``plan.sample`` at k·period_s,
    k = 0..N, if already at hand)."""
    if not period_s > 0.0:
        raise ConfigError(f"sampling period must be positive, got {period_s} s")
    N = round(horizon_s / period_s)
    if N < 1:
        raise ConfigError(f"tracker horizon {horizon_s} s is shorter than one period")
    if N * period_s < plan.duration_s - 0.5 * period_s:
        raise ConfigError(
            f"tracker horizon {horizon_s} s ends before the plan ({plan.duration_s:.4f} s)"
        )
    if samples is None:
        samples = plan.sample(np.arange(N + 1) * period_s)
    elif samples.input_v.shape != (N + 1,):
        raise ConfigError(
            f"the plan's samples must be N + 1 = {N + 1}, got {samples.input_v.shape}"
        )
    return discrete_tracker(
        model,
        samples.states,
        samples.input_v[:N],
        Q=Q,
        R=R,
        period_s=period_s,
        terminal=terminal,
        input_reference=input_reference,
        stationary=stationary,
    )


def tracker_input(tracker: DiscreteTracker, k: int, state_estimate: np.ndarray) -> float:
    """The tracker's demand [V] at cycle ``k`` (unclamped); beyond the horizon ``−K_final x``."""
    if k < 0:
        raise ValueError(f"cycle index must be >= 0, got {k}")
    if k < tracker.offset_v.shape[0]:
        return float(tracker.offset_v[k] - tracker.K[k, 0] @ state_estimate)
    return float(-(tracker.K_final[0] @ state_estimate))


# ----------------------------------------------------------------------------------------------
# Vectorised backward recursions


def _backward_lti(
    schur: tuple[np.ndarray, np.ndarray], c: np.ndarray, v_end: np.ndarray
) -> np.ndarray:
    """``v_k = Φᵀ v_{k+1} + c_k`` for k = N−1..0 from ``v_N = v_end``. c (N, n) → v (N + 1, n);
    ``schur``: (T, U) of ``Φᵀ``.

    In the complex Schur basis ``Φᵀ = U T Uᴴ`` (T upper triangular, U unitary, so no loss of
    accuracy) the recursion decouples into scalar first-order filters solved from the last
    coordinate up, each fed by the coordinates already solved.
    """
    N, n = c.shape
    T, U = schur
    # Coordinates as rows (n, ·), time backward along them: each filter reads and writes one
    # contiguous row, and einsum runs several times faster along long rows than across short
    # ones. The sums run in the same order, so v is the same to the bit (the golden replay
    # pins it).
    c_back = np.ascontiguousarray(c[::-1].T)  # column i: c_{N−1−i}
    drive_all = np.empty((n, N), dtype=complex)  # Uᴴ c, without complex temporaries
    drive_all.real = _cols(U.real.T, c_back)
    drive_all.imag = 0.0 - _cols(U.imag.T, c_back)  # (0 − x: +0 where x = ±0, as 0 − 1j·x)
    z = np.empty((n, N + 1), dtype=complex)  # column i: Uᴴ v_{N−i}
    z[:, 0] = U.conj().T @ v_end
    for p in range(n - 1, -1, -1):
        drive = drive_all[p]
        for q in range(p + 1, n):
            drive += T[p, q] * z[q, :-1]
        pole = T[p, p]
        z[p, 1:] = first_order_response(pole, drive, z[p, 0])
    v_back = _cols(U.real, np.ascontiguousarray(z.real)) - _cols(
        U.imag, np.ascontiguousarray(z.imag)
    )
    v: np.ndarray = np.ascontiguousarray(v_back.T[::-1])
    return v


def _rows(X: np.ndarray, M: np.ndarray) -> np.ndarray:
    """``X @ M`` for a tall X (N, n) without BLAS: OpenBLAS would start threads for it, and
    waking them costs far more than the product when the other core is busy."""
    result: np.ndarray = np.einsum("ki,ij->kj", X, M)
    return result


def _cols(M: np.ndarray, X: np.ndarray) -> np.ndarray:
    """``M @ X`` for a wide X (n, N), without BLAS as ``_rows``."""
    result: np.ndarray = np.einsum("ij,jk->ik", M, X)
    return result


def _matrix_powers(Phi: np.ndarray, count: int, negligible: float = 1e-30) -> np.ndarray:
    """Φ^j for j = 0..J−1, shape (J, n, n), J <= count: it stops once the powers are
    negligible (a stable Φ; also keeps denormal numbers out of the arithmetic)."""
    n = Phi.shape[0]
    low = np.empty((_POWER_BLOCK, n, n))
    low[0] = np.eye(n)
    for j in range(1, _POWER_BLOCK):
        low[j] = Phi @ low[j - 1]
    step = Phi @ low[-1]
    high = [np.eye(n)]
    while len(high) * _POWER_BLOCK < count:
        following = step @ high[-1]
        if np.abs(following).max() < negligible:
            break
        high.append(following)
    powers: np.ndarray = (np.array(high)[:, None] @ low[None]).reshape(-1, n, n)[:count]
    return powers


def _finite_horizon_deviation(
    Phi: np.ndarray,
    bd: np.ndarray,
    G_P: float,
    P: np.ndarray,
    Delta_N: np.ndarray,
    v_P: np.ndarray,
    b: np.ndarray,
    r_N: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """S_k and v_k for a terminal weight ``S_N = P + Delta_N``, in closed form.

    Relative to the stationary problem's value ``V^P_k``, every stage satisfies
    ``ℓ(x, u) + V^P_{k+1}(Ad x + Bd u) = V^P_k(x) + G_P (u − u^P_k(x))²``, so the remaining
    problem is: minimise ``Σ G_P w_i² + (x_N − r_N)ᵀΔ_N(x_N − r_N)`` subject to
    ``x_{i+1} = Φ x_i + Bd (f^P_i + w_i)``. Its terminal state from ``x_k`` is
    ``Φ^j x_k + d_k + δ`` (j = N − k, ``d_k`` the drift of the stationary offsets ``f^P``),
    where a shift δ costs ``δᵀW_j⁻¹δ`` with ``W_j = Σ_{p<j} Φ^p Bd Bdᵀ Φ^pᵀ / G_P``. Minimising
    over δ leaves ``(Φ^j x_k + d_k − r_N)ᵀ M_j (·)`` with ``M_j = (I + Δ_N W_j)⁻¹ Δ_N``, hence

        S_k = P + Φ^jᵀ M_j Φ^j,    v_k = v^P_k − Φ^jᵀ M_j (d_k − r_N).

    Everything is a batched 4×4 operation over j; no step depends on the previous one. Only
    the last J steps are computed, J such that Φ^J is negligible: before them S_k = P and
    v_k = v^P_k to working precision.
    """
    N = b.shape[0]
    n = Phi.shape[0]
    powers = _matrix_powers(Phi, N + 1)  # Φ^j, j = 0..J
    J = powers.shape[0] - 1
    start = N - J  # first k computed: j = N − k runs J..0
    g = np.einsum("pij,j->pi", powers[:J], bd)  # Φ^p Bd, p = 0..J−1
    W = np.zeros((J + 1, n, n))
    np.cumsum(np.einsum("pi,pj->pij", g, g) / G_P, axis=0, out=W[1:])
    M = np.linalg.solve(np.eye(n) + Delta_N @ W, np.broadcast_to(Delta_N, (J + 1, n, n)))
    M = 0.5 * (M + M.transpose(0, 2, 1))
    # Stationary offsets f^P_i (i >= start) and their drift d_k = Σ_{i≥k} Φ^{N−1−i} Bd f^P_i.
    f_P = (b[start:] + _rows(v_P[start + 1 :], bd[:, None])[:, 0]) / G_P
    drift = np.zeros((J + 1, n))
    # Row p of the summand is Φ^p Bd f_{N−1−p}; summing p = 0..N−1−k gives d_k.
    drift[:J] = np.cumsum(g * f_P[::-1, None], axis=0)[::-1]
    powers_k = powers[::-1]  # row k − start holds Φ^{N−k}
    M_k = M[::-1]
    S = np.empty((N + 1, n, n))
    S[:start] = P
    S_tail = P + powers_k.transpose(0, 2, 1) @ M_k @ powers_k
    S[start:] = 0.5 * (S_tail + S_tail.transpose(0, 2, 1))
    correction = np.einsum("kij,kj->ki", M_k, drift - r_N)
    v = v_P.copy()
    v[start:] -= np.einsum("kji,kj->ki", powers_k, correction)
    return S, v


def _frozen(array: np.ndarray) -> np.ndarray:
    array = np.asarray(array)
    if array.flags.writeable:
        array.setflags(write=False)
    return array
