"""The candidate's position-noise estimate (core/replanning.py ``NoiseEstimate``): against
synthetic data of known noise, and in the closed loop, where the controller must not be told
the plant's noise."""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.stats

from ballbeam.config import load_config
from ballbeam.core.metrics import dither_hz
from ballbeam.core.plant import EmulatedPlant
from ballbeam.core.replanning import NoiseEstimate, Settings, noise_window, run_closed_loop
from ballbeam.plant_assembly import plant_parameters

PAPER = "configs/paper.toml"
PERIOD_S = 1e-3
NOMINAL_M = 2e-4
ADC_STEP_M = Settings().adc_step_m
GAMMA = -0.41218
WINDOW = 100
WINDOWS = 10
# Two-sided tail of the acceptance intervals below: a seeded test that a correct estimator
# fails once in 10⁴ seeds.
TAIL = 1e-4


def plant(*overrides: str) -> EmulatedPlant:
    return plant_parameters(load_config(PAPER, list(overrides)))


def _manoeuvre(seconds: float) -> tuple[np.ndarray, np.ndarray]:
    """Encoder angles and the true ball position of a ball manoeuvred hard: the servo swings
    ±40° at 1.7 Hz, the ball follows a gain 10 % off the design's *and* the beam's sine
    (ẍ = 1.1·γ·sin θ: what a linear model with the design's γ leaves out is up to 17 % of
    the acceleration), integrated on a 0.1 ms grid."""
    fine = 10
    h = PERIOD_S / fine
    n = round(seconds / PERIOD_S)
    encoder = 2.0 * math.pi / 4096.0
    x, v = 0.05, -0.02
    thetas, positions = [], []
    for k in range(n * fine):
        theta = math.radians(40.0) * math.sin(2.0 * math.pi * 1.7 * k * h + 0.3)
        if k % fine == 0:
            thetas.append(round(theta / encoder) * encoder)
            positions.append(x)
        a = 1.1 * GAMMA * math.sin(theta)
        x += v * h + 0.5 * a * h * h
        v += a * h
    return np.array(thetas), np.array(positions)


def _read(positions: np.ndarray, sigma_m: float, seed: int) -> np.ndarray:
    """ADC readings: white Gaussian noise, quantised to the ADC's step."""
    noise = sigma_m * np.random.default_rng(seed).standard_normal(len(positions))
    return np.round((positions + noise) / ADC_STEP_M) * ADC_STEP_M


def _estimate(thetas: np.ndarray, readings: np.ndarray) -> tuple[NoiseEstimate, int]:
    s = Settings()
    estimate = NoiseEstimate(s.position_noise_prior_m, s.position_noise_prior_dof, 0.0)
    data_dof = 0
    for start in range(0, len(readings) - WINDOW + 1, WINDOW):
        rss, dof = noise_window(thetas[start:start + WINDOW], readings[start:start + WINDOW],
                                PERIOD_S)
        if estimate.add(rss, dof):
            data_dof += dof
    return estimate, data_dof


def _interval(sigma_m: float, data_dof: int) -> tuple[float, float]:
    """Where the pooled σ̂ falls with probability 1 − TAIL: the windows' residual sum of
    squares is σ_eff²·χ²(ν) (ν their degrees of freedom; σ_eff² = σ² + q²/12, the ADC's
    rounding adding its uniform variance), pooled with the prior's pseudo-observations."""
    s = Settings()
    prior = s.position_noise_prior_dof * s.position_noise_prior_m**2
    total_dof = s.position_noise_prior_dof + data_dof
    effective = sigma_m**2 + ADC_STEP_M**2 / 12.0
    low, high = scipy.stats.chi2.ppf([TAIL / 2, 1.0 - TAIL / 2], data_dof)
    return (
        math.sqrt((prior + effective * low) / total_dof),
        math.sqrt((prior + effective * high) / total_dof),
    )


@pytest.mark.parametrize(("scale", "seed"), [(1.0, 11), (5.0, 12), (1.0, 13), (5.0, 14)])
def test_the_estimate_recovers_the_noise_of_a_manoeuvring_ball(scale: float, seed: int) -> None:
    """One second of a hard manoeuvre the design's model does not explain exactly, at the
    nominal and 5× the nominal noise: σ̂ within the χ² interval of its degrees of freedom
    (10 windows of 96: ±~9 % of σ at this tail), and its stated confidence covers it."""
    sigma = scale * NOMINAL_M
    thetas, positions = _manoeuvre(WINDOWS * WINDOW * PERIOD_S)
    estimate, data_dof = _estimate(thetas, _read(positions, sigma, seed))
    assert estimate.rejected == 0
    assert data_dof == WINDOWS * (WINDOW - 4)  # θ swings: the four columns are independent
    low, high = _interval(sigma, data_dof)
    assert low <= estimate.std_m <= high
    assert high / low - 1.0 < 0.2  # the interval is a test, not a formality
    assert abs(estimate.std_m / sigma - 1.0) <= 4.0 * estimate.relative_std


