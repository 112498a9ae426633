"""Builds the pure core's objects from a validated :class:`~ballbeam.config.Config`.

This is the only place that knows both the config layout and the core's signatures.
"""

from __future__ import annotations

import functools
import json
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from ballbeam.config import (
    Config,
    ControllerSection,
    LimitsSection,
    SensorsSection,
)
from ballbeam.core.adaptation import BallGainAdaptation, DeadZoneLearning, NoiseAdaptation
from ballbeam.core.control import ControllerDesign, ObserverLaw, RestGains
from ballbeam.core.guard import AngleGuard, make_angle_guard, make_soft_cap
from ballbeam.core.law import ControlLaw, TrackerLaw
from ballbeam.core.metrics import RunMetrics, compute_metrics
from ballbeam.core.model import BALL_POSITION, LinearModel, PhysicalConstants, Row4, as_row4
from ballbeam.core.observer import ObserverNoise, design_observers
from ballbeam.core.planning.plan import Plan
from ballbeam.core.plant import PlantPhysics
from ballbeam.core.simulate import SimulationTrace, simulate_closed_loop
from ballbeam.core.task import Task
from ballbeam.core.tracker import (
    StationaryTracker,
    stationary_gain,
    stationary_tracker,
    synthesize_discrete,
)
from ballbeam.errors import ConfigError, PlanningError
from ballbeam.plant_assembly import (
    design_model,
    physical_constants,
    plant_parameters,
    sensor_periods_per_cycle,
    true_model,
)

if TYPE_CHECKING:  # the floor's module loads the LP solver: only when a floor is asked for
    from ballbeam.core.control import PlanTaken
    from ballbeam.core.floor import OwnFloor
    from ballbeam.core.replanning import Settings

DEFAULT_POSITION_NOISE_M = 2e-4


def make_task(config: Config) -> Task:
    """The ``[task]`` section as the core's reference (a square wave stays periodic)."""
    return config.task.reference()


def fixed_target_m(config: Config) -> float:
    """The one target this controller can bring the ball to (it plans once, from the start);
    ConfigError for a task that changes during the run."""
    kind = config.task.kind
    if kind != "fixed":
        keys = "task.sine" if kind == "sine" else "task.setpoints/square"
        raise ConfigError(
            f"{keys} need the re-planning controller; this controller plans once from the "
            "start and holds one target (task.target_m)"
        )
    return config.task.target_m


def planned_start(config: Config, target_m: float) -> np.ndarray:
    """The start in the law's coordinates: x from the target (the linear model is the same
    under a shift of x, so a plan to the origin there is a plan to the target)."""
    start = config.initial.state()
    start[BALL_POSITION] -= target_m
    return start


def make_plan(config: Config) -> Plan:
    constants = physical_constants(config)
    start = planned_start(config, fixed_target_m(config))
    theta_max_rad = config.limits.theta_rad
    kind = config.plan.kind
    # Imported per kind: the LP solver is only loaded when the time-optimal path is asked for.
    if kind == "bang_bang":
        from ballbeam.core.planning.bang_bang import plan_bang_bang

        return plan_bang_bang(constants, theta_max_rad, start)
    if kind == "rate_limited":
        from ballbeam.core.planning.rate_limited import plan_rate_limited

        return plan_rate_limited(
            constants, theta_max_rad, config.plan.servo_rate_limit_rad_s, start
        )
    # The margin keeps the path off the limit from every start: one on the limit (the paper's
    # −52°) first leaves it at full voltage (the tracker needs the room there too).
    return _time_optimal_plan(
        constants,
        as_row4(start),
        config.limits.voltage_v - config.plan.voltage_margin_v,
        theta_max_rad - math.radians(config.plan.theta_margin_deg),
        config.plan.step_s or config.controller.period_s,
        from_outside=True,
    )


