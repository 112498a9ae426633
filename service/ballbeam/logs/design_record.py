"""The controller design a run used, recorded in its log so ``replay --verify`` re-runs exactly it.

Encoding: a NumPy ``.npz`` archive (a zip of ``.npy`` arrays, the format NumPy documents in
NEP 1; read with ``allow_pickle=False``, so nothing in it is executable), attached to the MCAP
file as ``controller_design.npz``. Every array is little-endian float64 and bit-exact; scalars
are 0-d arrays. Arrays, with N the tracker's steps and M the guard's table length:

=========================  ========  ===================================================
name                       shape     meaning
=========================  ========  ===================================================
format_version             ()        1
period_s                   ()        control period [s]
plan_duration_s            ()        the planned path's duration [s]
voltage_limit_v            ()        |u| bound [V]
angle_per_count            ()        measurement units (57·θ) per encoder count
position_per_count         ()        measurement units (100·x) per ADC count
initial_state              (4,)      planned start (θ, θ̇, ẋ, x), SI
gains                      (N, 4)    tracker gain K_k
offset_v                   (N,)      tracker offset: u_k = offset_v[k] − K_k·x̂
final_gain                 (4,)      regulator after the horizon: u = −K·x̂
reference_states           (N, 4)    x_d at the cycle instants
reference_input_v          (N,)      u_d at the cycle instants
observer_Ad, observer_Bd   (4, 4),   observer model over one period
                           (4,)
observer_C, observer_L     (2, 4),   output matrix and steady-state Kalman gain
                           (4, 2)
deadband_v, deadzone_v     ()        command band sent as 0 V; modelled dead zone
rest_from_cycle            ()        the plan's end (cycle): rest observer and gains
rest_observer_L            (4, 2)    present with a rest filter: its Kalman gain
lookahead_periods          ()        present when each command carried the commands of this
                                     many periods after it (absent: none, the plant held)
target_m                   ()        present when the ball's target was not 0: the law
                                     works in x − target_m (reference_states, initial_state
                                     and the gains are in it)
rest_*                               present with rest gains: gain (4,), far_gain (4,)
                                     (optional), firm_gain (4,) and firm_cycles ()
                                     (optional), catch_gain (2,) and catch_cycles ()
                                     (optional), from_cycle, blend_cycles,
                                     theta_near_rad, theta_far_rad, position_near_m,
                                     position_far_m (scalars)
guard_*                              present when the angle guard is on: theta_limit_rad,
                                     voltage_limit_v, theta_per_v, rate_per_v,
                                     rate_step_rad_s, beyond_slope_s (scalars),
                                     theta_row, rate_row (4,), stopping_rad (M,);
                                     real time, when the look-ahead follows the measured
                                     lateness (absent in older logs: it does not):
                                     lateness_steps (S, 5), lateness_allowance_ns,
                                     lateness_hold_cycles and lateness_buckets (scalars;
                                     the last absent in older logs: one worst kept),
                                     lateness_start_ns (scalar, where the probe measured
                                     any: the watch's first worst)
adapt_*                              present with the ball-gain adaptation: design_gamma,
                                     position_noise_m, confidence, min_ratio, max_ratio,
                                     period_s, until_cycle, back_emf_v_s_per_rad,
                                     pace_step_per_cycle, resync_rate_per_cycle,
                                     resync_max_per_cycle, arc_theta_rad (scalars; the
                                     last three absent in older logs: no re-sync)
noise_levels, noise_tracking_L   present with noise adaptation: levels (K,), gains (K, 4, 2),
noise_rest_L, noise_expected_square, noise_smoothing_per_cycle: rest gains (K, 4, 2)
                                     (optional), scalars
learn_*                              present with dead-zone learning: min_motion_rad,
                                     judge_motion_rad, rate, below_v, max_v,
                                     max_lateness_ns (scalars; older logs: none)
soft_*                               present with the soft cap: theta_limit_rad,
                                     zone_gain_per_s, rate_gain_per_s, alpha,
                                     alpha_beta, gap_step_rad (scalars),
                                     allowed_rate_rad_s (K,)
=========================  ========  ===================================================

Integers (cycles) are stored as float64 too; they are exact below 2**53.
"""

from __future__ import annotations

import io
import math
import zipfile
from collections.abc import Mapping
from typing import Any

import numpy as np

