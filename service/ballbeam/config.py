"""Run configuration: pydantic models loaded from TOML files.

A config file may ``extends = "other.toml"`` (path relative to the file, or a shipped config's
name: ``extends = "paper"``) and override a few keys; ``--set dotted.key=value`` overrides are
merged the same way and validated with the rest.
Unknown keys, wrong types and out-of-range values are refused with a message naming the key.

The repository's ``configs/`` ship with the package (``ballbeam/configs``, package data): a
config argument that names no file is looked up there (``paper``, ``paths/bang_bang``,
``scenarios/noise_heavy.toml``), so an installed package runs from any directory.
"""

from __future__ import annotations

import itertools
import math
import tomllib
from collections.abc import Iterable, Mapping
from importlib import resources
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from ballbeam.core.metrics import EXPECTABLE_METRICS
from ballbeam.core.model import PhysicalConstants
from ballbeam.core.task import FixedTarget, SineWave, SquareWave, StepSchedule, Task
from ballbeam.errors import ConfigError
from ballbeam.files import not_a_regular_file

MAX_EXTENDS_DEPTH = 16
# What one run can hold; every size a config asks for is held to these at validation, before
# anything is planned, synthesised or started (Config._consistent).
# The fastest controller period: a finer plan grid gives the controller nothing (one voltage a
# period) and grows the planner's LP without bound.
MIN_PLAN_STEP_S = 5e-5
# The tracker synthesis holds ~770 bytes a grid step (horizon_s × rate_hz) at its peak: 2^19
# steps is ~400 MB, and still 60 s of horizon at 1 kHz.
MAX_SYNTHESIS_STEPS = 1 << 19
# `run` and `replay` read the whole log into memory, ~340 bytes of arrays a sensor sample: 2^22
# samples (70 min at 1 kHz) is ~1.4 GB.
MAX_RUN_SAMPLES = 1 << 22
# Physics steps a second (sensor_rate_hz × physics_substeps): the fastest sensor rate at its
# fewest substeps. Finer steps change the linear plant not at all (exact hold) and cost the
# nonlinear ball one RK4 step each.
MAX_PHYSICS_STEPS_PER_S = 200_000
MAX_NOISE_LEVELS = 16  # one observer design (a DARE) per level and filter: a table, not a sweep
# Interface-local IPv6 multicast (scope 1): the kernel loops it back and never transmits it.
DEFAULT_BUS_GROUP = "ff11:7079:7468:6f6e:6465:6d6f:6d63:6173"
# The paper's constants: ModelSection's defaults (they are written only in core/model.py).
_PAPER = PhysicalConstants()
# [task] positions stay this far from the beam's centre (the paper's beam is ±0.216 m).
TASK_POSITION_LIMIT_M = 0.2
MAX_SETPOINTS = 10_000
MAX_DISTURBANCES = 1_000
MAX_TAP_M_S = 1.0
MIN_TASK_PERIOD_S = 0.1
MAX_TASK_PERIOD_S = 86400.0  # the run's own duration bound


class _Section(BaseModel):
    model_config = ConfigDict(
        extra="forbid", frozen=True, validate_default=True, allow_inf_nan=False
    )


class ModelSection(_Section):
    """The controller's design model: the paper's constants (docs/design.md §2).

    The defaults are :class:`~ballbeam.core.model.PhysicalConstants`' own (their one home);
    a config sets a key only to differ from the paper.
    """

    torque_constant_nm_per_a: float = Field(_PAPER.torque_constant_nm_per_a, gt=0)
    gear_ratio: float = Field(_PAPER.gear_ratio, gt=0)
    armature_resistance_ohm: float = Field(_PAPER.armature_resistance_ohm, gt=0)
    armature_inertia_kg_m2: float = Field(_PAPER.armature_inertia_kg_m2, gt=0)
    # Physically meaningful ranges: a bench on a planet, a beam of a few centimetres to metres
    # (a 1e-300 m beam planned a 108 s path and overflowed the planner).
    gravity_m_per_s2: float = Field(_PAPER.gravity_m_per_s2, gt=0, le=30)
    arm_radius_m: float = Field(_PAPER.arm_radius_m, gt=0, le=1)
    beam_length_m: float = Field(_PAPER.beam_length_m, ge=0.05, le=10)
    angle_sensor_gain: float = Field(_PAPER.angle_sensor_gain, gt=0)
    position_sensor_gain: float = Field(_PAPER.position_sensor_gain, gt=0)


class LimitsSection(_Section):
    voltage_v: float = Field(5.0, gt=0, le=24, description="motor voltage bound |u|")
    theta_deg: float = Field(52.0, gt=0, lt=90, description="servo angle bound |θ|")

    @property
    def theta_rad(self) -> float:
        return math.radians(self.theta_deg)


class InitialSection(_Section):
    theta_deg: float = Field(-52.0, ge=-90, le=90)
    theta_rate_deg_s: float = Field(0.0, ge=-5000, le=5000)
    ball_velocity_m_s: float = Field(0.0, ge=-5, le=5)
    ball_position_m: float = Field(0.195, ge=-5, le=5)  # on the beam: checked with the model

    def state(self) -> np.ndarray:
        """Initial state vector (θ, θ̇, ẋ, x) in SI units."""
        return np.array(
            [
                math.radians(self.theta_deg),
                math.radians(self.theta_rate_deg_s),
                self.ball_velocity_m_s,
                self.ball_position_m,
            ]
        )


PlanKind = Literal["bang_bang", "rate_limited", "time_optimal"]


class PlanSection(_Section):
    kind: PlanKind = "time_optimal"
    servo_rate_limit_rad_s: float = Field(
        9.325, gt=0, le=100, description="rate_limited: bound on |θ̇| (paper: 9.325 or 8)"
    )
    voltage_margin_v: float = Field(
        0.45, ge=0, description="time_optimal: voltage kept back for the tracker's corrections"
    )
    theta_margin_deg: float = Field(
        0.5, ge=0, le=20, description="time_optimal: the path stays this far inside ±θ limit"
    )
    step_s: float | None = Field(
        None,
        ge=MIN_PLAN_STEP_S,
        le=0.05,
        description="time_optimal: control grid; default the controller period",
    )