@functools.lru_cache(maxsize=16)
def _time_optimal_plan(
    constants: PhysicalConstants,
    start: Row4,
    voltage_limit_v: float,
    theta_max_rad: float,
    step_s: float,
    *,
    from_outside: bool,
) -> Plan:
    """The time-optimal planner (its LPs are most of a design's cost), kept per process: the
    same start and limits come back often (T* beside every offline run, a sweep's points, the
    tests). The plan is frozen, its arrays read-only."""
    from ballbeam.core.planning.time_optimal import (
        plan_time_optimal,
        plan_time_optimal_from_outside,
    )

    planner = plan_time_optimal_from_outside if from_outside else plan_time_optimal
    return planner(
        LinearModel.from_constants(constants),
        np.array(start),
        voltage_limit_v=voltage_limit_v,
        theta_max_rad=theta_max_rad,
        step_s=step_s,
    )


def minimum_time_s(config: Config) -> float | None:
    """T*: the full model's minimum time from the config's start to rest at the task's target
    at the start (a step schedule's first) under the full voltage and angle limits (the
    time-optimal planner with zero margins); None where no such path exists (a start beyond
    the limit)."""
    try:
        plan = _time_optimal_plan(
            physical_constants(config),
            as_row4(planned_start(config, make_task(config).target_at(0.0))),
            config.limits.voltage_v,
            config.limits.theta_rad,
            config.controller.period_s,
            from_outside=False,
        )
    except PlanningError:
        return None
    return plan.duration_s


def plant_floor(config: Config, target_m: float = 0.0) -> OwnFloor | None:
    """The true plant's own floor from the config's start to rest at ``target_m``
    (core/floor.py): its α and γ, the command bound (or its saturation, if lower) less its dead
    zone, zero margins, the controller's grid as for T*; None where no such path exists."""
    from ballbeam.core.floor import own_floor

    plant = config.plant
    try:
        return own_floor(
            true_model(config),
            config.initial.state(),
            voltage_limit_v=min(config.limits.voltage_v, plant.saturation_v),
            deadzone_v=plant.deadzone_v,
            theta_max_rad=config.limits.theta_rad,
            step_s=config.controller.period_s,
            target_m=target_m,
            nonlinear_ball=plant.nonlinear_ball,
        )
    except PlanningError:
        return None