def test_the_manoeuvre_alone_leaves_no_residual_to_read_as_noise() -> None:
    """Without noise, the windows' fit leaves a residual far below the ADC's own step: the
    unmodelled acceleration is not read as sensor noise."""
    thetas, positions = _manoeuvre(WINDOWS * WINDOW * PERIOD_S)
    for start in range(0, len(positions), WINDOW):
        rss, dof = noise_window(thetas[start:start + WINDOW], positions[start:start + WINDOW],
                                PERIOD_S)
        assert math.sqrt(rss / dof) < 0.05 * ADC_STEP_M / math.sqrt(12.0)


def test_a_window_with_a_hard_stop_is_left_out() -> None:
    """The ball stopped dead from 0.3 m/s (a beam end) in the last window: no smooth motion
    explains the kink (it leaves 1.8 mm of RMS residual per m/s of velocity change over a
    0.1 s window: 4× the noise's variance here), so the window's variance is improbably large
    against the others and is refused; the rest still recover σ."""
    sigma = NOMINAL_M
    thetas, positions = _manoeuvre(WINDOWS * WINDOW * PERIOD_S)
    t = np.arange(len(positions)) * PERIOD_S
    tap_s = (WINDOWS - 0.5) * WINDOW * PERIOD_S
    tapped = positions + np.where(t > tap_s, -0.3 * (t - tap_s), 0.0)
    estimate, data_dof = _estimate(thetas, _read(tapped, sigma, 21))
    assert estimate.rejected == 1
    assert data_dof == (WINDOWS - 1) * (WINDOW - 4)
    low, high = _interval(sigma, data_dof)
    assert low <= estimate.std_m <= high


def test_a_held_servo_counts_its_coinciding_columns_once() -> None:
    """θ held: ∫∫θ is a multiple of t², so the fit has three columns, not four; the residual
    keeps n − 3 degrees of freedom and its variance is still unbiased."""
    rng = np.random.default_rng(3)
    thetas = np.full(WINDOW, 0.2)
    t = np.arange(WINDOW) * PERIOD_S
    rss_total, dof_total = 0.0, 0
    for _ in range(200):
        y = 0.01 + 0.5 * GAMMA * 0.2 * t**2 + NOMINAL_M * rng.standard_normal(WINDOW)
        rss, dof = noise_window(thetas, y, PERIOD_S)
        assert dof == WINDOW - 3
        rss_total += rss
        dof_total += dof
    low, high = scipy.stats.chi2.ppf([TAIL / 2, 1.0 - TAIL / 2], dof_total)
    assert low <= rss_total / NOMINAL_M**2 <= high


def test_no_noise_at_all_is_floored_at_the_adc_quantisation() -> None:
    thetas, positions = _manoeuvre(0.5)
    readings = np.round(positions / ADC_STEP_M) * ADC_STEP_M
    s = Settings()
    estimate = NoiseEstimate(1e-9, s.position_noise_prior_dof, ADC_STEP_M / math.sqrt(12.0))
    for start in range(0, len(readings), WINDOW):
        estimate.add(*noise_window(thetas[start:start + WINDOW], readings[start:start + WINDOW],
                                   PERIOD_S))
    assert estimate.std_m >= ADC_STEP_M / math.sqrt(12.0)


def test_the_controller_is_not_told_the_plants_noise() -> None:
    """``run_closed_loop`` designs from the noise prior, whatever the plant's noise, and
    after a second the design's σ follows the plant's own: the upper confidence bound (z = 3
    of 1/√(2ν), ν ≈ 960: +7 %) less the band-limited noise's share the windows' fit takes
    (≈ 2 %), within 4 of the estimate's standard deviations (2.3 %, 2.5 % for the noise's
    correlation): [0.95, 1.15] of the truth."""
    start = np.array([math.radians(18.0), 0.0, 0.0, -0.07])
    designs = []
    for noise_m in (NOMINAL_M, 5.0 * NOMINAL_M):
        run = run_closed_loop(plant(f"plant.position_noise_m={noise_m}"), start, 1e-3, seed=5)
        designs.append(run.controller.design.measurement_noise)
    np.testing.assert_array_equal(designs[0], designs[1])
    for noise_m in (NOMINAL_M, 5.0 * NOMINAL_M):
        # through the cycle of 1 s: its re-design learns the windows up to then
        run = run_closed_loop(plant(f"plant.position_noise_m={noise_m}"), start, 1.001, seed=5)
        c = run.controller
        assert 0.95 <= c.position_noise_m / noise_m <= 1.15
        times = [row[0] for row in c.noise_history]
        assert times == pytest.approx(np.arange(0.0, 1.0 + 1e-9, 0.1))


def test_at_five_times_the_noise_the_ball_comes_to_rest_without_dither() -> None:
    """5× the nominal noise, a start no other test uses: rest in the band for the last
    second (the servo within half a degree), no dither, the angle limit kept."""
    start = np.array([math.radians(-12.0), 0.0, -0.03, 0.06])
    run = run_closed_loop(plant("plant.position_noise_m=1e-3"), start, 4.0, seed=7)
    last = run.time_s >= run.time_s[-1] - 1.0
    assert np.all(np.abs(run.states[last, 3]) <= 5e-4)
    assert np.all(np.abs(run.states[last, 0]) <= math.radians(0.5))
    assert dither_hz(run.time_s, run.command_v) <= 5.0
    assert float(np.max(run.peak_theta_rad)) <= math.radians(52.0)