class TrackerSection(_Section):
    q: tuple[float, ...] = Field(
        (10.0, 0.0, 0.0, 10000.0), description="diagonal of Q for (θ, θ̇, ẋ, x)"
    )
    r: float = Field(0.01, gt=0, description="input weight R")
    # The longest plan (the time-optimal planner's 20 s) and well past it: beyond the plan the
    # reference is rest at the origin. Steps (× controller.rate_hz): Config._consistent.
    horizon_s: float = Field(8.0, gt=0, le=60)
    terminal: Literal["stationary", "zero"] = "stationary"
    input_reference: Literal["feedforward", "zero"] = Field(
        "feedforward",
        description="penalise (u - u_d) with the plan's input (feedforward) or u itself (paper)",
    )

    rest_regulator: bool = Field(
        True, description="after the plan, gentler gains near rest (rest_q, rest_r)"
    )
    rest_q: tuple[float, ...] = Field(
        (1000.0, 0.0, 0.0, 30000.0), description="Q of the regulator that holds rest"
    )
    rest_r: float = Field(1.0, gt=0, description="R of the regulator that holds rest")
    rest_blend_s: float = Field(
        0.05, ge=0, le=10, description="after the plan: gains blend to the rest regulator's"
    )
    rest_firm_r: float = Field(
        0.5, gt=0, description="right after the plan, R of firmer rest gains (rest_q) that "
        "fade into rest_r's over rest_firm_s"
    )
    rest_firm_s: float = Field(
        3.0, ge=0, le=60, description="how long the firmer rest gains take to fade [s] "
        "(0: rest_r's from the plan's end)"
    )
    rest_catch_s: float = Field(
        0.06, ge=0, le=10, description="right after the plan, a servo catch (a PD term on θ) "
        "fading to nothing over this long [s]: the plan's last brake leaves the servo a little "
        "off and moving, and it crept past the rest band (0: none)"
    )
    rest_catch_theta_v_per_rad: float = Field(
        80.0, ge=0, le=1000, description="the catch's gain on θ [V/rad]"
    )
    rest_catch_rate_v_s_per_rad: float = Field(
        1.0, ge=0, le=100, description="the catch's gain on θ̇ [V·s/rad]"
    )
    far_q: tuple[float, ...] | None = Field(
        (10.0, 0.0, 0.0, 50000.0),
        description="after the plan, Q of the gains far from rest (None: the tracking q)",
    )
    far_r: float = Field(0.01, gt=0, description="after the plan, R of the gains far from rest")
    rest_theta_near_deg: float = Field(0.5, ge=0, description="rest gains alone within |θ| <")
    rest_theta_far_deg: float = Field(2.0, gt=0, description="tracking gains alone beyond |θ| >")
    rest_position_near_m: float = Field(0.0003, ge=0, description="rest gains alone within |x| <")
    rest_position_far_m: float = Field(0.0008, gt=0, description="tracking gains beyond |x| >")

    adapt_ball_gain: bool = Field(
        True, description="estimate the ball's gain while the plan runs; follow the path at "
        "the pace it allows and predict with it"
    )
    ball_gain_confidence: float = Field(
        0.01, gt=0, le=1, description="ball-gain estimate used once its relative standard "
        "error is below this"
    )
    ball_gain_ratio_min: float = Field(
        0.5, gt=0, le=1, description="ball-gain estimate: smallest ratio to the model's used"
    )
    ball_gain_ratio_max: float = Field(
        1.5, ge=1, le=4, description="ball-gain estimate: largest ratio to the model's used"
    )
    clock_resync_per_s: float = Field(
        20.0, ge=0, le=1000, description="ball-gain adaptation: on the path's accelerating limit "
        "arcs, the rate [1/s] at which the path's clock takes up the ball's measured lag (0: off)"
    )
    clock_resync_max: float = Field(
        0.2, ge=0, le=1, description="clock re-synchronisation: the largest change of the "
        "path's clock rate it makes"
    )
    pace_slew_per_s: float = Field(
        3.0, gt=0, le=1000, description="ball-gain adaptation: how fast the path's pace may change"
    )

    @model_validator(mode="after")
    def _rest_bands(self) -> TrackerSection:
        if not self.rest_theta_near_deg < self.rest_theta_far_deg:
            raise ValueError("rest_theta_near_deg must be below rest_theta_far_deg")
        if not self.rest_position_near_m < self.rest_position_far_m:
            raise ValueError("rest_position_near_m must be below rest_position_far_m")
        return self

    @field_validator("q", "rest_q", "far_q")
    @classmethod
    def _q_positive_semidefinite(cls, q: tuple[float, ...] | None) -> tuple[float, ...] | None:
        if q is None:
            return q
        if len(q) != 4:
            raise ValueError(f"Q needs 4 diagonal entries for (θ, θ̇, ẋ, x), got {len(q)}")
        if any(not math.isfinite(value) or value < 0 for value in q):
            raise ValueError(f"Q must be positive semi-definite (diagonal >= 0), got {list(q)}")
        return q