def controller_design(config: Config, plan: Plan | None = None) -> ControllerDesign:
    target_m = fixed_target_m(config)
    plan = plan if plan is not None else make_plan(config)
    model = design_model(config)
    period_s = config.controller.period_s
    tracker_cfg = config.tracker
    # One sampling of the plan serves the tracker (k = 0..N) and the design's reference.
    samples = plan.sample(np.arange(round(tracker_cfg.horizon_s / period_s) + 1) * period_s)
    tracker = synthesize_discrete(
        model,
        plan,
        Q=np.diag(tracker_cfg.q),
        R=np.array([[tracker_cfg.r]]),
        period_s=period_s,
        horizon_s=tracker_cfg.horizon_s,
        terminal=tracker_cfg.terminal,
        input_reference=tracker_cfg.input_reference,
        stationary=_stationary_tracker(
            physical_constants(config), tuple(tracker_cfg.q), tracker_cfg.r, period_s
        ),
        samples=samples,
    )
    # The plan's end: from here the reference is rest at the origin.
    rest_from_cycle = math.ceil(plan.duration_s / period_s - 1e-9)
    offset_v = np.array(tracker.offset_v)
    rest_gains = None
    if tracker_cfg.rest_regulator:
        rest_gains = _rest_gains(config, rest_from_cycle)
        offset_v[min(rest_from_cycle, offset_v.shape[0]) :] = 0.0
    sensors = config.sensors
    constants = physical_constants(config)
    encoder_step_rad = sensors.encoder_step_rad
    adc_step_m = sensors.adc_step_m(constants.beam_length_m)
    observer_cfg = config.observer
    angle_noise_rad = observer_cfg.angle_noise_rad or encoder_step_rad / math.sqrt(12.0)
    position_noise_m = observer_cfg.position_noise_m or math.hypot(
        DEFAULT_POSITION_NOISE_M, adc_step_m / math.sqrt(12.0)
    )

    # Every filter the design holds (tracking and at rest, at each noise level), designed
    # together: (input noise, ball noise, noise level) → its law
    tracking = (observer_cfg.input_noise_v, observer_cfg.ball_noise_m_s2)
    resting = (observer_cfg.rest_input_noise_v, observer_cfg.rest_ball_noise_m_s2)
    kinds = (tracking, resting) if observer_cfg.rest_filter else (tracking,)
    levels = observer_cfg.noise_levels if observer_cfg.adapt_noise else ()
    wanted = list(dict.fromkeys((*kind, level) for level in (1.0, *levels) for kind in kinds))
    laws = dict(zip(wanted, _observer_laws(constants, period_s, tuple(
        ObserverNoise(input_v, ball_m_s2, angle_noise_rad, position_noise_m * level)
        for input_v, ball_m_s2, level in wanted
    )), strict=True))

    def observer_law(
        input_noise_v: float, ball_noise_m_s2: float, noise_level: float = 1.0
    ) -> ObserverLaw:
        return laws[input_noise_v, ball_noise_m_s2, noise_level]

    observer = observer_law(observer_cfg.input_noise_v, observer_cfg.ball_noise_m_s2)
    rest_observer = None
    if observer_cfg.rest_filter:
        # After the plan a quiet ball: a filter that smooths the sensor noise harder than the
        # tracking one, which must follow a fast path, can.
        rest_observer = observer_law(
            observer_cfg.rest_input_noise_v, observer_cfg.rest_ball_noise_m_s2
        )
    noise_adaptation = None
    if observer_cfg.adapt_noise:
        levels = observer_cfg.noise_levels
        rest_table = None
        if observer_cfg.rest_filter:
            rest_table = tuple(
                observer_law(
                    observer_cfg.rest_input_noise_v, observer_cfg.rest_ball_noise_m_s2, level
                ).L
                for level in levels
            )
        # E[(Δ²n)²] of first-order band-limited noise of std σ and pole a per period:
        # σ²(6 − 8a + 2a²), in measurement units (the sensor gain times metres).
        pole = math.exp(-2.0 * math.pi * observer_cfg.noise_bandwidth_hz * period_s)
        sigma_y = constants.position_sensor_gain * position_noise_m
        noise_adaptation = NoiseAdaptation(
            levels=levels,
            tracking_gains=tuple(
                observer_law(observer_cfg.input_noise_v, observer_cfg.ball_noise_m_s2, level).L
                for level in levels
            ),
            rest_gains=rest_table,
            expected_square=sigma_y * sigma_y * (6.0 - 8.0 * pole + 2.0 * pole * pole),
            smoothing_per_cycle=min(period_s / observer_cfg.noise_time_constant_s, 1.0),
        )
    guard = _angle_guard(config) if config.controller.theta_guard else None
    n_reference = tracker.K.shape[0]
    initial = planned_start(config, target_m)
    return ControllerDesign(
        period_s=tracker.period_s,
        plan_duration_s=float(plan.duration_s),
        gains=np.array(tracker.K[:, 0, :]),
        offset_v=offset_v,
        final_gain=np.array(tracker.K_final[0]),
        reference_states=np.array(samples.states[:n_reference]),
        reference_input_v=np.array(samples.input_v[:n_reference]),
        observer=observer,
        guard=guard,
        voltage_limit_v=config.limits.voltage_v,
        deadband_v=config.controller.command_deadband_v,
        deadzone_v=config.controller.deadzone_compensation_v,
        rest_from_cycle=rest_from_cycle,
        rest_observer=rest_observer,
        rest_gains=rest_gains,
        adaptation=_ball_gain_adaptation(config, model, rest_from_cycle, position_noise_m),
        deadzone_learning=_deadzone_learning(config),
        noise_adaptation=noise_adaptation,
        initial_state=as_row4(initial),
        angle_per_count=constants.angle_sensor_gain * encoder_step_rad,
        position_per_count=constants.position_sensor_gain * adc_step_m,
        # Only a real-time run on the authenticated bus sends it (its 64-byte CAN FD frames),
        # and only with a sample a period: the emulator steps it at its sample instants, and a
        # command does not say which of several samples in a period its period began with.
        lookahead_periods=(
            config.controller.lookahead_periods
            if config.run.mode == "realtime" and config.bus.authenticated
            and sensor_periods_per_cycle(config) == 1 else 0
        ),
        target_m=target_m,
    )


