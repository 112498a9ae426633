"""The controller seam (core/law.py) and ``controller.kind = "replanning"``: the re-planning law
offline and over the bus in lock-step, its plans recorded on /plans and injected by replay."""

from __future__ import annotations

import dataclasses
import itertools
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from ballbeam.assembly import control_law, plant_floor, run_offline
from ballbeam.config import load_config
from ballbeam.core.control import PlanTaken
from ballbeam.core.law import TrackerLaw
from ballbeam.core.planning.arcs import plan_arcs
from ballbeam.core.plant import SensorReading
from ballbeam.core.replanning import _sine_state
from ballbeam.core.task import SineWave, flat_feedforward
from ballbeam.evaluation.replay import verify
from ballbeam.logs.plan_record import PLANS, plan_from_message, plan_message, recorded_plans
from ballbeam.logs.reader import RunLog, read_log
from ballbeam.plant_assembly import design_model

from .conftest import PAPER, ballbeam

REPLANNING = ("controller.kind='replanning'",)
REST_BAND_M = 5e-4
REST_BAND_RAD = math.radians(0.5)


def _sets(*overrides: str) -> list[str]:
    return [item for override in overrides for item in ("--set", override)]


def _rest_s(time_s: np.ndarray, theta_rad: np.ndarray, x_m: np.ndarray, target_m: float) -> float:
    """The first time from which the ball stays within 0.5 mm of the target and the servo
    within 0.5° (DESIGN.md §8), computed here from the samples alone."""
    outside = (np.abs(x_m - target_m) > REST_BAND_M) | (np.abs(theta_rad) > REST_BAND_RAD)
    assert not outside[-1], "not at rest at the end of the run"
    last = np.flatnonzero(outside)
    return float(time_s[last[-1] + 1]) if last.size else float(time_s[0])


# ---- config ----------------------------------------------------------------------------------


def test_the_default_kind_is_the_tracker() -> None:
    assert load_config(PAPER).controller.kind == "tracker"


@pytest.mark.parametrize(
    ("overrides", "words"),
    [
        (("controller.kind='mpc'",), "'tracker' or 'replanning'"),
        ((*REPLANNING, "run.mode='realtime'"), "lock-step only"),
    ],
)
def test_a_kind_the_run_cannot_have_exits_2_in_one_line_before_anything_starts(
    tmp_path: Path, overrides: tuple[str, ...], words: str
) -> None:
    result = ballbeam("run", str(PAPER), *_sets(f"run.log_dir='{tmp_path}'", *overrides))
    assert result.returncode == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and words in lines[0], result.stderr
    assert "Traceback" not in result.stderr
    assert not list(tmp_path.iterdir())  # no log: no process was started


# ---- plans as recorded -----------------------------------------------------------------------


def test_a_plan_round_trips_through_its_json_message_to_the_bit() -> None:
    config = load_config(PAPER)
    start = np.array([math.radians(-40.0), 0.3, 0.05, 0.15])  # rolling, servo turning
    plan = plan_arcs(design_model(config), start, target_m=0.03,
                     voltage_limit_v=4.55, theta_max_rad=math.radians(51.7))
    text = json.dumps(plan_message(PlanTaken(17, 15, plan)))
    taken = plan_from_message(json.loads(text))
    assert taken.cycle == 17 and taken.request_cycle == 15 and not taken.design
    back = taken.plan
    assert back is not None
    for field in dataclasses.fields(plan):
        ours, theirs = getattr(plan, field.name), getattr(back, field.name)
        assert np.array(ours).tobytes() == np.array(theirs).tobytes(), field.name
    times = np.linspace(0.0, plan.duration_s, 101)
    assert plan.sample(times).states.tobytes() == back.sample(times).states.tobytes()
    # an answer of no plan, and a re-design, round-trip too
    for taken in (PlanTaken(9, 7, None), PlanTaken(102, 100, None, design=True)):
        assert plan_from_message(json.loads(json.dumps(plan_message(taken)))) == taken


