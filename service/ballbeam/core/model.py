"""Linear model of the SRV02 ball-and-beam (paper, section 2).

State ``x = (θ [rad], θ̇ [rad/s], ẋ [m/s], x [m])``, input ``u`` [V], output
``y = C x = (57 θ, 100 x)``.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from ballbeam.errors import ConfigError

N_STATES = 4
THETA, THETA_RATE, BALL_VELOCITY, BALL_POSITION = range(N_STATES)

# A state (or a row of a 4-column matrix) as plain Python floats: what the per-cycle law
# computes with (a fixed order of IEEE operations, no BLAS: the same bits on every CPU).
Row4 = tuple[float, float, float, float]


def as_row4(values: np.ndarray | list[float] | tuple[float, ...]) -> Row4:
    """Four numbers as a Row4 of Python floats (exact: float64 → float)."""
    a, b, c, d = (float(value) for value in values)
    return (a, b, c, d)


@dataclass(frozen=True)
class PhysicalConstants:
    """Physical constants of the SRV02 and the ball-and-beam module, SI units.

    The defaults are the paper's (docs/design.md §2) and this is their one home: the config's
    ``[model]`` section takes its defaults from here and only overrides them.
    """

    torque_constant_nm_per_a: float = 0.00767
    gear_ratio: float = 70.0  # 14:1 gearbox × 5:1 gears
    armature_resistance_ohm: float = 2.6
    armature_inertia_kg_m2: float = 3.87e-7
    gravity_m_per_s2: float = 9.81
    arm_radius_m: float = 0.0254  # r = 1 in
    beam_length_m: float = 0.4318  # L = 17 in
    angle_sensor_gain: float = 57.0  # C = [[57, 0, 0, 0], [0, 0, 0, 100]]
    position_sensor_gain: float = 100.0

    @property
    def load_inertia_kg_m2(self) -> float:
        """Jl = Jm·kg², the armature inertia seen at the output shaft."""
        return self.armature_inertia_kg_m2 * self.gear_ratio**2

    @property
    def alpha(self) -> float:
        """α = km·kg / (Rm·Jl): volts to servo acceleration [rad/s² per V]."""
        return (
            self.torque_constant_nm_per_a
            * self.gear_ratio
            / (self.armature_resistance_ohm * self.load_inertia_kg_m2)
        )

    @property
    def beta(self) -> float:
        """β = km·kg: back-EMF constant at the output [V·s/rad]."""
        return self.torque_constant_nm_per_a * self.gear_ratio

    @property
    def gamma(self) -> float:
        """γ = −5·g·r / (7·L): servo angle to ball acceleration [m/s² per rad]."""
        return -5.0 * self.gravity_m_per_s2 * self.arm_radius_m / (7.0 * self.beam_length_m)

    def slew_rate_rad_s(self, voltage_v: float) -> float:
        """Steady servo rate under a constant voltage: u/β."""
        return voltage_v / self.beta


@dataclass(frozen=True)
class LinearModel:
    """``ẋ = A x + B u``, ``y = C x``. Shapes: A (4, 4), B (4, 1), C (2, 4)."""

    A: np.ndarray
    B: np.ndarray
    C: np.ndarray

    @classmethod
    def from_constants(
        cls,
        constants: PhysicalConstants,
        motor_gain_scale: float = 1.0,
        ball_gain_scale: float = 1.0,
    ) -> LinearModel:
        """The paper's model; the scales multiply α and γ (plant-model mismatch studies)."""
        C = np.array(
            [
                [constants.angle_sensor_gain, 0.0, 0.0, 0.0],
                [0.0, 0.0, 0.0, constants.position_sensor_gain],
            ]
        )
        return cls.from_gains(
            alpha=constants.alpha * motor_gain_scale,
            alpha_beta=constants.alpha * constants.beta * motor_gain_scale,
            gamma=constants.gamma * ball_gain_scale,
            C=C,
        )

    @classmethod
    def from_gains(
        cls, alpha: float, alpha_beta: float, gamma: float, C: np.ndarray
    ) -> LinearModel:
        """The model's structure from its three gains (the plant physics uses its own)."""
        A = np.array(
            [
                [0.0, 1.0, 0.0, 0.0],
                [0.0, -alpha_beta, 0.0, 0.0],
                [gamma, 0.0, 0.0, 0.0],
                [0.0, 0.0, 1.0, 0.0],
            ]
        )
        B = np.array([[0.0], [alpha], [0.0], [0.0]])
        C = np.array(C, dtype=float)
        for matrix in (A, B, C):
            matrix.setflags(write=False)
        return cls(A=A, B=B, C=C)

    def discretize(self, period_s: float) -> DiscreteModel:
        """Exact zero-order-hold discretisation at ``period_s``."""
        if not period_s > 0.0:
            raise ConfigError(f"sampling period must be positive, got {period_s} s")
        n = self.B.shape[0]
        transition = zoh_transition(self.A, self.B, period_s)
        return DiscreteModel(
            Ad=transition[:n, :n].copy(),
            Bd=transition[:n, n:].copy(),
            C=self.C,
            period_s=period_s,
        )


@dataclass(frozen=True)
class DiscreteModel:
    """``x[k+1] = Ad x[k] + Bd u[k]`` under zero-order hold. Ad (4, 4), Bd (4, 1), C (2, 4)."""

    Ad: np.ndarray
    Bd: np.ndarray
    C: np.ndarray
    period_s: float

    @cached_property
    def n_states(self) -> int:
        return int(self.Ad.shape[0])


def zoh_propagate(
    A: np.ndarray, B: np.ndarray, state: np.ndarray, input_v: float, duration_s: float
) -> np.ndarray:
    """State after holding ``input_v`` for ``duration_s`` from ``state`` (exact)."""
    n = A.shape[0]
    transition = zoh_transition(A, B, duration_s)
    result: np.ndarray = transition[:n, :n] @ state + transition[:n, n] * input_v
    return result


def zoh_generator(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """``F = [[A, B], [0, 0]]`` (n + m, n + m): the state with the input held constant beside
    it. ``expm(F t) = [[Ad(t), Bd(t)], [0, I]]`` is the zero-order hold over ``t``; the
    tracker's Van Loan cost integral builds on F itself."""
    n, m = B.shape
    F = np.zeros((n + m, n + m))
    F[:n, :n] = A
    F[:n, n:] = B
    return F


def zoh_transition(A: np.ndarray, B: np.ndarray, duration_s: float) -> np.ndarray:
    """``expm(F t)`` with ``F = zoh_generator(A, B)``: ``[[Ad, Bd], [0, I]]`` over ``t``."""
    # Imported here: every process reads the model, few discretise it.
    from scipy.linalg import expm

    transition: np.ndarray = expm(zoh_generator(A, B) * duration_s)
    return transition
