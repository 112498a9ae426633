"""A plant's own floor (ballbeam.core.floor, assembly.plant_floor) against independent answers:
the README's T*, exact scaling and shift laws of the linear model, the servo-rate relaxation,
and, for the nonlinear ball, its own minimum time found by sequential linear programming."""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.optimize

from ballbeam.assembly import minimum_time_s, plant_floor
from ballbeam.config import load_config
from ballbeam.core.floor import LINEAR, NONLINEAR_CHORD, chord_ball_gain, own_floor
from ballbeam.core.model import LinearModel, PhysicalConstants
from ballbeam.core.planning.rate_limited import plan_rate_limited
from ballbeam.core.plant import PlantPhysics
from ballbeam.errors import ConfigError, PlanningError
from ballbeam.plant_assembly import plant_parameters, true_model

from .conftest import PAPER

THETA_MAX_RAD = math.radians(52.0)
PAPER_START = np.array([math.radians(-52.0), 0.0, 0.0, 0.195])


def floor_s(model: LinearModel, start: np.ndarray, **kwargs: float) -> float:
    options = {
        "voltage_limit_v": 5.0, "deadzone_v": 0.0, "theta_max_rad": THETA_MAX_RAD,
        "step_s": 2e-3, **kwargs,
    }
    return own_floor(model, start, **options).time_s  # type: ignore[arg-type]


def test_nominal_plant_without_dead_zone_is_the_readme_t_star() -> None:
    config = load_config(PAPER, ["plant.deadzone_v=0.0"])
    floor = plant_floor(config)
    assert floor is not None
    assert floor.time_s == minimum_time_s(config)
    assert floor.time_s == pytest.approx(1.746, abs=1e-9)  # README: T* = 1.746 s, 1 ms grid
    assert floor.method == LINEAR
    assert floor.drive_limit_v == 5.0


def test_the_plants_true_gains_are_used_as_the_emulator_applies_them() -> None:
    config = load_config(
        PAPER, ["plant.motor_gain_scale=0.8", "plant.ball_gain_scale=1.2", "plant.deadzone_v=0.3"]
    )
    floor = plant_floor(config)
    plant = plant_parameters(config)  # what the emulator integrates
    assert floor is not None
    assert floor.alpha == plant.alpha
    assert floor.alpha_beta == plant.alpha_beta
    assert floor.gamma == plant.gamma
    assert floor.drive_limit_v == pytest.approx(5.0 - 0.3)
    base = PhysicalConstants()
    assert floor.alpha == pytest.approx(0.8 * base.alpha)  # α scales ...
    assert floor.alpha_beta / floor.alpha == pytest.approx(base.beta)  # ... β stays
    assert floor.gamma == pytest.approx(1.2 * base.gamma)


def test_the_saturation_caps_the_drive_where_it_is_below_the_command_bound() -> None:
    floor = plant_floor(load_config(PAPER, ["plant.saturation_v=4.0", "plant.deadzone_v=0.2"]))
    assert floor is not None
    assert floor.drive_limit_v == pytest.approx(3.8)


def test_a_dead_zone_is_less_drive() -> None:
    model = LinearModel.from_constants(PhysicalConstants())
    times = [floor_s(model, PAPER_START, deadzone_v=d) for d in (0.0, 0.2, 0.4)]
    assert times == sorted(times) and times[0] < times[-1]
    # exactly the same problem as a lower voltage bound
    assert times[2] == floor_s(model, PAPER_START, voltage_limit_v=4.6)


def test_a_ball_gain_k_is_the_same_path_for_a_start_k_times_further() -> None:
    # ẍ = kγθ: the same servo motion moves the ball k times as far, so the floor from
    # (θ0, θ̇0, k·ẋ0, k·x0) with gain kγ is the floor from (θ0, θ̇0, ẋ0, x0) with γ, exactly.
    start = np.array([math.radians(20.0), 0.0, 0.08, -0.12])
    base = floor_s(LinearModel.from_constants(PhysicalConstants()), start)
    for k in (0.7, 1.3):
        scaled = start * np.array([1.0, 1.0, k, k])
        model = LinearModel.from_constants(PhysicalConstants(), ball_gain_scale=k)
        assert floor_s(model, scaled) == pytest.approx(base, abs=1e-9)


def test_a_stronger_ball_is_never_slower_from_a_level_start() -> None:
    start = np.array([0.0, 0.0, 0.0, 0.15])
    times = [
        floor_s(LinearModel.from_constants(PhysicalConstants(), ball_gain_scale=k), start)
        for k in (0.7, 0.85, 1.0, 1.15, 1.3)
    ]
    assert times == sorted(times, reverse=True)
    # ball alone under an instantaneous servo: T ∝ 1/√k; the servo's own time stretches less
    assert times[0] / times[-1] < math.sqrt(1.3 / 0.7)