# The parts of a design no plan changes are kept per process (pure functions of hashable
# config pieces; each result immutable): a sweep's points, a test run's many designs and a
# re-synthesis in replay then pay only for what depends on the plan.
_DESIGN_CACHE_SIZE = 64


def clear_design_caches() -> None:
    """Forget every kept plan and design piece: the next design costs what a fresh process
    pays (the benchmarks' one-shot figures)."""
    for cached in (_time_optimal_plan, _observer_laws, _stationary_tracker, _stationary_row,
                   _guard):
        cached.cache_clear()


@functools.lru_cache(maxsize=_DESIGN_CACHE_SIZE)
def _observer_laws(
    constants: PhysicalConstants, period_s: float, noises: tuple[ObserverNoise, ...]
) -> tuple[ObserverLaw, ...]:
    model = LinearModel.from_constants(constants).discretize(period_s)
    return tuple(
        ObserverLaw.from_arrays(gains.Ad, gains.Bd, gains.C, gains.L)
        for gains in design_observers(model, noises)
    )


@functools.lru_cache(maxsize=_DESIGN_CACHE_SIZE)
def _stationary_tracker(
    constants: PhysicalConstants, q: tuple[float, ...], r: float, period_s: float
) -> StationaryTracker:
    return stationary_tracker(
        LinearModel.from_constants(constants), Q=np.diag(q), R=np.array([[r]]), period_s=period_s
    )


@functools.lru_cache(maxsize=_DESIGN_CACHE_SIZE)
def _stationary_row(
    constants: PhysicalConstants, q: tuple[float, ...], r: float, period_s: float
) -> Row4:
    """The sampled-data LQR's gain for these weights, as the law's row."""
    gain, _ = stationary_gain(
        LinearModel.from_constants(constants), np.diag(q), np.array([[r]]), period_s
    )
    return as_row4(gain[0])


def _ball_gain_adaptation(
    config: Config, model: LinearModel, until_cycle: int, position_noise_m: float
) -> BallGainAdaptation | None:
    tracker_cfg = config.tracker
    if not tracker_cfg.adapt_ball_gain:
        return None
    return BallGainAdaptation(
        design_gamma=float(model.A[2, 0]),
        position_noise_m=position_noise_m,
        confidence=tracker_cfg.ball_gain_confidence,
        min_ratio=tracker_cfg.ball_gain_ratio_min,
        max_ratio=tracker_cfg.ball_gain_ratio_max,
        period_s=config.controller.period_s,
        until_cycle=until_cycle,
        back_emf_v_s_per_rad=float(-model.A[1, 1] / model.B[1, 0]),
        pace_step_per_cycle=tracker_cfg.pace_slew_per_s * config.controller.period_s,
        resync_rate_per_cycle=tracker_cfg.clock_resync_per_s * config.controller.period_s,
        resync_max_per_cycle=tracker_cfg.clock_resync_max,
        # A limit arc: the plan holds θ_d within a degree of its own limit.
        arc_theta_rad=config.limits.theta_rad - math.radians(config.plan.theta_margin_deg + 1.0),
    )


