"""Steady-state Kalman filter: convergence, covariance against a seeded ensemble, stability."""

from __future__ import annotations

import math

import numpy as np
import pytest
from numpy.testing import assert_allclose

from ballbeam.core.model import DiscreteModel, LinearModel, PhysicalConstants
from ballbeam.core.observer import (
    ObserverGains,
    correct,
    design_observer,
    initial_estimate,
    measurement_noise_covariance,
    predict,
    process_noise_covariance,
)
from ballbeam.errors import ConfigError

PERIOD_S = 1e-3
DISCRETE = LinearModel.from_constants(PhysicalConstants()).discretize(PERIOD_S)
NOISE = {
    "input_noise_v": 0.3,
    "ball_noise_m_s2": 0.05,
    "angle_noise_rad": 2.0 * math.pi / 4096 / math.sqrt(12.0),
    "position_noise_m": 2e-4,
}


@pytest.fixture(scope="module")
def gains() -> ObserverGains:
    return design_observer(DISCRETE, **NOISE)


def test_shapes_and_error_dynamics_are_stable(gains: ObserverGains) -> None:
    assert gains.L.shape == (4, 2)
    assert gains.P_prior.shape == gains.P_estimate.shape == (4, 4)
    # Current-estimator error: e_k = (I − L C) Ad e_{k−1} (+ noise).
    error_dynamics = gains.Ad - gains.L @ gains.C @ gains.Ad
    assert np.abs(np.linalg.eigvals(error_dynamics)).max() < 1.0
    assert np.linalg.eigvalsh(gains.P_estimate).min() > 0.0
    assert not gains.L.flags.writeable


def test_prior_covariance_matches_riccati_iteration(gains: ObserverGains) -> None:
    # Independent of the DARE solver: iterate the Kalman covariance update to a fixed point.
    Qn = process_noise_covariance(DISCRETE, NOISE["input_noise_v"], NOISE["ball_noise_m_s2"])
    Rn = measurement_noise_covariance(
        DISCRETE.C, NOISE["angle_noise_rad"], NOISE["position_noise_m"]
    )
    Ad, C = DISCRETE.Ad, DISCRETE.C
    prior = np.eye(4) * 1e-2
    for _ in range(40000):
        gain = prior @ C.T @ np.linalg.inv(C @ prior @ C.T + Rn)
        posterior = (np.eye(4) - gain @ C) @ prior
        prior = Ad @ posterior @ Ad.T + Qn
    assert_allclose(gains.P_prior, prior, rtol=1e-6, atol=1e-9 * np.abs(prior).max())
    assert_allclose(gains.L, gain, rtol=1e-6, atol=1e-9 * np.abs(gain).max())


def test_noise_covariances_are_in_measurement_units() -> None:
    Rn = measurement_noise_covariance(DISCRETE.C, 1e-3, 2e-4)
    assert_allclose(Rn, np.diag([(57.0 * 1e-3) ** 2, (100.0 * 2e-4) ** 2]), rtol=1e-12)
    Qn = process_noise_covariance(DISCRETE, 0.0, 1.0)
    # A held unit acceleration for h: Δẋ = h, Δx = h²/2.
    assert_allclose(Qn[2:, 2:], np.outer([1e-3, 0.5e-6], [1e-3, 0.5e-6]), rtol=1e-12)
    assert_allclose(Qn[:2, :], 0.0, atol=0.0)


def test_initial_estimate_explains_first_measurement_with_zero_rates(
    gains: ObserverGains,
) -> None:
    estimate = initial_estimate(gains, np.array([57.0 * -0.9, 100.0 * 0.195]))
    assert_allclose(estimate, [-0.9, 0.0, 0.0, 0.195], atol=1e-14)


