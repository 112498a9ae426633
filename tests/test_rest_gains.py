"""The rest phase after the plan (core/control.py RestGains) and the plan's voltage margin.

The firm rest gains' fade is checked by hand arithmetic; what they are for, on the plant: a
ball that arrives drifting (5× sensor noise, seed 3: ~0.7 mm/s after the last swing) is caught
inside the 0.5 mm rest band by the firm gains and rolls out of it under the gentle ones alone,
without the firm gains flipping the command's sign more than the 5 Hz dither bound allows.
The 0.45 V plan margin is checked the same way against a 0.4 V motor dead zone.
"""

from __future__ import annotations

import numpy as np
import pytest

from ballbeam.assembly import run_offline
from ballbeam.config import load_config
from ballbeam.core.control import RestGains
from ballbeam.core.metrics import sign_changes

from .conftest import PAPER

T_STAR_S = 1.746  # the paper start's true minimum time (bench/control_quality.py, README)
DITHER_BOUND_HZ = 5.0


def rest_gains(firm: tuple[float, float, float, float] | None) -> RestGains:
    return RestGains(
        gain=(1.0, 2.0, 3.0, 4.0), far_gain=None, from_cycle=100, blend_cycles=10,
        theta_near_rad=0.01, theta_far_rad=0.03, position_near_m=3e-4, position_far_m=8e-4,
        firm_gain=firm, firm_cycles=40,
    )


def test_the_firm_gains_fade_linearly_into_the_gentle_ones() -> None:
    law = rest_gains((3.0, 6.0, 9.0, 12.0))
    assert law.rest_row(100) == pytest.approx((3.0, 6.0, 9.0, 12.0))
    assert law.rest_row(120) == pytest.approx((2.0, 4.0, 6.0, 8.0))  # halfway
    assert law.rest_row(140) == (1.0, 2.0, 3.0, 4.0)
    assert law.rest_row(10_000) == (1.0, 2.0, 3.0, 4.0)
    assert rest_gains(None).rest_row(100) == (1.0, 2.0, 3.0, 4.0)


def settle_sign_changes_hz(overrides: list[str]) -> tuple[float | None, float]:
    """Rest time and the command's sign changes a second in the 1.5 s after the plan."""
    run = run_offline(load_config(PAPER, [*overrides, "run.duration_s=4.75"]))
    time_s, plan_end_s = run.trace.time_s, run.design.plan_duration_s
    window = (time_s >= plan_end_s) & (time_s < plan_end_s + 1.5)
    return run.metrics.rest_time_s, sign_changes(np.asarray(run.trace.voltage_v)[window]) / 1.5


def test_firm_rest_gains_catch_a_drifting_ball_without_dither() -> None:
    drifting = ["plant.position_noise_m=1e-3", "plant.seed=3"]
    firm_rest_s, firm_flips_hz = settle_sign_changes_hz(drifting)
    gentle_rest_s, _ = settle_sign_changes_hz([*drifting, "tracker.rest_firm_s=0"])
    assert firm_rest_s is not None and firm_rest_s < 1.15 * T_STAR_S
    # Under the gentle gains alone the ball rolls out of the band a second after the plan.
    assert gentle_rest_s is None or gentle_rest_s > 1.5 * T_STAR_S
    assert firm_flips_hz <= DITHER_BOUND_HZ


def test_the_plan_margin_covers_a_wide_dead_zone() -> None:
    """0.4 V of dead zone: the compensation adds 0.35 V to the demand, which 0.45 V of margin
    leaves room for on the saturated swings; with 0.25 V the ball enters the last arc fast."""
    wide = ["plant.deadzone_v=0.4", "plant.seed=4"]
    covered = run_offline(load_config(PAPER, [*wide, "run.duration_s=4.75"])).metrics
    short = run_offline(
        load_config(PAPER, [*wide, "run.duration_s=4.75", "plan.voltage_margin_v=0.25"])
    ).metrics
    assert covered.rest_time_s is not None and covered.rest_time_s < 1.1 * T_STAR_S
    assert covered.largest_step_v is not None and covered.largest_step_v <= 2.0
    assert short.rest_time_s is None or short.rest_time_s > 1.3 * T_STAR_S


