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
guard_*                              present when the angle guard is on: theta_limit_rad,
                                     voltage_limit_v, theta_per_v, rate_per_v,
                                     rate_step_rad_s, beyond_slope_s (scalars),
                                     theta_row, rate_row (4,), stopping_rad (M,)
=========================  ========  ===================================================
"""

from __future__ import annotations

import io
import zipfile
from typing import Any

import numpy as np

from ballbeam.core.control import ControllerDesign, ObserverLaw
from ballbeam.core.guard import AngleGuard
from ballbeam.errors import LogFormatError

ATTACHMENT_NAME = "controller_design.npz"
MEDIA_TYPE = "application/x-npz"
FORMAT_VERSION = 1
MAX_UNPACKED_BYTES = 64 << 20  # far above any real design (8000 steps: ~0.6 MB)

_SCALARS = ("period_s", "plan_duration_s", "voltage_limit_v", "angle_per_count",
            "position_per_count")
_GUARD_SCALARS = ("theta_limit_rad", "voltage_limit_v", "theta_per_v", "rate_per_v",
                  "rate_step_rad_s", "beyond_slope_s")


def encode_design(design: ControllerDesign) -> bytes:
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
    }
    guard = design.guard
    if guard is not None:
        arrays.update({f"guard_{name}": _f8(getattr(guard, name)) for name in _GUARD_SCALARS})
        arrays["guard_theta_row"] = _f8(guard.theta_row)
        arrays["guard_rate_row"] = _f8(guard.rate_row)
        arrays["guard_stopping_rad"] = _f8(guard.stopping_rad)
    buffer = io.BytesIO()
    np.savez_compressed(buffer, **arrays)  # type: ignore[arg-type]
    return buffer.getvalue()


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
            stopping = arrays["guard_stopping_rad"]
            if stopping.ndim != 1 or stopping.size < 2:
                raise ValueError("guard_stopping_rad must be a table of 2 or more entries")
            guard = AngleGuard(
                **{name: _scalar(arrays[f"guard_{name}"]) for name in _GUARD_SCALARS},
                theta_row=_four(arrays["guard_theta_row"]),
                rate_row=_four(arrays["guard_rate_row"]),
                stopping_rad=tuple(stopping.tolist()),
            )
        return ControllerDesign(
            **{name: _scalar(arrays[name]) for name in _SCALARS},
            gains=arrays["gains"],
            offset_v=arrays["offset_v"],
            final_gain=arrays["final_gain"],
            reference_states=arrays["reference_states"],
            reference_input_v=arrays["reference_input_v"],
            observer=ObserverLaw.from_arrays(
                arrays["observer_Ad"], arrays["observer_Bd"], arrays["observer_C"],
                arrays["observer_L"],
            ),
            guard=guard,
            initial_state=_four(arrays["initial_state"]),
        )
    except LogFormatError:
        raise
    except (KeyError, ValueError, TypeError) as error:
        detail = f"missing array {error}" if isinstance(error, KeyError) else str(error)
        raise LogFormatError(f"{where}: recorded controller design unusable: {detail}") from (
            error
        )


def design_difference(recorded: ControllerDesign, resynthesised: ControllerDesign) -> float:
    """Largest relative difference between two designs: over every array, the largest
    |a − b| relative to the largest |b| of that array (inf where shapes differ)."""
    worst = 0.0
    for name, a in _as_arrays(recorded).items():
        b = _as_arrays(resynthesised).get(name)
        if b is None or a.shape != b.shape:
            return float("inf")
        scale = float(np.max(np.abs(b), initial=0.0))
        difference = float(np.max(np.abs(a - b), initial=0.0))
        if difference:
            worst = max(worst, difference / scale if scale else float("inf"))
    return worst


def _as_arrays(design: ControllerDesign) -> dict[str, np.ndarray]:
    return dict(np.load(io.BytesIO(encode_design(design)), allow_pickle=False))


def _load(data: bytes, where: str) -> dict[str, np.ndarray]:
    try:
        with zipfile.ZipFile(io.BytesIO(data)) as archive:
            unpacked = sum(info.file_size for info in archive.infolist())
        if unpacked > MAX_UNPACKED_BYTES:
            raise LogFormatError(
                f"{where}: recorded controller design unpacks to {unpacked} bytes "
                f"(more than {MAX_UNPACKED_BYTES}); refused"
            )
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


def _f8(value: Any) -> np.ndarray:
    return np.asarray(value, dtype="<f8")


def _scalar(array: np.ndarray) -> float:
    if array.shape != ():
        raise ValueError(f"expected a scalar, got shape {array.shape}")
    return float(array)


def _four(array: np.ndarray) -> tuple[float, float, float, float]:
    if array.shape != (4,):
        raise ValueError(f"expected 4 values, got shape {array.shape}")
    a, b, c, d = array.tolist()
    return (a, b, c, d)