class ObserverSection(_Section):
    input_noise_v: float = Field(
        0.3, gt=0, description="std of the unmodelled input (dead zone, friction) per sample"
    )
    ball_noise_m_s2: float = Field(0.05, gt=0, description="std of unmodelled ball acceleration")
    rest_filter: bool = Field(
        True, description="after the plan, a quieter filter (the rest_* noise levels)"
    )
    rest_input_noise_v: float = Field(0.1, gt=0, description="rest filter: input noise std")
    rest_ball_noise_m_s2: float = Field(
        0.005, gt=0, description="rest filter: unmodelled ball acceleration std"
    )
    angle_noise_rad: float | None = Field(
        None, gt=0, description="angle measurement noise std; default from the encoder step"
    )
    position_noise_m: float | None = Field(
        None, gt=0, description="position measurement noise std; default from plant noise"
    )
    noise_bandwidth_hz: float = Field(
        200.0, gt=0, le=1e6, description="the position noise's bandwidth the design assumes"
    )
    adapt_noise: bool = Field(
        True, description="measure the position noise while running; filter for that level"
    )
    noise_levels: tuple[float, ...] = Field(
        (1.0, 2.0, 3.0, 5.0, 8.0),
        max_length=MAX_NOISE_LEVELS,
        description="noise levels (× the assumed) at which filters are designed and "
        "interpolated",
    )
    noise_time_constant_s: float = Field(
        0.3, gt=0, le=60, description="noise measurement: smoothing time constant"
    )

    @field_validator("noise_levels")
    @classmethod
    def _levels_increase_from_one(cls, levels: tuple[float, ...]) -> tuple[float, ...]:
        if len(levels) < 2 or levels[0] != 1.0 or any(
            not b > a for a, b in itertools.pairwise(levels)
        ):
            raise ValueError("noise_levels must start at 1 and increase, at least two of them")
        return levels


def _none_is_normal_scheduling(value: object) -> object:
    """Logs recorded before real time defaulted to SCHED_FIFO have ``realtime_priority: null``
    (no real-time scheduling): read as 0, its meaning today."""
    return 0 if value is None else value


ControllerKind = Literal["tracker", "replanning"]


class ControllerSection(_Section):
    kind: ControllerKind = Field(
        "tracker", description="the control law: the paper's time-varying LQ tracker of one "
        "plan (\"tracker\"), or issue 27's identify-and-re-plan law (\"replanning\": its "
        "plans are solved by a planner process beside the loop)"
    )
    plan_delay_cycles: int = Field(
        2, ge=1, le=1000, description="re-planning law: the fewest cycles from a plan's request "
        "to the cycle it takes effect (lock-step waits for it then, so lock-step equals "
        "offline); 2: a request sent after one cycle's command and answered within the next "
        "period is read at the start of the one after"
    )
    rate_hz: int = Field(1000, ge=10, le=20000)
    sensor_timeout_periods: int = Field(
        3, ge=1, le=10000, description="periods without a sensor frame before a fault (0 V)"
    )
    sensor_timeout_alive_periods: int = Field(
        10, ge=1, le=10000, description="with `ballbeam run`'s link showing the emulator alive "
        "(its samples late, e.g. starved of CPU): periods coasted on the model before 0 V; a "
        "dead emulator gets 0 V at the first silent period"
    )
    plant_lost_s: float = Field(
        0.5,
        gt=0,
        le=3600,
        description="sensor silence after which the run ends (shorter gaps: 0 V, then resume)",
    )
    phase_offset_us: int = Field(
        250, ge=0, le=100_000, description="real time: cycle start after the sensor frame"
    )
    start_timeout_s: float = Field(10.0, gt=0, le=3600, description="wait for the plant")
    lockstep_timeout_s: float = Field(
        2.0, gt=0, le=3600, description="lock-step: silence after which the plant is lost"
    )
    theta_guard: bool = Field(
        True, description="cap the voltage so the servo can always stop inside ±θ limit"
    )
    theta_guard_margin_deg: float = Field(
        0.01, ge=0, le=10, description="the guard stops the servo this far inside the limit"
    )
    theta_guard_latency_us: int = Field(
        1000,
        ge=0,
        le=100_000,
        description="real time: command latency the guard allows for (it looks this much further)",
    )
    lateness_probe_s: float = Field(
        0.3, ge=0, le=10, description="real time: before the run, how long the daemon measures "
        "its own lateness; the worst becomes start_lateness_us (0: no probe)"
    )
    start_lateness_us: int = Field(
        0, ge=0, le=100_000, description="real time: the lateness the angle guard starts the "
        "run with, kept as margin as long as one measured in the run (guard_lateness_hold_s "
        "to twice that), then let go; the daemon's probe sets it to what it measured"
    )
    guard_lateness_hold_s: float = Field(
        0.5, ge=0, le=60, description="real time: the angle guard looks ahead as far as the "
        "loop's worst lateness (skipped periods included) beyond theta_guard_latency_us, kept "
        "this long after it was measured (0: a fixed look-ahead)"
    )
    max_guard_latency_us: int = Field(
        30_000, ge=0, le=100_000, description="real time: the most lateness the probe may "
        "start the guard with"
    )
    theta_guard_brake_v: float | None = Field(
        None, gt=0, description="braking voltage the guard counts on; default V − dead zone"
    )
    theta_guard_realtime_margin_deg: float = Field(
        0.1,
        ge=0,
        le=10,
        description=(
            "real time: extra margin of both guards (a stalled host can hold a command for "
            "several periods; the guard's look-ahead follows the loop's lateness, and the "
            "commands' look-ahead drives the guard's own predictions meanwhile)"
        ),
    )
    soft_guard: bool = Field(
        True, description="a smooth cap on the servo rate near the limit, inside the hard guard"
    )
    soft_guard_margin_deg: float = Field(
        0.05, ge=0, le=10, description="the soft cap stops the servo this far inside the limit"
    )
    soft_guard_brake_v: float = Field(
        4.75, gt=0, description="braking voltage of the soft cap's braking curve"
    )
    soft_guard_zone_gain_per_s: float = Field(
        250.0, gt=0, description="allowed rate = gain × gap near the soft limit"
    )
    soft_guard_rate_gain_per_s: float = Field(
        40.0, gt=0, description="how hard the soft cap pulls the rate back to the allowed rate"
    )
    command_deadband_v: float = Field(
        0.05, ge=0, le=5, description="demands within this band are sent as 0 V"
    )
    deadzone_compensation_v: float = Field(
        0.1,
        ge=0,
        le=5,
        description="the motor dead zone the controller adds back (beyond the band) and models",
    )
    learn_deadzone: bool = Field(
        True, description="learn the motor's dead zone from the servo's response to small "
        "commands (starting from deadzone_compensation_v)"
    )
    deadzone_learning_rate: float = Field(
        0.3, gt=0, le=1, description="dead-zone learning: fraction of the way to each window's "
        "estimate"
    )
    deadzone_learning_counts: float = Field(
        4.0, ge=1, le=1000, description="dead-zone learning: encoder counts the model must move "
        "the servo in a window for it to count"
    )
    deadzone_learning_below_v: float = Field(
        1.5, gt=0, le=50, description="dead-zone learning: only commands below this teach it"
    )
    deadzone_max_v: float = Field(
        1.0, gt=0, le=50, description="dead-zone learning: the largest dead zone believed"
    )
    deadzone_learning_max_lateness_us: int = Field(
        500, ge=0, le=100_000, description="real time: dead-zone learning pauses while the "
        "loop's recent worst lateness is beyond this (late commands move the servo later than "
        "the model it learns from says)"
    )
    bound_tolerance_deg: float = Field(
        0.5,
        ge=0,
        le=10,
        description=(
            "a run breaks its safety bound (exit 1) when the plant's |θ| passes "
            "limits.theta_deg by more than this (paths that ride the limit touch it)"
        ),
    )
    spin_us: int = Field(
        200, ge=0, le=10_000,
        description="real time: busy-wait before each deadline, under SCHED_FIFO only (at normal "
        "priority the spin spends the CPU share that keeps the loop on time beside other jobs)",
    )
    cpu: int | None = Field(
        None, ge=-1, le=1023, description="real time: pin the daemon to this CPU (-1: don't)"
    )
    realtime_priority: int = Field(
        45, ge=0, le=99, description="real time: SCHED_FIFO priority for the daemon, where "
        "permitted (0: normal scheduling); below the kernel's interrupt threads (50)"
    )
    fair_slice_us: int = Field(
        100, ge=0, le=100_000, description="real time, at normal scheduling (SCHED_FIFO "
        "refused or off): the time slice the daemon asks the kernel for; a short one wakes "
        "it on time beside CPU-bound processes (Linux 6.12+; 0: the kernel's default)"
    )
    lookahead_periods: int = Field(
        20, ge=0, le=20, description="real time, on an authenticated (CAN FD) bus: each "
        "command also carries the commands of this many periods after it, which the plant "
        "applies while no newer command has come (a loop that misses periods goes on as "
        "planned instead of holding the last command); 0: none"
    )
    _old_priority = field_validator("realtime_priority", mode="before")(
        _none_is_normal_scheduling
    )

    @property
    def period_ns(self) -> int:
        return 1_000_000_000 // self.rate_hz

    @property
    def period_s(self) -> float:
        return self.period_ns * 1e-9