def test_the_servo_catch_fades_linearly_to_nothing() -> None:
    law = RestGains(
        gain=(1.0, 2.0, 3.0, 4.0), far_gain=None, from_cycle=100, blend_cycles=10,
        theta_near_rad=0.01, theta_far_rad=0.03, position_near_m=3e-4, position_far_m=8e-4,
        catch_gain=(80.0, 1.0), catch_cycles=60,
    )
    assert law.catch_terms(99) == (0.0, 0.0)  # still the plan
    assert law.catch_terms(100) == pytest.approx((80.0, 1.0))
    assert law.catch_terms(130) == pytest.approx((40.0, 0.5))  # halfway
    assert law.catch_terms(160) == (0.0, 0.0)
    assert rest_gains(None).catch_terms(100) == (0.0, 0.0)


@pytest.mark.parametrize(("catch_s", "rests_by_1_79_s"), [(0.06, True), (0.0, False)])
def test_the_servo_catch_keeps_the_plans_last_brake_from_creeping_past_the_rest_band(
    catch_s: float, rests_by_1_79_s: bool
) -> None:
    """Paper start, noise seed 6: the plan ends at 1.78 s with a full-voltage brake that leaves
    the servo at +0.13° and still turning; the demands that follow sit in the dead zone and it
    creeps to +0.68°, past the 0.5° rest band, for 60 ms (rest 1.843 s, where the other seeds
    rest at 1.774–1.782 s). The 60 ms catch holds it inside (rest 1.777 s), and the command's
    sign changes in the 1.5 s after the plan stay within the 5 Hz dither bound."""
    run = run_offline(load_config(PAPER, [
        "plant.seed=6", "run.duration_s=3.5", f"tracker.rest_catch_s={catch_s}",
    ]))
    rest_s = run.metrics.rest_time_s
    assert rest_s is not None
    assert (rest_s <= 1.79) is rests_by_1_79_s, rest_s
    peak_deg = np.degrees(np.max(np.abs(run.trace.true_states[
        (run.trace.time_s > 1.785) & (run.trace.time_s < 1.9), 0
    ])))
    assert bool(peak_deg <= 0.5) is rests_by_1_79_s, peak_deg
    plan_s = run.design.plan_duration_s
    settling = (run.trace.time_s > plan_s) & (run.trace.time_s < plan_s + 1.5)
    assert sign_changes(run.trace.voltage_v[settling]) / 1.5 <= DITHER_BOUND_HZ


@pytest.mark.parametrize(("lateness_ns", "learns"), [
    (0, True), (400_000, True), (3_000_000, False), (5_000_000, False),
])
def test_a_late_loop_does_not_learn_the_dead_zone(lateness_ns: int, learns: bool) -> None:
    """Real time: the dead-zone learning compares the servo's motion with the model's, which
    assumes commands land on time. A loop running later than 500 µs learns nothing, even where
    its probe raised the guard's latency allowance to 5 ms (so the guard's look-ahead covers
    the lateness): under load such a run had learnt 0.03 V for the plant's 0.1 V, and the ball
    went into a slow ±0.4 mm oscillation at rest. On time, it opens its windows as offline."""
    from ballbeam.assembly import controller_design
    from ballbeam.core.control import ControllerState, control_cycle
    from ballbeam.core.plant import PlantPhysics, initial_noise, next_noise, read_sensors
    from ballbeam.plant_assembly import plant_parameters

    config = load_config(PAPER, [
        "run.mode='realtime'", "run.duration_s=1.0", "controller.theta_guard_latency_us=5000",
    ])
    design = controller_design(config)
    assert design.deadzone_learning is not None
    physics = PlantPhysics(plant_parameters(config))
    rng = np.random.default_rng(1)
    state = np.asarray(config.initial.state(), dtype=float)
    noise = initial_noise(physics.params, rng)
    controller, windows = ControllerState(), 0
    for _ in range(1000):
        reading = read_sensors(physics.params, state, noise)
        controller, output = control_cycle(design, controller, reading, lateness_ns)
        windows += controller.deadzone_window is not None
        state = physics.advance(state, output.voltage_v, config.plant.physics_substeps)
        noise = next_noise(physics.params, noise, rng)
    assert (windows > 0) is learns, windows
    if not learns:
        assert controller.deadzone_v in (None, design.deadzone_v)  # the design's, untouched