def test_a_design_taken_round_trips_through_its_message_to_the_bit() -> None:
    """A re-design's message carries the design whole: every float and array of it, its
    identified model and guard, come back with the same bits; a part that is not one of a
    design's is refused."""
    from ballbeam.core.replanning import ReplanningController, Settings

    design = ReplanningController(Settings(), np.array([0.5, 0.0, 0.0, 0.1])).design
    message = json.loads(json.dumps(plan_message(PlanTaken(200, 198, None, True, design))))
    back = plan_from_message(message).design_made

    def leaves(value: object) -> list[bytes]:
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            return [b for f in dataclasses.fields(value) for b in leaves(getattr(value, f.name))]
        if isinstance(value, tuple):
            return [b for item in value for b in leaves(item)]
        if isinstance(value, np.ndarray):
            return [repr(value.shape).encode(), value.astype(np.float64).tobytes()]
        if isinstance(value, float):  # (numpy's float64 too: the bits are what count)
            return [np.float64(value).tobytes()]
        return [repr(value).encode()]

    assert type(back) is type(design) and leaves(back) == leaves(design)
    assert back.guard == design.guard and len(leaves(design)) > 1000
    message["made"]["fields"]["guard"]["type"] = "os.system"
    with pytest.raises(ValueError, match="not a part of a design"):
        plan_from_message(message)


# ---- offline ---------------------------------------------------------------------------------


def test_offline_a_change_of_target_is_re_planned_to_rest_near_the_floor_from_then() -> None:
    """A step schedule: the paper's start to 0, then 0.05 m at 3 s. After the change the ball
    rests at the new target within 1.3 × the plant's own floor from the true state at the
    change (an LP on the true plant, core/floor.py)."""
    change_s, target_m = 3.0, 0.05
    config = load_config(PAPER, (
        *REPLANNING, f"task.setpoints=[[0.0, 0.0], [{change_s}, {target_m}]]",
        "run.duration_s=5.0",
    ))
    trace = run_offline(config).trace
    states, time_s = trace.true_states, trace.time_s
    at = int(np.searchsorted(time_s, change_s))
    first = _rest_s(time_s[:at], states[:at, 0], states[:at, 3], 0.0)
    assert first < change_s - 0.5  # at rest at 0 well before the change
    rest_after_s = _rest_s(time_s[at:], states[at:, 0], states[at:, 3], target_m) - change_s
    start = states[at]
    floor = plant_floor(load_config(PAPER, (
        f"initial.theta_deg={math.degrees(start[0])}",
        f"initial.theta_rate_deg_s={math.degrees(start[1])}",
        f"initial.ball_velocity_m_s={start[2]}", f"initial.ball_position_m={start[3]}",
    )), target_m)
    assert floor is not None
    assert rest_after_s <= 1.3 * floor.time_s, (rest_after_s, floor.time_s)
    assert float(np.max(trace.peak_abs_theta_rad)) <= config.limits.theta_rad + 1e-12


def test_the_sines_flat_state_in_plain_floats_is_the_tasks_own() -> None:
    """The law's sine reference (plain floats, ``replanning._sine_state``) equals the task's
    flat outputs turned into state and drive by ``task.flat_feedforward`` (numpy)."""
    sine = SineWave(0.04, 10.0, -0.02)
    gamma, alpha, pole = -0.41218, 108.896, 58.466
    times = np.linspace(0.0, 25.0, 101)
    states, drives = flat_feedforward(sine.reference_at(times), gamma, alpha, pole)
    for time_s, state, drive in zip(times, states, drives, strict=True):
        ours, ours_drive = _sine_state((0.04, 10.0, -0.02), float(time_s), gamma, alpha, pole)
        np.testing.assert_allclose(ours, state, rtol=1e-12, atol=1e-15)
        assert ours_drive == pytest.approx(float(drive), rel=1e-12, abs=1e-15)


