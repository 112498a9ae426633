"""The servo-angle guard against an independent simulation of the motor."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from ballbeam.assembly import controller_design
from ballbeam.config import load_config
from ballbeam.core.guard import AngleGuard, guarded_voltage, stopping_distance_rad


@pytest.fixture(scope="module")
def guard() -> AngleGuard:
    design = controller_design(load_config(None, ["plan.kind=rate_limited"]))
    assert design.guard is not None
    return design.guard


def test_stopping_distance_matches_integration(guard: AngleGuard) -> None:
    for rate in (0.5, 3.0, 9.0):

        def braking(_t: float, y: np.ndarray) -> list[float]:
            return [y[1], -guard.alpha_beta * y[1] - guard.alpha * guard.brake_v]

        stopped = lambda _t, y: y[1]  # noqa: E731
        stopped.terminal = True  # type: ignore[attr-defined]
        solution = solve_ivp(braking, (0, 1), [0.0, rate], events=stopped, rtol=1e-11, atol=1e-13)
        assert stopping_distance_rad(guard, rate) == pytest.approx(solution.y[0, -1], rel=1e-7)
    assert stopping_distance_rad(guard, -1.0) == 0.0


def test_guard_keeps_the_servo_inside_even_when_driven_at_the_limit(guard: AngleGuard) -> None:
    """Demand +5 V for 0.5 s from -40° and simulate the motor model exactly: θ never passes
    the guard's limit, though the unguarded demand would run into the hard stop."""
    state = np.array([math.radians(-40), 0.0, 0.0, 0.0])
    highest = -math.inf
    for _ in range(500):
        voltage = guarded_voltage(guard, state, 5.0)
        state = guard.Ad @ state + guard.Bd[:, 0] * voltage
        highest = max(highest, state[0])
    assert highest <= guard.theta_limit_rad + 1e-9
    assert highest >= guard.theta_limit_rad - math.radians(0.5)  # and it does get close


def test_guard_passes_demands_that_are_safe(guard: AngleGuard) -> None:
    state = np.zeros(4)
    for demand in (-3.0, 0.0, 2.5):
        assert guarded_voltage(guard, state, demand) == demand
    assert guarded_voltage(guard, state, 12.0) == guard.voltage_limit_v
