"""Issue 27's candidate controller: identify the plant, re-plan to its own limit, from any state
to any target. Pure (no I/O); ``controller.kind = "replanning"`` runs it (``replanning_law.py``).
A measured experiment, not yet at issue 27's bounds: docs/decisions.md ("the second
candidate") has its figures and what is left.

Each 1 ms cycle (what needs a solve or a factorisation is asked of a planner: the plans, and
with each re-design the identification's windows since the last, ``Identification``):

* **Identification** (``WindowedLeastSquares``): the servo's α (volts → acceleration), its pole a
  and c = α·d (d the dead zone) from the encoder, and the ball's γ from the encoder and the
  position sensor, each by least squares on the *integral* form of its model over short
  windows (no derivative of a quantized signal is taken)::

      θ(t) − θ(0) = θ̇(0)·t − a ∫(θ − θ(0)) + α ∫∫u − c ∫∫sign u        (|u| above any d)
      x(t) = x(0) + ẋ(0)·t + γ ∫∫θ

  The initial conditions of each window are nuisance parameters, projected out; the windows'
  information adds up, starting from a Gaussian prior (the design values, broad), so the
  estimate always has a covariance: the controller's margins are read from it. A window the
  current estimate does not predict (a tap, a hard stop) is left out by a χ² test. The bang
  windows hold |u| nearly constant, where d and α cannot be told apart; the windows of small
  commands (at rest), where the motor sees u only past d, give d's likelihood on a grid
  (``DeadZoneLikelihood``), folded into the motor's Gaussian as its marginal of c.
* **Noise** (``NoiseEstimate``): the position sensor's noise is the bench's, not a datasheet's.
  Every 100 ms window of position samples is fitted by its own x0 + v0·t + ½b·t² + g∫∫θ (a
  model that explains the ball's motion, manoeuvres included); the residuals' squares and
  degrees of freedom are pooled from a weak prior (a scaled-inverse-χ² posterior, so the
  estimate has a confidence), a window improbably noisy against the rest (a hard stop) left
  out, the result floored at the ADC's quantisation. The identification's weights, the
  filter's R (so the rest threshold read from its covariance) and the design's steady
  observer (the terminal set, the detour test, the tracker's reserve) use its upper
  confidence bound.
* **Plan**: minimum-time arcs (``planning.arcs``) of the *identified* model, in drive units
  (the voltage past the dead zone). The usable drive is (5 V · α̂ − ĉ − z·σ) / α̂: the lower
  confidence bound of the full-voltage drive (or the weakest plant's in range, where that is
  higher: the prior alone is broader than the range), less a reserve for the tracker sized
  from the noise its correction carries. Every 10 ms the remaining plan is re-solved warm from the
  plan's own servo state and the estimated ball (the servo's small errors are the tracker's).
  Rest is reached in the terminal set, not at the exact target: a re-plan that ends later
  than the plan in force is taken only if that plan, tracked on (the identified model, the
  tracking law and the angle guard, stepped to its end), would not end in the set with the
  servo in its rest band; arcs are then added as needed. (A path to the exact point from a
  state a little off the plan takes a time that grows as a root of the error: re-planned so
  every 10 ms, the end kept receding.) When the ball is off by far more than the estimate's
  noise (a tap, a new target) the plan is made from the state then.
* **Estimate** (``estimate_gamma``): a Kalman filter on (θ, θ̇, ẋ, x, δγ, q), δγ the error of
  the design's γ: the ball's acceleration error δγ·θ is followed as θ swings (a fixed-gain
  observer lags it by 1–2.5 mm/s through a stroke), γ is learnt from every sample and handed to
  the design. q is the encoder's rounding, which holds while the servo stays inside a count:
  a still servo's angle is known to within its count, and the ball's creep says where in it.
  What the model leaves out of the ball's acceleration is taken in proportion to |θ|
  (``_filter``): at rest the estimate is as quiet as the encoder allows.
  A jump of the ball's speed the model does not allow (a tap) is found by a CUSUM of the
  position innovations (``JumpDetector``), and the filter runs again over the samples since
  with the speed's variance grown by it (``_admit_jump``).
* **Track**: drive = plan drive + K (plan state − estimate), K a discrete LQR of the identified
  model.
* **Terminal regulator**: at the plan's end, if the error is inside the terminal LQR's set
  (``regulator_keeps``: the errors from which its closed loop keeps the ball in the rest band
  and its drive within the limit, predicted until inside its invariant ellipse, the Lyapunov
  level set on which both hold), the LQR takes over (else a near plan to it); it hands back to
  a fresh plan only if the state leaves that set grown. The ellipse alone left out a ball at
  rest inside the band but near its edge, and a minimum-time move to the target then swung
  the servo across the band. The plan's last stroke is a full-drive brake onto rest: handed
  over inside it, the gentler regulator left the brake half done and the servo coasted past
  level.
* **A sine** (``sine``): the plan goes to rest where the sine will be when it ends; the
  terminal regulator then holds the state on the sine's flat state with its drive (θ = ẍ/γ,
  ...) wherever its drive stays unsaturated (that set, not the rest band's, is a sine's).
* **Safety filter**: the angle barrier of ``guard`` (hard barrier only), built for the
  identified motor at its lower drive bound.
* **Dead-zone compensation**: u = v + d̂·clip(v / w, −1, 1): a ramp through zero whose width w
  is twice the standard deviation the estimate's noise gives the terminal drive, so noise does
  not flip ±d̂. At rest the terminal drive first loses that much (a soft threshold): without
  it the command crosses zero as often as the noise does.
"""

from __future__ import annotations

import bisect
import copy
import math
from collections import deque
from dataclasses import dataclass, field, replace
from typing import NamedTuple

import numpy as np
import scipy.linalg

from ballbeam.core.guard import AngleGuard, guarded_voltage, make_angle_guard, make_soft_cap
from ballbeam.core.model import BALL_POSITION, THETA, LinearModel, as_row4
from ballbeam.core.observer import (
    design_observer,
    measurement_noise_covariance,
    process_noise_covariance,
)
from ballbeam.core.planning.arcs import (
    ArcPlan,
    _replay,
    _step,
    plan_arcs,
    replan,
)
from ballbeam.core.planning.lag_hold import _Params
from ballbeam.core.plant import (
    EmulatedPlant,
    PlantPhysics,
    command_as_received,
    initial_noise,
    next_noise,
    read_sensors,
)
from ballbeam.errors import ConfigError, PlanningError

_C = np.array([[57.0, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 100.0]])
# A window is left out when its own best fit leaves χ² beyond dof + this many standard
# deviations of χ² (√(2·dof)).
_OUTLIER_SIGMAS = 6.0
# ... the same tail, for the noise estimate's F-test
_OUTLIER_TAIL = 0.5 * math.erfc(_OUTLIER_SIGMAS / math.sqrt(2.0))  # the normal's upper tail
# The dead zone's likelihood grid step [V] (a few mV: far below what an encoder count tells)
_DEADZONE_GRID_V = 0.005
# The encoder's reading beyond its rounding (the filter's state q) taken as white noise of
# this fraction of the rounding's deviation: none in truth; keeps the update well posed.
_ENCODER_WHITE_FRACTION = 0.1
# Singular values below this fraction of the largest: columns that coincide (counted once).
_RANK_TOLERANCE = 1e-9
# The ball's speed jumps (JumpDetector): a CUSUM's drift per sample and its threshold, in
# standard deviations of the position innovation.
_JUMP_DRIFT = 1.5
_JUMP_THRESHOLD = 12.0
# The filter's steps kept to run again after a jump, and how many samples before the
# detector's sum left zero the jump may have come (the sum leaves zero after it).
_JUMP_LOOKBACK = 200
_JUMP_LOOKBACK_MARGIN = 10


class JumpDetector:
    """A two-sided CUSUM of the filter's normalised position innovations: a jump of the
    ball's speed the model does not allow (a tap) makes them grow in proportion to the time
    since, and the sum crosses its threshold within tens of milliseconds (a 2 cm/s tap in
    about 30 ms at the design noise), where noise, and an estimate lagging the ball by less
    than the drift, do not take it there (``_JUMP_DRIFT``: one and a half deviations a
    sample; ``_JUMP_THRESHOLD``: twelve; docs/decisions.md has the measurements). At the
    crossing it returns the speed that built the position error since the sum left zero (at
    least the jump's: the sum leaves zero after the jump, not before) and the samples since;
    then it starts again."""

    def __init__(self) -> None:
        self.sums = [0.0, 0.0]  # up, down
        self.since = [0, 0]  # samples since each left zero

    def step(self, innovation_m: float, std_m: float, period_s: float = 1e-3
             ) -> tuple[float, int] | None:
        z = innovation_m / std_m
        for side, signed in enumerate((z, -z)):
            total = self.sums[side] + signed - _JUMP_DRIFT
            self.since[side] = self.since[side] + 1 if total > 0.0 else 0
            self.sums[side] = max(total, 0.0)
        side = 0 if self.sums[0] >= self.sums[1] else 1
        if self.sums[side] <= _JUMP_THRESHOLD:
            return None
        samples = self.since[side]
        self.sums, self.since = [0.0, 0.0], [0, 0]
        return innovation_m / (samples * period_s), samples


class WindowedLeastSquares:
    """Bayesian least squares of global parameters over windows, each window with its own
    nuisance parameters (its initial conditions) projected out. Starts from a Gaussian prior.
    The windows' sums are kept unscaled, so the noise variance ``noise_var`` (common to all
    windows) may be re-estimated as the run goes and every window re-weighted by it."""

    def __init__(self, prior_mean: np.ndarray, prior_std: np.ndarray, noise_std: float) -> None:
        prior_std = np.asarray(prior_std, dtype=float)
        if not (noise_std > 0.0 and np.all(prior_std > 0.0)):
            raise ConfigError("identification needs positive prior and noise deviations")
        self.prior_information = np.diag(1.0 / prior_std**2)
        self.prior_vector = self.prior_information @ np.asarray(prior_mean, dtype=float)
        self.data_information = np.zeros_like(self.prior_information)  # Σ ΦᵀΦ
        self.data_vector = np.zeros_like(self.prior_vector)  # Σ Φᵀy
        self.noise_var = noise_std**2
        self.windows = 0
        self.rejected = 0

    def add(self, y: np.ndarray, nuisance: np.ndarray, regressors: np.ndarray) -> bool:
        """One window: observations y (n,), nuisance columns (n, q), global regressors (n, p).
        False (and nothing learnt) when the window is not what the model predicts: its
        residual from the current estimate, the nuisance projected out, is tested by χ²
        against the noise and the estimate's own uncertainty (a tap, a hard stop)."""
        basis = np.linalg.qr(nuisance)[0]
        regressors_p = regressors - basis @ (basis.T @ regressors)
        y_p = y - basis @ (basis.T @ y)
        residual = y_p - regressors_p @ self.mean
        # (σ²I + Φ Σ Φᵀ)⁻¹ by Woodbury: p × p solves only
        projected = regressors_p.T @ residual
        inner = self.information + regressors_p.T @ regressors_p / self.noise_var
        chi2 = (
            float(residual @ residual) / self.noise_var
            - float(projected @ np.linalg.solve(inner, projected)) / self.noise_var**2
        )
        dof = len(y) - nuisance.shape[1]
        if dof <= 0 or chi2 > dof + _OUTLIER_SIGMAS * math.sqrt(2.0 * dof):
            self.rejected += 1
            return False
        self.data_information += regressors_p.T @ regressors_p
        self.data_vector += regressors_p.T @ y_p
        self.windows += 1
        return True

    @property
    def information(self) -> np.ndarray:
        result: np.ndarray = self.prior_information + self.data_information / self.noise_var
        return result

    @property
    def mean(self) -> np.ndarray:
        vector = self.prior_vector + self.data_vector / self.noise_var
        result: np.ndarray = np.linalg.solve(self.information, vector)
        return result

    @property
    def covariance(self) -> np.ndarray:
        result: np.ndarray = np.linalg.inv(self.information)
        return result


