"""Servo-rate-limited minimum-time path (paper section 5, figure 6; docs/design.md §3).

The ball obeys ẍ = γθ, so the servo-angle bound |θ| ≤ θmax is a ball-acceleration bound
|ẍ| ≤ A = |γ|·θmax and the servo-rate bound |θ̇| ≤ θ̇max is a ball-jerk bound
|x⃛| ≤ J = |γ|·θ̇max. Taking the servo rate as the input (the motor lag 1/αβ ≈ 17 ms is
neglected), the task is the time-optimal control of a triple integrator from
(x0, ẋ0, γ·θ0) to rest at the origin (0, 0, 0), i.e. with θ = 0 at the end, under those two
bounds and no velocity bound.

Profile family. By the minimum principle the jerk is ±J between arcs on which the acceleration
rides a bound, with at most two switches in between; with the velocity unbounded every
extremal has the jerk pattern (sJ, 0, −sJ, 0, sJ), s = ±1, segment durations ≥ 0 (the zero-jerk
segments are the plateaus at a = ±A). In the frame where s = +1 the extremals form one
continuous family with two pieces:

- main piece: parametrised by w, the velocity at the instant the acceleration crosses zero
  between the two bangs (w ≥ max(0, velocity after bringing a to 0 at once));
- brake piece, only when the ball already decelerates toward a stop ahead of it (a0 < 0 and
  ẋ0 ≥ a0²/2J in that frame): parametrised by the first peak a1 ∈ [a0, 0], the acceleration
  never crossing zero.

The end position is monotone along each piece and the pieces of the two frames join end to end,
so exactly one extremal ends at x = 0; it is found by bracketed root finding on one scalar
(about 12 end-position evaluations). The durations agree with Ruckig to ~1e-12 s on random
starts (tests; 50,000 starts checked while writing this, including a0 = ±A).

From the paper's start (θ0 = −52°, ẋ0 = 0, x0 = 0.195 m, θmax = 52°, so the ball starts with the
wrong acceleration +0.374 m/s²) this gives 1.699815 s at θ̇max = 9.325 rad/s and 1.744578 s at
8 rad/s, as Ruckig does. The paper's 1.6390 s and 1.6760 s come from its own construction
(the bang-bang angle path with its transitions made at the maximum slope), which the stated
set-up does not pin down; they are not the minimum time for these bounds from this start.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import scipy.optimize

from ballbeam.core.model import (
    BALL_POSITION,
    BALL_VELOCITY,
    N_STATES,
    THETA,
    THETA_RATE,
    PhysicalConstants,
)
from ballbeam.core.planning.plan import PlanSamples
from ballbeam.errors import PlanningError

# Root-finding tolerance on the scalar parameter; the end-position error is this times ~T.
_XTOL = 1e-15
# Accepted end-state residual, relative to the problem's own scales.
_END_RTOL = 1e-9
# Shortest kept segment, relative to the whole path (well above the rounding of knot times).
_MIN_SEGMENT_RTOL = 1e-12


@dataclass(frozen=True)
class JerkSegment:
    """Constant jerk held for a duration."""

    jerk_m_s3: float
    duration_s: float


@dataclass(frozen=True, eq=False)
class JerkProfile:
    """A piecewise-cubic ball path: jerk held constant on each segment.

    knot_time_s: (n + 1,) segment starts and the end; knot_states: (n + 1, 3) the
    (position, velocity, acceleration) there. Before 0 it holds the start (jerk 0); from
    ``duration_s`` on it rests at the origin.
    """

    segments: tuple[JerkSegment, ...]
    knot_time_s: np.ndarray
    knot_states: np.ndarray

    @property
    def duration_s(self) -> float:
        return float(self.knot_time_s[-1])

    @property
    def initial_state(self) -> np.ndarray:
        """(position m, velocity m/s, acceleration m/s²) at time 0."""
        start: np.ndarray = self.knot_states[0].copy()
        return start

    def evaluate(self, time_s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Position [m], velocity [m/s], acceleration [m/s²], jerk [m/s³], each like time_s."""
        t = np.asarray(time_s, dtype=float)
        n = len(self.segments)
        jerks = np.array([seg.jerk_m_s3 for seg in self.segments] + [0.0])
        # side="right": a knot belongs to the segment that starts there.
        index = np.clip(np.searchsorted(self.knot_time_s, t, side="right") - 1, 0, n)
        before = t < 0.0
        index = np.where(before, 0, index)
        dt = np.where(before, 0.0, t - self.knot_time_s[index])
        jerk = np.where(before, 0.0, jerks[index])
        p, v, a = (self.knot_states[index, k] for k in range(3))
        position = p + dt * (v + dt * (a / 2.0 + dt * jerk / 6.0))
        velocity = v + dt * (a + dt * jerk / 2.0)
        acceleration = a + dt * jerk
        after = t >= self.duration_s
        zero = np.zeros_like(t)
        return (
            np.where(after, zero, position),
            np.where(after, zero, velocity),
            np.where(after, zero, acceleration),
            np.where(after, zero, jerk),
        )


