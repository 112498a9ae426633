"""Run metrics, computed from the true plant state (never from measurements)."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

SETTLE_BAND_M = 0.002
# Metrics a scenario may bound in its [expect] table: these and the bench's own figures.
BENCH_FIGURES = (
    "saturation_fraction",
    "lateness_p50_us",
    "lateness_p99_us",
    "lateness_max_us",
    "overruns",
    "frames_lost",
    "frames_rejected",
    "coasted_cycles",
    "recorder_dropped",
)


@dataclass(frozen=True)
class RunMetrics:
    settle_time_s: float | None  # first time after which |x| stays within 2 mm; None: never
    overshoot_mm: float  # largest excursion past 0, on the side opposite the start
    max_abs_theta_deg: float
    theta_violation_s: float  # time spent with |θ| beyond the limit
    max_abs_u_v: float
    tracking_rms_mm: float  # RMS of x − x_d

    def as_dict(self) -> dict[str, float | None]:
        return asdict(self)


def settle_time(time_s: np.ndarray, position_m: np.ndarray, band_m: float) -> float | None:
    outside = np.flatnonzero(np.abs(position_m) > band_m)
    if outside.size == 0:
        return float(time_s[0])
    last = int(outside[-1])
    if last == len(time_s) - 1:
        return None
    return float(time_s[last + 1])


def compute_metrics(
    time_s: np.ndarray,
    true_states: np.ndarray,
    voltage_v: np.ndarray,
    reference_position_m: np.ndarray,
    theta_limit_rad: float,
) -> RunMetrics:
    """time_s (N,) increasing; true_states (N, 4); voltage_v commands; reference (N,).

    Each sample stands for the interval up to the next one (the last for the previous gap)."""
    if len(time_s) < 2:
        raise ValueError("metrics need at least two samples")
    gaps_s = np.diff(time_s, append=2 * time_s[-1] - time_s[-2])
    theta = true_states[:, 0]
    position = true_states[:, 3]
    start_sign = math.copysign(1.0, position[0]) if position[0] != 0 else 0.0
    if start_sign == 0.0:
        overshoot_m = float(np.max(np.abs(position)))
    else:
        overshoot_m = max(0.0, float(np.max(-start_sign * position)))
    return RunMetrics(
        settle_time_s=settle_time(time_s, position, SETTLE_BAND_M),
        overshoot_mm=1e3 * overshoot_m,
        max_abs_theta_deg=math.degrees(float(np.max(np.abs(theta)))),
        theta_violation_s=float(np.sum(gaps_s[np.abs(theta) > theta_limit_rad])),
        max_abs_u_v=float(np.max(np.abs(voltage_v))),
        tracking_rms_mm=1e3 * float(np.sqrt(np.mean((position - reference_position_m) ** 2))),
    )


EXPECTABLE_METRICS = (*RunMetrics.__dataclass_fields__, *BENCH_FIGURES)