class PlantSection(_Section):
    """The emulated SRV02: the true plant, which may differ from the design model."""

    motor_gain_scale: float = Field(1.0, gt=0.1, le=10, description="true α / model α")
    ball_gain_scale: float = Field(1.0, gt=0.1, le=10, description="true γ / model γ")
    saturation_v: float = Field(5.0, gt=0, le=24)
    deadzone_v: float = Field(0.1, ge=0, le=5)
    position_noise_m: float = Field(2e-4, ge=0, le=0.05, description="sensor noise std")
    noise_bandwidth_hz: float = Field(200.0, gt=0, description="band limit of the sensor noise")
    nonlinear_ball: bool = False
    hard_stop_deg: float = Field(56.0, gt=0, lt=90)
    sensor_rate_hz: int = Field(1000, ge=10, le=20000)
    physics_substeps: int = Field(10, ge=10, le=1000, description="physics steps per sensor period")
    seed: int = Field(1, ge=0)
    hold_until_enabled: bool = Field(
        True, description="keep the ball at its start until the first enabled command"
    )
    watchdog_ms: float = Field(
        20.0, gt=0, le=10_000, description="no valid command for this long → 0 V"
    )
    lockstep_resend_ms: float = Field(
        20.0, gt=0, le=10_000, description="lock-step: resend the sample if no command came"
    )
    cpu: int | None = Field(
        None, ge=-1, le=1023, description="real time: pin the emulator to this CPU (-1: don't)"
    )
    realtime_priority: int = Field(
        44, ge=0, le=99, description="real time: SCHED_FIFO priority for the emulator, where "
        "permitted (0: normal scheduling)"
    )
    fair_slice_us: int = Field(
        100, ge=0, le=100_000, description="real time, at normal scheduling: the emulator's "
        "time slice (as controller.fair_slice_us)"
    )
    _old_priority = field_validator("realtime_priority", mode="before")(
        _none_is_normal_scheduling
    )
    command_loss: float = Field(0.0, ge=0, lt=1, description="fault injection: drop fraction")
    sensor_loss: float = Field(0.0, ge=0, lt=1, description="fault injection: drop fraction")
    disturbances: tuple[tuple[float, float], ...] = Field(
        (), max_length=MAX_DISTURBANCES,
        description="taps [[time_s, ball_velocity_change_m_s], ...]: the ball's velocity jumps "
        "at the first physics step at or after time_s (plant time from the ball's release)",
    )

    @field_validator("disturbances")
    @classmethod
    def _taps(cls, taps: tuple[tuple[float, float], ...]) -> tuple[tuple[float, float], ...]:
        for time_s, change_m_s in taps:
            if not time_s > 0:
                raise ValueError(f"a tap's time must be after the start (> 0), got {time_s:g} s")
            if abs(change_m_s) > MAX_TAP_M_S:
                raise ValueError(
                    f"a tap's velocity change must be within ±{MAX_TAP_M_S:g} m/s, "
                    f"got {change_m_s:g}"
                )
        for (before_s, _), (time_s, _) in itertools.pairwise(taps):
            if not time_s > before_s:
                raise ValueError(f"tap times must ascend: {time_s:g} s after {before_s:g} s")
        return taps