from ballbeam.core.adaptation import BallGainAdaptation, DeadZoneLearning, Gain, NoiseAdaptation
from ballbeam.core.control import ControllerDesign, ObserverLaw, RestGains
from ballbeam.core.guard import COMPUTE_ALLOWANCE_NS, AngleGuard, SoftCap
from ballbeam.core.model import Row4, as_row4
from ballbeam.errors import LogFormatError

ATTACHMENT_NAME = "controller_design.npz"
MEDIA_TYPE = "application/x-npz"
FORMAT_VERSION = 2
MAX_UNPACKED_BYTES = 64 << 20  # far above any real design (8000 steps: ~0.6 MB)

_SCALARS = ("period_s", "plan_duration_s", "voltage_limit_v", "angle_per_count",
            "position_per_count", "deadband_v", "deadzone_v")
_REST_SCALARS = ("theta_near_rad", "theta_far_rad", "position_near_m", "position_far_m")
_SOFT_SCALARS = ("theta_limit_rad", "zone_gain_per_s", "rate_gain_per_s", "alpha",
                 "alpha_beta", "gap_step_rad")
_ADAPT_SCALARS = ("design_gamma", "position_noise_m", "confidence", "min_ratio", "max_ratio",
                  "period_s", "back_emf_v_s_per_rad", "pace_step_per_cycle")
# Added later: a log recorded before them ran without clock re-synchronisation.
_ADAPT_OPTIONAL = {"resync_rate_per_cycle": 0.0, "resync_max_per_cycle": 0.0,
                   "arc_theta_rad": 0.0}
_LEARN_SCALARS = ("min_motion_rad", "judge_motion_rad", "rate", "below_v", "max_v")
_GUARD_SCALARS = ("theta_limit_rad", "voltage_limit_v", "theta_per_v", "rate_per_v",
                  "rate_step_rad_s", "beyond_slope_s")


def encode_design(design: ControllerDesign) -> bytes:
    buffer = io.BytesIO()
    np.savez_compressed(buffer, **design_arrays(design))  # type: ignore[arg-type]
    return buffer.getvalue()


def design_arrays(design: ControllerDesign) -> dict[str, np.ndarray]:
    """The arrays :func:`encode_design` writes, by name (little-endian float64)."""
    arrays: dict[str, np.ndarray] = {
        "format_version": np.array(FORMAT_VERSION, dtype="<i8"),
        **{name: _f8(getattr(design, name)) for name in _SCALARS},
        "initial_state": _f8(design.initial_state),
        "gains": _f8(design.gains),
        "offset_v": _f8(design.offset_v),
        "final_gain": _f8(design.final_gain),
        "reference_states": _f8(design.reference_states),
        "reference_input_v": _f8(design.reference_input_v),
        "observer_Ad": _f8(design.observer.Ad),
        "observer_Bd": _f8(design.observer.Bd),
        "observer_C": _f8(design.observer.C),
        "observer_L": _f8(design.observer.L),
        "rest_from_cycle": _f8(design.rest_from_cycle),
    }
    if design.lookahead_periods:
        arrays["lookahead_periods"] = _f8(design.lookahead_periods)
    if design.target_m != 0.0:
        arrays["target_m"] = _f8(design.target_m)
    if design.rest_observer is not None:
        arrays["rest_observer_L"] = _f8(design.rest_observer.L)
    rest = design.rest_gains
    if rest is not None:
        arrays.update({f"rest_{name}": _f8(getattr(rest, name)) for name in _REST_SCALARS})
        arrays["rest_gain"] = _f8(rest.gain)
        arrays["rest_from_cycle_gains"] = _f8(rest.from_cycle)
        arrays["rest_blend_cycles"] = _f8(rest.blend_cycles)
        if rest.far_gain is not None:
            arrays["rest_far_gain"] = _f8(rest.far_gain)
        if rest.firm_gain is not None:
            arrays["rest_firm_gain"] = _f8(rest.firm_gain)
            arrays["rest_firm_cycles"] = _f8(rest.firm_cycles)
        if rest.catch_gain is not None:
            arrays["rest_catch_gain"] = _f8(rest.catch_gain)
            arrays["rest_catch_cycles"] = _f8(rest.catch_cycles)
    adaptation = design.adaptation
    if adaptation is not None:
        arrays.update({
            f"adapt_{name}": _f8(getattr(adaptation, name))
            for name in (*_ADAPT_SCALARS, *_ADAPT_OPTIONAL)
        })
        arrays["adapt_until_cycle"] = _f8(adaptation.until_cycle)
    noise = design.noise_adaptation
    if noise is not None:
        arrays["noise_levels"] = _f8(noise.levels)
        arrays["noise_tracking_L"] = _f8(noise.tracking_gains)
        if noise.rest_gains is not None:
            arrays["noise_rest_L"] = _f8(noise.rest_gains)
        arrays["noise_expected_square"] = _f8(noise.expected_square)
        arrays["noise_smoothing_per_cycle"] = _f8(noise.smoothing_per_cycle)
    learning = design.deadzone_learning
    if learning is not None:
        arrays.update({f"learn_{name}": _f8(getattr(learning, name)) for name in _LEARN_SCALARS})
        arrays["learn_max_lateness_ns"] = _f8(learning.max_lateness_ns)
    guard = design.guard
    if guard is not None:
        arrays.update({f"guard_{name}": _f8(getattr(guard, name)) for name in _GUARD_SCALARS})
        arrays["guard_theta_row"] = _f8(guard.theta_row)
        arrays["guard_rate_row"] = _f8(guard.rate_row)
        arrays["guard_stopping_rad"] = _f8(guard.stopping_rad)
        if guard.lateness_steps:
            arrays["guard_lateness_steps"] = _f8(guard.lateness_steps)
            arrays["guard_lateness_allowance_ns"] = _f8(guard.lateness_allowance_ns)
            arrays["guard_lateness_hold_cycles"] = _f8(guard.lateness_hold_cycles)
            if guard.lateness_buckets:
                arrays["guard_lateness_buckets"] = _f8(1)
            if guard.lateness_start_ns:
                arrays["guard_lateness_start_ns"] = _f8(guard.lateness_start_ns)
        if guard.soft is not None:
            soft = guard.soft
            arrays.update({f"soft_{name}": _f8(getattr(soft, name)) for name in _SOFT_SCALARS})
            arrays["soft_allowed_rate_rad_s"] = _f8(soft.allowed_rate_rad_s)
    return arrays


