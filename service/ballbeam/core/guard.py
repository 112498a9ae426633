"""Servo-angle guard: caps the voltage so the servo can always stop before ±θ_limit.

The safe set is {θ + d(θ̇) <= θ_limit} (and its mirror), where d is the exact stopping
distance of the motor model θ̈ = −αβ·θ̇ − α·V_brake under full braking. Each cycle the
largest (smallest) voltage whose one-period successor stays in the safe set is found; the
successor is linear in u and d is increasing, so the bound is a monotone 1-D root.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

BISECTION_STEPS = 40


@dataclass(frozen=True)
class AngleGuard:
    theta_limit_rad: float  # the angle the servo must not pass (limit minus a margin)
    alpha: float  # model α [rad/s² per V]
    alpha_beta: float  # model αβ [1/s]
    brake_v: float  # braking voltage counted on (V_max less a dead-zone allowance)
    voltage_limit_v: float
    Ad: np.ndarray  # (4, 4) over the look-ahead: one period, plus the latency in real time
    Bd: np.ndarray  # (4, 1)


def stopping_distance_rad(guard: AngleGuard, rate_rad_s: float) -> float:
    """Angle travelled from rate ω > 0 until rest under full braking (0 for ω <= 0).

    ω̇ = −aω − c with a = αβ, c = α·V_brake: stops at t* = ln(1 + aω/c)/a after
    d = ω/a − (c/a²)·ln(1 + aω/c)."""
    if rate_rad_s <= 0.0:
        return 0.0
    a = guard.alpha_beta
    c = guard.alpha * guard.brake_v
    return rate_rad_s / a - (c / (a * a)) * math.log1p(a * rate_rad_s / c)


def guarded_voltage(guard: AngleGuard, estimate: np.ndarray, requested_v: float) -> float:
    """``requested_v`` clamped to ±V and to the guard's safe interval for this state."""
    # The successor is (free response) + Bd·u: the matrix part once per cycle, the rest in
    # scalars (the same floating-point operations as the whole expression, so bit for bit).
    theta_free = float(guard.Ad[0] @ estimate)
    rate_free = float(guard.Ad[1] @ estimate)
    theta_per_v = float(guard.Bd[0, 0])
    rate_per_v = float(guard.Bd[1, 0])

    def margin(input_v: float, sign: float) -> float:
        """Distance left to the limit (side ``sign``) after one period at ``input_v``."""
        theta = theta_free + theta_per_v * input_v
        rate = rate_free + rate_per_v * input_v
        return guard.theta_limit_rad - sign * theta - stopping_distance_rad(guard, sign * rate)

    limit = guard.voltage_limit_v
    voltage = min(max(requested_v, -limit), limit)
    for sign in (1.0, -1.0):
        # Pushing toward the limit on side `sign` means voltage·sign large.
        if margin(voltage, sign) >= 0.0:
            continue
        safest = -sign * limit
        if margin(safest, sign) < 0.0:
            return safest  # cannot stay inside: brake as hard as possible
        inside, outside = safest, voltage
        for _ in range(BISECTION_STEPS):
            middle = 0.5 * (inside + outside)
            if margin(middle, sign) >= 0.0:
                inside = middle
            else:
                outside = middle
        voltage = inside
    return voltage