def _deadzone_learning(config: Config) -> DeadZoneLearning | None:
    controller = config.controller
    if not controller.learn_deadzone:
        return None
    return DeadZoneLearning(
        min_motion_rad=controller.deadzone_learning_counts * config.sensors.encoder_step_rad,
        judge_motion_rad=4 * controller.deadzone_learning_counts * config.sensors.encoder_step_rad,
        rate=controller.deadzone_learning_rate,
        below_v=controller.deadzone_learning_below_v,
        max_v=controller.deadzone_max_v,
        max_lateness_ns=controller.deadzone_learning_max_lateness_us * 1000,
    )


def _rest_gains(config: Config, from_cycle: int) -> RestGains:
    tracker_cfg = config.tracker
    period_s = config.controller.period_s
    constants = physical_constants(config)
    rest_q = tuple(tracker_cfg.rest_q)
    far_gain = None
    if tracker_cfg.far_q is not None:
        far_gain = _stationary_row(constants, tuple(tracker_cfg.far_q), tracker_cfg.far_r, period_s)
    firm_gain = None
    if tracker_cfg.rest_firm_s > 0:
        firm_gain = _stationary_row(constants, rest_q, tracker_cfg.rest_firm_r, period_s)
    return RestGains(
        gain=_stationary_row(constants, rest_q, tracker_cfg.rest_r, period_s),
        far_gain=far_gain,
        from_cycle=max(from_cycle, 0),
        blend_cycles=max(round(tracker_cfg.rest_blend_s / period_s), 1),
        theta_near_rad=math.radians(tracker_cfg.rest_theta_near_deg),
        theta_far_rad=math.radians(tracker_cfg.rest_theta_far_deg),
        position_near_m=tracker_cfg.rest_position_near_m,
        position_far_m=tracker_cfg.rest_position_far_m,
        firm_gain=firm_gain,
        firm_cycles=max(round(tracker_cfg.rest_firm_s / period_s), 1),
        catch_gain=(
            (tracker_cfg.rest_catch_theta_v_per_rad, tracker_cfg.rest_catch_rate_v_s_per_rad)
            if tracker_cfg.rest_catch_s > 0 else None
        ),
        catch_cycles=max(round(tracker_cfg.rest_catch_s / period_s), 1),
    )


def _angle_guard(config: Config) -> AngleGuard:
    return _guard(
        physical_constants(config), config.controller, config.limits, config.plant.deadzone_v,
        config.run.mode == "realtime", config.sensors,
    )


@functools.lru_cache(maxsize=_DESIGN_CACHE_SIZE)
def _guard(
    constants: PhysicalConstants,
    controller: ControllerSection,
    limits: LimitsSection,
    deadzone_v: float,
    realtime: bool,
    sensors: SensorsSection,
) -> AngleGuard:
    alpha, alpha_beta = constants.alpha, constants.alpha * constants.beta
    # In real time a command lands some time after its sensor sample; the guard then judges
    # the state that far ahead, not just one period. And a stalled host can hold a command for
    # a few periods: both limits keep a little more room there.
    latency_s = controller.theta_guard_latency_us * 1e-6 if realtime else 0.0
    extra_deg = controller.theta_guard_realtime_margin_deg if realtime else 0.0
    discrete = LinearModel.from_constants(constants).discretize(controller.period_s + latency_s)
    brake_v = controller.theta_guard_brake_v or max(
        0.5 * limits.voltage_v, limits.voltage_v - deadzone_v
    )
    hard_limit_rad = math.radians(
        limits.theta_deg - controller.theta_guard_margin_deg - extra_deg
    )
    soft = None
    if controller.soft_guard:
        soft_limit_rad = math.radians(
            limits.theta_deg - controller.soft_guard_margin_deg - extra_deg
        )
        if realtime:
            soft_limit_rad = _on_encoder_level(
                soft_limit_rad, hard_limit_rad, sensors.encoder_step_rad
            )
        soft = make_soft_cap(
            theta_limit_rad=soft_limit_rad,
            alpha=alpha,
            alpha_beta=alpha_beta,
            brake_v=controller.soft_guard_brake_v,
            zone_gain_per_s=controller.soft_guard_zone_gain_per_s,
            rate_gain_per_s=controller.soft_guard_rate_gain_per_s,
            # Latency allowed beyond one period (a late loop, as its probe measured it): the
            # servo may run on that long before a braking command lands.
            reaction_s=max(latency_s - controller.period_s, 0.0),
        )
    return make_angle_guard(
        theta_limit_rad=hard_limit_rad,
        alpha=alpha,
        alpha_beta=alpha_beta,
        brake_v=brake_v,
        voltage_limit_v=limits.voltage_v,
        Ad=discrete.Ad,
        Bd=discrete.Bd,
        soft=soft,
        # Real time: a loop running later than that allowance looks further ahead, as late as
        # it has lately been (core/guard.py, LatenessWatch).
        lateness_allowance_ns=controller.theta_guard_latency_us * 1000,
        lateness_hold_cycles=(
            round(controller.guard_lateness_hold_s / controller.period_s) if realtime else 0
        ),
        lateness_start_ns=controller.start_lateness_us * 1000,
    )