def decode_design(data: bytes, where: str) -> ControllerDesign:
    """The design recorded in ``data``; LogFormatError naming ``where`` if it is not one."""
    arrays = _load(data, where)
    try:
        version = int(arrays["format_version"])
        if version != FORMAT_VERSION:
            raise LogFormatError(
                f"{where}: controller design format {version}; this version reads "
                f"{FORMAT_VERSION}"
            )
        guard = None
        if "guard_stopping_rad" in arrays:
            soft = None
            if "soft_allowed_rate_rad_s" in arrays:
                soft = SoftCap(
                    **{name: _scalar(arrays[f"soft_{name}"]) for name in _SOFT_SCALARS},
                    allowed_rate_rad_s=_table(arrays["soft_allowed_rate_rad_s"], "soft"),
                )
            scalars: dict[str, Any] = {
                name: _scalar(arrays[f"guard_{name}"]) for name in _GUARD_SCALARS
            }
            guard = AngleGuard(
                **scalars,
                theta_row=_four(arrays["guard_theta_row"]),
                rate_row=_four(arrays["guard_rate_row"]),
                stopping_rad=_table(arrays["guard_stopping_rad"], "guard"),
                soft=soft,
                **_lateness_fields(arrays),
            )
        observer = ObserverLaw.from_arrays(
            arrays["observer_Ad"], arrays["observer_Bd"], arrays["observer_C"],
            arrays["observer_L"],
        )
        rest_observer = None
        if "rest_observer_L" in arrays:
            rest_observer = ObserverLaw.from_arrays(
                arrays["observer_Ad"], arrays["observer_Bd"], arrays["observer_C"],
                arrays["rest_observer_L"],
            )
        rest_gains = None
        if "rest_gain" in arrays:
            rest_gains = RestGains(
                **{name: _scalar(arrays[f"rest_{name}"]) for name in _REST_SCALARS},
                gain=_four(arrays["rest_gain"]),
                far_gain=_four(arrays["rest_far_gain"]) if "rest_far_gain" in arrays else None,
                from_cycle=_count(arrays["rest_from_cycle_gains"]),
                blend_cycles=max(_count(arrays["rest_blend_cycles"]), 1),
                # Logs from before the firm rest gains have neither array.
                firm_gain=(
                    _four(arrays["rest_firm_gain"]) if "rest_firm_gain" in arrays else None
                ),
                firm_cycles=(
                    max(_count(arrays["rest_firm_cycles"]), 1)
                    if "rest_firm_cycles" in arrays else 1
                ),
                # Logs from before the servo catch have neither array.
                catch_gain=_two(arrays["rest_catch_gain"]) if "rest_catch_gain" in arrays else None,
                catch_cycles=(
                    max(_count(arrays["rest_catch_cycles"]), 1)
                    if "rest_catch_cycles" in arrays else 1
                ),
            )
        adaptation = None
        if "adapt_design_gamma" in arrays:
            adaptation = BallGainAdaptation(
                **{name: _scalar(arrays[f"adapt_{name}"]) for name in _ADAPT_SCALARS},
                **{
                    name: _scalar(arrays[f"adapt_{name}"]) if f"adapt_{name}" in arrays
                    else default
                    for name, default in _ADAPT_OPTIONAL.items()
                },
                until_cycle=_count(arrays["adapt_until_cycle"]),
            )
        noise = None
        if "noise_levels" in arrays:
            levels = tuple(float(v) for v in _table(arrays["noise_levels"], "noise"))
            noise = NoiseAdaptation(
                levels=levels,
                tracking_gains=_gains(arrays["noise_tracking_L"], len(levels)),
                rest_gains=(
                    _gains(arrays["noise_rest_L"], len(levels))
                    if "noise_rest_L" in arrays else None
                ),
                expected_square=_scalar(arrays["noise_expected_square"]),
                smoothing_per_cycle=_scalar(arrays["noise_smoothing_per_cycle"]),
            )
        learning = None
        if "learn_rate" in arrays:
            learning = DeadZoneLearning(
                **{name: _scalar(arrays[f"learn_{name}"]) for name in _LEARN_SCALARS},
                max_lateness_ns=_learning_lateness_ns(arrays, guard),
            )
        return ControllerDesign(
            **{name: _scalar(arrays[name]) for name in _SCALARS},
            gains=arrays["gains"],
            offset_v=arrays["offset_v"],
            final_gain=arrays["final_gain"],
            reference_states=arrays["reference_states"],
            reference_input_v=arrays["reference_input_v"],
            observer=observer,
            guard=guard,
            initial_state=_four(arrays["initial_state"]),
            rest_from_cycle=_count(arrays["rest_from_cycle"]),
            rest_observer=rest_observer,
            rest_gains=rest_gains,
            adaptation=adaptation,
            deadzone_learning=learning,
            noise_adaptation=noise,
            lookahead_periods=(
                _count(arrays["lookahead_periods"]) if "lookahead_periods" in arrays else 0
            ),
            target_m=_scalar(arrays["target_m"]) if "target_m" in arrays else 0.0,
        )
    except LogFormatError:
        raise
    except (KeyError, ValueError, TypeError) as error:
        detail = f"missing array {error}" if isinstance(error, KeyError) else str(error)
        raise LogFormatError(f"{where}: recorded controller design unusable: {detail}") from (
            error
        )


