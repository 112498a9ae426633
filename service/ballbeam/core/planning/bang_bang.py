"""Bang-bang minimum-time path for the ball alone (paper section 5, eqs 14-17, figure 5).

The servo is taken as instantaneous: θ itself is the input, bounded by |θ| <= θmax, so the
ball ẍ = γθ is a double integrator with |ẍ| <= A = |γ|·θmax. The minimum time to rest at
x = 0 is one switch between the two bounds on the curve x = −ẋ|ẋ|/2A (eq 16), taking
T = (s·ẋ0 + 2·sqrt(ẋ0²/2 + s·A·x0)) / A, with s = +1 above that curve (eq 17; from rest it is
2·sqrt(|x0|/A), 1.444 s from the paper's start).

The path is dynamically consistent for the ball subsystem only: ẍ_d = γ·θ_d holds exactly,
but θ_d jumps between ±θmax, so θ̇_d (an impulse at each jump) is reported as 0 and u_d as 0;
the servo cannot follow it, which is why the rate-limited and full-model planners exist.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ballbeam.core.model import (
    BALL_POSITION,
    BALL_VELOCITY,
    N_STATES,
    THETA,
    PhysicalConstants,
)
from ballbeam.core.planning.plan import PlanSamples
from ballbeam.errors import PlanningError


@dataclass(frozen=True)
class BangBangPlan:
    """θ_d = θ_first on [0, t1), −θ_first on [t1, T), then 0.

    Before 0 the plan holds the initial ball state with θ_d = θ_first (the first bang), so the
    desired angle does not jump at 0 a second time; θ̇_d = u_d = 0 throughout.
    θ_first is 0 when the ball starts at rest at the origin (duration 0).
    """

    theta_first_rad: float
    first_duration_s: float
    second_duration_s: float
    initial_position_m: float
    initial_velocity_m_s: float
    gamma_m_s2_per_rad: float
    theta_max_rad: float

    @property
    def kind(self) -> str:
        return "bang_bang"

    @property
    def duration_s(self) -> float:
        return self.first_duration_s + self.second_duration_s

    @property
    def switch_time_s(self) -> float:
        return self.first_duration_s

    def sample(self, time_s: np.ndarray) -> PlanSamples:
        t = np.atleast_1d(np.asarray(time_s, dtype=float))
        gamma = self.gamma_m_s2_per_rad
        a_first = gamma * self.theta_first_rad
        p0, v0 = self.initial_position_m, self.initial_velocity_m_s
        duration = self.duration_s
        # First arc runs forward from the start; the second runs backward from rest at T, so the
        # end is exactly at rest and the arcs meet at the switch up to rounding.
        tf = np.clip(t, 0.0, self.first_duration_s)
        to_end = np.clip(t, self.first_duration_s, duration) - duration
        first = t < self.first_duration_s
        theta = np.where(first, self.theta_first_rad, -self.theta_first_rad)
        velocity = np.where(first, v0 + a_first * tf, -a_first * to_end)
        position = np.where(first, p0 + v0 * tf + 0.5 * a_first * tf**2, -0.5 * a_first * to_end**2)
        after = t >= duration
        states = np.zeros((t.size, N_STATES))
        states[:, THETA] = np.where(after, 0.0, theta)
        states[:, BALL_VELOCITY] = np.where(after, 0.0, velocity)
        states[:, BALL_POSITION] = np.where(after, 0.0, position)
        return PlanSamples(time_s=t, states=states, input_v=np.zeros(t.size))


def plan_bang_bang(
    constants: PhysicalConstants, theta_max_rad: float, initial_state: np.ndarray
) -> BangBangPlan:
    """Minimum-time path from ``initial_state`` (θ, θ̇, ẋ, x) to rest at x = 0, |θ| <= θmax.

    Only the ball's position and velocity matter: the servo is taken as instantaneous.
    Raises PlanningError for a non-positive θmax or a malformed start.
    """
    start = np.asarray(initial_state, dtype=float)
    if start.shape != (N_STATES,) or not np.all(np.isfinite(start)):
        raise PlanningError(f"initial state must be 4 finite numbers, got {initial_state!r}")
    if not (math.isfinite(theta_max_rad) and theta_max_rad > 0.0):
        raise PlanningError(f"θmax must be positive, got {theta_max_rad} rad")
    gamma = constants.gamma
    A = abs(gamma) * theta_max_rad
    p0, v0 = float(start[BALL_POSITION]), float(start[BALL_VELOCITY])
    # s = +1 above the switching curve: accelerate toward −x first (eq 16). On the curve the
    # sign of v0 decides, and the second arc has zero length.
    above = p0 + v0 * abs(v0) / (2.0 * A)
    s = 1.0 if above > 0.0 or (above == 0.0 and v0 >= 0.0) else -1.0
    root = math.sqrt(max(0.5 * v0 * v0 + s * A * p0, 0.0))
    t1 = max((s * v0 + root) / A, 0.0)
    t2 = max(root / A, 0.0)  # = t1 − s·v0/A: the second arc cancels the velocity
    at_rest = t1 + t2 == 0.0
    # ẍ = γθ with γ < 0: the first acceleration −s·A needs θ = s·θmax.
    theta_first = 0.0 if at_rest else math.copysign(theta_max_rad, -s * gamma)
    return BangBangPlan(
        theta_first_rad=theta_first,
        first_duration_s=t1,
        second_duration_s=t2,
        initial_position_m=p0,
        initial_velocity_m_s=v0,
        gamma_m_s2_per_rad=gamma,
        theta_max_rad=theta_max_rad,
    )
