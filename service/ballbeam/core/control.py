"""The control law one cycle at a time: counts → measurement → observer → tracker → clamp.

The daemon, the offline simulation and ``replay --verify`` all run this same function, so a
recorded run can be reproduced bit for bit from its sensor readings.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ballbeam.core.guard import AngleGuard, guarded_voltage
from ballbeam.core.observer import ObserverGains, correct, initial_estimate, predict
from ballbeam.core.plans import Plan
from ballbeam.core.plant import SensorReading
from ballbeam.core.tracker import DiscreteTracker, tracker_input


@dataclass(frozen=True)
class ControllerDesign:
    """Everything a cycle needs, computed once before the run.

    reference_states: (N, 4) x_d at the cycle instants of the tracker horizon;
    reference_input_v: (N,) u_d there. Beyond N the reference is rest at the origin.
    """

    plan: Plan
    tracker: DiscreteTracker
    observer: ObserverGains
    reference_states: np.ndarray
    reference_input_v: np.ndarray
    voltage_limit_v: float
    guard: AngleGuard | None  # None: clamp to ±V only
    initial_state: np.ndarray  # the planned start: supplies the rates no sensor measures
    angle_per_count: float  # measurement units (57·θ) per encoder count
    position_per_count: float  # measurement units (100·x) per ADC count

    @property
    def period_s(self) -> float:
        return self.tracker.period_s

    def measurement(self, reading: SensorReading) -> np.ndarray:
        """y = (57·θ, 100·x) from raw counts."""
        return np.array(
            [
                reading.angle_counts * self.angle_per_count,
                reading.position_counts * self.position_per_count,
            ]
        )

    def reference(self, cycle: int) -> tuple[np.ndarray, float]:
        if cycle < len(self.reference_input_v):
            return self.reference_states[cycle], float(self.reference_input_v[cycle])
        return np.zeros(4), 0.0


@dataclass(frozen=True)
class ControllerState:
    cycle: int = 0
    prediction: np.ndarray | None = None  # x̂[k | k−1]; None before the first measurement


@dataclass(frozen=True)
class CycleOutput:
    voltage_v: float  # clamped command sent to the plant
    requested_v: float  # the tracker's unclamped demand
    estimate: np.ndarray  # x̂[k | k] (4,)
    measured: bool  # False when the cycle coasted on the observer


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
    requested_v = tracker_input(design.tracker, state.cycle, estimate)
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
