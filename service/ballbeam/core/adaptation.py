"""What the loop learns about the plant while it runs: the ball's gain (and with it the path's
pace), the motor's dead zone and the position sensor's noise level.

All are plain float arithmetic, like the rest of the cycle (``control.py``), and their
parameters are recorded with the design, so a run replays bit for bit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from ballbeam.core.model import Row4

FitSums = tuple[float, ...]  # see BallGainAdaptation.add_sample, .advance
EMPTY_FIT: FitSums = (0.0,) * 12
MIN_RESYNC_SPEED_M_S = 0.01  # below this a position error says little about a delay


@dataclass(frozen=True)
class BallGainAdaptation:
    """The ball's gain γ (ẍ = γ·θ) estimated while the plan runs, and the path followed at the
    pace that gain allows.

    A minimum-time path asks for the full angle on its arcs; a ball that rolls slower or faster
    than the model (a ball-gain error, the sine of a large angle) cannot follow it in time, and
    a tracker that insists rides the limit past the plan's switch and overshoots. A path's
    accelerations scale with the square of the pace at which it is played, so played at pace
    √(γ̂/γ) it asks of the true ball exactly the angles it asked of the model: the path stays
    the plan's, only its clock (τ, in cycles) runs at that pace. The observer predicts with γ̂.

    The ball's position is x(t) = x0 + v0·t + γ·G(t), G the double integral of the measured
    angle, so regressing the measured position on (1, t, G) gives γ with x0 and v0 (no
    differentiation of a noisy signal). The sums of the normal equations are the state; the
    3 × 3 solve is Cramer's rule, plain floats. The estimate counts once its standard error
    (from the design's position noise) is below ``confidence`` of |γ_design|; it is used only
    while the plan runs (afterwards the angle stays small and says little about γ).
    """

    design_gamma: float  # γ of the design model [m/s² per rad]
    position_noise_m: float
    confidence: float  # relative standard error below which the estimate is used
    min_ratio: float
    max_ratio: float
    period_s: float
    until_cycle: int  # the plan's end (path cycles)
    back_emf_v_s_per_rad: float  # β of the servo model (θ̈ = α·u − αβ·θ̇): the pace's feedforward
    pace_step_per_cycle: float  # how fast the pace may change (a jump of pace is a step of u)
    # Clock re-synchronisation on the path's accelerating limit arcs (see clock_shift_cycles).
    resync_rate_per_cycle: float = 0.0  # fraction of the measured lag taken up each cycle (0: off)
    resync_max_per_cycle: float = 0.0  # largest shift of the clock in one cycle [path cycles]
    arc_theta_rad: float = 0.0  # |θ_d| beyond this, with θ̇_d still, is a limit arc

    def clock_shift_cycles(self, estimate: Row4, reference: Row4, pace: float) -> float:
        """How far to move the path's clock this cycle, besides the pace [path cycles].

        Until the estimate is confident the path runs at the model's pace, and a slower ball
        falls behind it (ball gain 0.8: ~25 ms by the first arc); the pace alone keeps that lag
        to the end, and the ball overshoots. On an arc the angle is held at the limit, so the
        tracker cannot win the time back, but the clock can: θ_d is constant there, so moving
        τ moves only the ball's reference, not the servo's. A ball behind by δ seconds sits
        where the reference was δ ago, x̂ ≈ X − V·δ (X, V the reference played at the pace),
        so δ = −(x̂ − X)/V. Only on accelerating arcs, where the arc's acceleration γ·θ_d has
        the sign of V: on a decelerating one an error is mostly surplus speed, not a delay, and
        moving the clock would hide it.
        """
        if self.resync_rate_per_cycle == 0.0:
            return 0.0
        theta_d, theta_rate_d, velocity_d, position_d = reference
        if abs(theta_rate_d) > 1e-3 or abs(theta_d) < self.arc_theta_rad:
            return 0.0
        velocity = pace * velocity_d
        if velocity * (self.design_gamma * theta_d) <= 0.0 or abs(velocity) < MIN_RESYNC_SPEED_M_S:
            return 0.0
        lag_s = -(estimate[3] - position_d) / velocity
        shift = self.resync_rate_per_cycle * lag_s * pace / self.period_s
        limit = self.resync_max_per_cycle
        return -min(max(shift, -limit), limit)

    def pace(self, ratio: float, previous_pace: float) -> float:
        """√ratio, approached from the previous cycle's pace by at most one pace step."""
        target = math.sqrt(ratio) if ratio != 1.0 else 1.0
        step = self.pace_step_per_cycle
        return min(max(target, previous_pace - step), previous_pace + step)

    def add_sample(self, sums: FitSums, position_m: float) -> FitSums:
        """Accumulate the normal equations with a measured position at the current instant."""
        (n, s_t, s_tt, s_g, s_tg, s_gg, s_x, s_tx, s_gx, t, g1, g) = sums
        return (
            n + 1.0, s_t + t, s_tt + t * t, s_g + g, s_tg + t * g, s_gg + g * g,
            s_x + position_m, s_tx + t * position_m, s_gx + g * position_m, t, g1, g,
        )

    def advance(self, sums: FitSums, theta_rad: float) -> FitSums:
        """One period on: t, and the angle held over it integrated twice (exactly, as the
        zero-order hold the plant sees). Every cycle advances, measured or not, so that t and G
        are the plant's whatever frames were lost or periods skipped."""
        dt = self.period_s
        t, g1, g2 = sums[9:]
        return (
            *sums[:9], t + dt, g1 + theta_rad * dt, g2 + g1 * dt + 0.5 * theta_rad * dt * dt
        )

    def ratio(self, sums: FitSums) -> float:
        """γ̂ / γ_design once the fit is confident, else 1."""
        (n, s_t, s_tt, s_g, s_tg, s_gg, s_x, s_tx, s_gx) = sums[:9]
        # Cofactors of the symmetric normal matrix [[n, s_t, s_g], [s_t, s_tt, s_tg],
        # [s_g, s_tg, s_gg]].
        c00 = s_tt * s_gg - s_tg * s_tg
        c01 = s_tg * s_g - s_t * s_gg
        c02 = s_t * s_tg - s_tt * s_g
        det = n * c00 + s_t * c01 + s_g * c02
        if det <= 0.0:
            return 1.0
        c22 = n * s_tt - s_t * s_t
        c12 = s_t * s_g - n * s_tg
        gamma = (c02 * s_x + c12 * s_tx + c22 * s_gx) / det
        variance = self.position_noise_m * self.position_noise_m * c22 / det
        design = self.design_gamma
        if variance < 0.0 or variance > (self.confidence * design) ** 2:
            return 1.0
        return min(max(gamma / design, self.min_ratio), self.max_ratio)


DeadZoneWindow = tuple[float, float, float, float, float, float]
"""(sign of the command, start angle, model angle, model rate, Σ|command|, cycles): the servo
as the model moves it since the command took its sign, beside what the encoder shows."""


@dataclass(frozen=True)
class DeadZoneLearning:
    """The motor's dead zone d learnt from how far the servo moves under small commands.

    The command is compensated for d̂ (``ControllerDesign.compensated``) and the observer
    predicts with the drive d̂ leaves. While the command keeps its sign the servo model is run
    open loop from the window's start beside the measured angle; when the sign changes, the
    window is judged if the model moved the servo by at least ``min_motion_rad`` (several
    encoder counts: sub-count motion is invisible to the encoder and would read as a dead zone);
    a long window is judged, and a new one opened, each time the model has moved the servo by
    ``judge_motion_rad``.
    A drive s̄ − d̂ that moved the model by Δθ_model moved the servo by Δθ_measured, so the
    drive the motor really got is (s̄ − d̂)·Δθ_measured/Δθ_model, and the dead zone that explains
    it is d = s̄ − that; d̂ moves a fraction ``rate`` of the way there, within [0, ``max_v``].
    Only windows with a mean command below ``below_v`` teach it: there the dead zone is most of
    the model's error, while on full-scale moves a motor-gain error of a few per cent would be
    taken for volts of dead zone.
    """

    min_motion_rad: float
    judge_motion_rad: float  # a window that moved the model this far is judged and restarted
    rate: float
    below_v: float
    max_v: float
    # Real time: the window's model assumes each command lands when the cycle sends it; a loop
    # running later moves the servo later than that, and the difference reads as dead zone
    # (under load it had learnt 0.03 V for the plant's 0.1 V). Beyond this recent worst
    # lateness [ns] no window opens. Offline and in lock-step the lateness is 0.
    max_lateness_ns: float = math.inf

    def learns_at(self, worst_lateness_ns: int) -> bool:
        """May a window run while the loop's recent worst lateness is ``worst_lateness_ns``?"""
        return worst_lateness_ns <= self.max_lateness_ns

    def step(
        self,
        deadzone_v: float,
        window: DeadZoneWindow | None,
        sent_v: float,
        drive_v: float,
        theta_measured_rad: float,
        theta_rate_rad_s: float,
        servo: tuple[float, float, float, float, float, float],
    ) -> tuple[float, DeadZoneWindow | None]:
        """One cycle: ``sent_v`` and ``drive_v`` (its modelled drive) the command held over the
        coming period, ``theta_measured_rad`` the angle measured now; ``servo`` the model's
        (a00, a01, a10, a11, b0, b1) over one period."""
        sign = 1.0 if sent_v > 0.0 else -1.0 if sent_v < 0.0 else 0.0
        if window is not None and (
            window[0] != sign or window[0] * (window[2] - window[1]) >= self.judge_motion_rad
        ):
            deadzone_v = self._judge(deadzone_v, window, theta_measured_rad)
            window = None
        if sign == 0.0:
            return deadzone_v, None
        if window is None:
            window = (sign, theta_measured_rad, theta_measured_rad, theta_rate_rad_s, 0.0, 0.0)
        _, start, theta, rate, total_v, cycles = window
        a00, a01, a10, a11, b0, b1 = servo
        return deadzone_v, (
            sign, start, a00 * theta + a01 * rate + b0 * drive_v,
            a10 * theta + a11 * rate + b1 * drive_v, total_v + abs(sent_v), cycles + 1.0,
        )

    def _judge(self, deadzone_v: float, window: DeadZoneWindow, theta_now_rad: float) -> float:
        sign, start, theta_model, _, total_v, cycles = window
        modelled = sign * (theta_model - start)
        if modelled < self.min_motion_rad:
            return deadzone_v
        mean_v = total_v / cycles
        if mean_v >= self.below_v or mean_v <= deadzone_v:
            return deadzone_v
        measured = min(max(sign * (theta_now_rad - start) / modelled, 0.0), 2.0)
        explained_v = mean_v - (mean_v - deadzone_v) * measured
        learnt = deadzone_v + self.rate * (explained_v - deadzone_v)
        return min(max(learnt, 0.0), self.max_v)


Gain = tuple[tuple[float, float], tuple[float, float], tuple[float, float], tuple[float, float]]


@dataclass(frozen=True)
class NoiseAdaptation:
    """The position sensor's noise level measured while the run goes, and the filter designed
    for it.

    The observer is a steady-state Kalman filter for an assumed position noise σ; a sensor
    noisier than that is followed too closely, and the tracker turns the noise into command
    chatter (5× noise: input variation 3.4 times the plan's) and into a ball that will not rest.
    The second difference of the measured position, y[k] − 2y[k−1] + y[k−2], is noise alone
    (the ball's own motion adds well under a micrometre in a period), so its mean square,
    smoothed over ``smoothing_per_cycle``⁻¹ cycles, against the value the design's noise model
    predicts (``expected_square``) measures the noise level m = σ_actual/σ. The filter's gains
    are designed at the levels ``levels`` (tracking and, if any, rest) and interpolated at m,
    clamped to the table (never lighter than the design's own).
    """

    levels: tuple[float, ...]
    tracking_gains: tuple[Gain, ...]
    rest_gains: tuple[Gain, ...] | None
    expected_square: float  # E[(Δ²y)²] under the design's noise model [measurement units²]
    smoothing_per_cycle: float

    def smoothed(self, mean_square: float, second_difference: float) -> float:
        return mean_square + self.smoothing_per_cycle * (
            second_difference * second_difference - mean_square
        )

    def level(self, mean_square: float) -> float:
        ratio = mean_square / self.expected_square
        level = math.sqrt(ratio) if ratio > 1.0 else 1.0
        return min(max(level, self.levels[0]), self.levels[-1])

    def gain(self, level: float, rest: bool) -> Gain:
        """The Kalman gain at noise level ``level``, interpolated between the table's."""
        table = self.rest_gains if rest and self.rest_gains is not None else self.tracking_gains
        levels = self.levels
        upper = 1
        while upper < len(levels) - 1 and levels[upper] < level:
            upper += 1
        low, high = levels[upper - 1], levels[upper]
        f = min(max((level - low) / (high - low), 0.0), 1.0)
        a, b = table[upper - 1], table[upper]
        return (
            (a[0][0] + f * (b[0][0] - a[0][0]), a[0][1] + f * (b[0][1] - a[0][1])),
            (a[1][0] + f * (b[1][0] - a[1][0]), a[1][1] + f * (b[1][1] - a[1][1])),
            (a[2][0] + f * (b[2][0] - a[2][0]), a[2][1] + f * (b[2][1] - a[2][1])),
            (a[3][0] + f * (b[3][0] - a[3][0]), a[3][1] + f * (b[3][1] - a[3][1])),
        )