@pytest.mark.parametrize("overrides", [
    (),  # the paper's start and plant
    ("initial.ball_position_m=-0.15", "initial.ball_velocity_m_s=0.1",  # rolling, far side
     "plant.ball_gain_scale=1.2", "plant.motor_gain_scale=0.85", "plant.deadzone_v=0.3"),
])
def test_offline_a_sine_is_joined_and_followed_within_the_limits(
    overrides: tuple[str, ...],
) -> None:
    """The 4 cm, 10 s sine: the ball joins it and follows it, within 1 mm and 0.3 mm RMS
    from 3 s on (measured from the plant's truth against the sine itself), the servo within
    its limit at every physics step, no voltage above 2 V after the join."""
    config = load_config(PAPER, (
        *REPLANNING, "task.sine={amplitude_m=0.04, period_s=10.0}", "run.duration_s=12.0",
        *overrides,
    ))
    trace = run_offline(config).trace
    time_s, x_m = trace.time_s, trace.true_states[:, 3]
    error_m = x_m - (0.04 * np.sin(2.0 * math.pi / 10.0 * time_s))
    assert float(np.max(np.abs(error_m[time_s >= 3.0]))) <= 1e-3
    assert float(np.sqrt(np.mean(error_m[time_s >= 3.0] ** 2))) <= 3e-4
    assert float(np.max(trace.peak_abs_theta_rad)) <= config.limits.theta_rad + 1e-12
    assert float(np.max(np.abs(trace.voltage_v[time_s >= 3.0]))) <= 2.0


# ---- over the bus, lock-step; replay -----------------------------------------------------------


@pytest.fixture(scope="module")
def replanning_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    log_dir = tmp_path_factory.mktemp("replanning")
    result = ballbeam("run", str(PAPER), *_sets(
        f"run.log_dir='{log_dir}'", *REPLANNING, "run.duration_s=3.0",
    ), "--json", timeout_s=600)
    assert result.returncode == 0, result.stderr
    return Path(json.loads(result.stdout)["log_path"])


@pytest.mark.bus
def test_lockstep_replanning_rests_at_the_target_near_the_plants_own_floor(
    replanning_log: Path,
) -> None:
    run_log = read_log(replanning_log)
    truth = run_log.topics["/truth"].values
    time_s = np.asarray(truth["plant_time_s"])
    theta = np.asarray(truth["theta_rad"])
    x = np.asarray(truth["ball_position_m"])
    rest_s = _rest_s(time_s, theta, x, 0.0)
    floor = plant_floor(load_config(PAPER))
    assert floor is not None
    assert rest_s <= 1.3 * floor.time_s, (rest_s, floor.time_s)
    assert float(np.max(np.abs(x[time_s >= rest_s]))) <= REST_BAND_M
    # The answers it took are in the log, each at least the delay after its request; the
    # first plan (asked for at the first cycle) at the delay exactly: lock-step waits for it.
    delay = load_config(PAPER).controller.plan_delay_cycles
    taken = recorded_plans(run_log).values()
    assert all(t.cycle >= t.request_cycle + delay for t in taken if t.cycle > 0)
    plans = [t for t in taken if t.plan is not None]
    assert min(t.cycle for t in plans) == 0 and len(plans) > 10  # the first before the run
    assert any(t.design for t in taken)


@pytest.mark.bus
def test_lockstep_replanning_is_the_offline_run_command_for_command(replanning_log: Path) -> None:
    """The same law through the seam over the bus and offline: the same commands (the frames
    carry 1 mV steps)."""
    run_log = read_log(replanning_log)
    offline = run_offline(load_config(PAPER, (*REPLANNING, "run.duration_s=3.0"))).trace
    sent = np.asarray(run_log.topics["/command"].values["voltage_v"])
    assert np.array_equal(np.round(sent / 1e-3) * 1e-3, offline.voltage_v)


@pytest.mark.bus
def test_replay_verify_re_runs_the_replanning_law_on_its_recorded_plans(
    replanning_log: Path,
) -> None:
    result = verify(read_log(replanning_log))
    assert result.ok, (result.mismatch, result.plan_mismatch)
    assert result.design_source == "recorded plans" and result.cycles_checked == 3000