def _advance(p: float, v: float, a: float, jerk: float, dt: float) -> tuple[float, float, float]:
    """Exact state after holding ``jerk`` for ``dt``."""
    return (
        p + dt * (v + dt * (a / 2.0 + dt * jerk / 6.0)),
        v + dt * (a + dt * jerk / 2.0),
        a + dt * jerk,
    )


_Durations = tuple[float, float, float, float, float]


def _end_position(p: float, v: float, a: float, jerk_max: float, durations: _Durations) -> float:
    """End position of the (J, 0, −J, 0, J) pattern in the s = +1 frame."""
    for jerk, dt in zip((jerk_max, 0.0, -jerk_max, 0.0, jerk_max), durations, strict=True):
        p, v, a = _advance(p, v, a, jerk, dt)
    return p


def _main_durations(v0: float, a0: float, A: float, J: float, w: float) -> _Durations:
    """Segment durations on the main piece, s = +1 frame, for zero-crossing velocity w."""
    # Phase I: jerk +J to the peak a1 (plateau if it hits A), then −J until a = 0 at velocity w.
    # Its velocity gain is (2a1² − a0²)/2J without a plateau.
    a1_sq = 0.5 * (a0 * a0 + 2.0 * J * (w - v0))
    a1 = math.sqrt(max(a1_sq, 0.0))
    plateau1 = 0.0
    if a1 > A:
        a1 = A
        plateau1 = max((w - v0 - (2.0 * A * A - a0 * a0) / (2.0 * J)) / A, 0.0)
    t1 = max((a1 - a0) / J, 0.0)
    # Phase II: symmetric stop from (w, 0): −J down to −a2, plateau at −A if needed, +J up to 0.
    a2 = min(A, math.sqrt(max(w, 0.0) * J))
    plateau2 = max(w / a2 - a2 / J, 0.0) if a2 > 0.0 else 0.0
    return (t1, plateau1, a1 / J + a2 / J, plateau2, a2 / J)


def _brake_durations(v0: float, a0: float, A: float, J: float, a1: float) -> _Durations:
    """Segment durations on the brake piece, s = +1 frame, for the first peak a0 ≤ a1 ≤ 0."""
    # Velocity gain is (2a1² − a0² − 2a2²)/2J without the plateau at −A; it must cancel v0.
    a2_sq = a1 * a1 - 0.5 * a0 * a0 + J * v0
    a2 = math.sqrt(max(a2_sq, 0.0))
    plateau2 = 0.0
    if a2 > A:
        a2 = A
        plateau2 = max((v0 + (2.0 * a1 * a1 - a0 * a0 - 2.0 * A * A) / (2.0 * J)) / A, 0.0)
    return (max((a1 - a0) / J, 0.0), 0.0, max((a1 + a2) / J, 0.0), plateau2, a2 / J)


def _solve_monotone(f: Callable[[float], float], lo: float, step: float) -> float:
    """Root of an increasing f with f(lo) <= 0, expanding the bracket upward from lo."""
    hi = lo + step
    while f(hi) < 0.0:
        lo, step = hi, 2.0 * step
        hi = lo + step
        if not math.isfinite(hi):  # pragma: no cover - f grows like w², so this cannot happen
            raise PlanningError("rate-limited planner failed to bracket the end position")
    root: float = scipy.optimize.brentq(f, lo, hi, xtol=_XTOL, rtol=4.0 * np.finfo(float).eps)
    return root