def _gains(array: np.ndarray, count: int) -> tuple[Gain, ...]:
    if array.shape != (count, 4, 2) or not np.isfinite(array).all():
        raise ValueError(f"noise filter gains must be ({count}, 4, 2) finite numbers")
    return tuple(
        tuple((float(a), float(b)) for a, b in gain)  # type: ignore[misc]
        for gain in array
    )


def design_difference(recorded: ControllerDesign, resynthesised: ControllerDesign) -> float:
    """Largest relative difference between two designs: over every array, the largest
    |a − b| relative to the largest |b| of that array (inf where shapes differ)."""
    worst = 0.0
    others = design_arrays(resynthesised)  # once: encoding a design is not free
    for name, a in design_arrays(recorded).items():
        b = others.get(name)
        if b is None or a.shape != b.shape:
            return float("inf")
        scale = float(np.max(np.abs(b), initial=0.0))
        difference = float(np.max(np.abs(a - b), initial=0.0))
        if difference:
            worst = max(worst, difference / scale if scale else float("inf"))
    return worst


def _load(data: bytes, where: str) -> dict[str, np.ndarray]:
    try:
        with zipfile.ZipFile(io.BytesIO(data)) as archive:
            unpacked = sum(info.file_size for info in archive.infolist())
            if unpacked > MAX_UNPACKED_BYTES:
                raise LogFormatError(
                    f"{where}: recorded controller design unpacks to {unpacked} bytes "
                    f"(more than {MAX_UNPACKED_BYTES}); refused"
                )
            for info in archive.infolist():
                _check_array_size(archive, info, where)
        with np.load(io.BytesIO(data), allow_pickle=False) as archive:
            arrays = {name: archive[name] for name in archive.files}
    except LogFormatError:
        raise
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as error:
        raise LogFormatError(f"{where}: recorded controller design unreadable: {error}") from (
            error
        )
    for name, array in arrays.items():
        if array.dtype.kind not in "fi" or not np.all(np.isfinite(array)):
            raise LogFormatError(
                f"{where}: recorded controller design: array {name!r} is not finite numbers"
            )
    return {name: array.astype(np.float64, copy=False) if array.dtype.kind == "f" else array
            for name, array in arrays.items()}


