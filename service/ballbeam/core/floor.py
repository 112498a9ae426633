"""A plant's own floor: the least time *its* true model needs to bring the ball to rest at a
target (docs/design.md §8). Under model mismatch this, not the design model's T*, is the limit a
controller can be held to.

Linear ball: the full 4-state linear model with the plant's true α, αβ and γ (the plant's
``motor_gain_scale`` multiplies α and αβ = α·β, so β and the steady slope u/β stay; its
``ball_gain_scale`` multiplies γ), from the same start, with the drive the motor can see: the
command bound less the dead zone (a dead zone d before the motor turns a command u into
u − d·sign u, so ±(U − d) is exactly the drive range), zero margins, on the planner's grid. The
model is invariant to a shift of x, so a target x_t is planned from x0 − x_t.

Nonlinear ball (``ẍ = k(5/7)(x·φ̇² − g sin φ)``, ``sin φ = (r/L) sin θ``): its gravity term is
``γ sin θ``, γ the small-angle gain. Over |θ| ≤ θmax it lies between the chord ``γ_c θ``,
``γ_c = γ sin θmax / θmax`` (0.868 γ at 52°), and the tangent ``γ θ``; on the limit arcs, where
a minimum-time path spends most of its time, it is exactly ``γ_c θmax``. The floor taken is the
linear model's with γ replaced by γ_c (from the paper's start: 1.851 s, against 1.746 s with γ).
The small-angle model gives the ball more acceleration than it has at every angle short of
the limit, so its floor sits ~6 % below anything the ball can do: a bound no controller of this
ball could approach. The chord floor is not a proven bound (no convex model contains θ ↦ sin θ
without granting acceleration at θ = 0, and the centripetal term x·φ̇², up to ~0.04 m/s² at the
servo's top rate, is left out); it is checked against an independent answer instead
(tests/test_floor.py): the nonlinear ball's own minimum time by sequential linear programming
(the servo exact, sin θ linearised about the last iterate, the centripetal term included), whose
inputs, played open loop on the emulator's physics, do bring the ball to rest. On a 10 ms grid it
needs at most one step more than the chord floor, and no path two steps shorter was found.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ballbeam.core.model import BALL_POSITION, LinearModel
from ballbeam.core.planning.time_optimal import plan_time_optimal
from ballbeam.errors import ConfigError

LINEAR = "linear model, true α and γ"
NONLINEAR_CHORD = "nonlinear ball: linear model with γ·sin θmax/θmax (chord over ±θmax)"


@dataclass(frozen=True)
class OwnFloor:
    """The floor and what it was computed with."""

    time_s: float
    drive_limit_v: float  # the command bound less the dead zone
    alpha: float  # rad/s² per V
    alpha_beta: float  # 1/s
    gamma: float  # m/s² per rad: the plant's, or its chord gain for the nonlinear ball
    step_s: float
    method: str


def chord_ball_gain(gamma: float, theta_max_rad: float) -> float:
    """γ·sin θmax / θmax: the linear gain that gives the nonlinear ball's own acceleration on
    the limit arcs (and less than it at any smaller angle)."""
    if not 0.0 < theta_max_rad <= math.pi / 2:
        raise ConfigError(f"theta_max_rad must be in (0, π/2], got {theta_max_rad}")
    return gamma * math.sin(theta_max_rad) / theta_max_rad


def own_floor(
    true_model: LinearModel,
    initial_state: np.ndarray,
    *,
    voltage_limit_v: float,
    deadzone_v: float,
    theta_max_rad: float,
    step_s: float,
    target_m: float = 0.0,
    nonlinear_ball: bool = False,
    max_duration_s: float = 20.0,
) -> OwnFloor:
    """The minimum time of ``true_model`` (a plant's true linear model) from ``initial_state``
    (θ, θ̇, ẋ, x) to rest at x = ``target_m``, under ±(``voltage_limit_v`` − ``deadzone_v``)
    of drive and ±``theta_max_rad``, on a grid of ``step_s``.

    Raises PlanningError where no path exists (a start beyond the angle limit, too fast to
    stop), ConfigError where the dead zone leaves no drive.
    """
    drive_v = voltage_limit_v - deadzone_v
    if not drive_v > 0.0:
        raise ConfigError(
            f"a {deadzone_v} V dead zone leaves no drive under the {voltage_limit_v} V limit"
        )
    alpha = float(true_model.B[1, 0])
    alpha_beta = float(-true_model.A[1, 1])
    gamma = float(true_model.A[2, 0])
    method = LINEAR
    model = true_model
    if nonlinear_ball:
        gamma = chord_ball_gain(gamma, theta_max_rad)
        method = NONLINEAR_CHORD
        model = LinearModel.from_gains(alpha, alpha_beta, gamma, true_model.C)
    shifted = np.array(initial_state, dtype=float).reshape(4)
    shifted[BALL_POSITION] -= target_m
    plan = plan_time_optimal(
        model,
        shifted,
        voltage_limit_v=drive_v,
        theta_max_rad=theta_max_rad,
        step_s=step_s,
        max_duration_s=max_duration_s,
    )
    return OwnFloor(
        time_s=plan.duration_s,
        drive_limit_v=drive_v,
        alpha=alpha,
        alpha_beta=alpha_beta,
        gamma=gamma,
        step_s=step_s,
        method=method,
    )
