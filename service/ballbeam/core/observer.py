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

from dataclasses import dataclass

import numpy as np
import scipy.linalg

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


def design_observer(
    model: DiscreteModel,
    *,
    input_noise_v: float,
    ball_noise_m_s2: float,
    angle_noise_rad: float,
    position_noise_m: float,
) -> ObserverGains:
    """The steady-state Kalman gain for ``model`` (at its period) and these noise levels."""
    for name, value in (
        ("input_noise_v", input_noise_v),
        ("ball_noise_m_s2", ball_noise_m_s2),
        ("angle_noise_rad", angle_noise_rad),
        ("position_noise_m", position_noise_m),
    ):
        if not (np.isfinite(value) and value > 0.0):
            raise ConfigError(f"observer noise {name} must be positive, got {value}")
    Ad, Bd, C = model.Ad, model.Bd, model.C
    Qn = process_noise_covariance(model, input_noise_v, ball_noise_m_s2)
    Rn = measurement_noise_covariance(C, angle_noise_rad, position_noise_m)
    try:
        # The filtering Riccati equation is the control one for (Adᵀ, Cᵀ).
        P_prior = scipy.linalg.solve_discrete_are(Ad.T, C.T, Qn, Rn)
    except (np.linalg.LinAlgError, ValueError) as error:
        raise ConfigError(f"no steady-state Kalman filter for these noise levels: {error}") from (
            error
        )
    P_prior = 0.5 * (P_prior + P_prior.T)
    innovation = C @ P_prior @ C.T + Rn
    L = np.linalg.solve(innovation, C @ P_prior).T  # P̄ Cᵀ (C P̄ Cᵀ + Rn)⁻¹, symmetric innovation
    P_estimate = (np.eye(Ad.shape[0]) - L @ C) @ P_prior
    P_estimate = 0.5 * (P_estimate + P_estimate.T)
    arrays = (L, np.array(Ad), np.array(Bd), np.array(C), P_prior, P_estimate)
    for array in arrays:
        array.setflags(write=False)
    return ObserverGains(*arrays)


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
