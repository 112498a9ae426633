"""Plant physics and sensors against analytic answers."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal

from ballbeam.config import load_config
from ballbeam.core.plant import (
    EmulatedPlant,
    PlantPhysics,
    drive_voltage,
    next_noise,
    read_sensors,
    tap_step,
)
from ballbeam.plant_assembly import plant_parameters


def _params(**changes: object) -> EmulatedPlant:
    base = plant_parameters(load_config(None, ["plant.deadzone_v=0"]))
    return dataclasses.replace(base, **changes)  # type: ignore[arg-type]


def test_motor_step_response_matches_the_papers_formula() -> None:
    params = _params(hard_stop_rad=100.0)  # a free shaft: 300 ms at 5 V turns 2.6 rad
    physics = PlantPhysics(params)
    alpha, ab = params.alpha, params.alpha_beta
    state = np.zeros(4)
    times = []
    angles = []
    for k in range(1, 301):  # 300 ms at 1 kHz, 10 substeps each
        state = physics.advance(state, 5.0, 10)
        times.append(k * 1e-3)
        angles.append(state[0])
    t = np.array(times)
    # Paper §5: θ(t) = 5α(t/(αβ) − 1/(αβ)² + e^{−αβt}/(αβ)²).
    expected = 5 * alpha * (t / ab - 1 / ab**2 + np.exp(-ab * t) / ab**2)
    assert_allclose(angles, expected, rtol=1e-9, atol=1e-12)
    # The paper's slope of that ramp is 9.3250 rad/s (5/β = 9.3127 from its constants).
    assert_allclose((angles[-1] - angles[-2]) / 1e-3, 9.3250, rtol=2e-3)


def test_saturation_then_dead_zone() -> None:
    params = _params(deadzone_v=0.2)
    assert drive_voltage(params, 0.15) == 0.0
    assert drive_voltage(params, -0.2) == 0.0
    assert drive_voltage(params, 1.0) == pytest.approx(0.8)
    assert drive_voltage(params, -12.0) == pytest.approx(-4.8)
    assert drive_voltage(params, 5.0) == pytest.approx(4.8)


def test_linear_ball_follows_gamma_theta() -> None:
    params = _params()
    physics = PlantPhysics(params)
    theta = math.radians(10)
    state = physics.advance(np.array([theta, 0.0, 0.0, 0.0]), 0.0, 1000)  # 0.1 s, u = 0
    t = 1000 * params.substep_s
    assert_allclose(state[3], 0.5 * params.gamma * theta * t**2, rtol=1e-9)
    assert_allclose(state[2], params.gamma * theta * t, rtol=1e-9)


def test_nonlinear_ball_agrees_with_linear_for_small_angles_and_departs_for_large() -> None:
    small = np.array([math.radians(2), 0.0, 0.0, 0.1])
    linear = PlantPhysics(_params())
    nonlinear = PlantPhysics(_params(nonlinear_ball=True))
    a = linear.advance(small, 0.0, 2000)
    b = nonlinear.advance(small, 0.0, 2000)
    assert_allclose(a, b, rtol=2e-3, atol=1e-7)
    # At 50°: sin φ = (r/L) sin θ, so the ball accelerates less than γθ says.
    large = np.array([math.radians(50), 0.0, 0.0, 0.0])
    params = _params()
    b = nonlinear.advance(large, 0.0, 1)
    expected_accel = (
        -(5 / 7) * params.gravity_m_per_s2 * params.arm_to_beam_ratio * math.sin(math.radians(50))
    )
    assert_allclose(b[2] / params.substep_s, expected_accel, rtol=1e-6)


@pytest.mark.parametrize("nonlinear", [True, False])
def test_ball_stops_at_the_beam_end_and_servo_at_hard_stop(nonlinear: bool) -> None:
    params = _params(nonlinear_ball=nonlinear)
    physics = PlantPhysics(params)
    state = np.array([math.radians(-40), 0.0, 0.0, 0.15])  # rolls toward +x
    state = physics.advance(state, 0.0, 20000)
    assert state[3] == pytest.approx(params.beam_half_length_m)
    assert state[2] == 0.0
    state = physics.advance(np.array([0.0, 0.0, 0.0, 0.0]), 5.0, 5000)
    assert state[0] == pytest.approx(params.hard_stop_rad)


def test_sensors_quantise_to_encoder_and_adc_counts() -> None:
    params = _params()
    # 4096 counts per revolution; ±10 V 16-bit ADC; 10 V across the 17 in beam.
    assert params.encoder_step_rad == pytest.approx(2 * math.pi / 4096)
    assert params.adc_step_m == pytest.approx(20 / 65536 / (10 / 0.4318))
    reading = read_sensors(params, np.array([math.radians(-52), 0, 0, 0.195]), 0.0)
    assert reading.angle_counts == round(-52 / 360 * 4096)
    assert reading.position_counts == round(0.195 / params.adc_step_m)
    clipped = read_sensors(params, np.array([0, 0, 0, 5.0]), 0.0)
    assert clipped.position_counts == 32767


def test_band_limited_noise_has_the_configured_std_and_correlation() -> None:
    params = _params(position_noise_m=1e-3)
    rng = np.random.default_rng(7)
    noise = 0.0
    samples = np.empty(100_000)
    for k in range(samples.size):
        noise = next_noise(params, noise, rng)
        samples[k] = noise
    assert samples[1000:].std() == pytest.approx(1e-3, rel=0.05)
    lag1 = np.corrcoef(samples[1000:-1], samples[1001:])[0, 1]
    assert lag1 == pytest.approx(params.noise_pole, abs=0.02)


def test_peak_angle_over_the_physics_steps_of_a_period() -> None:
    """advance_with_peak returns the same state as advance and the largest |θ| at any of its
    substeps: a servo driven to the limit and braked peaks between the period's ends."""
    import math

    from ballbeam.config import load_config
    from ballbeam.core.plant import PlantPhysics
    from ballbeam.plant_assembly import plant_parameters

    for extra in ([], ["plant.nonlinear_ball=true"]):
        physics = PlantPhysics(plant_parameters(load_config(None, extra)))
        state = np.array([math.radians(50.0), 3.0, 0.0, 0.0])  # moving up at 3 rad/s
        end, peak = physics.advance_with_peak(state, -5.0, 100)  # braked over 10 ms
        np.testing.assert_allclose(end, physics.advance(state, -5.0, 100), rtol=0, atol=0)
        fine = [state]
        for _ in range(100):
            fine.append(physics.advance(fine[-1], -5.0, 1))
        assert peak == pytest.approx(max(abs(s[0]) for s in fine), rel=1e-9)
        assert peak > max(abs(state[0]), abs(end[0]))