def _solve_frame(p0: float, v0: float, a0: float, A: float, J: float) -> _Durations | None:
    """Durations of the extremal ending at x = 0 in the s = +1 frame, or None if it has none."""
    v_brake = v0 + a0 * abs(a0) / (2.0 * J)  # velocity once a is brought to 0 at once
    w_lo = max(0.0, v_brake)

    def main_end(w: float) -> float:
        return _end_position(p0, v0, a0, J, _main_durations(v0, a0, A, J, w))

    end_lo = main_end(w_lo)
    if end_lo <= 0.0:
        # Step of the order of the velocity that covers the remaining distance at accel. A.
        step = max(math.sqrt(A * -end_lo), A * A / J, abs(w_lo), 1e-9)
        return _main_durations(v0, a0, A, J, _solve_monotone(main_end, w_lo, step))
    if a0 < 0.0 and v_brake >= 0.0:

        def brake_end(a1: float) -> float:
            return _end_position(p0, v0, a0, J, _brake_durations(v0, a0, A, J, a1))

        if brake_end(a0) <= 0.0:
            root: float = scipy.optimize.brentq(
                brake_end, a0, 0.0, xtol=_XTOL, rtol=4.0 * np.finfo(float).eps
            )
            return _brake_durations(v0, a0, A, J, root)
    return None


def _build_profile(
    p0: float, v0: float, a0: float, segments: list[JerkSegment]
) -> tuple[np.ndarray, np.ndarray]:
    times = [0.0]
    states = [(p0, v0, a0)]
    p, v, a = p0, v0, a0
    for seg in segments:
        p, v, a = _advance(p, v, a, seg.jerk_m_s3, seg.duration_s)
        times.append(times[-1] + seg.duration_s)
        states.append((p, v, a))
    knot_time_s = np.array(times)
    knot_states = np.array(states)
    knot_time_s.setflags(write=False)
    knot_states.setflags(write=False)
    return knot_time_s, knot_states


def solve_jerk_profile(
    position_m: float,
    velocity_m_s: float,
    acceleration_m_s2: float,
    acceleration_max_m_s2: float,
    jerk_max_m_s3: float,
) -> JerkProfile:
    """Minimum-time path of a triple integrator to rest at the origin, |a| <= A, |jerk| <= J.

    Raises PlanningError for non-positive or non-finite limits, a non-finite start, or a start
    acceleration beyond A.
    """
    p0, v0, a0 = float(position_m), float(velocity_m_s), float(acceleration_m_s2)
    A, J = float(acceleration_max_m_s2), float(jerk_max_m_s3)
    if not (math.isfinite(A) and A > 0.0 and math.isfinite(J) and J > 0.0):
        raise PlanningError(f"limits must be positive and finite, got A = {A}, J = {J}")
    if not all(math.isfinite(x) for x in (p0, v0, a0)):
        raise PlanningError(f"initial state must be finite, got {(p0, v0, a0)}")
    if abs(a0) > A:
        raise PlanningError(
            f"initial acceleration {a0:.6g} m/s² is beyond the bound {A:.6g} m/s² "
            "(initial servo angle beyond θmax)"
        )
    segments: list[JerkSegment] = []
    if (p0, v0, a0) != (0.0, 0.0, 0.0):
        candidates: list[tuple[float, list[JerkSegment]]] = []
        for s in (1.0, -1.0):
            durations = _solve_frame(s * p0, s * v0, s * a0, A, J)
            if durations is None:
                continue
            jerks = (s * J, 0.0, -s * J, 0.0, s * J)
            total = sum(durations)
            # Segments of rounding-noise length would give coincident knots; drop them.
            segs = [
                JerkSegment(jerk_m_s3=j, duration_s=d)
                for j, d in zip(jerks, durations, strict=True)
                if d > _MIN_SEGMENT_RTOL * total
            ]
            candidates.append((total, segs))
        if not candidates:  # pragma: no cover - the two frames' families cover every start
            raise PlanningError(f"no rate-limited extremal reaches rest from {(p0, v0, a0)}")
        segments = min(candidates, key=lambda c: c[0])[1]
    knot_time_s, knot_states = _build_profile(p0, v0, a0, segments)
    _check_end(knot_time_s, knot_states, A, J)
    return JerkProfile(segments=tuple(segments), knot_time_s=knot_time_s, knot_states=knot_states)


