"""Builds the pure core's objects from a validated :class:`~ballbeam.config.Config`.

This is the only place that knows both the config layout and the core's signatures.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ballbeam.config import Config
from ballbeam.core.control import ControllerDesign, ObserverLaw
from ballbeam.core.guard import make_angle_guard
from ballbeam.core.metrics import RunMetrics, compute_metrics
from ballbeam.core.model import LinearModel, PhysicalConstants
from ballbeam.core.observer import design_observer
from ballbeam.core.planning.plan import Plan
from ballbeam.core.plant import ADC_COUNT_LIMIT, EmulatedPlant, PlantPhysics
from ballbeam.core.simulate import SimulationTrace, simulate_closed_loop
from ballbeam.core.tracker import synthesize_discrete

DEFAULT_POSITION_NOISE_M = 2e-4


def physical_constants(config: Config) -> PhysicalConstants:
    """The design model's physical constants: the paper's, with the config's ``[model]`` keys."""
    return PhysicalConstants(**config.model.model_dump())


def design_model(config: Config) -> LinearModel:
    """The linear model the controller is designed on."""
    return LinearModel.from_constants(physical_constants(config))


def true_model(config: Config) -> LinearModel:
    """The emulated plant's linear model: the design model with the ``[plant]`` gain scales."""
    return LinearModel.from_constants(
        physical_constants(config), config.plant.motor_gain_scale, config.plant.ball_gain_scale
    )


def make_plan(config: Config) -> Plan:
    constants = physical_constants(config)
    start = config.initial.state()
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
    from ballbeam.core.planning.time_optimal import plan_time_optimal

    return plan_time_optimal(
        design_model(config),
        start,
        voltage_limit_v=config.limits.voltage_v - config.plan.voltage_margin_v,
        # The margin keeps the path off the limit, but never excludes the start itself
        # (the paper starts exactly on −52°): then the path may touch the start's angle.
        theta_max_rad=min(
            theta_max_rad,
            max(theta_max_rad - math.radians(config.plan.theta_margin_deg), abs(float(start[0]))),
        ),
        step_s=config.plan.step_s or config.controller.period_s,
    )


def controller_design(config: Config, plan: Plan | None = None) -> ControllerDesign:
    plan = plan if plan is not None else make_plan(config)
    model = design_model(config)
    period_s = config.controller.period_s
    tracker_cfg = config.tracker
    tracker = synthesize_discrete(
        model,
        plan,
        Q=np.diag(tracker_cfg.q),
        R=np.array([[tracker_cfg.r]]),
        period_s=period_s,
        horizon_s=tracker_cfg.horizon_s,
        terminal=tracker_cfg.terminal,
        input_reference=tracker_cfg.input_reference,
    )
    sensors = config.sensors
    constants = physical_constants(config)
    encoder_step_rad = sensors.encoder_step_rad
    adc_step_m = sensors.adc_step_m(constants.beam_length_m)
    observer_cfg = config.observer
    observer = design_observer(
        model.discretize(period_s),
        input_noise_v=observer_cfg.input_noise_v,
        ball_noise_m_s2=observer_cfg.ball_noise_m_s2,
        angle_noise_rad=observer_cfg.angle_noise_rad or encoder_step_rad / math.sqrt(12.0),
        position_noise_m=observer_cfg.position_noise_m
        or math.hypot(DEFAULT_POSITION_NOISE_M, adc_step_m / math.sqrt(12.0)),
    )
    guard = None
    if config.controller.theta_guard:
        constants_alpha = constants.alpha
        # In real time a command lands some time after its sensor sample; the guard then
        # judges the state that far ahead, not just one period.
        latency_s = (
            config.controller.theta_guard_latency_us * 1e-6
            if config.run.mode == "realtime"
            else 0.0
        )
        discrete = model.discretize(period_s + latency_s)
        brake_v = config.controller.theta_guard_brake_v or max(
            0.5 * config.limits.voltage_v, config.limits.voltage_v - config.plant.deadzone_v
        )
        guard = make_angle_guard(
            theta_limit_rad=math.radians(
                config.limits.theta_deg - config.controller.theta_guard_margin_deg
            ),
            alpha=constants_alpha,
            alpha_beta=constants_alpha * constants.beta,
            brake_v=brake_v,
            voltage_limit_v=config.limits.voltage_v,
            Ad=discrete.Ad,
            Bd=discrete.Bd,
        )
    n_reference = tracker.K.shape[0]
    samples = plan.sample(np.arange(n_reference) * period_s)
    initial = config.initial.state()
    return ControllerDesign(
        period_s=tracker.period_s,
        plan_duration_s=float(plan.duration_s),
        gains=np.array(tracker.K[:, 0, :]),
        offset_v=np.array(tracker.offset_v),
        final_gain=np.array(tracker.K_final[0]),
        reference_states=np.array(samples.states),
        reference_input_v=np.array(samples.input_v),
        observer=ObserverLaw.from_arrays(observer.Ad, observer.Bd, observer.C, observer.L),
        guard=guard,
        voltage_limit_v=config.limits.voltage_v,
        initial_state=(float(initial[0]), float(initial[1]), float(initial[2]),
                       float(initial[3])),
        angle_per_count=constants.angle_sensor_gain * encoder_step_rad,
        position_per_count=constants.position_sensor_gain * adc_step_m,
    )


def plant_parameters(config: Config) -> EmulatedPlant:
    plant = config.plant
    constants = physical_constants(config)
    plant_model = true_model(config)
    sensor_period_s = 1.0 / plant.sensor_rate_hz
    return EmulatedPlant(
        alpha=float(plant_model.B[1, 0]),
        alpha_beta=float(-plant_model.A[1, 1]),
        gamma=float(plant_model.A[2, 0]),
        ball_gain_scale=plant.ball_gain_scale,
        saturation_v=plant.saturation_v,
        deadzone_v=plant.deadzone_v,
        nonlinear_ball=plant.nonlinear_ball,
        gravity_m_per_s2=constants.gravity_m_per_s2,
        arm_to_beam_ratio=constants.arm_radius_m / constants.beam_length_m,
        beam_half_length_m=constants.beam_length_m / 2.0,
        hard_stop_rad=math.radians(plant.hard_stop_deg),
        substep_s=sensor_period_s / plant.physics_substeps,
        encoder_step_rad=config.sensors.encoder_step_rad,
        adc_step_m=config.sensors.adc_step_m(constants.beam_length_m),
        adc_count_limit=ADC_COUNT_LIMIT,
        position_noise_m=plant.position_noise_m,
        noise_pole=math.exp(-2.0 * math.pi * plant.noise_bandwidth_hz * sensor_period_s),
    )


def sensor_periods_per_cycle(config: Config) -> int:
    return config.plant.sensor_rate_hz // config.controller.rate_hz


def run_cycles(config: Config) -> int:
    return round(config.run.duration_s * config.controller.rate_hz)


@dataclass(frozen=True)
class OfflineRun:
    design: ControllerDesign
    trace: SimulationTrace
    metrics: RunMetrics


def run_offline(config: Config) -> OfflineRun:
    design = controller_design(config)
    physics = PlantPhysics(plant_parameters(config))
    trace = simulate_closed_loop(
        design,
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
    )
    return OfflineRun(design=design, trace=trace, metrics=metrics)