def _check_array_size(archive: zipfile.ZipFile, info: zipfile.ZipInfo, where: str) -> None:
    """NumPy allocates an array as large as its header says before reading its data: a header
    must not claim more than its member holds (a few bytes could claim terabytes)."""
    with archive.open(info) as member:
        version = np.lib.format.read_magic(member)
        if version == (1, 0):
            shape, _, dtype = np.lib.format.read_array_header_1_0(member)
        else:
            shape, _, dtype = np.lib.format.read_array_header_2_0(member)
    claimed = dtype.itemsize * math.prod(shape)
    if claimed > info.file_size:
        raise LogFormatError(
            f"{where}: recorded controller design: array {info.filename!r} claims {claimed} "
            f"bytes in a member of {info.file_size}; refused"
        )


def _f8(value: Any) -> np.ndarray:
    return np.asarray(value, dtype="<f8")


def _scalar(array: np.ndarray) -> float:
    if array.shape != ():
        raise ValueError(f"expected a scalar, got shape {array.shape}")
    return float(array)


def _learning_lateness_ns(arrays: Mapping[str, np.ndarray], guard: AngleGuard | None) -> float:
    """The dead-zone learning's lateness bound; a log from before it had one paused the
    learning where the guard's look-ahead grew beyond its allowance."""
    if "learn_max_lateness_ns" in arrays:
        return _scalar(arrays["learn_max_lateness_ns"])
    if guard is None or not guard.lateness_steps:
        return math.inf
    return float(guard.lateness_allowance_ns - COMPUTE_ALLOWANCE_NS)


def _lateness_fields(arrays: Mapping[str, np.ndarray]) -> dict[str, Any]:
    """The guard's lateness look-ahead, where the log has one (none before it existed)."""
    if "guard_lateness_steps" not in arrays:
        return {}
    steps = arrays["guard_lateness_steps"]
    if steps.ndim != 2 or steps.shape[1] != 5 or not np.isfinite(steps).all():
        raise ValueError("the guard's lateness steps must be (S, 5) finite numbers")
    return {
        "lateness_steps": tuple(tuple(float(v) for v in row) for row in steps),
        "lateness_allowance_ns": _count(arrays["guard_lateness_allowance_ns"]),
        "lateness_hold_cycles": _count(arrays["guard_lateness_hold_cycles"]),
        "lateness_buckets": "guard_lateness_buckets" in arrays,
        "lateness_start_ns": (
            _count(arrays["guard_lateness_start_ns"]) if "guard_lateness_start_ns" in arrays else 0
        ),
    }


def _count(array: np.ndarray) -> int:
    value = _scalar(array)
    if not (0 <= value < 2**53 and value == int(value)):
        raise ValueError(f"expected a cycle count, got {value}")
    return int(value)


def _table(array: np.ndarray, what: str) -> tuple[float, ...]:
    if array.ndim != 1 or array.size < 2:
        raise ValueError(f"the {what} table must have 2 or more entries")
    return tuple(array.tolist())


def _two(array: np.ndarray) -> tuple[float, float]:
    if array.shape != (2,) or not np.isfinite(array).all():
        raise ValueError(f"expected 2 finite values, got shape {array.shape}")
    return float(array[0]), float(array[1])


def _four(array: np.ndarray) -> Row4:
    if array.shape != (4,):
        raise ValueError(f"expected 4 values, got shape {array.shape}")
    return as_row4(array)
