"""The control law one cycle at a time: counts → measurement → observer → tracker → clamp.

The daemon, the offline simulation and ``replay --verify`` all run this same function, so a
recorded run can be reproduced bit for bit from its sensor readings. The cycle is written in
plain Python float arithmetic, every sum in a fixed order: no BLAS (whose kernels, picked per
CPU, round matrix products differently) and no libm. IEEE 754 makes each +, −, ×, ÷ exact to
the bit on every machine, so a recorded design replays identically wherever it is run.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ballbeam.core.guard import AngleGuard, Row4, guarded_voltage
from ballbeam.core.plant import SensorReading
from ballbeam.errors import ConfigError

Row2 = tuple[float, float]


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
            Ad=_rows4(Ad), Bd=_tuple4(Bd.reshape(-1)), C=(_tuple4(C[0]), _tuple4(C[1])),
            L=tuple((float(a), float(b)) for a, b in L),  # type: ignore[arg-type]
        )


@dataclass(frozen=True)
class ControllerDesign:
    """Everything a cycle needs, computed once before the run (and recorded with it).

    gains (N, 4) and offset_v (N,): the tracker's ``u_k = offset_v[k] − gains[k]·x̂`` for
    k < N, then ``u = −final_gain·x̂``. reference_states (N, 4), reference_input_v (N,): x_d
    and u_d at the cycle instants (recorded beside each command; rest at the origin beyond N).
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
    initial_state: Row4  # the planned start: supplies the rates no sensor measures
    angle_per_count: float  # measurement units (57·θ) per encoder count
    position_per_count: float  # measurement units (100·x) per ADC count
    # The schedule as Python floats, built once (the cycle reads no numpy scalars).
    _gain_rows: tuple[Row4, ...] = field(init=False, repr=False, compare=False)
    _offsets: tuple[float, ...] = field(init=False, repr=False, compare=False)
    _final_row: Row4 = field(init=False, repr=False, compare=False)

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
        object.__setattr__(self, "_gain_rows", tuple(map(tuple, self.gains.tolist())))
        object.__setattr__(self, "_offsets", tuple(self.offset_v.tolist()))
        object.__setattr__(self, "_final_row", _tuple4(self.final_gain))

    @property
    def n_steps(self) -> int:
        return len(self._offsets)

    def measurement(self, reading: SensorReading) -> Row2:
        """y = (57·θ, 100·x) from raw counts."""
        return (
            reading.angle_counts * self.angle_per_count,
            reading.position_counts * self.position_per_count,
        )

    def reference(self, cycle: int) -> tuple[Row4, float]:
        if cycle < self.n_steps:
            return _tuple4(self.reference_states[cycle]), float(self.reference_input_v[cycle])
        return (0.0, 0.0, 0.0, 0.0), 0.0

    def tracker_input(self, cycle: int, estimate: Row4) -> float:
        """The tracker's demand [V] at ``cycle`` (unclamped); beyond the horizon the
        stationary regulator."""
        x0, x1, x2, x3 = estimate
        if cycle < self.n_steps:
            k0, k1, k2, k3 = self._gain_rows[cycle]
            return self._offsets[cycle] - (k0 * x0 + k1 * x1 + k2 * x2 + k3 * x3)
        k0, k1, k2, k3 = self._final_row
        return -(k0 * x0 + k1 * x1 + k2 * x2 + k3 * x3)


@dataclass(frozen=True)
class ControllerState:
    cycle: int = 0
    prediction: Row4 | None = None  # x̄[k | k−1]; None before the first measurement


@dataclass(frozen=True)
class CycleOutput:
    voltage_v: float  # clamped command sent to the plant
    requested_v: float  # the tracker's unclamped demand
    estimate: Row4  # x̂[k | k]
    measured: bool  # False when the cycle coasted on the observer


def predict(observer: ObserverLaw, estimate: Row4, input_v: float) -> Row4:
    """x̄ = Ad x̂ + Bd u."""
    x0, x1, x2, x3 = estimate
    (a0, a1, a2, a3), (b0, b1, b2, b3), (c0, c1, c2, c3), (d0, d1, d2, d3) = observer.Ad
    e0, e1, e2, e3 = observer.Bd
    return (
        a0 * x0 + a1 * x1 + a2 * x2 + a3 * x3 + e0 * input_v,
        b0 * x0 + b1 * x1 + b2 * x2 + b3 * x3 + e1 * input_v,
        c0 * x0 + c1 * x1 + c2 * x2 + c3 * x3 + e2 * input_v,
        d0 * x0 + d1 * x1 + d2 * x2 + d3 * x3 + e3 * input_v,
    )


def correct(observer: ObserverLaw, prediction: Row4, measurement: Row2) -> Row4:
    """x̂ = x̄ + L (y − C x̄)."""
    x0, x1, x2, x3 = prediction
    (p0, p1, p2, p3), (q0, q1, q2, q3) = observer.C
    innovation_0 = measurement[0] - (p0 * x0 + p1 * x1 + p2 * x2 + p3 * x3)
    innovation_1 = measurement[1] - (q0 * x0 + q1 * x1 + q2 * x2 + q3 * x3)
    (l00, l01), (l10, l11), (l20, l21), (l30, l31) = observer.L
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
    return _tuple4(estimate)


def control_cycle(
    design: ControllerDesign, state: ControllerState, reading: SensorReading | None
) -> tuple[ControllerState, CycleOutput]:
    """One control period. ``reading`` is None when no valid sensor frame arrived in time."""
    if state.prediction is None:
        if reading is None:
            raise ValueError("the first control cycle needs a sensor reading")
        estimate = initial_estimate(
            design.observer, design.measurement(reading), design.initial_state
        )
    elif reading is None:
        estimate = state.prediction  # coast on the model
    else:
        estimate = correct(design.observer, state.prediction, design.measurement(reading))
    requested_v = design.tracker_input(state.cycle, estimate)
    if design.guard is not None:
        voltage_v = guarded_voltage(design.guard, estimate, requested_v)
    else:
        limit = design.voltage_limit_v
        voltage_v = min(max(requested_v, -limit), limit)
    prediction = predict(design.observer, estimate, voltage_v)
    return (
        ControllerState(cycle=state.cycle + 1, prediction=prediction),
        CycleOutput(voltage_v, requested_v, estimate, reading is not None),
    )


def coast_cycles(
    design: ControllerDesign, state: ControllerState, held_voltage_v: float, count: int
) -> ControllerState:
    """Advance ``count`` cycles with no measurement and a known held voltage (skipped periods
    after an overrun, or 0 V while a fault holds the plant)."""
    if state.prediction is None:
        raise ValueError("cannot coast before the first measurement")
    prediction = state.prediction
    for _ in range(count):
        prediction = predict(design.observer, prediction, held_voltage_v)
    return ControllerState(cycle=state.cycle + count, prediction=prediction)


def _tuple4(values: np.ndarray | list[float] | tuple[float, ...]) -> Row4:
    a, b, c, d = (float(value) for value in values)
    return (a, b, c, d)


def _rows4(matrix: np.ndarray) -> tuple[Row4, Row4, Row4, Row4]:
    a, b, c, d = (_tuple4(row) for row in matrix)
    return (a, b, c, d)
