"""Offline closed loop: the plant physics and the control law, no bus, no clock.

It is the lock-step bench without the processes: sensors are read at the start of each
control period, the command is held over it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ballbeam.core.control import ControllerDesign, control_cycle, starting_state
from ballbeam.core.plant import (
    PlantPhysics,
    SensorReading,
    initial_noise,
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
    design: ControllerDesign,
    physics: PlantPhysics,
    initial_state: np.ndarray,
    n_cycles: int,
    sensor_periods_per_cycle: int,
    substeps_per_sensor_period: int,
    rng: np.random.Generator,
) -> SimulationTrace:
    params = physics.params
    state = np.asarray(initial_state, dtype=float)
    noise_m = initial_noise(params, rng)
    controller = starting_state(design)
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
    for _ in range(n_cycles):
        reading: SensorReading = read_sensors(params, state, noise_m)
        controller, output = control_cycle(design, controller, reading)
        for name, value in (
            ("true_states", state),
            ("angle_counts", reading.angle_counts),
            ("position_counts", reading.position_counts),
            ("estimates", output.estimate),
            ("voltage_v", output.voltage_v),
            ("requested_v", output.requested_v),
            ("reference_states", output.reference),
            ("reference_input_v", output.reference_input_v),
        ):
            columns[name].append(value)
        peak_rad = abs(float(state[0]))
        for _ in range(sensor_periods_per_cycle):
            state, step_peak_rad = physics.advance_with_peak(
                state, output.voltage_v, substeps_per_sensor_period
            )
            peak_rad = max(peak_rad, step_peak_rad)
            noise_m = next_noise(params, noise_m, rng)
        columns["peak_abs_theta_rad"].append(peak_rad)
    arrays = {name: np.array(values) for name, values in columns.items()}
    return SimulationTrace(time_s=np.arange(n_cycles) * design.period_s, **arrays)
