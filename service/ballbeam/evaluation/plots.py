"""Paper-style figures (x with x_d; θ with θ_d and the ±limit lines; u), written to PNG, or
to SVG for the HTML report."""

from __future__ import annotations

import math
from pathlib import Path
from typing import IO

import numpy as np

from ballbeam.errors import BallbeamError, OutputExistsError
from ballbeam.evaluation.summary import limit_from_log, run_series
from ballbeam.files import write_new
from ballbeam.logs.reader import RunLog


def plot_run(
    path: str | Path | IO[bytes],
    time_s: np.ndarray,
    true_states: np.ndarray,
    reference_states: np.ndarray,
    voltage_v: np.ndarray,
    theta_limit_rad: float,
    title: str,
    lateness_us: np.ndarray | None = None,
    lateness_time_s: np.ndarray | None = None,
    file_format: str | None = None,
) -> None:
    """Write the figure (to a new file at a path, or a binary stream in ``file_format``); an
    extra panel shows loop lateness when given (replay). OutputExistsError if anything is at
    the path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = 4 if lateness_us is not None else 3
    figure, axes = plt.subplots(panels, 1, sharex=True, figsize=(8, 2.4 * panels))
    axes[0].plot(time_s, reference_states[:, 3], "--", label="x_d")
    axes[0].plot(time_s, true_states[:, 3], label="x")
    axes[0].set_ylabel("ball position [m]")
    axes[1].plot(time_s, reference_states[:, 0], "--", label="θ_d")
    axes[1].plot(time_s, true_states[:, 0], label="θ")
    for sign in (-1, 1):
        axes[1].axhline(sign * theta_limit_rad, color="red", linewidth=0.8)
    axes[1].set_ylabel("servo angle [rad]")
    axes[1].set_title(f"limits ±{math.degrees(theta_limit_rad):.0f}°", fontsize=8, loc="right")
    axes[2].plot(time_s, voltage_v, label="u")
    axes[2].set_ylabel("voltage [V]")
    if lateness_us is not None:
        when = lateness_time_s if lateness_time_s is not None else time_s[: len(lateness_us)]
        axes[3].plot(when, lateness_us, linewidth=0.6, label="cycle lateness")
        axes[3].set_ylabel("lateness [µs]")
    axes[-1].set_xlabel("time [s]")
    for axis in axes:
        axis.grid(True, alpha=0.3)
        if axis.get_legend_handles_labels()[0]:
            axis.legend(loc="upper right", fontsize=8)
    figure.suptitle(title)
    figure.tight_layout()
    try:
        if isinstance(path, (str, Path)):
            # A new file only (never over one, never through a link), in the format its name
            # says (matplotlib's default where it says none).
            file_format = file_format or Path(path).suffix.removeprefix(".").lower() or None
            write_new(path, lambda stream: figure.savefig(stream, dpi=110, format=file_format))
        else:
            figure.savefig(path, dpi=110, format=file_format)
    except OutputExistsError:
        raise
    except OSError as error:
        raise BallbeamError(f"cannot write plot {path}: {error}") from error
    finally:
        plt.close(figure)


def plot_log(
    path: str | Path | IO[bytes], run_log: RunLog, title: str, file_format: str | None = None
) -> None:
    """The figure of a recorded run: truth against the reference (both on the truth samples'
    times; the reference is rest beyond the plan), the command, the loop's lateness."""
    series = run_series(run_log)
    reference = np.array(
        [
            np.interp(
                series.truth_time_s,
                series.reference_time_s,
                series.reference_states[:, column],
                right=0.0,
            )
            for column in range(4)
        ]
    ).T
    voltage = np.interp(series.truth_time_s, series.cycle_time_s, series.voltage_v)
    plot_run(
        path,
        series.truth_time_s,
        series.truth_states,
        reference,
        voltage,
        limit_from_log(run_log),
        title=title,
        lateness_us=series.lateness_ns * 1e-3,
        lateness_time_s=series.cycle_time_s,
        file_format=file_format,
    )
