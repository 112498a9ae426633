"""Desired paths: the common shape every planner returns (like ruckig's trajectories).

A plan gives the desired state ``x_d(t) = (θ, θ̇, ẋ, x)`` and input ``u_d(t)`` [V] for any time;
before 0 it holds the start, after ``duration_s`` it rests at the origin with ``u_d = 0``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np


@dataclass(frozen=True)
class PlanSamples:
    """Samples of a plan. states: (N, 4); input_v: (N,)."""

    time_s: np.ndarray
    states: np.ndarray
    input_v: np.ndarray


class Plan(Protocol):
    @property
    def kind(self) -> str: ...

    @property
    def duration_s(self) -> float: ...

    def sample(self, time_s: np.ndarray) -> PlanSamples: ...


def at_time(plan: Plan, time_s: float) -> tuple[np.ndarray, float]:
    """The desired state (4,) and input [V] at one instant."""
    samples = plan.sample(np.array([time_s]))
    return samples.states[0], float(samples.input_v[0])
