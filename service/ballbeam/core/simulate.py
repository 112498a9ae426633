"""Offline closed loop: the plant physics and the control law, no bus, no clock.

It is the lock-step bench without the processes: sensors are read at the start of each
control period, the command is held over it. ``missed_periods`` adds what real time does to a
late loop: periods in which no command comes, the plant driving the last command's look-ahead
(or holding it) and the controller coasting on its model through them.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from ballbeam.core.control import ControllerDesign, CycleOutput
from ballbeam.core.law import ControlLaw, TrackerLaw
from ballbeam.core.plant import (
    PlantPhysics,
    SensorReading,
    command_as_received,
    initial_noise,
    lookahead_as_received,
    next_noise,
    read_sensors,
)


@dataclass(frozen=True)
class SimulationTrace:
    """Per control cycle k (N cycles): time_s (N,), true_states (N, 4) at the cycle start,
    angle_counts / position_counts (N,), estimates (N, 4), voltage_v / requested_v (N,),
    reference_states (N, 4), reference_input_v (N,); peak_abs_theta_rad (N,) the largest |θ| at
    any physics step of each period (the safety promise is per physics step, not per sample)."""

    time_s: np.ndarray
    true_states: np.ndarray
    angle_counts: np.ndarray
    position_counts: np.ndarray
    estimates: np.ndarray
    voltage_v: np.ndarray
    requested_v: np.ndarray
    reference_states: np.ndarray
    reference_input_v: np.ndarray
    peak_abs_theta_rad: np.ndarray


def simulate_closed_loop(
    law: ControlLaw | ControllerDesign,
    physics: PlantPhysics,
    initial_state: np.ndarray,
    n_cycles: int,
    sensor_periods_per_cycle: int,
    substeps_per_sensor_period: int,
    rng: np.random.Generator,
    missed_periods: Mapping[int, int] | None = None,
) -> SimulationTrace:
    """``n_cycles`` control periods of ``law`` (in its starting state; a tracker's design: a
    :class:`TrackerLaw` of it) from ``initial_state``. ``missed_periods``: {cycle k: n}
    — before cycle k the loop misses n periods (they count in ``n_cycles``): the plant drives
    the look-ahead of the last command (a tracker's ``design.lookahead_periods``; none: it
    holds the command), the controller coasts through them and runs cycle k n periods late."""
    if isinstance(law, ControllerDesign):
        law = TrackerLaw(law)
    params = physics.params
    missed = dict(missed_periods or {})
    state = np.asarray(initial_state, dtype=float)
    noise_m = initial_noise(params, rng)
    columns: dict[str, list[object]] = {
        name: []
        for name in (
            "true_states",
            "angle_counts",
            "position_counts",
            "estimates",
            "voltage_v",
            "requested_v",
            "reference_states",
            "reference_input_v",
            "peak_abs_theta_rad",
        )
    }
    output: CycleOutput | None = None
    period_ns = round(law.period_s * 1e9)
    steps_done = 0  # the plant's clock in physics steps (its taps land on it)

    def drive(voltage_v: float) -> float:
        """One control period of physics at ``voltage_v``; the largest |θ| in it."""
        nonlocal state, noise_m, steps_done
        peak_rad = abs(float(state[0]))
        for _ in range(sensor_periods_per_cycle):
            state, step_peak_rad = physics.advance_with_peak(
                state, voltage_v, substeps_per_sensor_period, steps_done
            )
            steps_done += substeps_per_sensor_period
            peak_rad = max(peak_rad, step_peak_rad)
            noise_m = next_noise(params, noise_m, rng)
        return peak_rad

    def record(last: CycleOutput, voltage_v: float, reading: SensorReading | None) -> None:
        for name, value in (
            ("true_states", state),
            ("angle_counts", reading.angle_counts if reading is not None else 0),
            ("position_counts", reading.position_counts if reading is not None else 0),
            ("estimates", last.estimate),
            ("voltage_v", voltage_v),
            ("requested_v", last.requested_v if reading is not None else voltage_v),
            ("reference_states", last.reference),
            ("reference_input_v", last.reference_input_v),
        ):
            columns[name].append(value)
        columns["peak_abs_theta_rad"].append(drive(voltage_v))

    cycle = late = 0
    while cycle < n_cycles:
        if output is not None and (late := min(missed.get(cycle, 0), n_cycles - cycle)):
            lookahead_v = law.lookahead()  # sent with the last command
            for index in range(late):  # no command comes: the plant goes on without one
                drive_v = (
                    lookahead_as_received(lookahead_v[min(index, len(lookahead_v) - 1)])
                    if lookahead_v
                    else command_as_received(output.voltage_v)
                )
                record(output, drive_v, None)
            law.coast(output.voltage_v, late, lookahead_v)
            cycle += late
            if cycle >= n_cycles:
                break
        reading: SensorReading = read_sensors(params, state, noise_m)
        output = law.step(reading, late * period_ns)
        record(output, command_as_received(output.voltage_v), reading)
        cycle, late = cycle + 1, 0
    arrays = {name: np.array(values) for name, values in columns.items()}
    return SimulationTrace(time_s=np.arange(n_cycles) * law.period_s, **arrays)