def test_estimate_converges_on_noise_free_plant(gains: ObserverGains) -> None:
    n_steps = 4000
    t = np.arange(n_steps) * PERIOD_S
    inputs = 1.5 * np.sin(3.0 * t) + 0.5 * np.sign(np.sin(11.0 * t))
    state = np.array([-0.9, 0.4, -0.05, 0.195])  # the rates are unknown to the filter
    estimate = initial_estimate(gains, DISCRETE.C @ state)
    errors = []
    for u in inputs:
        errors.append(np.abs(estimate - state))
        state = DISCRETE.Ad @ state + DISCRETE.Bd[:, 0] * u
        estimate = correct(gains, predict(gains, estimate, u), DISCRETE.C @ state)
    errors_array = np.array(errors)
    assert errors_array[0, 1] > 0.3  # the initial rate error is large ...
    assert errors_array[-1].max() < 1e-9  # ... and gone
    assert errors_array[-500:, 2].max() < 1e-8


def test_ensemble_error_covariance_matches_filter_prediction(gains: ObserverGains) -> None:
    """Many seeded runs of the noise model the filter assumes: the spread of the estimation
    error across runs at the final step equals the steady-state covariance P_estimate."""
    rng = np.random.default_rng(20040322)
    n_runs, n_steps = 4000, 1500
    Ad, Bd, C = DISCRETE.Ad, DISCRETE.Bd[:, 0], DISCRETE.C
    held = np.array([0.0, 0.0, PERIOD_S, 0.5 * PERIOD_S**2])
    meas_std = np.array([57.0 * NOISE["angle_noise_rad"], 100.0 * NOISE["position_noise_m"]])
    state = np.tile([-0.5, 0.0, 0.0, 0.1], (n_runs, 1))
    state += rng.normal(size=(n_runs, 4)) * [1e-3, 1e-2, 1e-3, 1e-3]
    estimate = initial_estimate(gains, state[0] @ C.T) + np.zeros((n_runs, 4))
    for k in range(n_steps):
        u = 0.8 * math.sin(0.01 * k)
        state = (
            state @ Ad.T
            + np.outer(u + NOISE["input_noise_v"] * rng.normal(size=n_runs), Bd)
            + np.outer(NOISE["ball_noise_m_s2"] * rng.normal(size=n_runs), held)
        )
        measurement = state @ C.T + meas_std * rng.normal(size=(n_runs, 2))
        estimate = correct(gains, predict(gains, estimate, u), measurement)
    errors = estimate - state
    sample = np.cov(errors, rowvar=False)
    # Whitened by the predicted covariance, the sample covariance is the identity up to the
    # sampling error of n_runs draws (std ≈ sqrt(2 / n_runs) ≈ 0.022 on the diagonal).
    root = np.linalg.cholesky(gains.P_estimate)
    whitened = np.linalg.solve(root, np.linalg.solve(root, sample).T)
    assert_allclose(whitened, np.eye(4), atol=0.12)
    assert np.abs(errors.mean(axis=0)).max() < 5 * np.sqrt(np.diag(gains.P_estimate)).max()


def test_quantised_angle_does_not_make_the_filter_optimistic(gains: ObserverGains) -> None:
    """With the real encoder (θ rounded to 4096 counts/rev, modelled as white noise of std
    step/√12) the actual error spread stays within the predicted one."""
    rng = np.random.default_rng(4096)
    n_runs, n_steps = 2000, 1500
    Ad, Bd, C = DISCRETE.Ad, DISCRETE.Bd[:, 0], DISCRETE.C
    held = np.array([0.0, 0.0, PERIOD_S, 0.5 * PERIOD_S**2])
    step_rad = 2.0 * math.pi / 4096
    state = np.tile([-0.5, 0.0, 0.0, 0.1], (n_runs, 1))
    estimate = initial_estimate(gains, state[0] @ C.T) + np.zeros((n_runs, 4))
    for k in range(n_steps):
        u = 0.8 * math.sin(0.01 * k)
        state = (
            state @ Ad.T
            + np.outer(u + NOISE["input_noise_v"] * rng.normal(size=n_runs), Bd)
            + np.outer(NOISE["ball_noise_m_s2"] * rng.normal(size=n_runs), held)
        )
        angle = np.round(state[:, 0] / step_rad) * step_rad
        position = state[:, 3] + NOISE["position_noise_m"] * rng.normal(size=n_runs)
        measurement = np.stack([57.0 * angle, 100.0 * position], axis=1)
        estimate = correct(gains, predict(gains, estimate, u), measurement)
    spread = (estimate - state).std(axis=0)
    predicted = np.sqrt(np.diag(gains.P_estimate))
    assert np.all(spread < 1.1 * predicted), spread / predicted
    assert np.all(spread > 0.5 * predicted), spread / predicted


