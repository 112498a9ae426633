"""A command's look-ahead: what the plant drives while a late loop sends nothing.

The independent answers are the loop that misses no period (the rest time a gap must not
move by more than 10 ms) and the law itself run without measurements (what the look-ahead
must equal)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from ballbeam.assembly import controller_design, run_cycles
from ballbeam.config import Config, load_config
from ballbeam.core.control import (
    LOOKAHEAD_FLOOR,
    ControllerDesign,
    ControllerState,
    control_cycle,
    lookahead_count,
    lookahead_voltages,
    starting_state,
)
from ballbeam.core.guard import LatenessWatch
from ballbeam.core.metrics import rest_time
from ballbeam.core.plant import (
    PlantPhysics,
    SensorReading,
    initial_noise,
    next_noise,
    read_sensors,
)
from ballbeam.core.simulate import SimulationTrace, simulate_closed_loop
from ballbeam.plant_assembly import plant_parameters, sensor_periods_per_cycle

CONFIG = load_config(None, ["run.mode='realtime'", "run.duration_s=2.5"])


@pytest.fixture(scope="module")
def design() -> ControllerDesign:
    built = controller_design(CONFIG)
    assert built.lookahead_periods == 20  # real time on the authenticated bus: on by default
    return built


def closed_loop(
    config: Config, design: ControllerDesign, missed: dict[int, int] | None = None
) -> SimulationTrace:
    return simulate_closed_loop(
        design, PlantPhysics(plant_parameters(config)), config.initial.state(),
        n_cycles=run_cycles(config), sensor_periods_per_cycle=sensor_periods_per_cycle(config),
        substeps_per_sensor_period=config.plant.physics_substeps,
        rng=np.random.default_rng(config.plant.seed), missed_periods=missed,
    )


def rest_s(trace: SimulationTrace) -> float:
    rest = rest_time(trace.time_s, trace.true_states)
    assert rest is not None
    return rest


def test_only_a_real_time_run_on_the_authenticated_bus_sends_one() -> None:
    assert controller_design(load_config(None, ["run.duration_s=2.5"])).lookahead_periods == 0
    classic = load_config(None, ["run.mode='realtime'", "bus.authenticate=false"])
    assert controller_design(classic).lookahead_periods == 0  # 8-byte frames have no room
    two_samples = load_config(None, ["run.mode='realtime'", "plant.sensor_rate_hz=2000"])
    assert controller_design(two_samples).lookahead_periods == 0  # stepped per sample


def test_the_lookahead_is_what_the_law_sends_when_no_measurement_comes(
    design: ControllerDesign,
) -> None:
    """Mid-plan (path pace adapted, rest gains not yet), on the way to rest (rest gains and
    catch) and at rest: each entry is the command of a cycle that coasts on the model."""
    state: ControllerState = starting_state(design)
    reading = SensorReading(angle_counts=-2963, position_counts=1950)
    for stop_at in (700, 1790, 2300):
        while state.cycle < stop_at:
            state, _ = control_cycle(design, state, reading)
        expected, coasting = [], state
        for _ in range(lookahead_count(design, state)):
            coasting, output = control_cycle(design, coasting, None)
            expected.append(output.voltage_v)
        assert lookahead_voltages(design, state) == tuple(expected), stop_at


def test_it_covers_the_loops_recent_lateness_and_a_floor(design: ControllerDesign) -> None:
    state = starting_state(design)
    assert lookahead_count(design, state) == LOOKAHEAD_FLOOR
    late = state._replace(lateness=LatenessWatch(worst_ns=5_500_000))
    assert lookahead_count(design, late) == LOOKAHEAD_FLOOR + 6
    stalled = state._replace(lateness=LatenessWatch(worst_ns=80_000_000))
    assert lookahead_count(design, stalled) == 20
    assert lookahead_voltages(dataclasses.replace(design, lookahead_periods=0), state) == ()
    # After the plan, at rest (the sensors read 0): the commands are held as before, no cost.
    assert design.rest_gains is not None
    at_rest = state._replace(cycle=design.rest_gains.from_cycle - 1)
    while at_rest.cycle < design.rest_gains.from_cycle + 1000:
        at_rest, _ = control_cycle(design, at_rest, SensorReading(0, 0))
    assert lookahead_count(design, at_rest) == 0 and lookahead_voltages(design, at_rest) == ()


def test_a_loop_that_misses_periods_in_the_last_swing_still_rests_on_time(
    design: ControllerDesign,
) -> None:
    """Gaps of 2–6 periods starting anywhere in the last 60 ms of the last swing, where the
    servo turns at ~10 rad/s and a brake held 1 ms too long turns it ~0.5° back: with the
    look-ahead every run rests within 10 ms of the loop that missed none; the plant holding the
    last command instead rests 13–29 ms late for some of the same gaps."""
    on_time_s = rest_s(closed_loop(CONFIG, design))
    holding = dataclasses.replace(design, lookahead_periods=0)
    late_held = []
    for length in (2, 4, 6):
        for start in range(1740, 1790, 4):
            gap = {start: length}
            assert rest_s(closed_loop(CONFIG, design, gap)) - on_time_s <= 0.010, gap
            if rest_s(closed_loop(CONFIG, holding, gap)) - on_time_s > 0.010:
                late_held.append(gap)
    assert late_held  # the test tells the two apart


def test_a_stalled_loop_near_the_limit_leaves_the_plant_inside_52_degrees(
    design: ControllerDesign,
) -> None:
    """The look-ahead runs the angle guard on its predicted states. From each state of the
    swings onto both limit arcs, the loop stalled 25 periods after a 16 ms lateness (so 20
    periods ahead, the last held): the plant on the look-ahead stays inside 52° at every
    physics step (inside the soft limit, even), where the plant holding the last command
    passes it (52.07–52.10°)."""
    params = plant_parameters(CONFIG)
    physics = PlantPhysics(params)
    rng = np.random.default_rng(CONFIG.plant.seed)
    true_state = np.asarray(CONFIG.initial.state(), dtype=float)
    noise_m = initial_noise(params, rng)
    state = starting_state(design)
    limit_deg, held_peaks, ahead_peaks = 52.0, [], []

    def peak_deg(start: np.ndarray, voltages: tuple[float, ...]) -> float:
        peak_rad, driven = 0.0, start
        for index in range(25):
            driven, step_peak = physics.advance_with_peak(
                driven, voltages[min(index, len(voltages) - 1)], CONFIG.plant.physics_substeps
            )
            peak_rad = max(peak_rad, step_peak)
        return math.degrees(peak_rad)

    for cycle in range(1200):
        state, output = control_cycle(design, state, read_sensors(params, true_state, noise_m))
        true_state, _ = physics.advance_with_peak(
            true_state, output.voltage_v, CONFIG.plant.physics_substeps
        )
        noise_m = next_noise(params, noise_m, rng)
        if 190 <= cycle <= 320 or 1050 <= cycle <= 1150:
            stalled = state._replace(lateness=LatenessWatch(worst_ns=16_000_000))
            ahead = lookahead_voltages(design, stalled)
            assert len(ahead) == 20
            ahead_peaks.append(peak_deg(true_state, ahead))
            held_peaks.append(peak_deg(true_state, (output.voltage_v,)))
    assert design.guard is not None and design.guard.soft is not None
    # Inside the soft limit, even (51.855°; the look-ahead without the guard reached 51.91°).
    assert max(ahead_peaks) <= math.degrees(design.guard.soft.theta_limit_rad) < limit_deg
    assert max(held_peaks) > limit_deg  # what the look-ahead is safer than