class _WaveSection(_Section):
    """A periodic reference around ``offset_m`` that stays within the beam's task range."""

    amplitude_m: float = Field(gt=0, le=TASK_POSITION_LIMIT_M)
    period_s: float = Field(ge=MIN_TASK_PERIOD_S, le=MAX_TASK_PERIOD_S)
    offset_m: float = Field(0.0, ge=-TASK_POSITION_LIMIT_M, le=TASK_POSITION_LIMIT_M)

    @model_validator(mode="after")
    def _within_limit(self) -> _WaveSection:
        _wave_within_limit(self.amplitude_m, self.offset_m)
        return self


class SquareWaveSection(_WaveSection):
    """A square wave around ``offset_m``: +amplitude for the first half period, then −."""


class SineWaveSection(_WaveSection):
    """x_r(t) = offset_m + amplitude_m · sin(2π t / period_s)."""


def _wave_within_limit(amplitude_m: float, offset_m: float) -> None:
    if abs(offset_m) + amplitude_m > TASK_POSITION_LIMIT_M:
        raise ValueError(
            f"|offset_m| + amplitude_m = {abs(offset_m) + amplitude_m:g} m goes beyond "
            f"±{TASK_POSITION_LIMIT_M} m"
        )


class TaskSection(_Section):
    """Where the ball is to go: one fixed target (the paper's task: 0), a step schedule, a
    square wave (a step schedule's shorthand) or a sine. At most one besides the target."""

    target_m: float = Field(
        0.0, ge=-TASK_POSITION_LIMIT_M, le=TASK_POSITION_LIMIT_M,
        description="the ball's fixed target position [m]",
    )
    setpoints: tuple[tuple[float, float], ...] | None = Field(
        None, min_length=1, max_length=MAX_SETPOINTS,
        description="step schedule [[time_s, target_m], ...]: times ascending from 0",
    )
    square: SquareWaveSection | None = None
    sine: SineWaveSection | None = None

    @field_validator("setpoints")
    @classmethod
    def _schedule(
        cls, setpoints: tuple[tuple[float, float], ...] | None
    ) -> tuple[tuple[float, float], ...] | None:
        if setpoints is None:
            return None
        if setpoints[0][0] != 0.0:
            raise ValueError(f"the first setpoint must be at time 0, got {setpoints[0][0]:g} s")
        for (before_s, _), (time_s, _) in itertools.pairwise(setpoints):
            if not time_s > before_s:
                raise ValueError(f"setpoint times must ascend: {time_s:g} s after {before_s:g} s")
        if setpoints[-1][0] > MAX_TASK_PERIOD_S:
            raise ValueError(
                f"setpoint time {setpoints[-1][0]:g} s is beyond {MAX_TASK_PERIOD_S:g} s"
            )
        for time_s, target_m in setpoints:
            if abs(target_m) > TASK_POSITION_LIMIT_M:
                raise ValueError(
                    f"setpoint target {target_m:g} m at {time_s:g} s is beyond "
                    f"±{TASK_POSITION_LIMIT_M} m"
                )
        return setpoints

    @model_validator(mode="after")
    def _one_task(self) -> TaskSection:
        given = [
            name for name, present in (
                ("target_m", self.target_m != 0.0), ("setpoints", self.setpoints is not None),
                ("square", self.square is not None), ("sine", self.sine is not None),
            ) if present
        ]
        if len(given) > 1:
            raise ValueError(
                f"give one of target_m, setpoints, square or sine, not {' and '.join(given)}"
            )
        return self

    @property
    def kind(self) -> Literal["fixed", "steps", "sine"]:
        if self.sine is not None:
            return "sine"
        return "fixed" if self.setpoints is None and self.square is None else "steps"

    def reference(self) -> Task:
        """This section as the core's reference (a square wave stays periodic)."""
        if self.setpoints is not None:
            times, targets = zip(*self.setpoints, strict=True)
            return StepSchedule(times_s=tuple(times), targets_m=tuple(targets))
        if self.square is not None:
            square = self.square
            return SquareWave(square.amplitude_m, square.period_s, square.offset_m)
        if self.sine is not None:
            return SineWave(self.sine.amplitude_m, self.sine.period_s, self.sine.offset_m)
        return FixedTarget(self.target_m)


class SensorsSection(_Section):
    """Sensor hardware both sides agree on: frames carry raw encoder and ADC counts."""

    encoder_counts_per_rev: int = Field(4096, ge=16, le=1 << 15)
    adc_bits: int = Field(16, ge=4, le=16)
    adc_range_v: float = Field(20.0, gt=0, le=100, description="ADC full scale (±10 V is 20 V)")
    beam_span_v: float = Field(10.0, gt=0, le=100, description="track pot volts over the beam")

    @property
    def encoder_step_rad(self) -> float:
        return 2.0 * math.pi / self.encoder_counts_per_rev

    def adc_step_m(self, beam_length_m: float) -> float:
        volts_per_m = self.beam_span_v / beam_length_m
        return self.adc_range_v / float(2**self.adc_bits) / volts_per_m


class RunSection(_Section):
    duration_s: float = Field(5.0, gt=0, le=86400)
    mode: Literal["lockstep", "realtime"] = "lockstep"
    log_dir: str = Field("logs", min_length=1, description="where run MCAP files go")
    lockstep_poll_us: int = Field(
        0,
        ge=0,
        le=100_000,
        description=(
            "lock-step: poll the bus this long (yielding the CPU) before blocking; a few % "
            "faster on an idle machine, but it takes CPU from other runs on a busy one"
        ),
    )


