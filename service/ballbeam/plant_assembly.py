"""The emulated plant and the models from a validated :class:`~ballbeam.config.Config`.

What the plant emulator's process needs, apart from :mod:`ballbeam.assembly` (which imports the
controller's design stack, SciPy among it): a process pays for every import at its start, and
the emulator designs nothing.
"""

from __future__ import annotations

import math

from ballbeam.config import Config
from ballbeam.core.model import LinearModel, PhysicalConstants
from ballbeam.core.plant import ADC_COUNT_LIMIT, EmulatedPlant, tap_step


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


def plant_parameters(config: Config) -> EmulatedPlant:
    plant = config.plant
    constants = physical_constants(config)
    plant_model = true_model(config)
    sensor_period_s = 1.0 / plant.sensor_rate_hz
    substep_s = sensor_period_s / plant.physics_substeps
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
        substep_s=substep_s,
        encoder_step_rad=config.sensors.encoder_step_rad,
        adc_step_m=config.sensors.adc_step_m(constants.beam_length_m),
        adc_count_limit=ADC_COUNT_LIMIT,
        position_noise_m=plant.position_noise_m,
        noise_pole=math.exp(-2.0 * math.pi * plant.noise_bandwidth_hz * sensor_period_s),
        taps=tuple(
            (tap_step(time_s, substep_s), change_m_s) for time_s, change_m_s in plant.disturbances
        ),
    )


def sensor_periods_per_cycle(config: Config) -> int:
    return config.plant.sensor_rate_hz // config.controller.rate_hz