def _on_encoder_level(soft_limit_rad: float, hard_limit_rad: float, step_rad: float) -> float:
    """Real time: the soft limit moved to the nearest encoder level (never past the hard
    barrier's limit). Its extra margin puts it 0.35° inside the plan's arcs, where the tracker
    pushes out against it, and between two levels the servo cannot be held still: reading the
    outer level the cap pushed back, reading the inner one it let the tracker push out again,
    and the command hunted ±0.3 V at 50 Hz on the arcs (33 sign changes in 0.4 s). On a level,
    reading it asks for no motion. The nearest level, not the inner one: 0.09° further in, the
    last swing fell 0.3–0.6° short of the rest band (rest 1.80–1.82 s, not 1.776 s). Offline
    and in lock-step the soft limit is 0.05° from the arcs, which the servo rides, and stays:
    the same move there (0.007°) only shook fragile cases (a 5× noise seed: 1.08 → 1.88 T*)."""
    levels = round(soft_limit_rad / step_rad)
    if levels * step_rad > hard_limit_rad:
        levels = math.floor(hard_limit_rad / step_rad)
    return levels * step_rad


def position_noise_m(config: Config) -> float:
    """The position sensor's noise the controller expects: the config's, else the design's
    default with the ADC's quantisation."""
    adc_step_m = config.sensors.adc_step_m(physical_constants(config).beam_length_m)
    return config.observer.position_noise_m or math.hypot(
        DEFAULT_POSITION_NOISE_M, adc_step_m / math.sqrt(12.0)
    )


def replanning_settings(config: Config) -> Settings:
    """The re-planning law's settings from the config: its period, limits, sensors and the
    design model as the identification's prior (its other settings are its own defaults)."""
    from ballbeam.core.replanning import Settings

    model = design_model(config)
    return Settings(
        period_s=config.controller.period_s,
        voltage_limit_v=config.limits.voltage_v,
        theta_limit_rad=config.limits.theta_rad,
        encoder_step_rad=config.sensors.encoder_step_rad,
        adc_step_m=config.sensors.adc_step_m(physical_constants(config).beam_length_m),
        # the config's noise level is the estimate's prior, not the level it designs with
        position_noise_prior_m=position_noise_m(config),
        prior_alpha=float(model.B[1, 0]),
        prior_pole_per_s=float(-model.A[1, 1]),
        prior_gamma=float(model.A[2, 0]),
    )