class BusSection(_Section):
    """python-can bus, as python-can configures it."""

    interface: str = Field(
        "auto",
        description=(
            "a python-can interface, or auto: SocketCAN on a free CAN FD vcan interface where "
            "one is up (`ballbeam bus setup`), else udp_multicast on bus.channel"
        ),
    )
    channel: str = Field(
        DEFAULT_BUS_GROUP,
        description="the interface's channel (auto: the udp_multicast group it falls back to)",
    )
    port: int = Field(43113, ge=1, le=65535)
    isolate_runs: bool = Field(
        True, description="ballbeam run: give each run a private group and port"
    )
    allow_off_host: bool = Field(
        False, description="permit a multicast group whose traffic leaves this host"
    )
    options: dict[str, str | int | float | bool] = Field(default_factory=dict)
    authenticate: bool | None = Field(
        None,
        description=(
            "SecOC-style frames (CAN FD: classic payload + freshness + truncated HMAC, keyed "
            "by a per-run secret); default: on for auto, udp_multicast and virtual, off "
            "otherwise (classic 8-byte E2E frames, the DBC's contract for real CAN hardware)"
        ),
    )

    @property
    def authenticated(self) -> bool:
        """Whether this bus carries authenticated frames (``authenticate`` resolved)."""
        if self.authenticate is not None:
            return self.authenticate
        # auto goes on a virtual bus only (a CAN FD vcan, or the group): any process there
        # can write frames.
        return self.interface in ("auto", "udp_multicast", "virtual")

    @model_validator(mode="after")
    def _known_options(self) -> BusSection:
        if self.options:
            unknown = sorted(set(self.options) - _bus_option_names(self.interface))
            if unknown:
                raise ValueError(
                    f"bus.options: {', '.join(unknown)} not an option of python-can's "
                    f"{self.interface!r} interface"
                )
        if self.authenticated and not _bus_carries_fd(self.interface, self.options):
            # protocol/secoc.py: an authenticated frame is 24 bytes, a command with its
            # look-ahead 64; a classic CAN frame holds 8.
            raise ValueError(
                f"bus.options.fd: python-can's {self.interface!r} bus "
                + ("is set to classic CAN (fd = false)" if "fd" in self.options
                   else "sends classic CAN unless fd = true")
                + ", but authenticated frames (bus.authenticate"
                + (")" if self.authenticate else f", on by default for {self.interface})")
                + " need CAN FD's 64-byte payload: set bus.options.fd = true, or "
                "bus.authenticate = false"
            )
        return self


def _bus_carries_fd(interface: str, options: Mapping[str, object]) -> bool:
    """Whether python-can's ``interface`` bus, with ``options``, carries CAN FD frames: its
    ``fd`` keyword as given, else that keyword's default (``socketcan``: CAN FD, as ``open_bus``
    opens an authenticated one; a classic interface is refused there, by its MTU). True where
    the bus class has no such keyword (``virtual`` carries any frame) or cannot be loaded here
    (opening it says why)."""
    import importlib
    import inspect

    from can.interfaces import BACKENDS

    if "fd" in options:
        return bool(options["fd"])
    if interface == "socketcan":  # opened for CAN FD when authenticated (runtime/bus.py)
        return True
    if interface not in BACKENDS:
        return True
    module, class_name = BACKENDS[interface]
    try:
        bus_class = getattr(importlib.import_module(module), class_name)
    except ImportError:
        return True
    fd = inspect.signature(bus_class.__init__).parameters.get("fd")
    return fd is None or fd.default is inspect.Parameter.empty or bool(fd.default)


def _bus_option_names(interface: str) -> set[str]:
    """The keyword arguments python-can's bus class for ``interface`` names (its own and
    BusABC's), less those the bench sets itself. Unknown interfaces: ValueError."""
    import importlib
    import inspect

    import can
    from can.interfaces import BACKENDS

    if interface == "auto":
        return _bus_option_names("udp_multicast") & _bus_option_names("socketcan")
    if interface not in BACKENDS:
        raise ValueError(f"bus.interface {interface!r} is not one of python-can's interfaces")
    module, class_name = BACKENDS[interface]
    try:
        bus_class = getattr(importlib.import_module(module), class_name)
    except ImportError as error:
        raise ValueError(f"bus.interface {interface!r} cannot be loaded: {error}") from error
    names = set(inspect.signature(bus_class.__init__).parameters)
    names |= set(inspect.signature(can.BusABC.__init__).parameters)
    return names - {"self", "channel", "args", "kwargs"}