def test_predict_and_correct_accept_single_vectors(gains: ObserverGains) -> None:
    estimate = np.array([0.1, 0.2, 0.01, 0.05])
    prediction = predict(gains, estimate, 1.0)
    assert prediction.shape == (4,)
    assert_allclose(prediction, DISCRETE.Ad @ estimate + DISCRETE.Bd[:, 0], rtol=1e-14)
    corrected = correct(gains, prediction, DISCRETE.C @ prediction)
    assert_allclose(corrected, prediction, rtol=0, atol=0)


@pytest.mark.parametrize(
    "name", ["input_noise_v", "ball_noise_m_s2", "angle_noise_rad", "position_noise_m"]
)
def test_non_positive_noise_is_a_config_error(name: str) -> None:
    with pytest.raises(ConfigError, match=name):
        design_observer(DISCRETE, **{**NOISE, name: 0.0})


def test_the_filters_of_many_noise_levels_equal_scipys_riccati_solutions() -> None:
    """The doubling solver, all at once, against SciPy's QZ-based DARE solver one at a time
    (an independent method): noise levels across and beyond the configs' ranges, the servo's
    period from 0.25 to 4 ms, the ball's gain from 0.7 to 1.3 of the SRV02's."""
    import scipy.linalg

    from ballbeam.core.observer import ObserverNoise, design_observers

    angle_noise_rad = NOISE["angle_noise_rad"]
    noises = [
        ObserverNoise(input_v, ball_m_s2, angle_noise_rad, position_m)
        for input_v in (0.01, 0.3, 2.0)
        for ball_m_s2 in (1e-3, 0.05, 1.0)
        for position_m in (5e-5, 2e-4, 5e-3)
    ]
    for period_s, ball_gain in ((2.5e-4, 1.0), (1e-3, 0.7), (1e-3, 1.3), (4e-3, 1.0)):
        model = LinearModel.from_constants(
            PhysicalConstants(), ball_gain_scale=ball_gain
        ).discretize(period_s)
        designs = design_observers(model, noises)
        for noise, design in zip(noises, designs, strict=True):
            Qn = process_noise_covariance(model, noise.input_noise_v, noise.ball_noise_m_s2)
            Rn = measurement_noise_covariance(model.C, noise.angle_noise_rad,
                                              noise.position_noise_m)
            expected = scipy.linalg.solve_discrete_are(model.Ad.T, model.C.T, Qn, Rn)
            scale = np.abs(expected).max()
            assert_allclose(design.P_prior, expected, rtol=1e-9, atol=1e-12 * scale)
        single = design_observer(model, **vars(noises[13]))
        assert_allclose(single.L, designs[13].L, rtol=1e-12, atol=0)


def test_a_model_whose_ball_no_sensor_sees_has_no_steady_state_filter() -> None:
    """Without the position sensor the ball's double integrator is not detectable: its
    Riccati equation has no stabilising solution, and the design says so (whether the
    measurement noise left is singular or not)."""
    from ballbeam.core.observer import filtering_riccati

    blind_c = DISCRETE.C * np.array([[1.0], [0.0]])
    blind = DiscreteModel(DISCRETE.Ad, DISCRETE.Bd, blind_c, PERIOD_S)
    with pytest.raises(ConfigError, match="no steady-state Kalman filter"):
        design_observer(blind, **NOISE)
    Qn = process_noise_covariance(DISCRETE, NOISE["input_noise_v"], NOISE["ball_noise_m_s2"])
    with pytest.raises(ConfigError, match="no stabilising solution"):
        filtering_riccati(DISCRETE.Ad, blind_c, Qn[None], np.eye(2)[None] * 1e-4)