def _check_end(knot_time_s: np.ndarray, knot_states: np.ndarray, A: float, J: float) -> None:
    """Refuse a profile whose end state misses rest at the origin (a solver failure)."""
    duration = float(knot_time_s[-1])
    p0, v0, _ = knot_states[0]
    scale_p = max(abs(p0), abs(v0) * duration, A * duration**2, 1e-12)
    scale_v = max(abs(v0), A * duration, 1e-12)
    p, v, a = knot_states[-1]
    if abs(p) > _END_RTOL * scale_p or abs(v) > _END_RTOL * scale_v or abs(a) > _END_RTOL * A:
        raise PlanningError(f"rate-limited path ends at {(p, v, a)}, not at rest")
    if np.any(np.abs(knot_states[:, 2]) > A * (1.0 + 1e-12)):
        raise PlanningError("rate-limited path exceeds the acceleration bound")


@dataclass(frozen=True, eq=False)
class RateLimitedPlan:
    """Desired path with |θ| <= θmax and |θ̇| <= θ̇max, minimum time for the ball.

    θ_d = a/γ, θ̇_d = jerk/γ (piecewise constant), ẋ_d, x_d the ball path, and
    u_d = β·θ̇_d: the steady voltage for that servo rate; the motor lag is neglected, so the
    servo needs a short transient after each rate change that u_d does not supply. Before 0 the
    plan holds the start (θ0, 0, ẋ0, x0) with u_d = 0; from ``duration_s`` on it rests at 0.
    """

    profile: JerkProfile
    gamma_m_s2_per_rad: float
    beta_v_s_per_rad: float
    theta_max_rad: float
    theta_rate_max_rad_s: float

    @property
    def kind(self) -> str:
        return "rate_limited"

    @property
    def duration_s(self) -> float:
        return self.profile.duration_s

    @property
    def segments(self) -> tuple[JerkSegment, ...]:
        """Ball-jerk segments; the servo rate on each is jerk/γ."""
        return self.profile.segments

    def sample(self, time_s: np.ndarray) -> PlanSamples:
        t = np.atleast_1d(np.asarray(time_s, dtype=float))
        position, velocity, acceleration, jerk = self.profile.evaluate(t)
        states = np.empty((t.size, N_STATES))
        states[:, THETA] = acceleration / self.gamma_m_s2_per_rad
        theta_rate = jerk / self.gamma_m_s2_per_rad
        states[:, THETA_RATE] = theta_rate
        states[:, BALL_VELOCITY] = velocity
        states[:, BALL_POSITION] = position
        return PlanSamples(time_s=t, states=states, input_v=self.beta_v_s_per_rad * theta_rate)


def plan_rate_limited(
    constants: PhysicalConstants,
    theta_max_rad: float,
    theta_rate_max_rad_s: float,
    initial_state: np.ndarray,
) -> RateLimitedPlan:
    """Minimum-time path from ``initial_state`` (θ, θ̇, ẋ, x) to rest at 0 under the servo bounds.

    The initial servo angle θ0 sets the ball's initial acceleration γ·θ0; the initial servo rate
    is not used (the servo rate is the input here and may jump). Raises PlanningError for
    non-positive bounds or |θ0| > θmax.
    """
    start = np.asarray(initial_state, dtype=float)
    if start.shape != (N_STATES,):
        raise PlanningError(f"initial state must have shape ({N_STATES},), got {start.shape}")
    if not (theta_max_rad > 0.0 and theta_rate_max_rad_s > 0.0):
        raise PlanningError(
            f"servo bounds must be positive, got θmax = {theta_max_rad} rad, "
            f"θ̇max = {theta_rate_max_rad_s} rad/s"
        )
    gamma = constants.gamma
    if abs(start[THETA]) > theta_max_rad:
        raise PlanningError(
            f"initial servo angle {start[THETA]:.6g} rad is beyond θmax = {theta_max_rad:.6g} rad"
        )
    profile = solve_jerk_profile(
        position_m=start[BALL_POSITION],
        velocity_m_s=start[BALL_VELOCITY],
        # Clamp rounding: |θ0| <= θmax was checked above, the product may still round past A.
        acceleration_m_s2=float(
            np.clip(gamma * start[THETA], -abs(gamma) * theta_max_rad, abs(gamma) * theta_max_rad)
        ),
        acceleration_max_m_s2=abs(gamma) * theta_max_rad,
        jerk_max_m_s3=abs(gamma) * theta_rate_max_rad_s,
    )
    return RateLimitedPlan(
        profile=profile,
        gamma_m_s2_per_rad=gamma,
        beta_v_s_per_rad=constants.beta,
        theta_max_rad=theta_max_rad,
        theta_rate_max_rad_s=theta_rate_max_rad_s,
    )