def test_a_fast_motor_approaches_the_servo_rate_relaxation() -> None:
    # |θ̇| ≤ U/β on every path from rest, so the rate-limited minimum time (its planner agrees
    # with Ruckig) is a lower bound, reached as the motor lag 1/(αβ) vanishes.
    constants = PhysicalConstants()
    relaxed = plan_rate_limited(
        constants, THETA_MAX_RAD, 5.0 / constants.beta, PAPER_START
    ).duration_s
    times = [
        floor_s(LinearModel.from_constants(constants, motor_gain_scale=k), PAPER_START, step_s=1e-3)
        for k in (1.0, 3.0, 10.0)
    ]
    assert times == sorted(times, reverse=True)
    assert relaxed <= times[-1] <= relaxed * 1.01


def test_a_target_is_the_start_shifted() -> None:
    model = LinearModel.from_constants(PhysicalConstants())
    start = np.array([math.radians(-10.0), 0.0, 0.05, 0.1])
    shifted = start - np.array([0.0, 0.0, 0.0, -0.08])
    assert floor_s(model, start, target_m=-0.08) == floor_s(model, shifted)
    at = plant_floor(load_config(PAPER, ["initial.ball_position_m=0.15"]), target_m=0.05)
    shifted_config = plant_floor(load_config(PAPER, ["initial.ball_position_m=0.1"]))
    assert at is not None and shifted_config is not None
    assert at.time_s == shifted_config.time_s


def test_no_path_and_no_drive_are_told_apart() -> None:
    model = LinearModel.from_constants(PhysicalConstants())
    beyond = np.array([math.radians(60.0), 0.0, 0.0, 0.1])
    with pytest.raises(PlanningError):
        floor_s(model, beyond)
    with pytest.raises(ConfigError):
        floor_s(model, PAPER_START, deadzone_v=5.0)
    assert plant_floor(load_config(PAPER, ["limits.theta_deg=50"])) is None  # starts at -52°


def test_the_nonlinear_ball_is_floored_on_its_chord_gain() -> None:
    gamma = PhysicalConstants().gamma
    assert chord_ball_gain(gamma, THETA_MAX_RAD) == pytest.approx(
        gamma * math.sin(math.radians(52.0)) / 0.907571, rel=1e-6
    )
    floor = plant_floor(load_config(PAPER, ["plant.nonlinear_ball=true", "plant.deadzone_v=0"]))
    assert floor is not None
    assert floor.method == NONLINEAR_CHORD
    scale = math.sin(THETA_MAX_RAD) / THETA_MAX_RAD
    linear = plant_floor(
        load_config(PAPER, [f"plant.ball_gain_scale={scale!r}", "plant.deadzone_v=0"])
    )
    assert linear is not None
    assert floor.time_s == linear.time_s


# --- the nonlinear ball's own minimum time, independently -----------------------------------