def _with_plans(run_log: RunLog, messages: list[dict[str, Any]]) -> RunLog:
    topic = dataclasses.replace(
        run_log.json_topics[PLANS], messages=tuple(messages),
        log_time_ns=run_log.json_topics[PLANS].log_time_ns[: len(messages)],
    )
    return dataclasses.replace(run_log, json_topics={**run_log.json_topics, PLANS: topic})


@pytest.mark.bus
def test_verify_fails_on_a_recorded_plan_with_one_float_changed(replanning_log: Path) -> None:
    run_log = read_log(replanning_log)
    messages = [json.loads(json.dumps(message)) for message in run_log.json_topics[PLANS].messages]
    # Every arc's input of a plan taken mid-run, one part in 10⁹: the re-run tracks the plan
    # as injected (had it solved its own, the change would go unseen).
    index = next(
        i for i, m in enumerate(messages) if m["plan"] is not None and m["cycle"] >= 100
    )
    inputs = messages[index]["plan"]["input_v"]
    inputs[:] = [(float.fromhex(value) * (1.0 + 1e-9)).hex() for value in inputs]
    result = verify(_with_plans(run_log, messages))
    assert not result.ok and result.mismatch is not None
    following = [m["cycle"] for m in messages[index + 1 :] if m["plan"] is not None]
    # from the cycle it took effect, before the next plan takes over
    assert messages[index]["cycle"] <= result.mismatch.cycle < following[0]


@pytest.mark.bus
def test_verify_fails_where_the_re_run_adopts_a_plan_the_log_does_not_record(
    replanning_log: Path,
) -> None:
    run_log = read_log(replanning_log)
    messages = [dict(message) for message in run_log.json_topics[PLANS].messages]
    middle = len(messages) // 2
    while messages[middle].get("design"):
        middle += 1
    dropped = messages.pop(middle)
    result = verify(_with_plans(run_log, messages))
    # the re-run waits for the dropped answer; the next one answers a request it never made
    assert not result.ok and result.plan_mismatch is not None
    assert f"outstanding then is of cycle {dropped['request_cycle']}" in result.plan_mismatch


def test_the_seam_runs_the_tracker_as_before() -> None:
    """The paper's tracker behind the seam gives, reading for reading, what its own functions
    give called directly (as the daemon, the simulation and replay called them before)."""
    from ballbeam.assembly import controller_design
    from ballbeam.core.control import coast_cycles, control_cycle, starting_state
    from ballbeam.core.plant import SensorReading

    config = load_config(PAPER, ("run.duration_s=0.4",))
    trace = run_offline(config).trace
    design = controller_design(config)
    law = control_law(config, design)
    assert isinstance(law, TrackerLaw)
    direct = starting_state(design)
    for k, (angle, position) in enumerate(
        zip(trace.angle_counts.tolist(), trace.position_counts.tolist(), strict=True)
    ):
        if k % 97 == 50:  # now and then a gap of two periods, coasted
            direct = coast_cycles(design, direct, 0.5, 2)
            law.coast(0.5, 2)
        reading = SensorReading(int(angle), int(position))
        direct, expected = control_cycle(design, direct, reading, 0)
        assert law.step(reading) == expected
        assert law.state == direct
    assert law.started and law.cycle == direct.cycle


