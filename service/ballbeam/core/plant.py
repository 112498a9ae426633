"""The SRV02 ball-and-beam as the emulator and the offline simulation run it.

Beyond the design model: ±V saturation then a dead zone before the motor (paper figure 2),
the true plant's own gains (model mismatch), optionally the nonlinear ball (beam geometry,
ball stopping at the beam ends, servo hard stops), and sensors that report raw encoder and
ADC counts with band-limited noise on the ball track. Pure: the caller owns state and RNG.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from ballbeam.core.model import BALL_POSITION, BALL_VELOCITY, THETA, THETA_RATE, LinearModel

ADC_COUNT_LIMIT = 32767  # signed 16-bit frame field


@dataclass(frozen=True)
class EmulatedPlant:
    """Everything the emulated plant's physics needs, SI units: the true plant's gains (which
    may differ from the design model's) and its nonlinearities and sensors.
    """

    alpha: float  # true volts → servo acceleration [rad/s² per V]
    alpha_beta: float  # true back-EMF damping [1/s]
    gamma: float  # true servo angle → ball acceleration, linear ball [m/s² per rad]
    ball_gain_scale: float  # true / model ball gain, applied to the nonlinear ball too
    saturation_v: float
    deadzone_v: float
    nonlinear_ball: bool
    gravity_m_per_s2: float
    arm_to_beam_ratio: float  # r / L
    beam_half_length_m: float
    hard_stop_rad: float
    substep_s: float
    encoder_step_rad: float
    adc_step_m: float
    adc_count_limit: int
    position_noise_m: float
    noise_pole: float  # AR(1) pole of the band-limited sensor noise at the sensor rate
    # Taps: (physics step n, Δv [m/s]), n ascending: at plant time n·substep_s from the ball's
    # release its velocity jumps by Δv (``tap_step``).
    taps: tuple[tuple[int, float], ...] = ()


# Times are given in seconds and the steps counted: a time on a step (1.0 s = 10,000 steps of
# 0.1 ms, which the division makes 10,000.000000000002) is that step, not the next.
_STEP_TOLERANCE = 1e-9


def tap_step(time_s: float, substep_s: float) -> int:
    """The first physics step at or after ``time_s`` (≥ 1: a tap lands after the start)."""
    return max(1, math.ceil(time_s / substep_s - _STEP_TOLERANCE))


# The voltage frame carries the command in 1 mV steps (the DBC's Voltage signal; its look-ahead
# slots too): a plant drives the command as received, so the offline loop rounds it alike.
COMMAND_STEP_V = 0.001


def command_as_received(voltage_v: float) -> float:
    """The voltage a plant gets for ``voltage_v`` sent in a command frame (1 mV, rounded half
    to even, decoded as raw × step: the frame codec's own arithmetic)."""
    return round(voltage_v / COMMAND_STEP_V) * COMMAND_STEP_V


def lookahead_as_received(voltage_v: float) -> float:
    """The same for a look-ahead slot, which the codec decodes as raw / 1000."""
    return round(voltage_v * 1000.0) / 1000.0


class SensorReading(NamedTuple):
    """What the sensor frame carries: raw integer counts (a named tuple: one is built every
    cycle, several times faster than a frozen dataclass)."""

    angle_counts: int
    position_counts: int


def drive_voltage(params: EmulatedPlant, command_v: float) -> float:
    """Voltage reaching the motor: saturate, then remove the dead zone (paper figure 2)."""
    saturated = min(max(command_v, -params.saturation_v), params.saturation_v)
    if abs(saturated) <= params.deadzone_v:
        return 0.0
    return saturated - math.copysign(params.deadzone_v, saturated)


class PlantPhysics:
    """Integrates the plant in fixed substeps. Linear ball: exact ZOH over the held voltage;
    nonlinear ball: RK4 per substep. The servo hard stops and the beam ends are physical and
    apply to both (the linear ball checks them once per call, the nonlinear one per substep)."""

    def __init__(self, params: EmulatedPlant) -> None:
        self.params = params
        self._tap_steps = np.array([step for step, _ in params.taps], dtype=np.int64)
        true_model = LinearModel.from_gains(
            params.alpha, params.alpha_beta, params.gamma, C=np.zeros((2, 4))
        )
        step = true_model.discretize(params.substep_s)
        self._Ad = step.Ad
        self._bd = step.Bd[:, 0]
        # n substeps at a held voltage in one product (lock-step advances a whole period).
        self._powers: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        # θ after each of n substeps: rows of Ad^j and bd_j, j = 1..n (the safety check).
        self._theta_rows: dict[int, tuple[np.ndarray, np.ndarray]] = {}

    def advance(
        self, state: np.ndarray, command_v: float, substeps: int, from_step: int = 0
    ) -> np.ndarray:
        """State after ``substeps`` substeps holding ``command_v``. ``from_step``: the physics
        steps done since the ball's release (the plant's clock): taps due on the way apply."""
        drive_v = drive_voltage(self.params, command_v)
        taps = self._taps_within(from_step, substeps)
        if not taps:
            return self._advance_driven(state, drive_v, substeps)
        for steps, change_m_s, _ in taps:
            state = self._tap(self._advance_driven(state, drive_v, steps), change_m_s)
        return self._advance_driven(state, drive_v, from_step + substeps - taps[-1][2])

    def _taps_within(self, from_step: int, substeps: int) -> list[tuple[int, float, int]]:
        """The taps at steps n, from_step < n ≤ from_step + substeps: (steps to go from the
        one before, Δv, n)."""
        steps = self._tap_steps
        if not steps.size or substeps <= 0:
            return []
        first, last = (int(i) for i in np.searchsorted(
            steps, (from_step, from_step + substeps), side="right"
        ))
        taps, done = [], from_step
        for step, change_m_s in self.params.taps[first:last]:
            taps.append((step - done, change_m_s, step))
            done = step
        return taps

    @staticmethod
    def _tap(state: np.ndarray, change_m_s: float) -> np.ndarray:
        tapped = np.array(state, dtype=float)
        tapped[BALL_VELOCITY] += change_m_s
        return tapped

    def _advance_driven(self, state: np.ndarray, drive_v: float, substeps: int) -> np.ndarray:
        if not self.params.nonlinear_ball:
            if substeps <= 0:
                return state
            transition = self._powers.get(substeps)
            if transition is None:
                Ad_n, bd_n = np.eye(4), np.zeros(4)
                for _ in range(substeps):
                    Ad_n, bd_n = self._Ad @ Ad_n, self._Ad @ bd_n + self._bd
                transition = self._powers.setdefault(substeps, (Ad_n, bd_n))
            result: np.ndarray = transition[0] @ state + transition[1] * drive_v
            return self._apply_stops(result)
        for _ in range(substeps):
            state = self._rk4(state, drive_v)
            state = self._apply_stops(state)
        return state

    def advance_with_peak(
        self, state: np.ndarray, command_v: float, substeps: int, from_step: int = 0
    ) -> tuple[np.ndarray, float]:
        """``advance``, and the largest |θ| at any of its physics steps (its end included): the
        safety promise is per physics step, not per sample."""
        taps = self._taps_within(from_step, substeps)
        if not taps:
            return self._advance_with_peak(state, command_v, substeps)
        peak = 0.0
        for steps, change_m_s, _ in taps:
            state, step_peak = self._advance_with_peak(state, command_v, steps)
            state, peak = self._tap(state, change_m_s), max(peak, step_peak)
        state, step_peak = self._advance_with_peak(
            state, command_v, from_step + substeps - taps[-1][2]
        )
        return state, max(peak, step_peak)

    def _advance_with_peak(
        self, state: np.ndarray, command_v: float, substeps: int
    ) -> tuple[np.ndarray, float]:
        if not self.params.nonlinear_ball:
            rows = self._theta_rows.get(substeps)
            if rows is None:
                Ad_j, bd_j = np.eye(4), np.zeros(4)
                theta_rows, theta_per_v = [], []
                for _ in range(substeps):
                    Ad_j, bd_j = self._Ad @ Ad_j, self._Ad @ bd_j + self._bd
                    theta_rows.append(Ad_j[THETA].copy())
                    theta_per_v.append(bd_j[THETA])
                rows = self._theta_rows.setdefault(
                    substeps, (np.array(theta_rows), np.array(theta_per_v))
                )
            drive_v = drive_voltage(self.params, command_v)
            result = self._advance_driven(state, drive_v, substeps)
            # The array's own max: np.max's dispatch cost more than the reduction (sweeps).
            peak = float(np.abs(rows[0] @ state + rows[1] * drive_v).max()) if substeps else 0.0
            # The hard stop may hold θ below the free motion: the larger figure is kept.
            return result, max(peak, abs(float(result[THETA])))
        drive_v = drive_voltage(self.params, command_v)
        peak = 0.0
        for _ in range(substeps):
            state = self._apply_stops(self._rk4(state, drive_v))
            peak = max(peak, abs(float(state[THETA])))
        return state, peak

    def _derivative(self, state: np.ndarray, drive_v: float) -> np.ndarray:
        p = self.params
        theta, theta_rate, ball_velocity, ball_position = state
        theta_accel = p.alpha * drive_v - p.alpha_beta * theta_rate
        sin_phi = p.arm_to_beam_ratio * math.sin(theta)
        cos_phi = math.sqrt(1.0 - sin_phi * sin_phi)
        phi_rate = p.arm_to_beam_ratio * math.cos(theta) * theta_rate / cos_phi
        # Rolling solid ball: ẍ = (5/7)(x·φ̇² − g·sin φ); γ of the linear model is its slope.
        ball_accel = (
            p.ball_gain_scale
            * (5.0 / 7.0)
            * (ball_position * phi_rate**2 - p.gravity_m_per_s2 * sin_phi)
        )
        return np.array([theta_rate, theta_accel, ball_accel, ball_velocity])

    def _rk4(self, state: np.ndarray, drive_v: float) -> np.ndarray:
        h = self.params.substep_s
        k1 = self._derivative(state, drive_v)
        k2 = self._derivative(state + 0.5 * h * k1, drive_v)
        k3 = self._derivative(state + 0.5 * h * k2, drive_v)
        k4 = self._derivative(state + h * k3, drive_v)
        result: np.ndarray = state + (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
        return result

    def _apply_stops(self, state: np.ndarray) -> np.ndarray:
        p = self.params
        if abs(state[THETA]) <= p.hard_stop_rad and abs(state[BALL_POSITION]) <= (
            p.beam_half_length_m
        ):
            return state
        state = state.copy()
        if abs(state[THETA]) > p.hard_stop_rad:
            state[THETA] = math.copysign(p.hard_stop_rad, state[THETA])
            if state[THETA_RATE] * state[THETA] > 0:
                state[THETA_RATE] = 0.0
        if abs(state[BALL_POSITION]) > p.beam_half_length_m:
            state[BALL_POSITION] = math.copysign(p.beam_half_length_m, state[BALL_POSITION])
            if state[BALL_VELOCITY] * state[BALL_POSITION] > 0:
                state[BALL_VELOCITY] = 0.0
        return state


def next_noise(params: EmulatedPlant, noise_m: float, rng: np.random.Generator) -> float:
    """One sensor-period step of first-order band-limited noise with stationary std σ."""
    a = params.noise_pole
    return a * noise_m + math.sqrt(1.0 - a * a) * params.position_noise_m * rng.standard_normal()


def read_sensors(params: EmulatedPlant, state: np.ndarray, noise_m: float) -> SensorReading:
    """Encoder counts of θ and ADC counts of the (noisy) ball position, clipped to the ADC."""
    angle_counts = round(float(state[THETA]) / params.encoder_step_rad)
    position_counts = round((float(state[BALL_POSITION]) + noise_m) / params.adc_step_m)
    limit = params.adc_count_limit
    return SensorReading(angle_counts, max(-limit - 1, min(limit, position_counts)))


def initial_noise(params: EmulatedPlant, rng: np.random.Generator) -> float:
    return float(params.position_noise_m * rng.standard_normal())
