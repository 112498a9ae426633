"""The lag model's zero-order hold in closed form (docs/design.md §2).

The motor is one pole a = αβ, then θ, then the ball's two integrators: θ̈ = −a θ̇ + α u,
ẍ = γ θ. Over an input held for τ the exact response needs only the lag's step, ramp and
parabola (``_phis``); the same formulas give the grid states (``_simulate``), the responses
the time-optimal LPs use, and a plan's states between grid times (``_propagate``).

Over a held input θ̇ is monotone, so θ turns at most once, at an angle given in closed form
(``_turn_angle``): the first step, which starts from the known state, is bounded exactly by
it (``_first_step_interval``); ``_accel_max`` bounds |θ̈| for the samples after it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ballbeam.core.model import LinearModel
from ballbeam.core.recursion import first_order_response
from ballbeam.errors import ConfigError


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
        rate[1:] = first_order_response(E, w, x0[1], gain=1.0 - E)
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