def test_plans_adopted_while_coasting_come_with_the_next_output_at_their_own_cycles() -> None:
    """A gap of 25 periods (a fault's 0 V): the re-planning law predicts through it, its
    plan's clock running on; the plans it adopts are handed out with the next step, each at
    the cycle it took effect (so the daemon records them where replay finds them)."""
    from ballbeam.core.plant import SensorReading

    config = load_config(PAPER, (*REPLANNING, "run.duration_s=0.2"))
    trace = run_offline(config).trace
    law = control_law(config)
    readings = [
        SensorReading(int(a), int(p))
        for a, p in zip(trace.angle_counts.tolist(), trace.position_counts.tolist(), strict=True)
    ]
    delay = config.controller.plan_delay_cycles
    outputs = [law.step(reading) for reading in readings[: delay + 1]]
    taken = [t for output in outputs for t in output.adopted_plans]
    # the design it starts with and the first plan (asked for from the start, before the
    # run) at the first cycle; the re-plan asked for then, the delay later
    assert [(t.cycle, t.request_cycle, t.design) for t in taken] == [
        (0, 0, True), (0, 0, False), (delay, 0, False)
    ]
    assert taken[0].design_made is law.controller.design
    assert outputs[0].reference_input_v != 0.0
    for reading in readings[delay + 1 : 100]:
        law.step(reading)
    assert law.lookahead() == ()
    law.coast(0.0, 25)
    assert law.cycle == 125
    output = law.step(readings[125])
    cycles = [taken.cycle for taken in output.adopted_plans]
    assert cycles and cycles == sorted(cycles) and cycles[0] >= 100 and cycles[-1] <= 125


def _late_reading_setup() -> tuple[Any, Any, list[Any]]:
    from ballbeam.assembly import controller_design
    from ballbeam.core.plant import SensorReading

    # Fixed observer gains and no ball-gain fit: the model the check below runs is the law's.
    config = load_config(PAPER, ("run.duration_s=0.4", "observer.adapt_noise=false",
                                 "tracker.adapt_ball_gain=false"))
    trace = run_offline(config).trace
    readings = [SensorReading(int(a), int(p)) for a, p in zip(
        trace.angle_counts.tolist(), trace.position_counts.tolist(), strict=True)]
    return config, controller_design(config), readings


@pytest.mark.parametrize("age", [2, 5, 17])
def test_a_late_reading_corrects_the_estimate_as_if_it_had_come_in_time(age: int) -> None:
    """A reading of ``age`` cycles ago, all of them coasted at a held voltage: the estimate
    the law then steps on is the one the in-time correction, predicted on through the same
    voltages, gives (the check runs the model from the corrected state; the law adds Adᵈ δ
    to its coasted prediction instead)."""
    from ballbeam.core.control import correct, predict

    _, design, readings = _late_reading_setup()
    law = TrackerLaw(design)
    first = 150  # well into the first swing: the servo turns fast
    for reading in readings[:first]:
        law.step(reading)
    held_v = 2.0
    prior = law.state.prediction
    assert prior is not None
    in_time = correct(design.observer, prior, design.law_measurement(readings[first]))
    drive_v = design.modelled_drive_v(held_v, design.deadzone_at(law.state))
    for _ in range(age):
        in_time = predict(design.observer, in_time, drive_v)
    law.coast(held_v, age)
    coasted = law.state.prediction
    output = law.step(readings[first], age_cycles=age)
    assert np.allclose(output.estimate, design.in_x(in_time), rtol=0, atol=1e-12)
    assert not np.allclose(output.estimate, design.in_x(coasted), rtol=0, atol=1e-6)
    assert not output.measured and law.cycle == first + age + 1


def test_a_reading_older_than_the_last_taken_or_than_remembered_is_history() -> None:
    """A late reading of a cycle that measured (a newer reading was taken since), or of one
    longer ago than the law remembers, leaves the law as a plain coasted cycle would."""
    from ballbeam.core.law import LATE_READING_CYCLES

    _, design, readings = _late_reading_setup()
    for coasted, age in ((3, 4), (LATE_READING_CYCLES + 5, LATE_READING_CYCLES + 2)):
        late, plain = TrackerLaw(design), TrackerLaw(design)
        for reading in readings[:120]:
            late.step(reading)
            plain.step(reading)
        late.coast(1.0, coasted)
        plain.coast(1.0, coasted)
        assert late.step(readings[100], age_cycles=age) == plain.step(None)
        assert late.state == plain.state