# -- taps ([plant] disturbances) ---------------------------------------------------------------


def test_a_tap_lands_on_the_first_physics_step_at_or_after_its_time() -> None:
    assert tap_step(1.0, 1e-4) == 10_000  # 1.0 / 1e-4 is 10000.000000000002 in floats
    assert tap_step(0.3, 1e-4) == 3_000  # ... and 0.3 / 1e-4 is 2999.9999999999995
    assert tap_step(0.30001, 1e-4) == 3_001
    assert tap_step(1e-9, 1e-4) == 1
    config = load_config(None, ["plant.disturbances=[[0.5, 0.1], [1.00025, -0.2]]"])
    assert plant_parameters(config).taps == ((5_000, 0.1), (10_003, -0.2))


def test_a_tap_adds_its_velocity_and_the_ball_carries_it_on() -> None:
    """The linear plant superposes: a tap of Δv at step n changes the state at step m > n by
    e^{A(m−n)h}·(0, 0, Δv, 0) = (0, 0, Δv, Δv·(m−n)·h), the ball's velocity not reaching the
    servo."""
    change_m_s = 0.07
    base = _params(hard_stop_rad=100.0, beam_half_length_m=100.0)  # free: no stop to clip it
    tapped = dataclasses.replace(base, taps=((10_003, change_m_s),))
    start = np.array([0.3, 1.0, -0.05, 0.1])
    free, hit = PlantPhysics(base), PlantPhysics(tapped)
    free_state, hit_state = start, start
    for period in range(1_002):  # 10 steps a period: the tap is 3 steps into period 1000
        free_state = free.advance(free_state, 2.0, 10, period * 10)
        hit_state = hit.advance(hit_state, 2.0, 10, period * 10)
        if period == 999:
            assert_array_equal(hit_state, free_state)  # not yet
    elapsed_s = (10_020 - 10_003) * base.substep_s
    assert_allclose(hit_state - free_state, [0.0, 0.0, change_m_s, change_m_s * elapsed_s],
                    atol=1e-12)


def test_the_peak_tracking_advance_taps_the_same() -> None:
    params = dataclasses.replace(_params(), taps=((25, 0.1), (25, 0.05), (30, -0.3)))
    physics = PlantPhysics(params)
    start = np.array([0.0, 0.0, 0.0, 0.05])
    plain, peaked, peak = start, start, 0.0
    for period in range(5):
        plain = physics.advance(plain, 4.0, 10, period * 10)
        peaked, step_peak = physics.advance_with_peak(peaked, 4.0, 10, period * 10)
        peak = max(peak, step_peak)
    assert_array_equal(plain, peaked)
    assert peak == pytest.approx(abs(plain[0]))  # θ rises monotonically from rest at 4 V
    untapped = start
    for period in range(5):
        untapped = PlantPhysics(_params()).advance(untapped, 4.0, 10, period * 10)
    assert plain[2] - untapped[2] == pytest.approx(0.1 + 0.05 - 0.3, abs=1e-12)


def test_the_nonlinear_ball_takes_the_tap_too() -> None:
    params = _params(nonlinear_ball=True)
    start = np.array([0.2, 0.0, 0.0, 0.0])
    free = PlantPhysics(params).advance(start, 0.0, 10, 0)
    hit = PlantPhysics(dataclasses.replace(params, taps=((10, -0.2),))).advance(start, 0.0, 10, 0)
    assert_array_equal(hit[[0, 1, 3]], free[[0, 1, 3]])  # the tap at the period's end
    assert hit[2] - free[2] == pytest.approx(-0.2, abs=1e-15)