def control_law(
    config: Config,
    design: ControllerDesign | None = None,
    recorded_plans: Mapping[tuple[int, bool], PlanTaken] | None = None,
    *,
    plans_in_process: bool = True,
) -> ControlLaw:
    """The law ``controller.kind`` names, in its starting state. The tracker runs ``design``
    (default: the config's); the re-planner solves its plans in this process (offline), or
    with ``plans_in_process`` False leaves its requests to the caller's planner (the daemon),
    or takes ``recorded_plans``, the answers a run took (a replay)."""
    if config.controller.kind == "replanning":
        from ballbeam.core.replanning import solve_request
        from ballbeam.core.replanning_law import ReplanningLaw

        return ReplanningLaw(
            replanning_settings(config),
            config.initial.state(),
            make_task(config),
            encoder_step_rad=config.sensors.encoder_step_rad,
            adc_step_m=config.sensors.adc_step_m(physical_constants(config).beam_length_m),
            plan_delay_cycles=config.controller.plan_delay_cycles,
            planner=solve_request if plans_in_process and recorded_plans is None else None,
            recorded=recorded_plans,
        )
    return TrackerLaw(design if design is not None else controller_design(config))


def counts_per_measurement(config: Config) -> tuple[float, float]:
    """Measurement units (the sensor gains' 57·θ, 100·x) per encoder and per ADC count, as
    the tracker's design has them."""
    constants = physical_constants(config)
    return (
        constants.angle_sensor_gain * config.sensors.encoder_step_rad,
        constants.position_sensor_gain * config.sensors.adc_step_m(constants.beam_length_m),
    )


def run_cycles(config: Config) -> int:
    return round(config.run.duration_s * config.controller.rate_hz)


@dataclass(frozen=True)
class OfflineRun:
    design: ControllerDesign | None  # the tracker's (None: another law)
    trace: SimulationTrace
    metrics: RunMetrics


# Keys the controller design (plan, synthesis, observer, guard) and T* do not read: the true
# plant (but its dead zone, which sets the guard's braking voltage), the run's length and log,
# the bus, the scenario bounds. Configs that differ only there share one design (sweeps cache
# it); a key added to a design function must leave these lists.
_DESIGN_READS_PLANT = ("deadzone_v",)
_DESIGN_READS_RUN = ("mode",)
_DESIGN_IGNORES = ("bus", "expect")


def design_key(config: Config) -> str:
    """Equal for two configs exactly when :func:`controller_design` gives them one design."""
    data = config.model_dump(mode="json", exclude=set(_DESIGN_IGNORES))
    data["plant"] = {key: data["plant"][key] for key in _DESIGN_READS_PLANT}
    data["run"] = {key: data["run"][key] for key in _DESIGN_READS_RUN}
    return json.dumps(data, sort_keys=True)


def minimum_time_key(config: Config) -> str:
    """Equal for two configs exactly when :func:`minimum_time_s` gives them one T*."""
    return json.dumps(
        config.model_dump(
            mode="json", include={"model", "initial", "limits", "controller", "task"}
        ),
        sort_keys=True,
    )


def run_offline(config: Config) -> OfflineRun:
    design = controller_design(config) if config.controller.kind == "tracker" else None
    return run_offline_with(config, design, minimum_time_s(config))


def run_offline_with(
    config: Config, design: ControllerDesign | None, minimum_time: float | None
) -> OfflineRun:
    """The offline run of ``config`` with its design and T* already made (a sweep reuses them
    across points that share them: :func:`design_key`, :func:`minimum_time_key`); ``design``
    None: a law without one (``controller.kind``)."""
    physics = PlantPhysics(plant_parameters(config))
    trace = simulate_closed_loop(
        control_law(config, design),
        physics,
        config.initial.state(),
        n_cycles=run_cycles(config),
        sensor_periods_per_cycle=sensor_periods_per_cycle(config),
        substeps_per_sensor_period=config.plant.physics_substeps,
        rng=np.random.default_rng(config.plant.seed),
    )
    metrics = compute_metrics(
        trace.time_s,
        trace.true_states,
        trace.voltage_v,
        trace.reference_states[:, 3],
        config.limits.theta_rad,
        reference_input_v=trace.reference_input_v,
        minimum_time_s=minimum_time,
        peak_abs_theta_rad=trace.peak_abs_theta_rad,
        target_m=make_task(config).target_at(trace.time_s),
    )
    return OfflineRun(design=design, trace=trace, metrics=metrics)