def nonlinear_ball_reaches_rest(
    start: np.ndarray, n_steps: int, step_s: float, guess_theta: np.ndarray, iterations: int = 25
) -> tuple[bool, np.ndarray]:
    """Can the nonlinear ball (gravity term γ sin θ, centripetal term x·φ̇²) be brought to rest
    at the origin in ``n_steps`` held inputs within ±5 V and ±52°? Sequential LPs: the servo is
    exact (linear), sin θ is linearised about the last iterate within a trust region, the
    centripetal term taken from it, the ball's acceleration integrated as piecewise linear
    between grid points. (True, inputs) once the terminal miss vanishes."""
    constants = PhysicalConstants()
    motor = LinearModel.from_constants(constants).discretize(step_s)
    Ad, bd = motor.Ad[:2, :2], motor.Bd[:2, 0]
    n = n_steps
    free = np.zeros((n + 1, 2))
    free[0] = start[:2]
    response = np.zeros((n + 1, n, 2))  # servo state k per input j
    impulse = bd.copy()
    impulses = []
    for _ in range(n):
        impulses.append(impulse)
        impulse = Ad @ impulse
    for k in range(1, n + 1):
        free[k] = Ad @ free[k - 1]
        response[k, :k] = np.array(impulses[:k])[::-1]
    theta_of_u, rate_of_u = response[:, :, 0], response[:, :, 1]
    ratio = constants.arm_radius_m / constants.beam_length_m
    gain = (5.0 / 7.0) * constants.gravity_m_per_s2 * ratio  # ẍ = −gain·sin θ + centripetal
    total_s = n * step_s
    times = np.arange(n + 1) * step_s
    w_v = np.full(n + 1, step_s)  # ∫a dt and ∫(T − t)a dt of a piecewise-linear a
    w_v[[0, -1]] = step_s / 2
    w_x = step_s * (total_s - times)
    w_x[0], w_x[-1] = step_s * (total_s / 2 - step_s / 6), step_s**2 / 6
    theta_bar = np.interp(
        np.linspace(0, 1, n + 1), np.linspace(0, 1, len(guess_theta)), guess_theta
    )
    centripetal = np.zeros(n + 1)
    inputs = np.zeros(n)
    miss = math.inf
    for iteration in range(iterations):
        slope = -gain * np.cos(theta_bar)
        offset = -gain * (np.sin(theta_bar) - np.cos(theta_bar) * theta_bar) + centripetal
        base_accel = offset + slope * free[:, 0]
        rows = np.vstack([
            theta_of_u[-1], rate_of_u[-1], (slope * w_v) @ theta_of_u, (slope * w_x) @ theta_of_u
        ])
        rhs = -np.array([
            free[-1, 0], free[-1, 1], start[2] + w_v @ base_accel,
            start[3] + start[2] * total_s + w_x @ base_accel,
        ])
        weights = np.array([1.0, 0.1, 10.0, 100.0])
        trust = 0.2 if iteration < iterations // 2 else 0.05
        inner = theta_of_u[1:]
        a_ub = np.vstack([inner, -inner, inner, -inner])
        b_ub = np.concatenate([
            THETA_MAX_RAD - free[1:, 0], THETA_MAX_RAD + free[1:, 0],
            theta_bar[1:] + trust - free[1:, 0], trust - theta_bar[1:] + free[1:, 0],
        ])
        result = scipy.optimize.linprog(
            np.concatenate([np.zeros(n), np.repeat(weights, 2)]),
            A_ub=np.hstack([a_ub, np.zeros((a_ub.shape[0], 8))]),
            b_ub=b_ub,
            A_eq=np.hstack([rows, np.kron(np.eye(4), [1.0, -1.0])]),
            b_eq=rhs,
            bounds=[(-5.0, 5.0)] * n + [(0.0, None)] * 8,
            method="highs",
        )
        assert result.status == 0, result.message
        inputs, miss = result.x[:n], float(result.fun)
        theta = free[:, 0] + theta_of_u @ inputs
        rate = free[:, 1] + rate_of_u @ inputs
        accel = -gain * np.sin(theta)
        mean_accel = (accel[:-1] + accel[1:]) / 2
        velocity = start[2] + np.concatenate([[0.0], np.cumsum(step_s * mean_accel)])
        position = start[3] + np.concatenate([
            [0.0], np.cumsum(step_s * velocity[:-1] + step_s**2 * (2 * accel[:-1] + accel[1:]) / 6)
        ])
        phi_rate = ratio * np.cos(theta) * rate / np.sqrt(1.0 - (ratio * np.sin(theta)) ** 2)
        centripetal = (5.0 / 7.0) * position * phi_rate**2
        moved = float(np.max(np.abs(theta - theta_bar)))
        theta_bar = theta
        if moved < 1e-9:
            break
    return miss < 1e-7, inputs


@pytest.mark.slow
@pytest.mark.parametrize(
    "start",
    [PAPER_START, np.array([math.radians(10.0), 0.0, -0.05, 0.12])],
    ids=["paper", "rolling"],
)
def test_the_chord_floor_is_the_nonlinear_balls_own_minimum_time(start: np.ndarray) -> None:
    step_s = 0.01
    chord = LinearModel.from_constants(
        PhysicalConstants(), ball_gain_scale=math.sin(THETA_MAX_RAD) / THETA_MAX_RAD
    )
    plan = own_floor(
        chord, start, voltage_limit_v=5.0, deadzone_v=0.0, theta_max_rad=THETA_MAX_RAD,
        step_s=step_s,
    )
    n = round(plan.time_s / step_s)
    from ballbeam.core.planning.time_optimal import plan_time_optimal

    guess = plan_time_optimal(
        chord, start, voltage_limit_v=5.0, theta_max_rad=THETA_MAX_RAD, step_s=step_s
    ).grid_states[:, 0]
    # the nonlinear ball needs no more than a step beyond the chord floor ...
    reached, inputs = nonlinear_ball_reaches_rest(start, n + 1, step_s, guess)
    assert reached
    # ... (played open loop on the emulator's own nonlinear physics, it does come to rest) ...
    config = load_config(PAPER, ["plant.nonlinear_ball=true", "plant.deadzone_v=0"])
    physics = PlantPhysics(plant_parameters(config))
    state = start.copy()
    for voltage_v in inputs:
        state = physics.advance(state, float(voltage_v), round(step_s / physics.params.substep_s))
    assert abs(state[3]) < 2e-3 and abs(state[2]) < 5e-3 and abs(state[0]) < 1e-3
    # ... and cannot do it two steps sooner: the chord floor is within a step of its own.
    assert not nonlinear_ball_reaches_rest(start, n - 2, step_s, guess)[0]
    # The small-angle floor is well below it: a floor no controller of this ball can reach.
    small_angle = floor_s(LinearModel.from_constants(PhysicalConstants()), start, step_s=step_s)
    assert small_angle < plan.time_s - 2 * step_s


def test_true_model_is_the_plants_linear_model() -> None:
    config = load_config(PAPER, ["plant.motor_gain_scale=1.1"])
    model = true_model(config)
    assert float(model.B[1, 0]) == plant_parameters(config).alpha
