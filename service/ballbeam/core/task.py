"""The task: where the ball is to be over time, x_r(t), and the reference's flat outputs.

Four shapes: a fixed target (the paper's task, at 0), a step schedule, a square wave (a step
schedule written as a period) and a sine. Each gives

- ``target_at(t)``: x_r(t) [m] (a step's new target holds from its instant on);
- ``reference_at(t)``: x_r and its first four derivatives (:class:`FlatOutputs`), from which
  :func:`flat_feedforward` gives the servo angle, its rate and the voltage that hold the ball on
  the reference (ẍ = γθ, so θ = ẍ/γ, θ̇ = x⃛/γ, θ̈ = x⁗/γ, u = (θ̈ + αβ θ̇)/α); a step's
  derivatives are 0 (its jumps are for a re-planner to join, not for a feedforward);
- ``change_times_s(start_s, end_s)``: the instants t, start_s < t ≤ end_s, at which a step
  target changes (a controller re-plans there), and ``next_change_after(t)``.

Times are on the run's clock (0: the first control cycle). ``t`` may be a float or an array
(N,); the answer has its shape.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from typing import Literal, overload

import numpy as np

from ballbeam.errors import ConfigError

TaskKind = Literal["fixed", "steps", "sine"]


@dataclass(frozen=True)
class FlatOutputs:
    """x_r and its derivatives at the asked times (floats, or arrays (N,)): position [m],
    velocity [m/s], acceleration [m/s²], jerk [m/s³], snap [m/s⁴]."""

    position_m: np.ndarray
    velocity_m_s: np.ndarray
    acceleration_m_s2: np.ndarray
    jerk_m_s3: np.ndarray
    snap_m_s4: np.ndarray


class _Reference:
    """What every task shape answers; a shape defines ``_positions`` and ``_flat`` over arrays
    and ``change_times_s``."""

    kind: TaskKind

    @overload
    def target_at(self, time_s: float) -> float: ...
    @overload
    def target_at(self, time_s: np.ndarray) -> np.ndarray: ...
    def target_at(self, time_s: float | np.ndarray) -> float | np.ndarray:
        """x_r at ``time_s`` [m]."""
        times = np.asarray(time_s, dtype=float)
        positions = self._positions(np.atleast_1d(times))
        return float(positions[0]) if times.ndim == 0 else positions.reshape(times.shape)

    def reference_at(self, time_s: float | np.ndarray) -> FlatOutputs:
        """x_r and its first four derivatives at ``time_s`` (each of ``time_s``'s shape)."""
        times = np.asarray(time_s, dtype=float)
        columns = self._flat(np.atleast_1d(times))
        shaped = [column.reshape(times.shape) for column in columns]
        return FlatOutputs(*shaped)

    def next_change_after(self, time_s: float) -> float | None:
        """The first instant after ``time_s`` at which the target changes; None: none."""
        changes = self.change_times_s(time_s, math.inf)
        return float(changes[0]) if changes.size else None

    def change_times_s(self, start_s: float, end_s: float) -> np.ndarray:
        raise NotImplementedError

    def _positions(self, times_s: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def _flat(self, times_s: np.ndarray) -> tuple[np.ndarray, ...]:
        positions = self._positions(times_s)
        zeros = np.zeros_like(positions)
        return positions, zeros, zeros, zeros, zeros


@dataclass(frozen=True)
class FixedTarget(_Reference):
    """One target for the whole run."""

    target_m: float = 0.0
    kind: TaskKind = "fixed"

    def change_times_s(self, start_s: float, end_s: float) -> np.ndarray:
        return np.empty(0)

    def _positions(self, times_s: np.ndarray) -> np.ndarray:
        return np.full(times_s.shape, self.target_m)


@dataclass(frozen=True)
class StepSchedule(_Reference):
    """targets_m[i] from times_s[i] on; times ascend from 0 (before 0: the first target)."""

    times_s: tuple[float, ...]
    targets_m: tuple[float, ...]
    kind: TaskKind = "steps"

    def __post_init__(self) -> None:
        if not self.times_s or len(self.times_s) != len(self.targets_m):
            raise ConfigError("a step schedule needs as many targets as times, at least one")
        if self.times_s[0] != 0.0 or any(
            b <= a for a, b in itertools.pairwise(self.times_s)
        ):
            raise ConfigError("a step schedule's times must ascend from 0")

    def change_times_s(self, start_s: float, end_s: float) -> np.ndarray:
        times = np.asarray(self.times_s[1:])
        return times[(times > start_s) & (times <= end_s)]

    def _positions(self, times_s: np.ndarray) -> np.ndarray:
        index = np.searchsorted(np.asarray(self.times_s), times_s, side="right") - 1
        return np.asarray(self.targets_m)[np.maximum(index, 0)]


@dataclass(frozen=True)
class SquareWave(_Reference):
    """offset + amplitude for the first half period, offset − amplitude for the second, and
    so on: a step schedule whose changes are at every half period k·period/2 (k ≥ 1)."""

    amplitude_m: float
    period_s: float
    offset_m: float = 0.0
    kind: TaskKind = "steps"

    def __post_init__(self) -> None:
        if not (self.period_s > 0 and math.isfinite(self.period_s)):
            raise ConfigError(f"a square wave needs a period > 0, got {self.period_s}")

    @property
    def half_period_s(self) -> float:
        return 0.5 * self.period_s

    def as_steps(self, until_s: float) -> StepSchedule:
        """The same reference up to ``until_s`` as an explicit step schedule."""
        index = np.arange(max(int(self._halves(np.array([until_s]))[0]), 0) + 1)
        return StepSchedule(
            times_s=tuple((index * self.half_period_s).tolist()),
            targets_m=tuple(self._level(index).tolist()),
        )

    def change_times_s(self, start_s: float, end_s: float) -> np.ndarray:
        if not end_s > start_s:
            return np.empty(0)
        first = max(int(self._halves(np.array([start_s]))[0]) + 1, 1)
        if math.isinf(end_s):
            return np.array([first * self.half_period_s])
        last = int(self._halves(np.array([end_s]))[0])
        return np.arange(first, last + 1) * self.half_period_s

    def _halves(self, times_s: np.ndarray) -> np.ndarray:
        """The index k of the half period [k·h, (k+1)·h) each time lies in, judged against
        the change instants k·h themselves (so that t = k·h, however rounded, is in k)."""
        half = self.half_period_s
        k = np.floor(times_s / half)
        k = np.where((k + 1) * half <= times_s, k + 1, k)
        k = np.where(k * half > times_s, k - 1, k)
        return k

    def _level(self, halves: np.ndarray) -> np.ndarray:
        sign = np.where(np.mod(halves, 2) == 0, 1.0, -1.0)
        return self.offset_m + self.amplitude_m * sign

    def _positions(self, times_s: np.ndarray) -> np.ndarray:
        return self._level(np.maximum(self._halves(times_s), 0))


@dataclass(frozen=True)
class SineWave(_Reference):
    """x_r(t) = offset + amplitude · sin(2π t / period): smooth, no change instants."""

    amplitude_m: float
    period_s: float
    offset_m: float = 0.0
    kind: TaskKind = "sine"

    def __post_init__(self) -> None:
        if not (self.period_s > 0 and math.isfinite(self.period_s)):
            raise ConfigError(f"a sine needs a period > 0, got {self.period_s}")

    def change_times_s(self, start_s: float, end_s: float) -> np.ndarray:
        return np.empty(0)

    def _positions(self, times_s: np.ndarray) -> np.ndarray:
        return self.offset_m + self.amplitude_m * np.sin(2.0 * math.pi / self.period_s * times_s)

    def _flat(self, times_s: np.ndarray) -> tuple[np.ndarray, ...]:
        w = 2.0 * math.pi / self.period_s
        s, c = np.sin(w * times_s), np.cos(w * times_s)
        a = self.amplitude_m
        return (self.offset_m + a * s, a * w * c, -a * w**2 * s, -a * w**3 * c, a * w**4 * s)


Task = FixedTarget | StepSchedule | SquareWave | SineWave


def flat_feedforward(
    reference: FlatOutputs, gamma: float, alpha: float, alpha_beta: float
) -> tuple[np.ndarray, np.ndarray]:
    """The state and input that keep the linear model on ``reference`` (its flat output is
    x): states (..., 4) = (θ, θ̇, ẋ, x) with θ = ẍ/γ, θ̇ = x⃛/γ; input_v (...,) = (θ̈ + αβ·θ̇)/α
    with θ̈ = x⁗/γ. ``gamma`` [m/s² per rad], ``alpha`` [rad/s² per V], ``alpha_beta`` [1/s]."""
    theta = np.asarray(reference.acceleration_m_s2) / gamma
    theta_rate = np.asarray(reference.jerk_m_s3) / gamma
    theta_accel = np.asarray(reference.snap_m_s4) / gamma
    states = np.stack(
        [theta, theta_rate, np.asarray(reference.velocity_m_s),
         np.asarray(reference.position_m)], axis=-1,
    )
    return states, (theta_accel + alpha_beta * theta_rate) / alpha