def _coasting_replanner(estimate_gamma: bool, measured: int, coasted: int) -> tuple[Any, Any]:
    """A re-planning controller on a real start's true (θ, x) for ``measured`` cycles, then
    ``coasted`` cycles without a sample; with the true states."""
    from ballbeam.core.replanning import ReplanningController, Settings

    config = load_config(PAPER, ("run.duration_s=0.4",))
    states = run_offline(config).trace.true_states
    controller = ReplanningController(
        Settings(estimate_gamma=estimate_gamma), np.array(states[0], dtype=float)
    )
    for state in states[:measured]:
        controller.step(float(state[0]), float(state[3]))
    for _ in range(coasted):
        controller.step(None, None)
    return controller, states


@pytest.mark.parametrize("age", [1, 4, 17])
def test_the_re_planning_filter_takes_a_late_sample_as_if_it_had_come_in_time(age: int) -> None:
    """The Kalman filter on (θ, θ̇, ẋ, x, δγ, q): a sample of ``age`` cycles ago, whose cycle and
    the ones since went on without a sample (the filter predicting only), leaves the state
    and covariance the filter would have had taking it in its own cycle and predicting on
    through the same drives; the identification's windows get it in place of the
    prediction."""
    from ballbeam.core.replanning import filter_step

    first = 150  # in the first swing: the servo turns fast
    controller, states = _coasting_replanner(True, first, age)
    steps = list(controller._recent)[-age:]
    assert all(step.measured is None for step in steps)
    theta, position = float(states[first][0]), float(states[first][3])
    rows = steps[0].rows
    y = (rows.angle_gain * theta, rows.position_gain * position)
    state, covariance = steps[0].state, steps[0].covariance
    for index, step in enumerate(steps):  # in order: the sample at its own cycle
        state, covariance, _ = filter_step(
            step.rows, state, covariance, step.drive_v, y if index == 0 else None,
            step.ball_noise_var,
        )
    coasted = controller.estimate.copy()
    assert controller.take_late(theta, position, age)
    assert np.allclose(controller.estimate, state[:4], rtol=0, atol=1e-12)
    assert controller._gamma_error == pytest.approx(state[4], abs=1e-12)
    assert np.allclose(controller._covariance, covariance, rtol=0, atol=1e-15)
    assert not np.allclose(controller.estimate, coasted, rtol=0, atol=1e-6)
    sample = first - controller._samples_from
    assert (controller._theta[sample], controller._position[sample]) == (theta, position)


def test_the_fixed_gain_observer_takes_a_late_sample_and_coasts_on_its_model() -> None:
    """Without the γ filter: a period without a sample is the model's prediction
    (Ad x̂ + bd u), and a late sample is the observer's correction at its cycle, predicted on
    through the same drives (numpy here, the law's plain floats there)."""
    age, first = 6, 150
    controller, states = _coasting_replanner(False, first, age)
    steps = list(controller._recent)[-age:]
    ad = np.array(steps[0].rows.filter.Ad)
    bd = np.array(steps[0].rows.filter.bd)
    gain = np.array(steps[0].rows.L)
    for before, after in itertools.pairwise(steps):
        assert np.allclose(ad @ np.array(before.state) + bd * before.drive_v, after.state,
                           rtol=0, atol=1e-12)
    theta, position = float(states[first][0]), float(states[first][3])
    filter_rows = steps[0].rows.filter
    y = np.array([filter_rows.angle_gain * theta, filter_rows.position_gain * position])
    c = np.zeros((2, 4))
    c[0, 0], c[1, 3] = filter_rows.angle_gain, filter_rows.position_gain
    estimate = np.array(steps[0].state)
    for index, step in enumerate(steps):
        estimate = ad @ estimate + bd * step.drive_v
        if index == 0:
            estimate = estimate + gain @ (y - c @ estimate)
    assert controller.take_late(theta, position, age)
    assert np.allclose(controller.estimate, estimate, rtol=0, atol=1e-12)


