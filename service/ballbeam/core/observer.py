"""Steady-state Kalman filter: estimates θ̇ and ẋ from quantised θ and x, with the known input.

Model, per controller period h (the discrete model, input held over the period)::

    x_{k+1} = Ad x_k + Bd (u_k + w_k) + Γ a_k,   y_k = C x_k + n_k

- ``w_k``: unmodelled input (dead zone, friction, gain error), std ``input_noise_v`` volts,
  held over the period like the input itself, so it enters through ``Bd``;
- ``a_k``: unmodelled ball acceleration, std ``ball_noise_m_s2``, held over the period, so
  ``Γ = (0, 0, h, h²/2)``: it changes ẋ by ``a h`` and x by ``a h²/2``;
- ``n_k``: measurement noise in the paper's output units, ``y = (57 θ, 100 x)``: std
  ``57·angle_noise_rad`` and ``100·position_noise_m`` (independent; quantisation is treated as
  white noise of std step/√12 by whoever picks the defaults).

"Current estimator" form (the estimate at k already uses ``y_k``)::

    x̄_k = Ad x̂_{k−1} + Bd u_{k−1}            (predict)
    x̂_k = x̄_k + L (y_k − C x̄_k)              (correct)

with the steady-state gain ``L = P̄ Cᵀ (C P̄ Cᵀ + Rn)⁻¹`` and ``P̄`` the prior covariance from the
filtering Riccati equation (the dual DARE). The estimation error then evolves as
``e_k = (I − L C) Ad e_{k−1} + noise``; its covariance is ``P̂ = (I − L C) P̄``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ballbeam.core.model import BALL_POSITION, THETA, DiscreteModel
from ballbeam.errors import ConfigError


@dataclass(frozen=True)
class ObserverGains:
    """L (4, 2), Ad (4, 4), Bd (4, 1), C (2, 4); P_prior, P_estimate (4, 4) the steady-state
    error covariances of the prediction and of the corrected estimate."""

    L: np.ndarray
    Ad: np.ndarray
    Bd: np.ndarray
    C: np.ndarray
    P_prior: np.ndarray
    P_estimate: np.ndarray


def process_noise_covariance(
    model: DiscreteModel, input_noise_v: float, ball_noise_m_s2: float
) -> np.ndarray:
    """Qn (4, 4): input disturbance through Bd plus a held ball acceleration."""
    h = model.period_s
    ball = np.zeros(model.n_states)
    ball[2:] = (h, 0.5 * h * h)  # (ẋ, x) after holding a unit acceleration for h
    Bd = model.Bd[:, 0]
    result: np.ndarray = input_noise_v**2 * np.outer(Bd, Bd) + ball_noise_m_s2**2 * np.outer(
        ball, ball
    )
    return result


def measurement_noise_covariance(
    C: np.ndarray, angle_noise_rad: float, position_noise_m: float
) -> np.ndarray:
    """Rn (2, 2) in output units: C diag(σθ², 0, 0, σx²) Cᵀ = diag((57σθ)², (100σx)²)."""
    state_noise = np.zeros(C.shape[1])
    state_noise[THETA] = angle_noise_rad**2
    state_noise[BALL_POSITION] = position_noise_m**2
    result: np.ndarray = (C * state_noise) @ C.T
    return result


@dataclass(frozen=True)
class ObserverNoise:
    """The noise levels a filter is designed for (the module's docstring says where each
    enters)."""

    input_noise_v: float
    ball_noise_m_s2: float
    angle_noise_rad: float
    position_noise_m: float


def design_observer(
    model: DiscreteModel,
    *,
    input_noise_v: float,
    ball_noise_m_s2: float,
    angle_noise_rad: float,
    position_noise_m: float,
) -> ObserverGains:
    """The steady-state Kalman gain for ``model`` (at its period) and these noise levels."""
    noise = ObserverNoise(input_noise_v, ball_noise_m_s2, angle_noise_rad, position_noise_m)
    return design_observers(model, [noise])[0]


def design_observers(
    model: DiscreteModel, noises: Sequence[ObserverNoise]
) -> tuple[ObserverGains, ...]:
    """:func:`design_observer` for each of ``noises``, their Riccati equations solved
    together (a design needs a filter for each of several noise levels)."""
    for noise in noises:
        for name, value in vars(noise).items():
            if not (np.isfinite(value) and value > 0.0):
                raise ConfigError(f"observer noise {name} must be positive, got {value}")
    Ad, Bd, C = model.Ad, model.Bd, model.C
    Qn = np.array([
        process_noise_covariance(model, noise.input_noise_v, noise.ball_noise_m_s2)
        for noise in noises
    ])
    Rn = np.array([
        measurement_noise_covariance(C, noise.angle_noise_rad, noise.position_noise_m)
        for noise in noises
    ])
    P_prior = filtering_riccati(Ad, C, Qn, Rn)
    innovation = C @ P_prior @ C.T + Rn
    # P̄ Cᵀ (C P̄ Cᵀ + Rn)⁻¹, the innovation's covariance symmetric
    L = np.linalg.solve(innovation, C @ P_prior).swapaxes(-1, -2)
    P_estimate = (np.eye(Ad.shape[0]) - L @ C) @ P_prior
    P_estimate = 0.5 * (P_estimate + P_estimate.swapaxes(-1, -2))
    designs = []
    for index in range(len(noises)):
        arrays = (L[index], np.array(Ad), np.array(Bd), np.array(C), P_prior[index],
                  P_estimate[index])
        for array in arrays:
            array.setflags(write=False)
        designs.append(ObserverGains(*arrays))
    return tuple(designs)


# The doubling converges quadratically: each step squares the error's contraction (the
# filter's closed-loop poles over twice as many periods). Far more steps than any filter in
# the configs' ranges needs; one that has not converged by then has no steady state.
_DOUBLING_STEPS = 60
_DOUBLING_TOLERANCE = 1e-14


def filtering_riccati(Ad: np.ndarray, C: np.ndarray, Qn: np.ndarray, Rn: np.ndarray) -> np.ndarray:
    """The prior covariances P̄ (..., n, n) of the steady-state Kalman filters of the model
    (Ad, C) for each process noise Qn (..., n, n) and measurement noise Rn (..., m, m): the
    stabilising solutions of P̄ = Ad P̄ Adᵀ − Ad P̄ Cᵀ (C P̄ Cᵀ + Rn)⁻¹ C P̄ Adᵀ + Qn, all at
    once, by the structure-preserving doubling algorithm (Chu, Fan & Lin, 2005) on the dual
    control equation (Adᵀ, Cᵀ): a few batched 4 × 4 solves in place of a QZ decomposition
    each. ConfigError where it does not converge (no stabilising solution)."""
    try:
        A = np.broadcast_to(Ad.T, Qn.shape).copy()
        G = C.T @ np.linalg.solve(Rn, np.broadcast_to(C, (*Rn.shape[:-2], *C.shape)))
        H = np.array(Qn, dtype=float)
        identity = np.eye(Ad.shape[0])
        for _ in range(_DOUBLING_STEPS):
            W = identity + G @ H
            inverse_A = np.linalg.solve(W, A)  # (I + G H)⁻¹ A
            inverse_G = np.linalg.solve(W, G)  # (I + G H)⁻¹ G
            A_t = A.swapaxes(-1, -2)
            step = A_t @ H @ inverse_A
            H = H + step
            G = G + A @ inverse_G @ A_t
            A = A @ inverse_A
            if not np.isfinite(H).all():
                break
            if (np.abs(step).max(axis=(-2, -1)) <= _DOUBLING_TOLERANCE * np.abs(H).max(
                axis=(-2, -1)
            )).all():
                solution: np.ndarray = 0.5 * (H + H.swapaxes(-1, -2))
                return solution
    except np.linalg.LinAlgError:  # a singular step: no solution of this equation either
        pass
    raise ConfigError("no steady-state Kalman filter for these noise levels (its Riccati "
                      "equation has no stabilising solution)")


def predict(gains: ObserverGains, estimate: np.ndarray, input_v: float | np.ndarray) -> np.ndarray:
    """x̄_{k+1} = Ad x̂_k + Bd u_k. estimate (..., 4), input_v scalar or (...,) → (..., 4)."""
    result: np.ndarray = estimate @ gains.Ad.T + np.asarray(input_v)[..., None] * gains.Bd[:, 0]
    return result


def correct(gains: ObserverGains, prediction: np.ndarray, measurement: np.ndarray) -> np.ndarray:
    """x̂_k = x̄_k + L (y_k − C x̄_k). prediction (..., 4), measurement (..., 2) → (..., 4)."""
    result: np.ndarray = prediction + (measurement - prediction @ gains.C.T) @ gains.L.T
    return result


def initial_estimate(
    gains: ObserverGains, measurement: np.ndarray, prior_state: np.ndarray | None = None
) -> np.ndarray:
    """The state (4,) that explains the first measurement (2,) exactly; the unmeasured rates
    come from ``prior_state`` (the scenario's known start), or zero."""
    # C measures θ and x only, so the least-squares solution of minimum norm sets θ̇ = ẋ = 0.
    result: np.ndarray = np.linalg.lstsq(gains.C, np.asarray(measurement, dtype=float))[0]
    if prior_state is not None:
        unmeasured = ~np.any(gains.C != 0.0, axis=0)
        result[unmeasured] = np.asarray(prior_state, dtype=float)[unmeasured]
    return result