class Config(_Section):
    model: ModelSection = ModelSection()
    limits: LimitsSection = LimitsSection()
    initial: InitialSection = InitialSection()
    plan: PlanSection = PlanSection()
    tracker: TrackerSection = TrackerSection()
    observer: ObserverSection = ObserverSection()
    controller: ControllerSection = ControllerSection()
    plant: PlantSection = PlantSection()
    task: TaskSection = TaskSection()
    sensors: SensorsSection = SensorsSection()
    run: RunSection = RunSection()
    bus: BusSection = BusSection()
    expect: dict[str, dict[str, float]] = Field(
        default_factory=dict, description="scenario bounds: metric = { min = .., max = .. }"
    )

    @model_validator(mode="after")
    def _consistent(self) -> Config:
        if 1_000_000_000 % self.controller.rate_hz:
            raise ValueError(
                f"controller.rate_hz = {self.controller.rate_hz} does not give a whole number "
                "of nanoseconds per period"
            )
        if self.plant.sensor_rate_hz % self.controller.rate_hz:
            raise ValueError(
                f"controller.rate_hz = {self.controller.rate_hz} must divide "
                f"plant.sensor_rate_hz = {self.plant.sensor_rate_hz}"
            )
        self._sizes_fit_a_run()
        self._controller_fits_the_run()
        half_beam_m = self.model.beam_length_m / 2
        if abs(self.initial.ball_position_m) > half_beam_m:
            raise ValueError(
                f"initial.ball_position_m = {self.initial.ball_position_m} is off the beam "
                f"(|x| <= model.beam_length_m / 2 = {half_beam_m:g} m)"
            )
        if abs(self.initial.theta_deg) > self.plant.hard_stop_deg:
            raise ValueError(
                f"initial.theta_deg = {self.initial.theta_deg} is beyond the servo hard stops "
                f"(plant.hard_stop_deg = {self.plant.hard_stop_deg})"
            )
        if self.plan.voltage_margin_v >= self.limits.voltage_v:
            raise ValueError(
                f"plan.voltage_margin_v = {self.plan.voltage_margin_v} leaves no voltage under "
                f"limits.voltage_v = {self.limits.voltage_v}"
            )
        taps = self.plant.disturbances
        if taps and taps[-1][0] >= self.run.duration_s:
            raise ValueError(
                f"plant.disturbances: a tap at {taps[-1][0]:g} s is not within the run "
                f"(run.duration_s = {self.run.duration_s:g})"
            )
        for metric, bound in self.expect.items():
            if metric not in EXPECTABLE_METRICS:
                raise ValueError(
                    f"expect.{metric}: unknown metric; known: {', '.join(EXPECTABLE_METRICS)}"
                )
            unknown = set(bound) - {"min", "max"}
            if unknown or not bound:
                raise ValueError(
                    f"expect.{metric} must be a table with 'min' and/or 'max', got {bound}"
                )
        return self

    def _controller_fits_the_run(self) -> None:
        if self.controller.kind != "replanning":
            return
        if self.run.mode == "realtime":
            raise ValueError(
                'controller.kind = "replanning" runs in lock-step only (run.mode = "lockstep"): '
                "its plans and identification are solved off the cycle, but in real time its "
                "cycle still takes most of the period, the loop falls tens of periods behind "
                "the sensor stream under load and the ball rests late (docs/decisions.md)"
            )

    def _sizes_fit_a_run(self) -> None:
        """Products of sizes a run must hold (the bounds' reasons: MAX_* at the top)."""
        rate_hz = self.controller.rate_hz
        steps = self.tracker.horizon_s * rate_hz
        if steps > MAX_SYNTHESIS_STEPS:
            raise ValueError(
                f"tracker.horizon_s = {self.tracker.horizon_s} at controller.rate_hz = {rate_hz} "
                f"is {steps:.0f} synthesis steps, more than {MAX_SYNTHESIS_STEPS} (at most "
                f"{MAX_SYNTHESIS_STEPS / rate_hz:g} s at this rate)"
            )
        duration_s = self.run.duration_s
        if round(duration_s * rate_hz) < 1:  # the daemon's own count of cycles
            raise ValueError(
                f"run.duration_s = {duration_s} is shorter than one control cycle "
                f"(controller.rate_hz = {rate_hz}: {1 / rate_hz:g} s); nothing would run"
            )
        sensor_rate_hz = self.plant.sensor_rate_hz
        samples = duration_s * sensor_rate_hz
        if samples > MAX_RUN_SAMPLES:
            raise ValueError(
                f"run.duration_s = {duration_s} at plant.sensor_rate_hz = {sensor_rate_hz} is "
                f"{samples:.0f} samples, more than a run's log can hold ({MAX_RUN_SAMPLES}: at "
                f"most {MAX_RUN_SAMPLES / sensor_rate_hz:g} s at this rate)"
            )
        substeps = self.plant.physics_substeps
        if sensor_rate_hz * substeps > MAX_PHYSICS_STEPS_PER_S:
            raise ValueError(
                f"plant.physics_substeps = {substeps} at plant.sensor_rate_hz = "
                f"{sensor_rate_hz} is {sensor_rate_hz * substeps} physics steps a second, more "
                f"than {MAX_PHYSICS_STEPS_PER_S}"
            )
        # The emulator keeps time in whole nanoseconds: a sensor period or physics step that is
        # not one drifts from the daemon's period and from the physics' own step.
        if 1_000_000_000 % (sensor_rate_hz * substeps):
            raise ValueError(
                f"plant.sensor_rate_hz = {sensor_rate_hz} with plant.physics_substeps = "
                f"{substeps} does not give a physics step of a whole number of nanoseconds"
            )


def _deep_merge(base: dict[str, Any], override: Mapping[str, Any]) -> dict[str, Any]:
    merged = dict(base)
    for key, value in override.items():
        if isinstance(value, Mapping) and isinstance(merged.get(key), dict):
            merged[key] = _deep_merge(merged[key], value)
        else:
            merged[key] = value
    return merged


MAX_CONFIG_BYTES = 1 << 20  # far above any real config (the paper's is 4 KiB)
# Tables and arrays inside one another: ours go 4 deep (a spec's array of tables of arrays).
# Deeper input is refused where it is parsed, before any recursive code sees it.
MAX_TOML_NESTING = 16


def parse_toml(text: str, source: str) -> dict[str, Any]:
    """``text`` parsed as TOML: a ConfigError naming ``source`` if it is not valid TOML, holds
    a number Python will not read, or nests tables and arrays deeper than MAX_TOML_NESTING."""
    try:
        return _loads_bounded(text, source)
    except tomllib.TOMLDecodeError as error:
        raise ConfigError(f"{source}: not valid TOML: {error}") from error


def _loads_bounded(text: str, source: str) -> dict[str, Any]:
    """``tomllib.loads`` (its TOMLDecodeError passes through), with ConfigError for what it
    parses but this project will not take. tomllib recurses once per level of nesting: a deep
    enough text exhausts the interpreter's stack."""
    try:
        data = tomllib.loads(text)
    except RecursionError:
        data = None  # raised outside the handler: its traceback holds a thousand frames
    except tomllib.TOMLDecodeError:
        raise
    except ValueError as error:  # an integer past Python's digit limit for int(str)
        raise ConfigError(f"{source}: not a usable TOML value: {error}") from error
    if data is None or _nesting_depth(data) > MAX_TOML_NESTING:
        raise ConfigError(
            f"{source}: tables and arrays nested more than {MAX_TOML_NESTING} deep"
        )
    return data