def test_coasted_periods_are_predicted_on_what_the_plant_drove() -> None:
    """Periods the law made no command for: the plant drove the look-ahead's entries, then
    held its last (without one, the held command); the fixed-gain observer's prediction is
    Ad x̂ + bd u on each, the identified dead zone taken out (numpy here), and nothing else is
    decided in them: no plan is asked for."""
    from ballbeam.core.replanning import _dead_zone
    from ballbeam.core.replanning_law import ReplanningLaw

    controller, _ = _coasting_replanner(False, 150, 0)
    rows = controller._rows()
    ad, bd = np.array(rows.filter.Ad), np.array(rows.filter.bd)
    deadzone_v = controller.design.identified.deadzone_v
    estimate, drive_v = controller.estimate.copy(), controller._last_drive_v
    applied = (4.5, -0.1, 2.0, 0.0)
    for applied_v in applied:
        controller.coast(applied_v)
    for applied_v in applied:
        estimate = ad @ estimate + bd * drive_v
        drive_v = _dead_zone(applied_v, deadzone_v)
    assert np.allclose(controller.estimate, estimate, rtol=0, atol=1e-12)
    assert controller._command[-4:] == list(applied) and controller.cycle == 154
    assert controller.issued is None

    config = load_config(PAPER, (*REPLANNING, "run.duration_s=0.2"))
    trace = run_offline(config).trace
    law = control_law(config)
    assert isinstance(law, ReplanningLaw)
    law.step(SensorReading(int(trace.angle_counts[0]), int(trace.position_counts[0])))
    driven: list[float] = []
    law.controller.coast = driven.append  # type: ignore[method-assign,assignment]
    law.coast(1.0, 5, (2.0, 3.0))
    law.coast(1.5, 2)
    assert driven == [2.0, 3.0, 3.0, 3.0, 3.0, 1.5, 1.5] and law.cycle == 8


def test_the_re_planning_law_takes_late_samples_only_as_old_as_it_says() -> None:
    """A late sample is run again through every period since: the law takes one at most
    ``late_reading_cycles`` back (the daemon asks it), and steps through an older one as
    through a period without a sample (one it would otherwise take: no sample came since)."""
    from ballbeam.core.replanning_law import ReplanningLaw

    config = load_config(PAPER, (*REPLANNING, "run.duration_s=0.3"))
    trace = run_offline(config).trace
    readings = [SensorReading(int(a), int(p)) for a, p in zip(
        trace.angle_counts.tolist(), trace.position_counts.tolist(), strict=True)]
    laws = []
    for _ in range(3):
        law = control_law(config)
        assert isinstance(law, ReplanningLaw)
        for reading in readings[:120]:
            law.step(reading)
        for _ in range(30):  # periods 120–149 without their samples
            law.step(None)
        laws.append(law)
    oldest = laws[0].late_reading_cycles
    assert 0 < oldest < 32
    taken, history, plain = laws
    taken.step(readings[150 - oldest], age_cycles=oldest)
    history.step(readings[150 - oldest - 1], age_cycles=oldest + 1)
    plain.step(None)
    assert np.array_equal(history.controller.estimate, plain.controller.estimate)
    assert not np.allclose(taken.controller.estimate, plain.controller.estimate, rtol=0,
                           atol=1e-9)


def test_a_late_sample_older_than_one_taken_since_or_than_remembered_is_history() -> None:
    """A sample of a cycle that had its own (or of one before a cycle that had one), or of
    one longer ago than the filter remembers, changes nothing."""
    controller, states = _coasting_replanner(True, 150, 3)
    before = (controller.estimate.copy(), controller._covariance, list(controller._theta))
    theta, position = float(states[140][0]), float(states[140][3])
    assert not controller.take_late(theta, position, 10)  # cycle 140 had its sample
    assert not controller.take_late(theta, position, len(controller._recent) + 1)
    assert not controller.take_late(theta, position, 0)
    after = (controller.estimate, controller._covariance, controller._theta)
    assert np.array_equal(before[0], after[0]) and before[1:] == after[1:]