def _double_integral_of_held(values: np.ndarray, period_s: float) -> np.ndarray:
    """∫∫ of a zero-order-held sequence (n,) at the n + 1 sample times: exact. Rows (m, n)
    are sequences of their own: (m, n + 1)."""
    values = np.asarray(values, dtype=float)
    zero = np.zeros((*values.shape[:-1], 1))
    first = np.concatenate([zero, np.cumsum(values, axis=-1) * period_s], axis=-1)
    increments = period_s * first[..., :-1] + 0.5 * period_s**2 * values
    return np.concatenate([zero, np.cumsum(increments, axis=-1)], axis=-1)


def _integral_of_sampled(values: np.ndarray, period_s: float) -> np.ndarray:
    """∫ of a sampled signal (n,) at its sample times (trapezoids)."""
    return np.concatenate([[0.0], np.cumsum(0.5 * period_s * (values[1:] + values[:-1]))])


def servo_window(
    theta_rad: np.ndarray, command_v: np.ndarray, period_s: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(y, nuisance, regressors) of the servo over one window: θ at n + 1 samples, the n
    commands held between them. Regressors for (a, α, c = α·d)."""
    n = len(command_v)
    t = np.arange(n + 1) * period_s
    y = theta_rad - theta_rad[0]
    nuisance = np.column_stack([np.ones(n + 1), t])
    regressors = np.column_stack([
        -_integral_of_sampled(y, period_s),
        _double_integral_of_held(command_v, period_s),
        -_double_integral_of_held(np.sign(command_v), period_s),
    ])
    return y, nuisance, regressors


class DeadZoneLikelihood:
    """The dead zone d's log-likelihood on a grid, from servo windows whose commands are all
    small (at rest, ``|u|`` below any dead zone in range): there the motor sees
    u − d·sign u only where |u| > d, a model no least squares takes (d is not a linear
    parameter once some |u| is inside it), and the bang windows the least squares does take
    hold |u| nearly constant, where d and α cannot be told apart. Each window's likelihood is
    evaluated at every grid value with the servo's a and α as identified then (small drives:
    their error is far below the encoder's), the initial angle and rate projected out. A
    servo that stays put under |u| says d ≥ |u|; one that moves says how much got through."""

    def __init__(self, grid_v: np.ndarray, noise_std_rad: float) -> None:
        self.grid_v = np.asarray(grid_v, dtype=float)
        self.log_likelihood = np.zeros_like(self.grid_v)
        self.noise_var = noise_std_rad**2
        self.windows = 0
        self.rejected = 0

    def add(
        self, theta_rad: np.ndarray, command_v: np.ndarray, pole_per_s: float, alpha: float,
        period_s: float,
    ) -> bool:
        """One window (θ at n + 1 samples, the n commands held between them); False (nothing
        learnt) when no grid value explains it within the χ² test of the least squares (a tap
        or a hard stop)."""
        y, nuisance, regressors = servo_window(theta_rad, command_v, period_s)
        u = np.asarray(command_v, dtype=float)
        d = self.grid_v[:, None]
        through = np.where(np.abs(u) > d, u - d * np.sign(u), 0.0)  # (G, n)
        driven = _double_integral_of_held(through, period_s)
        # (the servo's own term, −a∫(θ − θ0), is the least squares' first regressor)
        predicted = alpha * driven + pole_per_s * regressors[:, 0]
        basis = np.linalg.qr(nuisance)[0]
        residual = y - predicted  # (G, n + 1)
        residual = residual - (residual @ basis) @ basis.T
        chi2 = np.sum(residual * residual, axis=1) / self.noise_var
        dof = len(y) - nuisance.shape[1]
        if float(chi2.min()) > dof + _OUTLIER_SIGMAS * math.sqrt(2.0 * dof):
            self.rejected += 1
            return False
        self.log_likelihood -= 0.5 * chi2
        self.windows += 1
        return True

    def posterior(self, mean_v: float, std_v: float) -> tuple[float, float]:
        """Mean and standard deviation of d under a Gaussian prior (``mean_v``, ``std_v``)
        times this likelihood, on the grid (d ≥ 0; the grid's step counted in)."""
        log_p = self.log_likelihood - 0.5 * ((self.grid_v - mean_v) / std_v) ** 2
        weights = np.exp(log_p - log_p.max())
        weights /= weights.sum()
        mean = float(weights @ self.grid_v)
        step = float(self.grid_v[1] - self.grid_v[0])
        variance = float(weights @ (self.grid_v - mean) ** 2) + step * step / 12.0
        return mean, math.sqrt(variance)


def ball_window(
    theta_rad: np.ndarray, position_m: np.ndarray, period_s: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(y, nuisance, regressors) of the ball over one window of samples (n,): regressor for γ."""
    n = len(position_m)
    t = np.arange(n) * period_s
    nuisance = np.column_stack([np.ones(n), t])
    once = _integral_of_sampled(theta_rad, period_s)
    twice = _integral_of_sampled(once, period_s)
    return np.asarray(position_m, dtype=float), nuisance, twice[:, None]


def noise_window(
    theta_rad: np.ndarray, position_m: np.ndarray, period_s: float
) -> tuple[float, int]:
    """(residual sum of squares, its degrees of freedom) of the position samples (n,) about
    the window's own best fit of x = x0 + v0·t + ½b·t² + g∫∫θ: the ball's motion as the model
    explains it (g any gain; b what it leaves out, constant over a short window), so what is
    left is the sensor's noise. Columns that coincide (θ held: ∫∫θ ∝ t²) count once."""
    n = len(position_m)
    t = np.arange(n) * period_s
    once = _integral_of_sampled(theta_rad, period_s)
    columns = np.column_stack([np.ones(n), t, t * t, _integral_of_sampled(once, period_s)])
    norms = np.linalg.norm(columns, axis=0)
    columns = columns / np.where(norms > 0.0, norms, 1.0)
    u, singular, _ = np.linalg.svd(columns, full_matrices=False)
    basis = u[:, singular > _RANK_TOLERANCE * singular[0]]
    y = np.asarray(position_m, dtype=float)
    residual = y - basis @ (basis.T @ y)
    return float(residual @ residual), n - basis.shape[1]


class NoiseEstimate:
    """The position sensor's noise variance σ², pooled from a scaled-inverse-χ² prior
    (``prior_std_m`` worth ``prior_dof`` degrees of freedom) and the residuals of windows
    (``noise_window``): after ν degrees of freedom the estimate's relative standard deviation
    (of σ) is 1/√(2ν). Floored at ``floor_m`` (the ADC's quantisation: no reading is finer).
    A window whose variance is improbably large against the pooled estimate (F-test, the
    tail of ``_OUTLIER_SIGMAS`` normal deviations; a tap, a hard stop) is left out; a small
    one is never refused (the estimate may only move towards trusting the sensor through
    many degrees of freedom, never through one window)."""

    def __init__(self, prior_std_m: float, prior_dof: float, floor_m: float) -> None:
        if not (prior_std_m > 0.0 and prior_dof > 0.0 and floor_m >= 0.0):
            raise ConfigError("the noise estimate needs a positive prior and weight")
        self.sum_squares_m2 = prior_dof * prior_std_m**2
        self.dof = float(prior_dof)
        self.floor_var_m2 = floor_m**2
        self.windows = 0
        self.rejected = 0

    def add(self, sum_squares_m2: float, dof: int) -> bool:
        # Imported here, not with this module: every daemon imports the module, whichever law
        # it runs, and windows are learnt by the planner (``identify``), never in a cycle.
        from scipy.stats import f as f_distribution

        if dof <= 0:
            return False
        ratio = sum_squares_m2 / dof / self.variance_m2
        if ratio > f_distribution.isf(_OUTLIER_TAIL, dof, self.dof):
            self.rejected += 1
            return False
        self.sum_squares_m2 += sum_squares_m2
        self.dof += dof
        self.windows += 1
        return True

    @property
    def variance_m2(self) -> float:
        return max(self.sum_squares_m2 / self.dof, self.floor_var_m2)

    @property
    def std_m(self) -> float:
        return math.sqrt(self.variance_m2)

    @property
    def relative_std(self) -> float:
        """The estimate's relative standard deviation (of σ)."""
        return 1.0 / math.sqrt(2.0 * self.dof)

    def upper_m(self, z: float) -> float:
        """σ's upper confidence bound, z standard deviations."""
        return self.std_m * (1.0 + z * self.relative_std)


@dataclass(frozen=True)
class Identified:
    """The plant as identified, with standard deviations: θ̈ = −a θ̇ + α·drive, ẍ = γ θ,
    drive = u − d·sign u for |u| > d."""

    pole_per_s: float
    alpha: float
    deadzone_v: float
    gamma: float
    covariance_motor: np.ndarray  # of (a, α, c = α·d)
    gamma_std: float

    def drive_std(self, command_v: float) -> float:
        """σ of α·(u − d) at a command u > d, in volts of drive (/α̂)."""
        g = np.array([0.0, command_v, -1.0])
        return math.sqrt(float(g @ self.covariance_motor @ g)) / self.alpha

    @property
    def deadzone_std_v(self) -> float:
        c = self.alpha * self.deadzone_v
        g = np.array([0.0, -c / self.alpha**2, 1.0 / self.alpha])
        return math.sqrt(float(g @ self.covariance_motor @ g))

    @property
    def alpha_std(self) -> float:
        return math.sqrt(float(self.covariance_motor[1, 1]))

    @property
    def params(self) -> _Params:
        return _Params(self.pole_per_s, self.alpha, self.gamma)

    def model(self) -> LinearModel:
        return LinearModel.from_gains(self.alpha, self.pole_per_s, self.gamma, _C)


@dataclass(frozen=True)
class Settings:
    """The candidate's settings (each with its reason)."""

    period_s: float = 1e-3
    voltage_limit_v: float = 5.0  # the command's bound
    theta_limit_rad: float = math.radians(52.0)  # the servo must never pass it
    # The sensors' resolution: datasheet facts (4096 counts a turn; a ±10 V 16-bit ADC over
    # the track's 10 V on a 0.4318 m beam).
    encoder_step_rad: float = 2.0 * math.pi / 4096.0
    adc_step_m: float = 20.0 / 2**16 * 0.4318 / 10.0
    # The position sensor's noise is the bench's, not a datasheet's: it is estimated online
    # (``NoiseEstimate``) from this prior, the design's nominal level worth this many degrees
    # of freedom (a factor of a few either way is not unlikely under it: the first window
    # outweighs it), and the design uses its upper confidence bound (``confidence_z``).
    position_noise_prior_m: float = 2e-4
    position_noise_prior_dof: float = 2.0
    noise_window: int = 100  # samples a noise window: an estimate within the first 0.1 s
    # Prior of the identification: the design's gains, broad enough for the plants in range.
    prior_alpha: float = 108.896
    prior_pole_per_s: float = 58.466
    prior_gamma: float = -0.41218
    # (a uniform spread over gains 0.8–1.2 and dead zones 0–0.4 V has these deviations)
    prior_relative_std: float = 0.12
    prior_deadzone_v: float = 0.2
    prior_deadzone_std_v: float = 0.12
    # The range the controller is for: the weakest motor (of the prior's gain) and the widest
    # dead zone. The drive's margins never assume a plant worse than this, so the first plan
    # (on the prior alone) drives as hard as the weakest plant in range can.
    weakest_motor_gain: float = 0.8
    widest_deadzone_v: float = 0.4
    # What the identified model leaves out, as the observer's process noise beyond the
    # identified gains' own uncertainty: drive [V] and ball acceleration [m/s²].
    unmodelled_drive_v: float = 0.05
    unmodelled_ball_m_s2: float = 0.01
    confidence_z: float = 3.0  # margins are z standard deviations
    servo_window: int = 40  # samples a servo window
    ball_window: int = 200  # samples a ball window
    identify_above_v: float = 0.5  # servo windows need every |u| above any dead zone in range
    identify_every: int = 100  # cycles between model updates
    replan_every: int = 10  # cycles between re-plans
    model_change: float = 0.01  # a relative change of the identified model that re-plans cold
    plan_theta_margin_rad: float = math.radians(0.3)  # the plan's angle stays this inside
    detour_position_m: float = 2e-3  # a re-plan that adds arcs only past this ball error ...
    detour_speed_m_s: float = 1e-2  # ... or this
    track_q: tuple[float, float, float, float] = (10.0, 0.0, 0.0, 1e4)
    track_r: float = 0.01
    terminal_q: tuple[float, float, float, float] = (100.0, 0.0, 0.0, 3e4)
    terminal_r: float = 1.0
    soft_zone_gain_per_s: float = 250.0  # the soft cap: allowed rate = gain × gap near it
    soft_rate_gain_per_s: float = 40.0  # how hard the rate is pulled back to the allowed rate
    rest_band_m: float = 5e-4  # the task's rest band: the ball within this of the target
    rest_band_rad: float = math.radians(0.5)  # ... and the servo within this of level
    terminal_exit_factor: float = 25.0  # the terminal LQR hands back beyond this × its level
    # γ's error a state of the estimator (a Kalman filter on (θ, θ̇, ẋ, x, δγ, q)) rather than
    # process noise of a fixed-gain observer: the ball's acceleration error γ̃·θ is followed
    # as θ swings, and γ is learnt from every sample
    estimate_gamma: bool = True


def dlqr(
    Ad: np.ndarray, Bd: np.ndarray, q: tuple[float, ...], r: float
) -> tuple[np.ndarray, np.ndarray]:
    """Discrete LQR: gain K (4,) and the Riccati solution P (4, 4)."""
    Q, R = np.diag(q), np.array([[r]])
    P = scipy.linalg.solve_discrete_are(Ad, Bd, Q, R)
    gain: np.ndarray = np.linalg.solve(R + Bd.T @ P @ Bd, Bd.T @ P @ Ad)[0]
    return gain, P


@dataclass
class _Design:
    """Everything derived from one identified model."""

    identified: Identified
    Ad: np.ndarray
    bd: np.ndarray
    L: np.ndarray
    K: np.ndarray
    K_terminal: np.ndarray
    P_terminal: np.ndarray
    terminal_level: float
    drive_limit_v: float  # the plan's drive
    drive_max_v: float  # the drive the guard may use (lower confidence bound at full command)
    ramp_v: float  # dead-zone compensation ramp half-width (terminal regulator)
    ramp_tracking_v: float  # ... while tracking a plan
    guard: AngleGuard
    reserve_v: float
    estimate_covariance: np.ndarray  # of the estimate's error (the observer's steady state)
    process_noise: np.ndarray  # (4, 4) of the filter that estimates γ's error as a state
    ball_process_noise: np.ndarray  # (4, 4) of a unit held ball acceleration
    measurement_noise: np.ndarray  # (2, 2)


def _design(identified: Identified, s: Settings, position_noise_m: float) -> _Design:
    """The design for ``identified`` and the position noise ``position_noise_m`` (σ)."""
    discrete = identified.model().discretize(s.period_s)
    Ad, Bd = discrete.Ad, discrete.Bd
    z = s.confidence_z
    U = s.voltage_limit_v
    observer = design_observer(
        discrete,
        input_noise_v=math.hypot(identified.drive_std(U), s.unmodelled_drive_v),
        ball_noise_m_s2=math.hypot(
            identified.gamma_std * s.theta_limit_rad, s.unmodelled_ball_m_s2
        ),
        angle_noise_rad=s.encoder_step_rad / math.sqrt(12.0),
        position_noise_m=position_noise_m,
    )
    K, _ = dlqr(Ad, Bd, s.track_q, s.track_r)
    K_t, P_t = dlqr(Ad, Bd, s.terminal_q, s.terminal_r)
    drive_max = _drive_max(identified, s)
    # Tracker's reserve: z σ of the drive the estimate's noise puts into the correction.
    reserve = z * math.sqrt(float(K @ observer.P_estimate @ K))
    ramp = 2.0 * math.sqrt(float(K_t @ observer.P_estimate @ K_t))
    ramp_tracking = 2.0 * math.sqrt(float(K @ observer.P_estimate @ K))
    # The terminal set: the largest level set of the terminal LQR's Lyapunov function on which
    # its drive stays within the limit and the ball, less z σ of the estimate's error, within
    # the rest band (so once in it, the ball never leaves the band; the servo's band is left
    # to the regulator's convergence: a set inside both is too thin to be entered).
    P_inv = np.linalg.inv(P_t)
    sigma = np.sqrt(np.diag(observer.P_estimate))
    level = min(
        drive_max**2 / float(K_t @ P_inv @ K_t),
        (s.rest_band_m - z * sigma[BALL_POSITION]) ** 2 / P_inv[BALL_POSITION, BALL_POSITION],
    )
    theta_sigma = math.sqrt(float(observer.P_estimate[THETA, THETA]))
    # the estimate's error: half an encoder count of bias when the servo slows, and noise
    guard_limit = s.theta_limit_rad - 0.5 * s.encoder_step_rad - z * theta_sigma
    # the smooth cap (a rate loop onto the braking curve) acts first, so the tracker pushing
    # the servo toward the limit is met continuously, not by the dead-beat barrier
    soft = make_soft_cap(
        theta_limit_rad=guard_limit - s.encoder_step_rad,
        alpha=identified.alpha,
        alpha_beta=identified.pole_per_s,
        brake_v=drive_max,
        zone_gain_per_s=s.soft_zone_gain_per_s,
        rate_gain_per_s=s.soft_rate_gain_per_s,
    )
    guard = make_angle_guard(
        theta_limit_rad=guard_limit,
        soft=soft,
        alpha=identified.alpha,
        alpha_beta=identified.pole_per_s,
        brake_v=drive_max,
        voltage_limit_v=drive_max,
        Ad=Ad,
        Bd=Bd,
    )
    return _Design(
        identified=identified,
        Ad=Ad,
        bd=Bd[:, 0].copy(),
        L=observer.L,
        K=K,
        K_terminal=K_t,
        P_terminal=P_t,
        terminal_level=level,
        drive_limit_v=max(0.5, drive_max - reserve),
        estimate_covariance=observer.P_estimate,
        process_noise=process_noise_covariance(
            discrete,
            math.hypot(identified.drive_std(U), s.unmodelled_drive_v),
            0.0,  # the filter's: in proportion to |θ| (``_filter``)
        ),
        ball_process_noise=process_noise_covariance(discrete, 0.0, 1.0),
        measurement_noise=measurement_noise_covariance(
            _C, _ENCODER_WHITE_FRACTION * s.encoder_step_rad / math.sqrt(12.0), position_noise_m
        ),
        drive_max_v=drive_max,
        ramp_v=ramp,
        ramp_tracking_v=ramp_tracking,
        guard=guard,
        reserve_v=reserve,
    )


def _drive_max(identified: Identified, s: Settings) -> float:
    """The drive a full command gives at least [V of drive, in the identified α's units]: its
    lower confidence bound, or the weakest plant's in range where that is higher (a
    Gaussian's z σ reaches past a bounded range: the prior's 3σ is a motor at 64 %)."""
    U = s.voltage_limit_v
    statistical = U - identified.deadzone_v - s.confidence_z * identified.drive_std(U)
    weakest_alpha = s.weakest_motor_gain * s.prior_alpha
    in_range = (U - s.widest_deadzone_v) * weakest_alpha / identified.alpha
    return max(statistical, min(in_range, U - identified.deadzone_v))


# --- the cycle's arithmetic in plain floats ------------------------------------------------
# Every product the law makes each cycle is written out over Python floats in a fixed order
# (no numpy, no BLAS): a BLAS kernel picks its own summation order and fused multiply-adds,
# so a numpy product of tiny matrices differs in its last bits between machines, and a
# replay would not be bit for bit; and a numpy call on a 5 × 5 matrix costs its overhead,
# not its arithmetic.

Vec = tuple[float, ...]
Mat = tuple[tuple[float, ...], ...]


def _vec(values: np.ndarray) -> Vec:
    return tuple(float(v) for v in np.asarray(values, dtype=float).ravel())


def _mat(values: np.ndarray) -> Mat:
    return tuple(_vec(row) for row in np.asarray(values, dtype=float))


def _dot4(a: Vec, b: Vec) -> float:
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2] + a[3] * b[3]


def _dot6(a: Vec, b: Vec) -> float:
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2] + a[3] * b[3] + a[4] * b[4] + a[5] * b[5]


def _quadratic4(m: Mat, e: Vec) -> float:
    """eᵀ M e, M (4, 4): (M e) first, then e · (M e)."""
    return _dot4(e, tuple(_dot4(row, e) for row in m))


@dataclass(frozen=True)
class FilterRows:
    """What one filter step needs of a design, as tuples of floats (made once a design)."""

    period_s: float
    Ad: Mat  # (4, 4)
    bd: Vec  # (4,)
    process_noise: Mat  # (4, 4)
    ball_process_noise: Mat  # (4, 4): of a unit held ball acceleration
    measurement_noise: Mat  # (2, 2): of (57 θ, 100 x), beyond the encoder's count
    angle_gain: float  # the measurement's rows: (angle_gain·θ, position_gain·x)
    position_gain: float
    encoder_step_rad: float


def filter_step(
    rows: FilterRows,
    state: Vec,
    covariance: Mat,
    drive_v: float,
    measured: tuple[float, float] | None,
    ball_noise_var: float,
) -> tuple[Vec, Mat, tuple[float, float] | None]:
    """One Kalman step (predict with the drive held over the period, then correct with the
    measurement ``measured`` = (angle_gain·(θ + q), position_gain·x)) on (θ, θ̇, ẋ, x, δγ, q),
    where ẍ = (γ̂ + δγ)·θ, δγ is constant and q is the encoder's rounding error. q is the
    count's whole uncertainty (variance step²/12) and is not white: it holds while the servo
    stays inside its count and is new once the servo has swept one, so it decays at
    ρ = exp(−|θ̇| h / step). A still servo's angle is then known only to within its count,
    and the ball's slow creep from that unmeasured fraction tells where in the count it is
    (a white rounding error would average to certainty, and the creep would bias the
    position's innovations until the jump detector took it for a tap).
    ``ball_noise_var`` scales the ball's process noise. Returns the state (6,), its
    covariance (6, 6) and the position's innovation with its predicted standard deviation
    [m]; with no measurement (a period without its sample) the prediction, its covariance
    and no innovation."""
    h = rows.period_s
    theta, rate = state[0], state[1]
    step_rad = rows.encoder_step_rad
    rho = math.exp(-abs(rate) * h / step_rad)
    a = rows.Ad
    # δγ·∫θ and δγ·∫∫θ over the step, θ moving at its rate (a fast stroke moves θ by a
    # percent of itself in one step)
    F = (
        (*a[0], 0.0, 0.0),
        (*a[1], 0.0, 0.0),
        (*a[2], h * (theta + 0.5 * rate * h), 0.0),
        (*a[3], 0.5 * h * h * (theta + rate * h / 3.0), 0.0),
        (0.0, 0.0, 0.0, 0.0, 1.0, 0.0),
        (0.0, 0.0, 0.0, 0.0, 0.0, rho),
    )
    bd = rows.bd
    prior = (*(_dot6(F[i], state) + bd[i] * drive_v for i in range(4)), state[4], rho * state[5])
    # F P Fᵀ + Q: P is symmetric (kept so), so P's rows are its columns; F's last rows pick
    # δγ and ρ q, so F P's are P's (the latter by ρ); the upper triangle is mirrored
    FP = (
        *(tuple(_dot6(row, column) for column in covariance) for row in F[:4]),
        covariance[4],
        tuple(rho * v for v in covariance[5]),
    )
    q, qb = rows.process_noise, rows.ball_process_noise
    rounding_var = (1.0 - rho * rho) * step_rad * step_rad / 12.0
    upper = [
        [
            _dot6(FP[i], F[j]) + q[i][j] + ball_noise_var * qb[i][j] if j < 4
            else FP[i][4] if j == 4
            else rho * FP[i][5] + (rounding_var if i == 5 else 0.0)
            for j in range(i, 6)
        ]
        for i in range(6)
    ]
    P = tuple(
        tuple(upper[i][j - i] if j >= i else upper[j][i - j] for j in range(6)) for i in range(6)
    )
    if measured is None:
        return prior, P, None
    ga, gp = rows.angle_gain, rows.position_gain
    hp0 = tuple(ga * (u + v) for u, v in zip(P[0], P[5], strict=True))  # H P: θ + q, and x
    hp1 = tuple(gp * v for v in P[3])
    r = rows.measurement_noise
    s00, s01 = (hp0[0] + hp0[5]) * ga + r[0][0], hp0[3] * gp + r[0][1]
    s10, s11 = (hp1[0] + hp1[5]) * ga + r[1][0], hp1[3] * gp + r[1][1]
    det = s00 * s11 - s01 * s10
    # the gain (S⁻¹ H P)ᵀ, S (2, 2) inverted in closed form
    gain = tuple(
        ((s11 * hp0[i] - s01 * hp1[i]) / det, (s00 * hp1[i] - s10 * hp0[i]) / det)
        for i in range(6)
    )
    r0 = measured[0] - ga * (prior[0] + prior[5])
    r1 = measured[1] - gp * prior[3]
    new_state = tuple(prior[i] + (gain[i][0] * r0 + gain[i][1] * r1) for i in range(6))
    # P − G H P, symmetrised: ½ of it and its transpose, entry by entry
    updated = [[0.0] * 6 for _ in range(6)]
    for i in range(6):
        gi0, gi1 = gain[i]
        row = P[i]
        for j in range(i, 6):
            gj0, gj1 = gain[j]
            value = 0.5 * (
                (row[j] - (gi0 * hp0[j] + gi1 * hp1[j])) + (P[j][i] - (gj0 * hp0[i] + gj1 * hp1[i]))
            )
            updated[i][j] = updated[j][i] = value
    symmetric = tuple(tuple(row) for row in updated)
    return new_state, symmetric, (r1 / gp, math.sqrt(s11) / gp)


class _FilterInput(NamedTuple):
    """One filter step's inputs: run again from another state after a jump (_admit_jump), or
    with the sample that came late for it (take_late). A named tuple: one is made every cycle
    (a frozen dataclass sets each field through ``object.__setattr__``)."""

    state: Vec
    covariance: Mat
    rows: FilterRows
    drive_v: float
    measured: tuple[float, float] | None  # None: the period's sample had not come
    ball_noise_var: float

    def run(self) -> tuple[Vec, Mat, tuple[float, float] | None]:
        return filter_step(
            self.rows, self.state, self.covariance, self.drive_v, self.measured,
            self.ball_noise_var,
        )


class _ObserverInput(NamedTuple):
    """The fixed-gain observer's step inputs (without estimate_gamma), kept as _FilterInput's
    are: ``covariance`` is empty, ``rows`` the cycle's."""

    state: Vec
    covariance: Mat
    rows: _CycleRows
    drive_v: float
    measured: tuple[float, float] | None
    ball_noise_var: float = 0.0

    def run(self) -> tuple[Vec, Mat, tuple[float, float] | None]:
        return _observe(self.rows, self.state, self.drive_v, self.measured), (), None


@dataclass(frozen=True)
class EndCheck:
    """The terminal set (:func:`regulator_keeps`'s arguments), and what the planner needs to
    tell where the plan in force ends if it is tracked on: the identified model over a period
    and the tracking gain."""

    period_s: float
    Ad: Mat
    bd: Vec
    K: Vec
    drive_v: float
    closed_loop: Mat
    closed_loop_stride: Mat
    K_terminal: Vec
    P_terminal: Mat
    band_m: float
    level: float
    guard: AngleGuard
    # the rest band's servo angle: the regulator, a gentle servo loop, would take long to
    # level a servo the plan's end left outside it
    theta_band_rad: float

    def admits(self, error: Vec, factor: float = 1.0) -> bool:
        """Whether ``error`` (from rest at the target) is inside the terminal set grown by
        ``factor`` (a level: its bounds by the square root)."""
        scale = math.sqrt(factor)
        return regulator_keeps(
            self.closed_loop, self.closed_loop_stride, self.K_terminal, self.P_terminal, error,
            scale * self.band_m, scale * self.drive_v, factor * self.level,
        )

    def keeps(self, plan: ArcPlan, elapsed_s: float, estimate: Vec) -> bool:
        """Whether ``plan``, tracked on from ``estimate`` (absolute position) at ``elapsed_s``
        into it, ends inside the terminal set (and the servo inside the rest band)."""
        end = self.tracked_end(plan, elapsed_s, estimate)
        return bool(abs(end[THETA]) <= self.theta_band_rad) and self.admits(end)

    def tracked_end(self, plan: ArcPlan, elapsed_s: float, estimate: Vec) -> Vec:
        """The state (relative to the target) at the end of ``plan`` tracked on from
        ``estimate``: the identified model stepped every period under u = u_plan + K·(r − x)
        through the angle guard (its barrier and the drive's bound are what leave an error
        uncorrected where the plan rides the angle limit), the plan sampled at once."""
        steps = max(0, math.ceil((plan.duration_s - elapsed_s) / self.period_s))
        samples = plan.sample(elapsed_s + self.period_s * np.arange(steps))
        (a00, a01, a02, a03), (a10, a11, a12, a13), (a20, a21, a22, a23), (
            a30, a31, a32, a33) = self.Ad
        b0, b1, b2, b3 = self.bd
        k0, k1, k2, k3 = self.K
        guard = self.guard
        x0, x1, x2, x3 = estimate
        x3 -= plan.target_m
        for (r0, r1, r2, r3), drive_v in zip(
            samples.states.tolist(), samples.input_v.tolist(), strict=True
        ):
            u = guarded_voltage(guard, (x0, x1, x2, x3), drive_v + (
                k0 * (r0 - x0) + k1 * (r1 - x1) + k2 * (r2 - x2) + k3 * (r3 - x3)))
            x0, x1, x2, x3 = (
                a00 * x0 + a01 * x1 + a02 * x2 + a03 * x3 + b0 * u,
                a10 * x0 + a11 * x1 + a12 * x2 + a13 * x3 + b1 * u,
                a20 * x0 + a21 * x1 + a22 * x2 + a23 * x3 + b2 * u,
                a30 * x0 + a31 * x1 + a32 * x2 + a33 * x3 + b3 * u,
            )
        return (x0, x1, x2, x3)


@dataclass(frozen=True)
class _CycleRows:
    """A design's matrices the cycle uses, as tuples of floats (made once a design)."""

    design: _Design
    filter: FilterRows
    L: Mat  # (4, 2): the fixed-gain observer's (without estimate_gamma)
    K: Vec
    K_terminal: Vec
    P_terminal: Mat
    estimate_covariance: Mat
    # the largest level of the terminal LQR's Lyapunov function on which its drive stays
    # within the drive limit (a sine's terminal set)
    unsaturated_level: float
    # the terminal LQR's closed loop over one period and over ``_STRIDE`` periods
    closed_loop: Mat
    closed_loop_stride: Mat
    # the terminal set's ball band: the rest band less z σ of the ball's estimate
    terminal_band_m: float
    end_check: EndCheck

    @classmethod
    def of(cls, d: _Design, s: Settings) -> _CycleRows:
        K_terminal, P_terminal = _vec(d.K_terminal), _mat(d.P_terminal)
        covariance = _mat(d.estimate_covariance)
        z = s.confidence_z
        # (elementwise, so each entry is the same on every machine: no BLAS)
        closed_loop = _mat(d.Ad - np.outer(d.bd, d.K_terminal))
        closed_loop_stride = _power(closed_loop, _STRIDE)
        terminal_band_m = s.rest_band_m - z * math.sqrt(covariance[BALL_POSITION][BALL_POSITION])
        return cls(
            design=d,
            filter=FilterRows(
                period_s=s.period_s, Ad=_mat(d.Ad), bd=_vec(d.bd),
                process_noise=_mat(d.process_noise),
                ball_process_noise=_mat(d.ball_process_noise),
                measurement_noise=_mat(d.measurement_noise),
                angle_gain=float(_C[0, THETA]), position_gain=float(_C[1, BALL_POSITION]),
                encoder_step_rad=s.encoder_step_rad,
            ),
            L=_mat(d.L), K=_vec(d.K), K_terminal=K_terminal,
            P_terminal=P_terminal, estimate_covariance=covariance,
            unsaturated_level=d.drive_max_v**2 / _inverse_quadratic(P_terminal, K_terminal),
            closed_loop=closed_loop,
            closed_loop_stride=closed_loop_stride,
            terminal_band_m=terminal_band_m,
            end_check=EndCheck(
                period_s=s.period_s, Ad=_mat(d.Ad), bd=_vec(d.bd), K=_vec(d.K),
                drive_v=d.drive_max_v, closed_loop=closed_loop,
                closed_loop_stride=closed_loop_stride, K_terminal=K_terminal,
                P_terminal=P_terminal,
                # where the estimate is noisier than the band, no state is sure to rest in
                # it: the band itself, then
                band_m=terminal_band_m if terminal_band_m > 0.0 else s.rest_band_m,
                level=d.terminal_level, guard=d.guard, theta_band_rad=s.rest_band_rad,
            ),
        )


def _matmul4(a: Mat, b: Mat) -> Mat:
    columns = tuple(zip(*b, strict=True))
    return tuple(tuple(_dot4(row, column) for column in columns) for row in a)


def _power(m: Mat, n: int) -> Mat:
    result = m
    for _ in range(n - 1):
        result = _matmul4(result, m)
    return result


# The terminal set's prediction: every period for the first _EXACT_STEPS (where a moving
# servo or ball peaks), then every _STRIDE periods (the regulator's slow tail moves the ball
# by far less than the band's margin in that time), for at most _HORIZON_STEPS.
_EXACT_STEPS = 100
_STRIDE = 10
_HORIZON_STEPS = 3000


def regulator_keeps(
    closed_loop: Mat, closed_loop_stride: Mat, K: Vec, P: Mat, error: Vec,
    band_m: float, drive_v: float, level: float,
) -> bool:
    """Whether the linear regulator u = −K·e, from ``error``, keeps the ball within
    ``band_m`` and its drive within ``drive_v`` at every step to come: its closed loop
    predicted until the error is inside the invariant level set eᵀPe ≤ ``level`` (on which
    both bounds hold for good). The set of such errors is the regulator's largest
    constraint-admissible set, of which that level set is an inner ellipse."""
    e, k = error, 0
    while k < _HORIZON_STEPS:
        if abs(e[BALL_POSITION]) > band_m or abs(_dot4(K, e)) > drive_v:
            return False
        # (the level falls every step: looked at every stride's steps is soon enough)
        if k % _STRIDE == 0 and _quadratic4(P, e) <= level:
            return True
        step, k = (closed_loop, k + 1) if k < _EXACT_STEPS else (closed_loop_stride, k + _STRIDE)
        e = (_dot4(step[0], e), _dot4(step[1], e), _dot4(step[2], e), _dot4(step[3], e))
    return False


def _inverse_quadratic(m: Mat, v: Vec) -> float:
    """vᵀ M⁻¹ v for a symmetric positive definite M, by Cholesky in plain floats (a replay
    makes the rows again from a recorded design: no LAPACK bits)."""
    n = len(v)
    lower = [[0.0] * n for _ in range(n)]
    for i in range(n):
        for j in range(i + 1):
            total = m[i][j] - sum(lower[i][k] * lower[j][k] for k in range(j))
            lower[i][j] = math.sqrt(total) if i == j else total / lower[j][j]
    y: list[float] = []
    for i in range(n):  # L y = v: vᵀ M⁻¹ v = |y|²
        y.append((v[i] - sum(lower[i][k] * y[k] for k in range(i))) / lower[i][i])
    return sum(value * value for value in y)


# (time [s], σ̂ [m], its relative standard deviation, the σ the design uses [m]) of a noise
# window (and of the prior, at 0)
NoiseWindow = tuple[float, float, float, float]


@dataclass
class Identification:
    """What the windows have taught (the motor's and the ball's least squares, the position
    noise), and where the next windows start, as sample indices of the run.

    The planner learns it, not the cycle: each window is a QR or an SVD (and the noise's an F
    quantile), milliseconds on a loaded machine, where the cycle has one. A design request
    carries the samples since the windows of the identification the law holds; its answer
    carries the identification they give (:func:`identify`, on a copy)."""

    motor: WindowedLeastSquares
    ball: WindowedLeastSquares
    noise: NoiseEstimate
    deadzone: DeadZoneLikelihood
    servo_from: int = 0
    ball_from: int = 0
    noise_from: int = 0
    learnt_cycles: int = 0  # the cycles whose samples are learnt: 0 .. learnt_cycles − 1

    @classmethod
    def prior(cls, s: Settings) -> Identification:
        rel = s.prior_relative_std
        prior_c = s.prior_alpha * s.prior_deadzone_v
        motor = WindowedLeastSquares(
            np.array([s.prior_pole_per_s, s.prior_alpha, prior_c]),
            np.array([
                rel * s.prior_pole_per_s,
                rel * s.prior_alpha,
                math.hypot(s.prior_alpha * s.prior_deadzone_std_v, rel * prior_c),
            ]),
            s.encoder_step_rad / math.sqrt(12.0),
        )
        noise = NoiseEstimate(
            s.position_noise_prior_m, s.position_noise_prior_dof, s.adc_step_m / math.sqrt(12.0)
        )
        ball = WindowedLeastSquares(
            np.array([s.prior_gamma]), np.array([rel * abs(s.prior_gamma)]),
            noise.upper_m(s.confidence_z),
        )
        deadzone = DeadZoneLikelihood(
            np.arange(0.0, s.voltage_limit_v / 2, _DEADZONE_GRID_V),
            s.encoder_step_rad / math.sqrt(12.0),
        )
        return cls(motor, ball, noise, deadzone)

    @property
    def first_needed(self) -> int:
        """The first sample a window still to come needs."""
        return min(self.servo_from, self.ball_from, self.noise_from)

    def position_noise_m(self, s: Settings) -> float:
        """The position noise σ a design assumes: the estimate's upper confidence bound."""
        return self.noise.upper_m(s.confidence_z)

    def identified(self, s: Settings) -> Identified:
        mean, covariance = self.motor_estimate()
        a, alpha, c = mean
        return Identified(
            pole_per_s=float(max(a, 1.0)),
            alpha=float(max(alpha, 1.0)),
            deadzone_v=float(min(max(c / alpha, 0.0), s.voltage_limit_v / 2)),
            gamma=float(self.ball.mean[0]),
            covariance_motor=covariance,
            gamma_std=math.sqrt(float(self.ball.covariance[0, 0])),
        )

    def motor_estimate(self) -> tuple[np.ndarray, np.ndarray]:
        """The motor's (a, α, c) mean and covariance: the least squares', with what the rest
        windows say of d folded in. The grid's posterior of d (the least squares' marginal of
        d as its prior) is made the joint's marginal of c = α·d by a Gaussian update with the
        observation of c that has exactly that effect (so a, α move with c as they
        correlate)."""
        mean, covariance = self.motor.mean, self.motor.covariance
        if not self.deadzone.windows:
            return mean, covariance
        alpha = max(float(mean[1]), 1.0)
        prior_var = float(covariance[2, 2])
        d_mean, d_std = self.deadzone.posterior(
            float(mean[2]) / alpha, math.sqrt(prior_var) / alpha
        )
        post_mean, post_var = alpha * d_mean, (alpha * d_std) ** 2
        if not post_var < prior_var:
            return mean, covariance
        observed_var = 1.0 / (1.0 / post_var - 1.0 / prior_var)
        observed = observed_var * (post_mean / post_var - float(mean[2]) / prior_var)
        gain = covariance[:, 2] / (prior_var + observed_var)
        return (
            mean + gain * (observed - float(mean[2])),
            covariance - np.outer(gain, covariance[2, :]),
        )

    def learn(
        self, s: Settings, theta_rad: Vec, position_m: Vec, command_v: Vec, first_sample: int,
        through_cycle: int,
    ) -> list[NoiseWindow]:
        """The windows that the cycles ``learnt_cycles`` .. ``through_cycle`` complete, in the
        order the cycles complete them. The samples (θ and x of each cycle, the command of
        each but the last) are the run's from index ``first_sample``. At each re-design's
        cycle the ball's windows are re-weighted by the noise then, from the next on."""
        def window(values: Vec, start: int, end: int) -> np.ndarray:
            return np.array(values[start - first_sample : end - first_sample])

        noise_windows: list[NoiseWindow] = []
        for cycle in range(self.learnt_cycles, through_cycle + 1):
            if cycle > 1 and (cycle - 1) % s.identify_every == 0:
                self.ball.noise_var = self.position_noise_m(s) ** 2
            k = cycle + 1  # samples so far
            # servo windows: samples servo_from .. k − 1 with the commands between them
            if k - self.servo_from > s.servo_window:
                commands = window(command_v, self.servo_from, k - 1)
                angles = window(theta_rad, self.servo_from, k)
                if np.all(np.abs(commands) >= s.identify_above_v):
                    self.motor.add(*servo_window(angles, commands, s.period_s))
                elif np.all(np.abs(commands) < s.identify_above_v):
                    a, alpha, _ = self.motor.mean
                    self.deadzone.add(angles, commands, float(a), float(alpha), s.period_s)
                self.servo_from = k - 1
            if k - self.ball_from >= s.ball_window:
                self.ball.add(*ball_window(
                    window(theta_rad, self.ball_from, k), window(position_m, self.ball_from, k),
                    s.period_s,
                ))
                self.ball_from = k
            if k - self.noise_from >= s.noise_window:
                self.noise.add(*noise_window(
                    window(theta_rad, self.noise_from, k), window(position_m, self.noise_from, k),
                    s.period_s,
                ))
                noise_windows.append((
                    k * s.period_s, self.noise.std_m, self.noise.relative_std,
                    self.position_noise_m(s),
                ))
                self.noise_from = k
        self.learnt_cycles = through_cycle + 1
        return noise_windows


@dataclass(frozen=True)
class PlanRequest:
    """What the law would pass to the planner at its step ``cycle``: the state, target,
    identified model and limits, and (a warm re-plan) the plan in force with the choice the
    law made of its answers. :func:`solve_plan_request` answers it, in this process or in
    another (the request pickles: floats, tuples and an ``ArcPlan``)."""

    cycle: int  # the controller's step whose estimate the request is of
    kind: str  # "cold" (the grid planner), "near" (four arcs, else cold), "warm" (a re-plan)
    state: tuple[float, float, float, float]  # (θ, θ̇, ẋ, x) planned from
    target_m: float
    pole_per_s: float
    alpha: float
    gamma: float
    drive_limit_v: float
    theta_max_rad: float
    # "warm": the plan in force, the time into it, and what the law decided from the estimate
    plan: ArcPlan | None = None
    elapsed_s: float = 0.0
    far: bool = False  # the ball is far off the plan: a detour is taken
    moved: bool = False  # the identified model moved since the plan was made
    cold_state: tuple[float, float, float, float] | None = None  # a detour's cold plan from
    # the estimate, and what tells whether the plan in force ends in the terminal set from it
    # (a re-plan that ends later is then not taken)
    estimate: tuple[float, float, float, float] | None = None
    end_check: EndCheck | None = None
    # (a sine) the plan ends where the sine is then: (amplitude m, period s, offset m), and
    # the sine's time at the request's state
    sine: tuple[float, float, float] | None = None
    sine_time_s: float = 0.0


@dataclass(frozen=True)
class PlanAnswer:
    """The planner's answer to the request of ``request_cycle``: a plan for the request's
    state at that cycle (a law adopting it later samples it that much further on), or None
    (the law keeps its plan); ``counts``: the solves made, for the controller's tallies;
    ``error``: a failure other than the planner finding no plan (PlanningError), in words."""

    request_cycle: int
    plan: ArcPlan | None
    counts: tuple[str, ...] = ()
    error: str | None = None
    # the plan's arc boundaries, made where it is solved (the cycle only samples it)
    sampler: _PlanSampler | None = field(default=None, compare=False)


@dataclass(frozen=True)
class DesignRequest:
    """A re-design the law wants at its step ``cycle``: the identification it holds, the
    samples since that one's windows (from the run's sample ``first_sample``: θ and x through
    ``cycle``, the commands before it), and (estimate_gamma) γ as the filter has it then with
    its σ, ``gamma_error`` of it the filter's own error state, re-based when the design is
    taken."""

    cycle: int
    settings: Settings
    identification: Identification
    first_sample: int
    theta_rad: Vec
    position_m: Vec
    command_v: Vec
    filter_gamma: tuple[float, float] | None = None  # (γ, its σ)
    gamma_error: float = 0.0


@dataclass(frozen=True)
class DesignAnswer:
    """The design of the request of ``request_cycle``, and the identification it is of
    (with the noise windows learnt for it)."""

    request_cycle: int
    design: _Design
    identification: Identification
    noise_windows: tuple[NoiseWindow, ...] = ()
    # the design's matrices as the cycle's tuples, made where it is solved
    rows: _CycleRows | None = field(default=None, compare=False)


class Learnt(NamedTuple):
    """What a design request's samples teach: the identification, its noise windows, the
    plant as identified and the noise level a design is for."""

    identification: Identification
    noise_windows: tuple[NoiseWindow, ...]
    identified: Identified
    position_noise_m: float


def identify(request: DesignRequest) -> Learnt:
    """The request's samples learnt, on a copy of its identification."""
    s = request.settings
    identification = copy.deepcopy(request.identification)
    noise_windows = identification.learn(
        s, request.theta_rad, request.position_m, request.command_v, request.first_sample,
        request.cycle,
    )
    identified = identification.identified(s)
    if request.filter_gamma is not None:  # γ is the filter's
        gamma, gamma_std = request.filter_gamma
        identified = replace(identified, gamma=gamma, gamma_std=gamma_std)
    return Learnt(
        identification, tuple(noise_windows), identified, identification.position_noise_m(s)
    )


def solve_design_request(request: DesignRequest) -> DesignAnswer:
    """The identification of the request's samples and the design (observer, tracker,
    terminal set, guard) of the plant it identifies. Pure."""
    learnt = identify(request)
    design = _design(learnt.identified, request.settings, learnt.position_noise_m)
    return DesignAnswer(
        request.cycle, design, learnt.identification, learnt.noise_windows,
        _CycleRows.of(design, request.settings),
    )


def answer_with_design(request: DesignRequest, design: _Design) -> DesignAnswer:
    """The answer to ``request`` with ``design`` (a replay's: the run's recorded one) in
    place of its own: only the identification is learnt again (its last bits are this
    machine's LAPACK's, and reach the run only through designs, which are the run's)."""
    learnt = identify(request)
    return DesignAnswer(request.cycle, design, learnt.identification, learnt.noise_windows)


def solve_request(request: PlanRequest | DesignRequest) -> PlanAnswer | DesignAnswer:
    """What the planner does with a request of either kind."""
    if isinstance(request, DesignRequest):
        return solve_design_request(request)
    return solve_plan_request(request)


def solve_plan_request(request: PlanRequest) -> PlanAnswer:
    """The plan the law asked for: the solves (and the choice among them) it used to make
    inside its cycle, with the plan's sampler. Pure; PlanningError where the grid planner
    finds no plan is an answer of None."""
    answer = _solve_plan(request)
    if answer.plan is None:
        return answer
    return replace(answer, sampler=_PlanSampler(answer.plan))


def _solve_plan(request: PlanRequest) -> PlanAnswer:
    if request.sine is not None and request.kind != "warm":
        return _solve_to_sine(request)
    r = request
    params = _Params(r.pole_per_s, r.alpha, r.gamma)
    state = np.array(r.state)
    if r.kind == "warm":
        assert r.plan is not None
        return _solve_warm(r, params, state)
    if r.kind == "near":
        empty = ArcPlan((), (), (), (0.0, 0.0, 0.0, 0.0), r.target_m, r.drive_limit_v,
                        r.theta_max_rad, params.pole_per_s, params.alpha, params.gamma)
        found = replan(empty, 0.0, state, target_m=r.target_m, params=params)
        if found is not None:
            return PlanAnswer(r.cycle, found, ("near",))
    return _solve_cold(r, state)


# A plan to a sine ends where the sine is when the plan ends: its duration and its end are
# found together by fixed-point iteration (the sine moves little within a plan's change of
# duration: a few iterations agree to a cycle).
_SINE_PLAN_ITERATIONS = 4


def _solve_to_sine(r: PlanRequest) -> PlanAnswer:
    """A plan (cold, or near: four arcs first) from the request's state to rest where the
    sine is at the plan's end (the follower takes the sine's own speed from there)."""
    assert r.sine is not None and r.kind != "warm"
    duration_s = 0.0
    answer = PlanAnswer(r.cycle, None)
    for _ in range(_SINE_PLAN_ITERATIONS):
        target_m = _sine_state(r.sine, r.sine_time_s + duration_s)[0][3]
        answer = _solve_plan(replace(r, target_m=target_m, sine=None))
        if answer.plan is None or abs(answer.plan.duration_s - duration_s) < 0.5 * 1e-3:
            break
        duration_s = answer.plan.duration_s
    return answer


def _sine_state(
    sine: tuple[float, float, float], time_s: float, gamma: float = 1.0, alpha: float = 1.0,
    pole_per_s: float = 0.0,
) -> tuple[tuple[float, float, float, float], float]:
    """The state (θ, θ̇, ẋ, x) and drive that hold the model on the sine at ``time_s``: its
    flat outputs (θ = ẍ/γ, θ̇ = x⃛/γ, u = (θ̈ + aθ̇)/α with θ̈ = x⁗/γ), in plain floats."""
    amplitude, period, offset = sine
    w = 2.0 * math.pi / period
    sin, cos = math.sin(w * time_s), math.cos(w * time_s)
    theta = -amplitude * w * w * sin / gamma
    theta_rate = -amplitude * w * w * w * cos / gamma
    theta_accel = amplitude * w * w * w * w * sin / gamma
    state = (theta, theta_rate, amplitude * w * cos, offset + amplitude * sin)
    return state, (theta_accel + pole_per_s * theta_rate) / alpha


def _solve_cold(r: PlanRequest, state: np.ndarray, counts: tuple[str, ...] = ()) -> PlanAnswer:
    try:
        plan = plan_arcs(
            LinearModel.from_gains(r.alpha, r.pole_per_s, r.gamma, _C),
            state,
            target_m=r.target_m,
            voltage_limit_v=r.drive_limit_v,
            theta_max_rad=r.theta_max_rad,
        )
    except PlanningError as error:
        return PlanAnswer(r.cycle, None, (*counts, "cold"), error=f"no plan: {error}")
    return PlanAnswer(r.cycle, plan, (*counts, "cold"))


def _solve_warm(r: PlanRequest, params: _Params, from_state: np.ndarray) -> PlanAnswer:
    plan = r.plan
    assert plan is not None
    warm = replace(plan, voltage_limit_v=r.drive_limit_v)
    # a root with arcs added is taken only for a detour or a new model: the repairs that
    # would find one are most of a warm re-plan's work otherwise, and thrown away
    new = replan(
        warm, r.elapsed_s, from_state, target_m=r.target_m, params=params,
        repairs=r.far or r.moved,
    )
    counts: tuple[str, ...] = ("replan",)
    check = r.end_check
    if check is not None and r.estimate is not None and not r.far:
        # Rest is reached in the terminal set, not at the exact target: a path to the exact
        # target from a state a little off the plan can take far longer than the plan has
        # left (its time grows as a root of the error), and re-planned every period it ends
        # ever later. So the plan in force is kept while, tracked on, it ends in the set; a
        # path with arcs added is taken only when it does not.
        left_s = plan.duration_s - r.elapsed_s
        if new is not None and new.duration_s <= left_s + check.period_s:
            return PlanAnswer(r.cycle, new, counts)
        if check.keeps(plan, r.elapsed_s, r.estimate):
            return PlanAnswer(r.cycle, None, (*counts, "kept"))
        if not r.moved:
            new = replan(
                warm, r.elapsed_s, from_state, target_m=r.target_m, params=params, repairs=True
            )
        if new is not None:
            return PlanAnswer(r.cycle, new, counts)
    keeps_arcs = new is not None and len(new.input_v) <= len(plan.shifted(r.elapsed_s)[0])
    if new is not None and (keeps_arcs or r.far or r.moved):
        return PlanAnswer(r.cycle, new, counts)
    if new is None:
        counts += ("missed",)
    if (r.far or (r.moved and new is None)) and r.cold_state is not None:
        if r.sine is not None:
            detour = _solve_to_sine(replace(r, kind="near", state=r.cold_state))
            return replace(detour, counts=(*counts, *detour.counts))
        return _solve_cold(r, np.array(r.cold_state), counts)
    return PlanAnswer(r.cycle, None, counts)


class _PlanSampler:
    """``ArcPlan.sample`` at one time in plain floats (``arcs._step``, the closed form
    ``_propagate`` evaluates over arrays), with the plan's arc boundaries computed once:
    ``sample`` recomputes them at each call, which for a plan of a few arcs is a quarter of
    the law's cycle."""

    def __init__(self, plan: ArcPlan) -> None:
        self.plan = plan
        self.edges = plan.switch_times_s
        self._edges: Vec = _vec(np.asarray(self.edges))
        self.bounds = [plan.start] + [
            _replay(plan.params, plan.start, plan.input_v[: i + 1], plan.duration_s_each[: i + 1])
            for i in range(len(plan.input_v))
        ]

    def at(self, time_s: float) -> tuple[np.ndarray, float]:
        """The plan's state (4,) and input at ``time_s``."""
        k = bisect.bisect_right(self._edges, time_s) - 1
        if k < 0:
            return np.array(self.plan.start, dtype=float), 0.0
        if k >= len(self.plan.input_v):
            return np.zeros(4), 0.0
        u = float(self.plan.input_v[k])
        state = _step(self.plan.params, self.bounds[k], u, time_s - self._edges[k])
        return np.array(state), u


@dataclass
class CycleRecord:
    """What one cycle did (for plots and metrics)."""

    command_v: float
    plan_state: np.ndarray
    plan_drive_v: float  # the drive asked (plan, correction, safety filter)
    terminal: bool
    feedforward_v: float = 0.0  # the plan's own drive (0 under the terminal regulator)
    estimate: np.ndarray | None = None  # the state estimate the cycle used


@dataclass
class ReplanningController:
    """The candidate controller. ``step`` takes one cycle's measurements and returns the
    command; ``set_target`` changes the target (re-planned from the state then)."""

    settings: Settings
    initial_state: np.ndarray
    target_m: float = 0.0
    # a sine to follow instead of a target: (amplitude m, period s, offset m); its time is
    # ``sine_time_s``, which the caller sets before each step
    sine: tuple[float, float, float] | None = None
    sine_time_s: float = field(init=False, default=0.0)
    design: _Design = field(init=False)
    identification: Identification = field(init=False)  # as of the design in force
    estimate: np.ndarray = field(init=False)
    plan: ArcPlan | None = field(init=False, default=None)
    plan_start_cycle: int = field(init=False, default=0)
    terminal: bool = field(init=False, default=False)
    cycle: int = field(init=False, default=0)
    replans: int = field(init=False, default=0)
    missed: int = field(init=False, default=0)
    cold_plans: int = field(init=False, default=0)
    near_plans: int = field(init=False, default=0)
    kept_plans: int = field(init=False, default=0)  # later-ending re-plans not taken
    jumps: int = field(init=False, default=0)  # the ball's speed jumps admitted (_admit_jump)
    _jumps: JumpDetector = field(init=False, default_factory=lambda: JumpDetector())
    # the filter's (or the fixed-gain observer's) last steps, for a jump or a late sample to
    # run it again from before (_admit_jump, take_late)
    _recent: deque[_FilterInput | _ObserverInput] = field(
        init=False, default_factory=lambda: deque(maxlen=_JUMP_LOOKBACK)
    )
    _last_drive_v: float = field(init=False, default=0.0)
    # the samples (θ, x, command) from the run's sample _samples_from on: those the next
    # design request carries to the identification's windows
    _theta: list[float] = field(init=False, default_factory=list)
    _position: list[float] = field(init=False, default_factory=list)
    _command: list[float] = field(init=False, default_factory=list)
    _samples_from: int = field(init=False, default=0)
    _gamma_error: float = field(init=False, default=0.0)  # the filter's δγ (estimate_gamma)
    _rounding_rad: float = field(init=False, default=0.0)  # ... and its encoder rounding q
    # the filter's covariance of (θ, θ̇, ẋ, x, δγ, q), rows of floats (estimate_gamma)
    _covariance: Mat = field(init=False, default=())
    _cycle_rows: _CycleRows | None = field(init=False, default=None)
    # Deferred planning (the law over a planner): a plan wanted is a request, answered later
    # through ``adopt``; at most one is outstanding (a newer one is dropped meanwhile), and
    # ``issued`` is the request this step made, for whoever runs the planner to take.
    deferred: bool = field(init=False, default=False)
    outstanding: PlanRequest | None = field(init=False, default=None)
    issued: PlanRequest | None = field(init=False, default=None)
    # ... and so the re-design from each new identification (Riccati equations: tens of ms)
    design_outstanding: DesignRequest | None = field(init=False, default=None)
    design_issued: DesignRequest | None = field(init=False, default=None)
    _sampler: _PlanSampler | None = field(init=False, default=None)
    # the prior's and each noise window's, as the designs taken learnt them
    noise_history: list[NoiseWindow] = field(init=False, default_factory=list)

    def __post_init__(self) -> None:
        s = self.settings
        self.identification = Identification.prior(s)
        self.noise_history.append((
            0.0, self.identification.noise.std_m, self.identification.noise.relative_std,
            self.position_noise_m,
        ))
        self.design = _design(self.identification.identified(s), s, self.position_noise_m)
        self.estimate = np.array(self.initial_state, dtype=float)

    def _rows(self) -> _CycleRows:
        """The design in force as the cycle's tuples (made again when the design changes)."""
        rows = self._cycle_rows
        if rows is None or rows.design is not self.design:
            rows = self._cycle_rows = _CycleRows.of(self.design, self.settings)
        return rows

    @property
    def identified(self) -> Identified:
        return self.design.identified

    @property
    def position_noise_m(self) -> float:
        """The position noise σ the next design assumes (the identification's, as taken)."""
        return self.identification.position_noise_m(self.settings)

    def set_target(self, target_m: float) -> None:
        self.target_m = float(target_m)
        self._drop_plan()
        self.terminal = False

    def _drop_plan(self) -> None:
        """No plan in force; an answer still to come is of the state before (not adopted)."""
        self.plan = None
        self.outstanding = None

    def _request(self, request: PlanRequest) -> None:
        """Every plan the law makes is asked for here: solved now and adopted, or (deferred)
        issued, unless one is outstanding (the planner never falls behind: the next request
        is of a newer state)."""
        if self.deferred:
            if self.outstanding is None:
                self.outstanding = self.issued = request
            return
        self.outstanding = request
        self.adopt(solve_plan_request(request))

    def adopt(self, answer: PlanAnswer) -> bool:
        """Take the answer to the outstanding request: its plan (if any) is in force from
        now, timed from the request's cycle (it was made for the state then). False (and
        nothing changes) for an answer to another request."""
        request = self.outstanding
        if request is None or answer.request_cycle != request.cycle:
            return False
        self.outstanding = None
        for count in answer.counts:
            if count == "replan":
                self.replans += 1
            elif count == "missed":
                self.missed += 1
            elif count == "cold":
                self.cold_plans += 1
            elif count == "near":
                self.near_plans += 1
            elif count == "kept":
                self.kept_plans += 1
        if answer.plan is not None and not self.terminal:
            self.plan = answer.plan
            self.plan_start_cycle = request.cycle
            if answer.sampler is not None:
                self._sampler = answer.sampler
        return True

    def _request_design(self, request: DesignRequest) -> None:
        if self.deferred:
            if self.design_outstanding is None:
                self.design_outstanding = self.design_issued = request
            return
        self.design_outstanding = request
        self.adopt_design(solve_design_request(request))

    def adopt_design(self, answer: DesignAnswer) -> bool:
        """Take the re-design of the outstanding identification: the filter's γ error is
        re-based on the γ the design took (what it learnt since stays). False (and nothing
        changes) for an answer to another request."""
        request = self.design_outstanding
        if request is None or answer.request_cycle != request.cycle:
            return False
        self.design_outstanding = None
        self._gamma_error -= request.gamma_error
        self.design = answer.design
        if answer.rows is not None:
            self._cycle_rows = answer.rows
        self.identification = answer.identification
        self.noise_history.extend(answer.noise_windows)
        # the samples no window to come needs
        done = self.identification.first_needed - self._samples_from
        if done > 0:
            del self._theta[:done], self._position[:done], self._command[:done]
            self._samples_from += done
        return True

    def _plan_request(self, kind: str, state: np.ndarray) -> PlanRequest:
        d = self.design
        p = d.identified.params
        return PlanRequest(
            cycle=self.cycle, kind=kind, state=_row(state), target_m=self.target_m,
            pole_per_s=p.pole_per_s, alpha=p.alpha, gamma=p.gamma,
            drive_limit_v=d.drive_limit_v,
            theta_max_rad=self.settings.theta_limit_rad - self.settings.plan_theta_margin_rad,
            sine=self.sine, sine_time_s=self.sine_time_s,
        )

    def _reference(self) -> tuple[tuple[float, float, float, float], float]:
        """What the terminal regulator holds the state on, and its drive: rest at the target,
        or the sine's flat state now (the identified model's)."""
        if self.sine is None:
            return (0.0, 0.0, 0.0, self.target_m), 0.0
        p = self.design.identified.params
        return _sine_state(self.sine, self.sine_time_s, p.gamma, p.alpha, p.pole_per_s)

    def _clipped(self, state: np.ndarray | None) -> np.ndarray:
        """The state to plan from (default: the estimate), its angle inside the plan's."""
        s = self.settings
        state = (self.estimate if state is None else state).copy()
        limit = s.theta_limit_rad - s.plan_theta_margin_rad
        state[THETA] = float(np.clip(state[THETA], -limit, limit))
        return state

    # --- one cycle --------------------------------------------------------------------

    def step(self, theta_rad: float | None, position_m: float | None) -> CycleRecord:
        """One cycle on the period's sample (θ, x), or on none (both None: its sample has
        not come; the filter predicts only, and the identification's windows get the
        prediction, which a late sample replaces: take_late)."""
        if not self.cycle:
            if theta_rad is None or position_m is None:
                raise ValueError("the first control cycle needs a sample")
            d = self.design
            self.estimate = np.array(
                [theta_rad, self.initial_state[1], self.initial_state[2], position_m]
            )
            initial = scipy.linalg.block_diag(
                d.estimate_covariance, d.identified.gamma_std**2,
                self.settings.encoder_step_rad**2 / 12.0,
            )
            # the position is one sample's: its error is that sample's noise, not the steady
            # filter's (which has averaged a run of them; so trusted, the first sample's
            # error was blamed on γ and the ball's speed through the first strokes)
            initial[BALL_POSITION, :] = initial[:, BALL_POSITION] = 0.0
            initial[BALL_POSITION, BALL_POSITION] = self.position_noise_m**2
            self._covariance = _mat(initial)
        else:
            self._estimate(theta_rad, position_m)
        self._observed(theta_rad, position_m)
        record = self._drive()
        record.command_v = self._compensate(record.plan_drive_v)
        self._driven(record.command_v)
        return record

    def coast(self, applied_v: float) -> None:
        """A period the law made no command for (the loop overran it, or held 0 V in a
        fault): the plant drove ``applied_v``. The filter predicts on that drive, the plan's
        clock runs on, and the identification's windows get the prediction and the drive
        (a late sample replaces the prediction: take_late); nothing is planned or decided
        (the next step does), so a stall's periods cost a prediction each."""
        if not self.cycle:
            raise ValueError("the first control cycle needs a sample")
        self._estimate(None, None)
        self._observed(None, None)
        self._driven(applied_v)

    def _estimate(self, theta_rad: float | None, position_m: float | None) -> None:
        """The filter's step to this period, on its sample (θ, x) or on none."""
        rows = self._rows()
        y = None
        if theta_rad is not None and position_m is not None:
            y = (rows.filter.angle_gain * theta_rad, rows.filter.position_gain * position_m)
        if self.settings.estimate_gamma:
            self._filter(y)
        else:
            step = _ObserverInput(self.estimate.tolist(), (), rows, self._last_drive_v, y)
            self._recent.append(step)
            self.estimate = np.array(step.run()[0])

    def _observed(self, theta_rad: float | None, position_m: float | None) -> None:
        """The period's sample (or the prediction) for the identification's windows, and at
        every ``identify_every`` cycles the re-design they ask for."""
        self._theta.append(float(self.estimate[THETA]) if theta_rad is None else theta_rad)
        self._position.append(
            float(self.estimate[BALL_POSITION]) if position_m is None else position_m
        )
        if self.cycle and self.cycle % self.settings.identify_every == 0:
            self._request_design(self._design_request())

    def _driven(self, command_v: float) -> None:
        """The period's command, as the plant drove it (the identified dead zone taken out
        for the filter's next prediction); the period is over."""
        self._command.append(command_v)
        self._last_drive_v = _dead_zone(command_v, self.design.identified.deadzone_v)
        self.cycle += 1

    def _filter(self, y: tuple[float, float] | None) -> None:
        """One Kalman step on (θ, θ̇, ẋ, x, δγ, q): ẍ = (γ̂ + δγ)·θ, δγ constant, q the
        encoder's rounding (``filter_step``)."""
        s = self.settings
        # what the model leaves out of the ball's acceleration is a fraction of γθ (the
        # nonlinear ball, a gain; all of unmodelled_ball_m_s2 at the angle limit); at θ = 0 the
        # servo's unmeasured fraction of a count is the filter's rounding state, not noise
        ball_noise_var = (
            s.unmodelled_ball_m_s2 * float(self.estimate[THETA]) / s.theta_limit_rad
        ) ** 2
        step = _FilterInput(
            (*self.estimate.tolist(), self._gamma_error, self._rounding_rad), self._covariance,
            self._rows().filter,
            self._last_drive_v, y, ball_noise_var,
        )
        self._recent.append(step)
        state, covariance, innovation = step.run()
        self._take_filtered(state, covariance)
        # the detector counts in deviations of the noise: until a window has measured it,
        # the prior's σ may be off by the whole range and its sums tell nothing
        if innovation is None or not self.identification.noise.windows:
            return
        jump = self._jumps.step(*innovation, s.period_s)
        if jump is not None:
            self._admit_jump(*jump)

    def take_late(self, theta_rad: float, position_m: float, age_cycles: int) -> bool:
        """The sample of ``age_cycles`` cycles ago, which came after its cycle had gone on
        without it: the filter runs again from that cycle with it, through the cycles since
        with the drives they sent (a Kalman filter's answer to a measurement out of
        sequence; the commands sent meanwhile stay what they were), and the identification's
        windows get it in place of the prediction. Whether it was taken: a sample older than
        the filter remembers, or than one taken since, is history (nothing changes)."""
        recent = self._recent
        index = len(recent) - age_cycles
        if age_cycles <= 0 or index < 0 or any(
            recent[i].measured is not None for i in range(index, len(recent))
        ):
            return False
        rows = self._rows().filter
        first = recent[index]._replace(
            measured=(rows.angle_gain * theta_rad, rows.position_gain * position_m)
        )
        recent[index] = first
        self._run_again(index, first.state, first.covariance)
        sample = self.cycle - age_cycles - self._samples_from
        if 0 <= sample < len(self._theta):
            self._theta[sample], self._position[sample] = theta_rad, position_m
        return True

    def _design_request(self) -> DesignRequest:
        """A re-design from the samples since the identification's windows (γ the filter's,
        with estimate_gamma: the design takes it, and the filter's state is re-based)."""
        s = self.settings
        first = self.identification.first_needed
        offset = first - self._samples_from
        filter_gamma, gamma_error = None, 0.0
        if s.estimate_gamma:
            gamma_error = self._gamma_error
            filter_gamma = (
                self.design.identified.gamma + gamma_error, math.sqrt(self._covariance[4][4])
            )
        return DesignRequest(
            self.cycle, s, self.identification, first, tuple(self._theta[offset:]),
            tuple(self._position[offset:]), tuple(self._command[offset:]), filter_gamma,
            gamma_error,
        )

    def _admit_jump(self, speed_m_s: float, samples: int) -> None:
        """The ball's speed jumped (a tap) by at most ``speed_m_s``, a little before the
        detector's sum left zero ``samples`` ago: the filter runs again over the samples
        since, from its state there with the speed's variance grown by that much and the
        position's by what the jump built before (τ·jump, τ up to ``_JUMP_LOOKBACK_MARGIN``
        samples), so that those samples, not the model, say how fast the ball goes now (at
        rest the model is trusted so much that a tap would take the filter a second to
        believe, and its γ error would take the blame meanwhile). Not from before the jump:
        the samples before it would pull the speed back towards the old one."""
        self.jumps += 1
        start = max(0, len(self._recent) - samples)
        first = self._recent[start]
        # the jump came up to the margin's samples before the sum left zero, τ earlier
        # (uniform): the state there is off by the jump in speed and by τ·jump in position
        tau_max_s = _JUMP_LOOKBACK_MARGIN * self.settings.period_s
        v2 = speed_m_s * speed_m_s
        grown = [list(row) for row in first.covariance]
        grown[2][2] += v2
        grown[2][3] += v2 * tau_max_s / 2.0
        grown[3][2] += v2 * tau_max_s / 2.0
        grown[3][3] += v2 * tau_max_s * tau_max_s / 3.0
        self._run_again(start, first.state, tuple(tuple(row) for row in grown))

    def _run_again(self, start: int, state: Vec, covariance: Mat) -> None:
        """The remembered filter steps from ``start`` on, run again from ``state`` and
        ``covariance``; each step's inputs are rewritten (a later re-run starts from these),
        and where they end is the estimate."""
        recent = self._recent
        for index in range(start, len(recent)):
            step = recent[index]._replace(state=state, covariance=covariance)
            recent[index] = step
            state, covariance, _ = step.run()
        self._take_filtered(state, covariance)

    @property
    def ball_gain(self) -> tuple[float, float]:
        """The filter's γ [m/s² per rad] and its standard deviation (``estimate_gamma``)."""
        return (
            self.design.identified.gamma + self._gamma_error, math.sqrt(self._covariance[4][4])
        )

    @property
    def estimate_std(self) -> np.ndarray:
        """(4,) the standard deviations of the estimate's (θ, θ̇, ẋ, x) that the filter
        states (``estimate_gamma``)."""
        return np.sqrt([self._covariance[i][i] for i in range(4)])

    def _take_filtered(self, state: Vec, covariance: Mat) -> None:
        """The filter's result as the estimate (with the γ filter: its δγ and covariance)."""
        if self.settings.estimate_gamma:
            self.estimate = np.array(state[:4])
            self._gamma_error, self._rounding_rad = state[4], state[5]
            self._covariance = covariance
        else:
            self.estimate = np.array(state)

    def _error(self) -> Vec:
        e0, e1, e2, e3 = self.estimate.tolist()
        if self.sine is None:
            return (e0, e1, e2, e3 - self.target_m)
        r0, r1, r2, r3 = self._reference()[0]
        return (e0 - r0, e1 - r1, e2 - r2, e3 - r3)

    def _in_terminal_set(self, factor: float = 1.0) -> bool:
        """Inside the terminal set: at a target, where the regulator keeps the ball in the
        rest band; on a sine, where its drive stays within the limit (the band is the
        sine's to keep, not the set's)."""
        rows = self._rows()
        error = self._error()
        if self.sine is not None:
            return _quadratic4(rows.P_terminal, error) <= factor * rows.unsaturated_level
        return rows.end_check.admits(error, factor)

    def _left_terminal_set(self) -> bool:
        """Whether the state has left the terminal set grown by ``terminal_exit_factor`` (the
        estimate's noise alone must not hand back)."""
        return not self._in_terminal_set(self.settings.terminal_exit_factor)

    def request_plan(self, state: np.ndarray) -> None:
        """Ask for a cold plan from ``state`` (the run's start, before its first step)."""
        self._request(self._plan_request("cold", self._clipped(np.array(state, dtype=float))))

    def _plan_from_estimate(self, near: bool = False, state: np.ndarray | None = None) -> None:
        """A fresh plan from the estimate (or ``state``); ``near``: close to the target, where
        the four-arc guess solves it directly (no grid plan). A plan not found keeps the
        plan in force."""
        self._request(self._plan_request("near" if near else "cold", self._clipped(state)))

    def _elapsed(self) -> float:
        return (self.cycle - self.plan_start_cycle) * self.settings.period_s

    def _drive(self) -> CycleRecord:
        d = self.design
        if self.sine is not None and not self.terminal and self._in_terminal_set():
            # on a sine the regulator follows wherever its drive stays unsaturated: a plan
            # (to rest where the sine will be) is for outside that set only
            self.terminal = True
            self._drop_plan()
        if self.terminal and self._left_terminal_set():
            self.terminal = False
            self._drop_plan()
            self._plan_from_estimate(near=True)
        if not self.terminal and self.plan is None:
            if self._in_terminal_set():
                self.terminal = True
            else:
                self._plan_from_estimate()
        if not self.terminal and self.plan is not None:
            self._maybe_replan()
        plan = self.plan
        if not self.terminal and plan is not None and self._elapsed() >= plan.duration_s:
            if self._in_terminal_set():
                self.terminal = True
            else:  # outside the terminal set: a (small) minimum-time move to it
                self._plan_from_estimate(near=True)
                plan = self.plan
        if self.terminal or (plan is None and self.sine is not None):
            # (a sine, its plan being solved: follow it meanwhile rather than drive nothing)
            drive = -_dot4(self._rows().K_terminal, self._error())
            held, feedforward = self._reference()
            reference = np.array(held)
        elif plan is None:  # no plan yet (it is being solved): nothing to track, no drive
            drive = 0.0
            reference = np.array([0.0, 0.0, 0.0, self.target_m])
            feedforward = 0.0
        else:
            state, feedforward = self._plan_sampler(plan).at(self._elapsed())
            reference = state.copy()
            reference[BALL_POSITION] += plan.target_m
            r, e = reference.tolist(), self.estimate.tolist()
            error = (r[0] - e[0], r[1] - e[1], r[2] - e[2], r[3] - e[3])
            drive = feedforward + _dot4(self._rows().K, error)
        if self.terminal:
            # at rest every drive smaller than the estimate's noise is a reaction to noise:
            # a soft threshold (continuous) leaves it out (the sine's own drive is no reaction)
            drive = math.copysign(max(abs(drive) - self._ramp_v(), 0.0), drive)
        if self.sine is not None and (self.terminal or plan is None):
            drive += feedforward
        drive = guarded_voltage(d.guard, as_row4(self.estimate), drive)
        return CycleRecord(0.0, reference, drive, self.terminal, feedforward, self.estimate.copy())

    def _maybe_replan(self) -> None:
        s = self.settings
        plan = self.plan
        assert plan is not None
        if (self.cycle - self.plan_start_cycle) % s.replan_every or self.outstanding is not None:
            return
        elapsed = self._elapsed()
        sampler = self._plan_sampler(plan)
        edges = sampler.edges
        if len(edges) >= 2 and elapsed >= edges[-2]:
            return  # the last arc: tracked to its end, where the terminal regulator takes over
        on_plan = sampler.at(elapsed)[0]
        est = self.estimate
        d = self.design
        # the plan's own servo state, the estimated ball (absolute position); a re-plan is
        # for the identified model and drive as they are now
        from_state = np.array([on_plan[0], on_plan[1], est[2], est[3]])
        moved = _moved(plan, d.identified.params, d.drive_limit_v, s.model_change)
        far = abs(est[3] - (on_plan[3] + plan.target_m)) > s.detour_position_m or abs(
            est[2] - on_plan[2]
        ) > s.detour_speed_m_s
        self._request(replace(
            self._plan_request("warm", from_state),
            target_m=plan.target_m,  # (a sine's plan ends where the sine was to be)
            plan=plan, elapsed_s=elapsed, far=bool(far), moved=moved,
            cold_state=_row(self._clipped(from_state if moved else None)),
            estimate=_row(est),
            end_check=self._rows().end_check if self.sine is None else None,
        ))

    def _plan_sampler(self, plan: ArcPlan) -> _PlanSampler:
        if self._sampler is None or self._sampler.plan is not plan:
            self._sampler = _PlanSampler(plan)
        return self._sampler

    def _ramp_v(self) -> float:
        """Twice the σ of the terminal drive the estimate's error carries: from the design's
        steady observer, or the filter's running covariance (``estimate_gamma``), the
        encoder's rounding given: that share of the error moves only as the servo crosses a
        count, so the compensation cannot chatter on it (counted, a sine's small drives went
        under-compensated)."""
        d = self.design
        if not self.settings.estimate_gamma:
            return d.ramp_v
        C, K = self._covariance, self._rows().K_terminal
        # Kᵀ (P − c cᵀ / P_qq) K, c the state's covariance with q
        with_rounding = _dot4(K, tuple(row[5] for row in C[:4]))
        return 2.0 * math.sqrt(max(
            _quadratic4(tuple(row[:4] for row in C[:4]), K) - with_rounding**2 / C[5][5], 0.0
        ))

    def _compensate(self, drive_v: float) -> float:
        d = self.design
        dz = d.identified.deadzone_v
        ramp = max(self._ramp_v() if self.terminal else d.ramp_tracking_v, 1e-6)
        command = drive_v + dz * max(-1.0, min(1.0, drive_v / ramp))
        limit = self.settings.voltage_limit_v
        return max(-limit, min(limit, command))


def _observe(
    rows: _CycleRows, estimate: Vec, drive_v: float, y: tuple[float, float] | None
) -> Vec:
    """The fixed-gain observer's step (without estimate_gamma): predict, then correct (with
    no measurement, the prediction)."""
    f = rows.filter
    prior = tuple(_dot4(f.Ad[i], estimate) + f.bd[i] * drive_v for i in range(4))
    if y is None:
        return prior
    r0 = y[0] - f.angle_gain * prior[THETA]
    r1 = y[1] - f.position_gain * prior[BALL_POSITION]
    return tuple(prior[i] + (rows.L[i][0] * r0 + rows.L[i][1] * r1) for i in range(4))


def _moved(plan: ArcPlan, params: _Params, drive_v: float, tolerance: float) -> bool:
    """Whether the model or the drive a plan was made with differ from these by more than
    ``tolerance`` (relative)."""
    pairs = (
        (plan.voltage_limit_v, drive_v), (plan.alpha, params.alpha),
        (plan.pole_per_s, params.pole_per_s), (plan.gamma, params.gamma),
    )
    return any(abs(new - old) > tolerance * abs(old) for old, new in pairs)


def _row(state: np.ndarray) -> tuple[float, float, float, float]:
    return (float(state[0]), float(state[1]), float(state[2]), float(state[3]))


def _dead_zone(command_v: float, deadzone_v: float) -> float:
    if abs(command_v) <= deadzone_v:
        return 0.0
    return command_v - math.copysign(deadzone_v, command_v)


@dataclass(frozen=True)
class ClosedLoopRun:
    """A closed-loop run of the candidate on the emulated plant, one row a cycle."""

    time_s: np.ndarray  # (n,) end of each cycle
    states: np.ndarray  # (n, 4) true state at the end of each cycle
    peak_theta_rad: np.ndarray  # (n,) largest |θ| over the cycle's physics steps
    command_v: np.ndarray  # (n,)
    plan_drive_v: np.ndarray  # (n,) the drive asked before compensation
    feedforward_v: np.ndarray  # (n,) the plan's own drive
    reference: np.ndarray  # (n, 4)
    estimate: np.ndarray  # (n, 4) the estimate each cycle used (of the state at its start)
    terminal: np.ndarray  # (n,) bool
    target_m: np.ndarray  # (n,)
    controller: ReplanningController


def run_closed_loop(
    plant: EmulatedPlant,
    initial_state: np.ndarray,
    duration_s: float,
    *,
    seed: int,
    settings: Settings | None = None,
    substeps: int = 10,
    targets: tuple[tuple[float, float], ...] = ((0.0, 0.0),),
) -> ClosedLoopRun:
    """The candidate on ``plant`` from ``initial_state`` for ``duration_s``; ``targets``: a
    step schedule ((time_s, target_m), ...) from 0. Taps are the plant's own."""
    # the sensors' resolution is a datasheet's; their noise the controller estimates
    s = settings or Settings(encoder_step_rad=plant.encoder_step_rad, adc_step_m=plant.adc_step_m)
    rng = np.random.default_rng(seed)
    physics = PlantPhysics(plant)
    state = np.array(initial_state, dtype=float)
    noise = initial_noise(plant, rng)
    schedule = sorted(targets)
    controller = ReplanningController(s, state.copy(), target_m=schedule[0][1])
    n = round(duration_s / s.period_s)
    states = np.zeros((n, 4))
    peaks, commands, drives, feedforward = np.zeros(n), np.zeros(n), np.zeros(n), np.zeros(n)
    references, terminal, target = np.zeros((n, 4)), np.zeros(n, dtype=bool), np.zeros(n)
    estimates = np.zeros((n, 4))
    next_target = 1
    for k in range(n):
        if next_target < len(schedule) and k * s.period_s >= schedule[next_target][0] - 1e-12:
            controller.set_target(schedule[next_target][1])
            next_target += 1
        reading = read_sensors(plant, state, noise)
        record = controller.step(
            reading.angle_counts * plant.encoder_step_rad,
            reading.position_counts * plant.adc_step_m,
        )
        before = abs(float(state[THETA]))
        state, peak = physics.advance_with_peak(
            state, command_as_received(record.command_v), substeps, from_step=k * substeps
        )
        noise = next_noise(plant, noise, rng)
        states[k], peaks[k] = state, max(before, peak)
        commands[k], drives[k] = record.command_v, record.plan_drive_v
        feedforward[k] = record.feedforward_v
        references[k], terminal[k] = record.plan_state, record.terminal
        estimates[k], target[k] = record.estimate, controller.target_m
    return ClosedLoopRun(
        time_s=(np.arange(n) + 1) * s.period_s,
        states=states,
        peak_theta_rad=peaks,
        command_v=commands,
        plan_drive_v=drives,
        feedforward_v=feedforward,
        reference=references,
        estimate=estimates,
        terminal=terminal,
        target_m=target,
        controller=controller,
    )
