"""The control law one cycle at a time: counts → measurement → observer → tracker → clamp.

The daemon, the offline simulation and ``replay --verify`` all run this same function, so a
recorded run can be reproduced bit for bit from its sensor readings. The cycle is written in
plain Python float arithmetic, every sum in a fixed order: no BLAS (whose kernels, picked per
CPU, round matrix products differently) and no libm. IEEE 754 makes each +, −, ×, ÷ exact to
the bit on every machine, so a recorded design replays identically wherever it is run.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np

from ballbeam.core.adaptation import (
    EMPTY_FIT,
    BallGainAdaptation,
    DeadZoneLearning,
    DeadZoneWindow,
    FitSums,
    Gain,
    NoiseAdaptation,
)
from ballbeam.core.guard import (
    NO_LATENESS,
    AngleGuard,
    LatenessWatch,
    guarded_voltage,
    starting_watch,
    watch_lateness,
)
from ballbeam.core.model import Row4, as_row4
from ballbeam.core.planning.arcs import ArcPlan
from ballbeam.core.plant import SensorReading
from ballbeam.errors import ConfigError

Row2 = tuple[float, float]

# A command's look-ahead covers at least this many periods (simulated gaps of 2–6 periods
# anywhere in the last swing: with 4, none rested more than 10 ms late; with 2, 1 of 100).
LOOKAHEAD_FLOOR = 4


@dataclass(frozen=True)
class ObserverLaw:
    """The steady-state Kalman filter as the cycle runs it (see ``observer.py`` for its design):
    predict ``x̄ = Ad x̂ + Bd u``, correct ``x̂ = x̄ + L (y − C x̄)``. Rows of Ad (4 × 4), Bd (4),
    C (2 × 4), L (4 × 2)."""

    Ad: tuple[Row4, Row4, Row4, Row4]
    Bd: Row4
    C: tuple[Row4, Row4]
    L: tuple[Row2, Row2, Row2, Row2]

    @classmethod
    def from_arrays(
        cls, Ad: np.ndarray, Bd: np.ndarray, C: np.ndarray, L: np.ndarray
    ) -> ObserverLaw:
        if Ad.shape != (4, 4) or Bd.reshape(-1).shape != (4,) or C.shape != (2, 4) or (
            L.shape != (4, 2)
        ):
            raise ConfigError("the observer needs Ad (4, 4), Bd (4,), C (2, 4) and L (4, 2)")
        return cls(
            Ad=_rows4(Ad), Bd=as_row4(Bd.reshape(-1)), C=(as_row4(C[0]), as_row4(C[1])),
            L=tuple((float(a), float(b)) for a, b in L),  # type: ignore[arg-type]
        )


@dataclass(frozen=True)
class RestGains:
    """Gentler gains that take over near rest after the plan, from cycle ``from_cycle`` on.

    The tracking gains are stiff so that the ball follows a fast plan and recovers from model
    error; at rest the same gains turn 0.2 mm of sensor noise into servo motion. The weight of
    the stiff gains, w in [0, 1], is the largest of a time ramp 1 → 0 over ``blend_cycles``
    after ``from_cycle`` and the state's distance from rest, (|θ| − near)/(far − near) and
    (|x| − near)/(far − near): K = K_rest + w (K_stiff − K_rest), continuous in the state.
    ``far_gain``: the stiff gains after the plan (None: the tracking schedule's own).
    ``firm_gain``: rest gains firmer than ``gain``, used at ``from_cycle`` and fading linearly
    into it over ``firm_cycles``: a ball that arrives drifting ~1 mm/s is caught (the gentle
    gains' demand for it stays inside the command band, and it rolls out of the rest band);
    once it has settled the gentle gains hold it without dither.
    ``catch_gain``: (V per rad of θ, V per rad/s of θ̇), added to whatever gains act at
    ``from_cycle`` and fading to nothing over ``catch_cycles``: the plan ends with a full-voltage
    brake whose last cycle leaves the servo a few tenths of a degree and 0.1–0.4 rad/s off;
    with demands that small inside the dead zone it crept past the 0.5° rest band in one noise
    draw of ten and took 60 ms to come back (rest at 1.84 s instead of 1.78 s).
    """

    gain: Row4
    far_gain: Row4 | None
    from_cycle: int
    blend_cycles: int
    theta_near_rad: float
    theta_far_rad: float
    position_near_m: float
    position_far_m: float
    firm_gain: Row4 | None = None  # the rest gains right after the plan (None: ``gain`` alone)
    firm_cycles: int = 1  # ... fading into ``gain`` over this many cycles
    catch_gain: tuple[float, float] | None = None  # (θ, θ̇) terms right after the plan
    catch_cycles: int = 1  # ... fading to nothing over this many cycles

    def catch_terms(self, cycle: int) -> tuple[float, float]:
        """The catch's θ and θ̇ gains at ``cycle`` (0, 0 outside its window)."""
        if self.catch_gain is None or cycle < self.from_cycle:
            return 0.0, 0.0
        h = 1.0 - (cycle - self.from_cycle) / self.catch_cycles
        if h <= 0.0:
            return 0.0, 0.0
        return h * self.catch_gain[0], h * self.catch_gain[1]

    def rest_row(self, cycle: int) -> Row4:
        """The rest gains at ``cycle``: firm right after the plan, fading into the gentle ones."""
        firm = self.firm_gain
        h = 1.0 - (cycle - self.from_cycle) / self.firm_cycles
        if firm is None or h <= 0.0:
            return self.gain
        h = min(h, 1.0)
        g0, g1, g2, g3 = self.gain
        f0, f1, f2, f3 = firm
        return (g0 + h * (f0 - g0), g1 + h * (f1 - g1), g2 + h * (f2 - g2), g3 + h * (f3 - g3))

    def stiff_weight(self, cycle: int, estimate: Row4) -> float:
        ramp = 1.0 - (cycle - self.from_cycle) / self.blend_cycles
        theta = (abs(estimate[0]) - self.theta_near_rad) / (
            self.theta_far_rad - self.theta_near_rad
        )
        position = (abs(estimate[3]) - self.position_near_m) / (
            self.position_far_m - self.position_near_m
        )
        return min(max(max(ramp, theta, position), 0.0), 1.0)


@dataclass(frozen=True)
class ControllerDesign:
    """Everything a cycle needs, computed once before the run (and recorded with it).

    gains (N, 4) and offset_v (N,): the tracker's ``u_k = offset_v[k] − gains[k]·x̂`` for
    k < N, then ``u = −final_gain·x̂``. reference_states (N, 4), reference_input_v (N,): x_d
    and u_d at the cycle instants (recorded beside each command; rest at the origin beyond N).

    After the plan (cycle ``rest_from_cycle`` on) the observer may switch to gains designed for
    a quiet ball (``rest_observer``), and the tracker blend into gentler ones (``rest_gains``).
    The command goes through a dead-zone compensation with a band: demands within
    ±``deadband_v`` are sent as 0 V (noise at rest does not flip the command's sign), larger
    ones are shifted by ``deadzone_v − deadband_v``, so that a motor with a ``deadzone_v`` dead
    zone receives the demand less the band; the observer predicts with that modelled drive.
    """

    period_s: float
    plan_duration_s: float
    gains: np.ndarray
    offset_v: np.ndarray
    final_gain: np.ndarray
    reference_states: np.ndarray
    reference_input_v: np.ndarray
    observer: ObserverLaw
    guard: AngleGuard | None  # None: clamp to ±V only
    voltage_limit_v: float
    deadband_v: float
    deadzone_v: float
    rest_from_cycle: int
    rest_observer: ObserverLaw | None
    rest_gains: RestGains | None
    adaptation: BallGainAdaptation | None  # None: the design's ball gain, the plan's pace
    deadzone_learning: DeadZoneLearning | None  # None: the design's dead zone throughout
    noise_adaptation: NoiseAdaptation | None  # None: the filter for the design's noise only
    initial_state: Row4  # the planned start: supplies the rates no sensor measures
    angle_per_count: float  # measurement units (57·θ) per encoder count
    position_per_count: float  # measurement units (100·x) per ADC count
    # Real time: each command also carries the commands of the next this-many periods, for the
    # plant to apply while no newer command has come (0: none; the plant holds the last).
    lookahead_periods: int = 0
    # The ball's target [m]: the law (plan, observer, gains) works in x − target_m (the linear
    # model is the same under a shift of x); its estimates and references are reported in x.
    target_m: float = 0.0
    # The schedule as Python floats, built once (the cycle reads no numpy scalars).
    _gain_rows: tuple[Row4, ...] = field(init=False, repr=False, compare=False)
    _offsets: tuple[float, ...] = field(init=False, repr=False, compare=False)
    _final_row: Row4 = field(init=False, repr=False, compare=False)
    _reference_rows: tuple[Row4, ...] = field(init=False, repr=False, compare=False)
    _reference_inputs: tuple[float, ...] = field(init=False, repr=False, compare=False)
    # The servo's own model over one period, (a00, a01, a10, a11, b0, b1): dead-zone learning.
    servo_rows: tuple[float, float, float, float, float, float] = field(
        init=False, repr=False, compare=False
    )
    _target_y: float = field(init=False, repr=False, compare=False)  # target_m, measured
    _n_steps: int = field(init=False, repr=False, compare=False)  # read several times a cycle

    def __post_init__(self) -> None:
        N = self.offset_v.shape[0]
        if (
            self.gains.shape != (N, 4)
            or self.final_gain.shape != (4,)
            or self.reference_states.shape != (N, 4)
            or self.reference_input_v.shape != (N,)
        ):
            raise ConfigError(
                "a controller design needs gains (N, 4), offset_v (N,), final_gain (4,), "
                "reference_states (N, 4) and reference_input_v (N,)"
            )
        for array in (self.gains, self.offset_v, self.final_gain, self.reference_states,
                      self.reference_input_v):
            array.setflags(write=False)
        object.__setattr__(self, "_gain_rows", _row_tuples(self.gains))
        object.__setattr__(self, "_offsets", tuple(self.offset_v.tolist()))
        object.__setattr__(self, "_final_row", as_row4(self.final_gain))
        object.__setattr__(self, "_reference_rows", _row_tuples(self.reference_states))
        object.__setattr__(self, "_reference_inputs", tuple(self.reference_input_v.tolist()))
        (a00, a01, _, _), (a10, a11, _, _) = self.observer.Ad[0], self.observer.Ad[1]
        servo = (a00, a01, a10, a11, self.observer.Bd[0], self.observer.Bd[1])
        object.__setattr__(self, "servo_rows", servo)
        object.__setattr__(self, "_target_y", self.target_m * self.observer.C[1][3])
        object.__setattr__(self, "_n_steps", N)

    @property
    def n_steps(self) -> int:
        return self._n_steps

    def measurement(self, reading: SensorReading) -> Row2:
        """y = (57·θ, 100·x) from raw counts."""
        return (
            reading.angle_counts * self.angle_per_count,
            reading.position_counts * self.position_per_count,
        )

    def law_measurement(self, reading: SensorReading) -> Row2:
        """y as the law sees it: the position from the target (100·(x − target_m))."""
        angle_y, position_y = self.measurement(reading)
        if self.target_m == 0.0:
            return angle_y, position_y
        return angle_y, position_y - self._target_y

    def in_x(self, row: Row4) -> Row4:
        """A state of the law (x from the target) with its position in x."""
        if self.target_m == 0.0:
            return row
        return row[0], row[1], row[2], row[3] + self.target_m

    def reference(self, position: float) -> tuple[Row4, float]:
        """x_d and u_d at path position ``position`` (cycles, interpolated between rows)."""
        index = int(position)
        n = self._n_steps
        if index >= n:
            return (0.0, 0.0, 0.0, 0.0), 0.0
        rows, inputs = self._reference_rows, self._reference_inputs
        if index + 1 >= n:
            return rows[index], inputs[index]
        f = position - index
        (a0, a1, a2, a3), (b0, b1, b2, b3) = rows[index], rows[index + 1]
        u0, u1 = inputs[index], inputs[index + 1]
        return (
            a0 + f * (b0 - a0), a1 + f * (b1 - a1), a2 + f * (b2 - a2), a3 + f * (b3 - a3)
        ), u0 + f * (u1 - u0)

    def tracker_input(
        self,
        position: float,
        estimate: Row4,
        pace: float = 1.0,
        reference: tuple[Row4, float] | None = None,
    ) -> float:
        """The tracker's demand [V] at path position ``position`` (unclamped); beyond the
        horizon the stationary regulator; after the plan blended with the rest gains.

        At a pace other than 1 the path is followed time-scaled: its rates (θ̇_d, ẋ_d) scale
        with the pace and the servo's feedforward u_d = (θ̈_d + αβ·θ̇_d)/α with them (θ̈_d with
        the pace squared). ``reference``: x_d and u_d at ``position``, if already at hand."""
        x0, x1, x2, x3 = estimate
        cycle = int(position)
        n_steps = self._n_steps
        if cycle + 1 < n_steps:
            f = position - cycle
            o0, o1 = self._offsets[cycle], self._offsets[cycle + 1]
            offset = o0 + f * (o1 - o0)
            (a0, a1, a2, a3), (b0, b1, b2, b3) = self._gain_rows[cycle], self._gain_rows[cycle + 1]
            k0, k1, k2, k3 = a0 + f * (b0 - a0), a1 + f * (b1 - a1), a2 + f * (b2 - a2), (
                a3 + f * (b3 - a3)
            )
        elif cycle < n_steps:
            offset = self._offsets[cycle]
            k0, k1, k2, k3 = self._gain_rows[cycle]
        else:
            offset = 0.0
            k0, k1, k2, k3 = self._final_row
        rest = self.rest_gains
        if rest is not None and cycle >= rest.from_cycle:
            if rest.far_gain is not None:
                k0, k1, k2, k3 = rest.far_gain
            w = rest.stiff_weight(cycle, estimate)
            r0, r1, r2, r3 = rest.rest_row(cycle)
            k0, k1, k2, k3 = r0 + w * (k0 - r0), r1 + w * (k1 - r1), r2 + w * (k2 - r2), (
                r3 + w * (k3 - r3)
            )
            if rest.catch_gain is not None:
                catch_theta, catch_rate = rest.catch_terms(cycle)
                k0, k1 = k0 + catch_theta, k1 + catch_rate
        demand = offset - (k0 * x0 + k1 * x1 + k2 * x2 + k3 * x3)
        if pace == 1.0 or cycle >= n_steps or self.adaptation is None:
            return demand
        (_, theta_rate, ball_rate, _), input_v = (
            reference if reference is not None else self.reference(position)
        )
        slower = pace - 1.0
        feedforward_v = slower * (pace + 1.0) * input_v + pace * (1.0 - pace) * (
            self.adaptation.back_emf_v_s_per_rad * theta_rate
        )
        return demand + slower * (k1 * theta_rate + k2 * ball_rate) + feedforward_v

    def observer_at(self, cycle: int) -> ObserverLaw:
        if self.rest_observer is not None and cycle >= self.rest_from_cycle:
            return self.rest_observer
        return self.observer

    def deadzone_at(self, state: ControllerState) -> float:
        """The dead zone the cycle compensates: the learnt one, else the design's."""
        return self.deadzone_v if state.deadzone_v is None else state.deadzone_v

    def compensated(self, voltage_v: float, deadzone: float) -> float:
        """The command sent for a demand (dead-zone compensation with a band)."""
        band, limit = self.deadband_v, self.voltage_limit_v
        if voltage_v > band:
            return min(voltage_v + (deadzone - band), limit)
        if voltage_v < -band:
            return max(voltage_v - (deadzone - band), -limit)
        return 0.0

    def modelled_drive_v(self, sent_v: float, deadzone: float) -> float:
        """The drive a motor with dead zone ``deadzone`` receives for a sent voltage."""
        if sent_v > deadzone:
            return sent_v - deadzone
        if sent_v < -deadzone:
            return sent_v + deadzone
        return 0.0


def _row_tuples(array: np.ndarray) -> tuple[Row4, ...]:
    """The rows of ``array`` (N, 4) as tuples of floats, one tuple shared by each run of rows
    that are equal bit for bit (the stationary gains are one row N times, the reference is
    rest for most of the horizon): building N tuples of fresh floats was most of a design's
    cost."""
    n = array.shape[0]
    if n == 0:
        return ()
    bits = np.ascontiguousarray(array, dtype=np.float64).view(np.int64)
    starts = np.flatnonzero(np.any(bits[1:] != bits[:-1], axis=1)) + 1
    bounds = [0, *starts.tolist(), n]
    rows = [tuple(row) for row in array[bounds[:-1]].tolist()]
    if len(rows) == n:
        return tuple(rows)
    which = np.repeat(np.arange(len(rows)), np.diff(bounds)).tolist()
    return tuple(map(rows.__getitem__, which))


class ControllerState(NamedTuple):
    """What the law carries from one cycle to the next. Immutable; a named tuple, not a frozen
    dataclass: one is built every cycle, and a tuple is built in a quarter of the time."""

    cycle: int = 0
    prediction: Row4 | None = None  # x̄[k | k−1]; None before the first measurement
    path_position: float = 0.0  # τ: where on the reference (in cycles) this cycle tracks
    fit: FitSums = EMPTY_FIT  # the ball-gain fit's sums
    ball_gain_ratio: float = 1.0  # γ̂ / γ_design: scales the observer's ball rows
    pace: float = 1.0  # the path's clock rate: τ advances by this each cycle
    deadzone_v: float | None = None  # the learnt dead zone (None: the design's)
    deadzone_window: DeadZoneWindow | None = None  # the dead-zone learning's open window
    # The noise measurement: the mean square of the position's second difference (None: not
    # started; then the design's expectation) and the last two positions measured in a row.
    noise_mean_square: float | None = None
    last_positions: tuple[float, ...] = ()
    lateness: LatenessWatch = NO_LATENESS  # real time: the loop's worst recent lateness


def starting_state(design: ControllerDesign) -> ControllerState:
    """The state a run starts in: nothing measured yet but the lateness before it."""
    return ControllerState(lateness=starting_watch(design.guard))


class PlanTaken(NamedTuple):
    """A re-planning law took its planner's answer at ``cycle``: the plan (None: the planner
    had none; the law kept its plan) solved for the request of ``request_cycle``, or
    (``design``) the re-design of the plant as identified then; the design the law starts
    with is one too, taken at cycle 0 to a request of cycle 0."""

    cycle: int
    request_cycle: int
    plan: ArcPlan | None
    design: bool = False
    # (a re-design) the design taken, recorded so a replay uses it rather than solving its
    # Riccati equations again through this machine's LAPACK; None in a log from before
    design_made: Any = None


class CycleOutput(NamedTuple):
    """One cycle's result (a named tuple: one is built every cycle, see ControllerState)."""

    voltage_v: float  # clamped command sent to the plant
    requested_v: float  # the tracker's unclamped demand
    estimate: Row4  # x̂[k | k], its position in x (not from the target)
    measured: bool  # False when the cycle coasted on the observer
    reference: Row4  # x_d tracked this cycle, its position in x
    reference_input_v: float  # u_d at the same path position
    # A re-planning law: the planner's answers it took since its last output (a coasted
    # period may take one too), each with the cycle from which it took effect.
    adopted_plans: tuple[PlanTaken, ...] = ()


def predict(observer: ObserverLaw, estimate: Row4, input_v: float, ball_ratio: float = 1.0) -> Row4:
    """x̄ = Ad x̂ + Bd u; ``ball_ratio`` scales the ball's response to the servo (rows 2 and 3's
    angle and input terms: the ball's gain γ enters the exact discretisation only there)."""
    x0, x1, x2, x3 = estimate
    (a0, a1, a2, a3), (b0, b1, b2, b3), (c0, c1, c2, c3), (d0, d1, d2, d3) = observer.Ad
    e0, e1, e2, e3 = observer.Bd
    if ball_ratio == 1.0:
        return (
            a0 * x0 + a1 * x1 + a2 * x2 + a3 * x3 + e0 * input_v,
            b0 * x0 + b1 * x1 + b2 * x2 + b3 * x3 + e1 * input_v,
            c0 * x0 + c1 * x1 + c2 * x2 + c3 * x3 + e2 * input_v,
            d0 * x0 + d1 * x1 + d2 * x2 + d3 * x3 + e3 * input_v,
        )
    return (
        a0 * x0 + a1 * x1 + a2 * x2 + a3 * x3 + e0 * input_v,
        b0 * x0 + b1 * x1 + b2 * x2 + b3 * x3 + e1 * input_v,
        ball_ratio * (c0 * x0 + c1 * x1 + e2 * input_v) + (c2 * x2 + c3 * x3),
        ball_ratio * (d0 * x0 + d1 * x1 + e3 * input_v) + (d2 * x2 + d3 * x3),
    )


def correct(
    observer: ObserverLaw, prediction: Row4, measurement: Row2, gain: Gain | None = None
) -> Row4:
    """x̂ = x̄ + L (y − C x̄), L the observer's or ``gain``."""
    x0, x1, x2, x3 = prediction
    (p0, p1, p2, p3), (q0, q1, q2, q3) = observer.C
    innovation_0 = measurement[0] - (p0 * x0 + p1 * x1 + p2 * x2 + p3 * x3)
    innovation_1 = measurement[1] - (q0 * x0 + q1 * x1 + q2 * x2 + q3 * x3)
    (l00, l01), (l10, l11), (l20, l21), (l30, l31) = observer.L if gain is None else gain
    return (
        x0 + (l00 * innovation_0 + l01 * innovation_1),
        x1 + (l10 * innovation_0 + l11 * innovation_1),
        x2 + (l20 * innovation_0 + l21 * innovation_1),
        x3 + (l30 * innovation_0 + l31 * innovation_1),
    )


def initial_estimate(observer: ObserverLaw, measurement: Row2, prior_state: Row4) -> Row4:
    """The state that explains the first measurement exactly: each output reads one state
    (y_i = C_ij x_j), so x_j = y_i / C_ij; the unmeasured rates come from ``prior_state``."""
    estimate = list(prior_state)
    for row, value in zip(observer.C, measurement, strict=True):
        for j, gain in enumerate(row):
            if gain != 0.0:
                estimate[j] = value / gain
    return as_row4(estimate)


def correction_gain(
    design: ControllerDesign, state: ControllerState
) -> tuple[ObserverLaw, Gain | None]:
    """The observer a measurement corrects through at this cycle, and the noise adaptation's
    gain for it (None: the observer's own)."""
    observer = design.observer_at(int(state.path_position))
    noise = design.noise_adaptation
    if noise is None:
        return observer, None
    mean_square = (
        noise.expected_square if state.noise_mean_square is None else state.noise_mean_square
    )
    return observer, noise.gain(noise.level(mean_square), observer is design.rest_observer)


def late_correction(
    design: ControllerDesign,
    state: ControllerState,
    reading: SensorReading,
    priors: Sequence[Row4],
) -> tuple[ControllerState, tuple[Row4, ...]]:
    """A sample of an earlier cycle, read only now: ``priors`` are the predictions x̄ of that
    cycle and of each one since (all coasted on the model, no measurement among them), and
    ``state`` is this cycle's. Returns this cycle's state and the later priors as they would
    have been had the sample come in time.

    The model is linear in the state and the inputs were what they were either way, so a
    correction δ = L (y − C x̄) made at that cycle is Adᵐ δ m cycles on: the sample, however
    late, still tells the estimate where the plant was, and the model carries that to now
    (a starved loop that coasted on stale estimates, and then commanded 0 V, ran the servo
    into its end stop). The adaptations learn from samples in time only."""
    observer, gain = correction_gain(design, state)
    prior = priors[0]
    corrected = correct(observer, prior, design.law_measurement(reading), gain)
    delta = as_row4([c - p for c, p in zip(corrected, prior, strict=True)])
    later: list[Row4] = []
    ratio = state.ball_gain_ratio
    for prediction in (*priors[1:], state.prediction):
        delta = predict(design.observer, delta, 0.0, ratio)
        if prediction is not None:
            later.append(as_row4([x + d for x, d in zip(prediction, delta, strict=True)]))
    *earlier, now = later
    return state._replace(prediction=now), tuple(earlier)


def control_cycle(
    design: ControllerDesign,
    state: ControllerState,
    reading: SensorReading | None,
    lateness_ns: int = 0,
) -> tuple[ControllerState, CycleOutput]:
    """One control period. ``reading`` is None when no valid sensor frame arrived in time;
    ``lateness_ns`` (real time): how late the cycle started, skipped periods included."""
    deadzone_v = design.deadzone_at(state)
    measurement = design.law_measurement(reading) if reading is not None else None
    if state.prediction is None:
        if measurement is None:
            raise ValueError("the first control cycle needs a sensor reading")
        estimate = initial_estimate(design.observer, measurement, design.initial_state)
    elif measurement is None:
        estimate = state.prediction  # coast on the model
    else:
        observer, gain = correction_gain(design, state)
        estimate = correct(observer, state.prediction, measurement, gain)
    # The measured angle and position in SI units (each output reads one state).
    (c_theta, _, _, _), (_, _, _, c_position) = design.observer.C
    theta_measured_rad = measurement[0] / c_theta if measurement is not None else estimate[0]
    position = state.path_position
    reference, reference_input_v = design.reference(position)
    fit, ratio = state.fit, state.ball_gain_ratio
    adaptation = design.adaptation
    pace = 1.0
    resync = 0.0  # path cycles the clock moves besides the pace (re-synchronisation)
    if adaptation is not None:
        if position < adaptation.until_cycle:
            if measurement is not None:
                fit = adaptation.add_sample(fit, measurement[1] / c_position)
                ratio = adaptation.ratio(fit)
            fit = adaptation.advance(fit, theta_measured_rad)
        pace = adaptation.pace(ratio, state.pace)
        if ratio != 1.0 and position < adaptation.until_cycle:
            resync = adaptation.clock_shift_cycles(estimate, reference, pace)
    requested_v = design.tracker_input(
        position, estimate, pace, (reference, reference_input_v)
    )
    lateness = watch_lateness(design.guard, state.lateness, lateness_ns)
    if design.guard is not None:
        capped_v = guarded_voltage(design.guard, estimate, requested_v, lateness.worst_ns)
    else:
        limit = design.voltage_limit_v
        capped_v = min(max(requested_v, -limit), limit)
    voltage_v = design.compensated(capped_v, deadzone_v)
    drive_v = design.modelled_drive_v(voltage_v, deadzone_v)
    window = state.deadzone_window
    learning = design.deadzone_learning
    if learning is not None:
        if measurement is None or not learning.learns_at(lateness.worst_ns):
            # A window needs the angle measured at both ends, and commands that landed when
            # the model says: learnt from a late loop, the dead zone drifted to 0.03 V (the
            # plant's: 0.1 V) and the ball went into a slow ±0.4 mm oscillation at rest
            # (unprivileged, under load).
            window = None
        else:
            deadzone_v, window = learning.step(
                deadzone_v, window, voltage_v, drive_v, theta_measured_rad, estimate[1],
                design.servo_rows,
            )
            drive_v = design.modelled_drive_v(voltage_v, deadzone_v)
    # Rest and tracking observers share Ad, Bd: predicting with either is the same.
    prediction = predict(design.observer, estimate, drive_v, ratio)
    noise_mean_square, last_positions = _measure_noise(design, state, measurement)
    return (
        ControllerState(
            cycle=state.cycle + 1, prediction=prediction, path_position=position + pace + resync,
            fit=fit, ball_gain_ratio=ratio, pace=pace, deadzone_v=deadzone_v,
            deadzone_window=window, noise_mean_square=noise_mean_square,
            last_positions=last_positions, lateness=lateness,
        ),
        CycleOutput(
            voltage_v, requested_v, design.in_x(estimate), reading is not None,
            design.in_x(reference), reference_input_v,
        ),
    )


def _measure_noise(
    design: ControllerDesign, state: ControllerState, measurement: Row2 | None
) -> tuple[float | None, tuple[float, ...]]:
    """The noise measurement after this cycle: a second difference needs three positions
    measured in consecutive cycles (a missed one restarts the chain)."""
    noise = design.noise_adaptation
    if noise is None or measurement is None:
        return state.noise_mean_square, ()
    position_y = measurement[1]
    mean_square = state.noise_mean_square
    if len(state.last_positions) == 2:
        older, last = state.last_positions
        start = noise.expected_square if mean_square is None else mean_square
        mean_square = noise.smoothed(start, position_y - 2.0 * last + older)
    return mean_square, (*state.last_positions[-1:], position_y)


def lookahead_count(design: ControllerDesign, state: ControllerState) -> int:
    """How many periods a command's look-ahead covers: LOOKAHEAD_FLOOR more than the loop's
    recent worst lateness (``state.lateness``), at most ``design.lookahead_periods``; none
    once the plan is over and the estimate is within the rest gains' near band (the commands
    there are tenths of a volt at most, and held as before). Each period costs the cycle
    ~4.5 µs, and a loop's CPU time is its lateness beside CPU-bound processes at normal
    priority: 20 periods always (+90 µs a cycle) made it later (2 hogs, 6 s runs: 111–219
    overruns against 18–146, rest median 1.782 s against 1.776 s)."""
    rest = design.rest_gains
    if (
        rest is not None and state.cycle >= rest.from_cycle + rest.catch_cycles
        and state.prediction is not None
        and rest.stiff_weight(state.cycle, state.prediction) == 0.0
    ):
        return 0
    period_ns = round(design.period_s * 1e9)
    late_periods = -(-state.lateness.worst_ns // period_ns)  # rounded up
    return min(design.lookahead_periods, LOOKAHEAD_FLOOR + late_periods)


def lookahead_voltages(design: ControllerDesign, state: ControllerState) -> tuple[float, ...]:
    """The commands for the next :func:`lookahead_count` periods, as the law would send them
    if no measurement came: the estimate predicted on the model, the path's clock run on at
    its pace, the tracker, the angle guard (at the loop's recent lateness) and the dead-zone
    compensation as in a cycle. ``state``: the state after this period's cycle.

    Sent with each command, they let the plant go on as planned when the loop misses periods,
    instead of holding the last command: at the end of the last swing the servo turns at
    ~10 rad/s, and a full-voltage brake held 3–10 ms too long turned it back 0.6–1° (the rest
    band is 0.5°) and rested the ball 15–30 ms late (simulated gaps of 2–16 periods in the
    last 0.3 s: 25 of 500 rested > 10 ms late held, none with 16 or 20 periods ahead)."""
    prediction = state.prediction
    if prediction is None or design.lookahead_periods <= 0:
        return ()
    deadzone = design.deadzone_at(state)
    guard = design.guard
    worst_ns = state.lateness.worst_ns
    limit = design.voltage_limit_v
    position, pace, ratio = state.path_position, state.pace, state.ball_gain_ratio
    voltages = []
    for _ in range(lookahead_count(design, state)):
        requested_v = design.tracker_input(position, prediction, pace)
        if guard is not None:
            capped_v = guarded_voltage(guard, prediction, requested_v, worst_ns)
        else:
            capped_v = min(max(requested_v, -limit), limit)
        voltage_v = design.compensated(capped_v, deadzone)
        voltages.append(voltage_v)
        prediction = predict(
            design.observer, prediction, design.modelled_drive_v(voltage_v, deadzone), ratio
        )
        position += pace
    return tuple(voltages)


def coast_cycles(
    design: ControllerDesign,
    state: ControllerState,
    held_voltage_v: float,
    count: int,
    lookahead_v: tuple[float, ...] = (),
    priors: list[Row4] | None = None,
) -> ControllerState:
    """Advance ``count`` cycles with no measurement (skipped periods after an overrun, or 0 V
    while a fault holds the plant); the path's clock runs on. The plant drove the commands in
    ``lookahead_v`` (sent with the last command) one per period, then held the last of them;
    without them it held ``held_voltage_v``. Before the first measurement only the counters
    advance. ``priors`` (if given) gets each coasted cycle's prediction, for a late sample
    (:func:`late_correction`)."""
    prediction = state.prediction
    fit = state.fit
    if prediction is not None:
        deadzone = design.deadzone_at(state)
        held_drive_v = design.modelled_drive_v(
            lookahead_v[-1] if lookahead_v else held_voltage_v, deadzone
        )
        for index in range(count):
            drive_v = (
                design.modelled_drive_v(lookahead_v[index], deadzone)
                if index < len(lookahead_v) else held_drive_v
            )
            if design.adaptation is not None:
                fit = design.adaptation.advance(fit, prediction[0])
            if priors is not None:
                priors.append(prediction)
            prediction = predict(design.observer, prediction, drive_v, state.ball_gain_ratio)
    return ControllerState(
        cycle=state.cycle + count, prediction=prediction,
        path_position=state.path_position + count * state.pace, fit=fit,
        ball_gain_ratio=state.ball_gain_ratio, pace=state.pace, deadzone_v=state.deadzone_v,
        # Skipped periods measured nothing: the noise's chain of positions and the dead-zone
        # window (which needs the angle at both ends) start again.
        noise_mean_square=state.noise_mean_square, lateness=state.lateness,
    )


def _rows4(matrix: np.ndarray) -> tuple[Row4, Row4, Row4, Row4]:
    a, b, c, d = (as_row4(row) for row in matrix)
    return (a, b, c, d)