def _nesting_depth(value: Any) -> int:
    """How deep tables and arrays nest in ``value`` (a scalar: 0), stopping soon past the
    limit; without recursion."""
    deepest = 0
    stack: list[tuple[Any, int]] = [(value, 1)]
    while stack and deepest <= MAX_TOML_NESTING:
        item, depth = stack.pop()
        if isinstance(item, dict):
            children: Iterable[Any] = item.values()
        elif isinstance(item, list):
            children = item
        else:
            continue
        deepest = max(deepest, depth)
        stack.extend((child, depth + 1) for child in children)
    return deepest


def read_toml_file(path: Path, kind: str = "config") -> dict[str, Any]:
    """One TOML file of ours (a config, a sweep or tuning spec), read with the checks every
    such file gets: a regular file (not /dev/zero or a FIFO), at most 1 MiB, UTF-8, valid
    TOML; else one ConfigError that names ``kind`` and the path."""
    problem = not_a_regular_file(path)
    if problem is not None:
        raise ConfigError(f"cannot read {kind} {path}: {problem}")
    try:
        with path.open("rb") as stream:
            text = stream.read(MAX_CONFIG_BYTES + 1)
        if len(text) > MAX_CONFIG_BYTES:
            raise ConfigError(
                f"{path}: larger than {MAX_CONFIG_BYTES // 1024} KiB; not a {kind} file"
            )
        decoded = text.decode("utf-8")
    except FileNotFoundError as error:
        raise ConfigError(f"{kind} file not found: {path}") from error
    except IsADirectoryError as error:
        raise ConfigError(f"{kind} path is a directory, not a file: {path}") from error
    except (OSError, UnicodeDecodeError) as error:
        raise ConfigError(f"cannot read {kind} file {path}: {error}") from error
    return parse_toml(decoded, str(path))


def _read_toml(path: Path, depth: int = 0) -> dict[str, Any]:
    if depth > MAX_EXTENDS_DEPTH:
        raise ConfigError(f"{path}: 'extends' chain is deeper than {MAX_EXTENDS_DEPTH} files")
    data = read_toml_file(path)
    parent = data.pop("extends", None)
    if parent is None:
        return data
    if not isinstance(parent, str):
        raise ConfigError(f"{path}: 'extends' must be a file path string")
    base = _read_toml(_extended_path(path, parent), depth + 1)
    return _deep_merge(base, data)


def _extended_path(path: Path, parent: str) -> Path:
    """What ``extends = parent`` in ``path`` names: a file relative to ``path``, else a
    shipped config's name (``"paper"``), as a config argument is resolved."""
    relative = (path.parent / parent).resolve()
    if relative.exists():
        return relative
    shipped = shipped_configs()
    for candidate in (shipped / parent, shipped / f"{parent}.toml"):
        if candidate.is_file():
            return candidate.resolve()
    return relative  # not found either way: reading it says so, with the path


def parse_override(assignment: str) -> dict[str, Any]:
    """``"a.b=1.5"`` → ``{"a": {"b": 1.5}}``; the value is TOML, or else a bare string."""
    key, separator, text = assignment.partition("=")
    key = key.strip()
    if not separator or not key or any(not part.strip() for part in key.split(".")):
        raise ConfigError(f"override {assignment!r} is not of the form dotted.key=value")
    try:
        value = _loads_bounded(f"value = {text.strip()}", f"override {key!r}")["value"]
    except tomllib.TOMLDecodeError:
        value = text.strip()
    nested: dict[str, Any] = {}
    cursor = nested
    parts = [part.strip() for part in key.split(".")]
    for part in parts[:-1]:
        cursor = cursor.setdefault(part, {})
    cursor[parts[-1]] = value
    return nested


def _describe(error: ValidationError, source: str) -> str:
    lines = []
    for item in error.errors():
        key = ".".join(str(part) for part in item["loc"]) or "(top level)"
        if item["type"] == "extra_forbidden":
            lines.append(f"unknown key {key!r}")
        else:
            message = item["msg"].removeprefix("Value error, ")
            lines.append(f"{key!r}: {message}" if item["loc"] else message)
    return f"{source}: " + "; ".join(lines)


def config_from_mapping(data: Mapping[str, Any], source: str = "config") -> Config:
    try:
        return Config.model_validate(dict(data))
    except ValidationError as error:
        raise ConfigError(_describe(error, source)) from error


def shipped_configs() -> Path:
    """The configs shipped with the package (the repository's ``configs/``)."""
    return Path(str(resources.files("ballbeam") / "configs"))


def resolve_config_path(name: str | Path) -> Path:
    """``name`` itself if it exists, else the shipped config it names (``.toml`` optional)."""
    path = Path(name)
    if path.exists():
        return path
    shipped = shipped_configs()
    for candidate in (shipped / path, shipped / f"{path}.toml"):
        if candidate.is_file():
            return candidate
    raise ConfigError(
        f"config file not found: {name} (nor a shipped config of that name; "
        "`ballbeam configs` lists them)"
    )


def load_config(path: str | Path | None, overrides: Iterable[str] = ()) -> Config:
    """Load ``path`` (or the paper's defaults when None) and apply ``--set`` overrides."""
    data: dict[str, Any] = {} if path is None else read_config_data(path)
    return config_from_data(data, overrides, str(path) if path is not None else "config")


def read_config_data(path: str | Path) -> dict[str, Any]:
    """The TOML mapping of a config file (or shipped name) with its ``extends`` chain merged:
    what a process on another host needs to build the same config without the file."""
    return _read_toml(resolve_config_path(path))


def config_from_data(
    data: Mapping[str, Any], overrides: Iterable[str] = (), source: str = "config"
) -> Config:
    """``data`` (as :func:`read_config_data` gives it) with ``--set`` overrides, validated."""
    merged = dict(data)
    for assignment in overrides:
        merged = _deep_merge(merged, parse_override(assignment))
    return config_from_mapping(merged, source)
