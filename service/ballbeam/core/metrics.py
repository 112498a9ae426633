"""Run metrics, computed from the true plant state (never from measurements)."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from ballbeam.core.task import Task

SETTLE_BAND_M = 0.002
# Rest (docs/design.md §6): |x| <= 0.5 mm and |θ| <= 0.5° from that instant to the end of the run.
REST_POSITION_M = 5e-4
REST_THETA_RAD = math.radians(0.5)
DITHER_WINDOW_S = 1.0  # dither is counted over the run's last second
# A one-period step of u_d above this is the plan's own switch: steps of u next to it are not
# chatter (the tracker follows the switch within a period or two).
PLAN_SWITCH_V = 0.5
PLAN_SWITCH_WINDOW = 2  # periods either side of a plan switch
# Metrics a scenario may bound in its [expect] table: these and the bench's own figures.
BENCH_FIGURES = (
    "saturation_fraction",
    "lateness_p50_us",
    "lateness_p99_us",
    "lateness_max_us",
    "overruns",
    "frames_lost",
    "plant_missed_periods",
    "frames_rejected",
    "coasted_cycles",
    "recorder_dropped",
)


@dataclass(frozen=True)
class RunMetrics:
    settle_time_s: float | None  # first time after which |x − target| stays within 2 mm
    overshoot_mm: float  # largest excursion past the target, on the side opposite the start
    max_abs_theta_deg: float
    theta_violation_s: float  # time spent with |θ| beyond the limit
    max_abs_u_v: float
    tracking_rms_mm: float  # RMS of x − x_d
    # Control quality (docs/design.md §6); None where the inputs they need were not given.
    rest_time_s: float | None = None  # |x| <= 0.5 mm and |θ| <= 0.5° from here on; None: never
    rest_ratio: float | None = None  # rest time / the true minimum time T* from this start
    input_tv_ratio: float | None = None  # Σ|Δu| / Σ|Δu_d|
    dither_hz: float | None = None  # sign changes of u per second over the last second
    largest_step_v: float | None = None  # largest |Δu| away from the plan's own switches
    # RMS of x − x_r(t), the task's own reference, over the run's second half (a sine's
    # tracking error once it is joined)
    task_rms_mm: float | None = None

    def as_dict(self) -> dict[str, float | None]:
        return asdict(self)


def inside_from(time_s: np.ndarray, outside: np.ndarray) -> float | None:
    """First time after which ``outside`` (N,) is False to the end; None if the last sample is
    outside."""
    indices = np.flatnonzero(outside)
    if indices.size == 0:
        return float(time_s[0])
    last = int(indices[-1])
    if last == len(time_s) - 1:
        return None
    return float(time_s[last + 1])


def settle_time(time_s: np.ndarray, position_m: np.ndarray, band_m: float) -> float | None:
    """First time after which |x| stays within ``band_m`` to the end."""
    return inside_from(time_s, np.abs(position_m) > band_m)


def rest_time(
    time_s: np.ndarray,
    true_states: np.ndarray,
    position_band_m: float = REST_POSITION_M,
    theta_band_rad: float = REST_THETA_RAD,
    target_m: float | np.ndarray = 0.0,
) -> float | None:
    """First time after which |x − target| <= position band and |θ| <= angle band to the end;
    None if the last sample is outside either. ``target_m``: a float, or one per sample (N,)."""
    return inside_from(
        time_s, outside_rest_band(true_states, target_m, position_band_m, theta_band_rad)
    )


@dataclass(frozen=True)
class SegmentRest:
    """One segment of a task between two changes of target: from ``start_s`` (0 or a change)
    to the next change or the run's end, with its ``target_m``; ``rest_after_s``: from
    ``start_s`` to rest at the target within the segment (rest as :func:`rest_time`, the
    segment's last sample its end); None: not at rest by then, or no sample in it."""

    start_s: float
    target_m: float
    rest_after_s: float | None


def segment_rest_times(
    time_s: np.ndarray, true_states: np.ndarray, task: Task
) -> tuple[SegmentRest, ...]:
    """Rest after each change of target: the task's changes within the run (time_s (N,)
    increasing, true_states (N, 4)) split it into segments; each is judged on its own samples
    (a segment starts at its change, inclusive, and ends before the next)."""
    time_s = np.asarray(time_s, dtype=float)
    starts = np.concatenate(([min(0.0, float(time_s[0]))],
                             task.change_times_s(0.0, float(time_s[-1]))))
    segments = []
    for index, start_s in enumerate(starts):
        end_s = starts[index + 1] if index + 1 < len(starts) else math.inf
        inside = (time_s >= start_s) & (time_s < end_s)
        target_m = float(task.target_at(float(start_s)))
        rest_s = None
        if inside.any():
            rest_s = rest_time(time_s[inside], true_states[inside], target_m=target_m)
        segments.append(SegmentRest(
            start_s=float(start_s), target_m=target_m,
            rest_after_s=None if rest_s is None else rest_s - float(start_s),
        ))
    return tuple(segments)


def outside_rest_band(
    true_states: np.ndarray,
    target_m: float | np.ndarray = 0.0,
    position_band_m: float = REST_POSITION_M,
    theta_band_rad: float = REST_THETA_RAD,
) -> np.ndarray:
    """(N,) True where the ball is more than the band from ``target_m`` (a float, or one per
    sample) or the servo more than its band from level."""
    away_m = np.abs(true_states[:, 3] - target_m) > position_band_m
    tilted = np.abs(true_states[:, 0]) > theta_band_rad
    return np.asarray(away_m | tilted)


def first_entry_time(
    time_s: np.ndarray, true_states: np.ndarray, target_m: float = 0.0
) -> float | None:
    """First sample time inside the rest band (whether it stays or not); None: never."""
    inside = np.flatnonzero(~outside_rest_band(true_states, target_m))
    return float(time_s[inside[0]]) if inside.size else None


def relapse_s(time_s: np.ndarray, true_states: np.ndarray, target_m: float = 0.0) -> float | None:
    """Rest time less the first entry into the rest band: 0 when the ball stays from its first
    entry; a limit cycle or a servo creeping out and back in shows as the time lost. None when
    the run ends outside the band (it never rests)."""
    rest_s = inside_from(time_s, outside_rest_band(true_states, target_m))
    entry_s = first_entry_time(time_s, true_states, target_m)
    if rest_s is None or entry_s is None:
        return None
    return rest_s - entry_s


def total_variation(values: np.ndarray) -> float:
    """Σ|Δv| over the sequence."""
    return float(np.sum(np.abs(np.diff(np.asarray(values, dtype=float)))))


def input_tv_ratio(voltage_v: np.ndarray, reference_input_v: np.ndarray) -> float:
    """Σ|Δu| / Σ|Δu_d|: how much more the command moves than the plan's own input (inf when
    the plan's input never moves and the command does)."""
    command = total_variation(voltage_v)
    plan = total_variation(reference_input_v)
    if plan == 0.0:
        return 0.0 if command == 0.0 else math.inf
    return command / plan


def sign_changes(values: np.ndarray) -> int:
    """How often consecutive non-zero values change sign (exact zeros are skipped)."""
    signs = np.sign(np.asarray(values, dtype=float))
    signs = signs[signs != 0.0]
    return int(np.count_nonzero(signs[1:] != signs[:-1]))


def dither_hz(
    time_s: np.ndarray, voltage_v: np.ndarray, window_s: float = DITHER_WINDOW_S
) -> float:
    """Sign changes of u per second over the last ``window_s`` of the run."""
    last = time_s >= time_s[-1] - window_s + 1e-12
    span_s = float(time_s[-1] - time_s[last][0]) + float(time_s[-1] - time_s[-2])
    return sign_changes(voltage_v[last]) / span_s


def largest_step_v(voltage_v: np.ndarray, reference_input_v: np.ndarray) -> float:
    """Largest one-period |Δu| outside ±PLAN_SWITCH_WINDOW periods of a plan switch (a
    one-period |Δu_d| above PLAN_SWITCH_V)."""
    steps = np.abs(np.diff(np.asarray(voltage_v, dtype=float)))
    switches = np.abs(np.diff(np.asarray(reference_input_v, dtype=float))) > PLAN_SWITCH_V
    near_switch = np.zeros_like(switches)
    for shift in range(-PLAN_SWITCH_WINDOW, PLAN_SWITCH_WINDOW + 1):
        near_switch |= np.roll(switches, shift) & _rolled_valid(len(switches), shift)
    free = steps[~near_switch]
    return float(free.max()) if free.size else 0.0


def _rolled_valid(n: int, shift: int) -> np.ndarray:
    """Mask of the entries of np.roll(·, shift) that did not wrap around."""
    valid = np.ones(n, dtype=bool)
    if shift > 0:
        valid[:shift] = False
    elif shift < 0:
        valid[shift:] = False
    return valid


def compute_metrics(
    time_s: np.ndarray,
    true_states: np.ndarray,
    voltage_v: np.ndarray,
    reference_position_m: np.ndarray,
    theta_limit_rad: float,
    reference_input_v: np.ndarray | None = None,
    minimum_time_s: float | None = None,
    peak_abs_theta_rad: np.ndarray | None = None,
    voltage_time_s: np.ndarray | None = None,
    target_m: float | np.ndarray = 0.0,
) -> RunMetrics:
    """time_s (N,) increasing; true_states (N, 4); voltage_v commands; reference (N,).

    reference_input_v (N,): the plan's u_d (for the input's total variation and its switches);
    minimum_time_s: T* from this start (for rest_ratio); peak_abs_theta_rad (N,): the largest
    |θ| over every physics step of each period (else the samples' |θ|); voltage_time_s: the
    commands' own times where they are not sampled at time_s (a recorded run); target_m: the
    task's target (a float, or x_r at each sample (N,)): settle, overshoot and rest are
    measured from it.
    Each sample stands for the interval up to the next one (the last for the previous gap)."""
    if len(time_s) < 2:
        raise ValueError("metrics need at least two samples")
    gaps_s = np.diff(time_s, append=2 * time_s[-1] - time_s[-2])
    theta = true_states[:, 0]
    position = true_states[:, 3] - target_m  # from the target
    start_sign = math.copysign(1.0, position[0]) if position[0] != 0 else 0.0
    if start_sign == 0.0:
        overshoot_m = float(np.max(np.abs(position)))
    else:
        overshoot_m = max(0.0, float(np.max(-start_sign * position)))
    rest_s = rest_time(time_s, true_states, target_m=target_m)
    peak = (
        np.abs(theta)
        if peak_abs_theta_rad is None
        else np.maximum(np.abs(theta), peak_abs_theta_rad)
    )
    return RunMetrics(
        settle_time_s=settle_time(time_s, position, SETTLE_BAND_M),
        overshoot_mm=1e3 * overshoot_m,
        max_abs_theta_deg=math.degrees(float(np.max(peak))),
        theta_violation_s=float(np.sum(gaps_s[peak > theta_limit_rad])),
        max_abs_u_v=float(np.max(np.abs(voltage_v))),
        tracking_rms_mm=1e3 * float(
            np.sqrt(np.mean((true_states[:, 3] - reference_position_m) ** 2))
        ),
        rest_time_s=rest_s,
        rest_ratio=(
            rest_s / minimum_time_s
            if rest_s is not None and minimum_time_s is not None and minimum_time_s > 0.0
            else None
        ),
        input_tv_ratio=(
            None if reference_input_v is None else input_tv_ratio(voltage_v, reference_input_v)
        ),
        dither_hz=dither_hz(time_s if voltage_time_s is None else voltage_time_s, voltage_v)
        if len(voltage_v) >= 2
        else None,
        largest_step_v=(
            None if reference_input_v is None else largest_step_v(voltage_v, reference_input_v)
        ),
        task_rms_mm=1e3 * float(np.sqrt(np.mean(position[len(position) // 2 :] ** 2))),
    )


EXPECTABLE_METRICS = (*RunMetrics.__dataclass_fields__, *BENCH_FIGURES)
