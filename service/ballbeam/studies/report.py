"""What a sweep says: a summary table for the terminal and the plots (each metric against each
swept key; each metric's distribution with its quantiles)."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from ballbeam.files import replace_file
from ballbeam.studies.spec import SEED_KEY, SweepSpec

QUANTILES = (0.1, 0.5, 0.9)
# Shown first in the terminal table when present; the plots draw every metric.
HEADLINE = (
    "rest_ratio",
    "rest_time_s",
    "input_tv_ratio",
    "dither_hz",
    "largest_step_v",
    "max_abs_theta_deg",
    "settle_time_s",
    "overshoot_mm",
    "tracking_rms_mm",
)


def _format(value: float) -> str:
    return "-" if not math.isfinite(value) else f"{value:.4g}"


def summary_text(table: Any, metrics: list[str], *, title: str) -> str:
    """Per metric: how many points have it, min, p10, median, p90, max."""
    ordered = [m for m in HEADLINE if m in metrics] + [m for m in metrics if m not in HEADLINE]
    header = ("metric", "n", "min", "p10", "median", "p90", "max")
    rows: list[tuple[str, ...]] = []
    for metric in ordered:
        values = table[metric].to_numpy(dtype=float)
        values = values[np.isfinite(values)]
        if values.size == 0:
            rows.append((metric, "0", "-", "-", "-", "-", "-"))
            continue
        q10, q50, q90 = np.quantile(values, QUANTILES)
        rows.append(
            (metric, str(values.size), *(_format(v) for v in (values.min(), q10, q50, q90,
                                                                values.max())))
        )
    widths = [max(len(row[i]) for row in [header, *rows]) for i in range(len(header))]
    lines = [title, "  ".join(h.ljust(w) for h, w in zip(header, widths, strict=True))]
    lines += ["  ".join(c.ljust(w) for c, w in zip(row, widths, strict=True)) for row in rows]
    return "\n".join(lines)


def failures_text(table: Any, limit: int = 5) -> str:
    failed = table[table["error"].notna()]
    if failed.empty:
        return ""
    lines = [f"{len(failed)} point(s) failed (the 'error' column); first:"]
    for _, row in failed.head(limit).iterrows():
        lines.append(f"  {row['point_id']}: {row['error'][:160]}")
    return "\n".join(lines)


def _grid_shape(count: int) -> tuple[int, int]:
    columns = min(3, count)
    return math.ceil(count / columns), columns


def _save(figure: Any, path: Path) -> None:
    """Whole, in place of an earlier run's plot, never through a link (``files.replace_file``)."""
    replace_file(path, lambda stream: figure.savefig(stream, dpi=90, format="png"))


def plot_sweep(table: Any, spec: SweepSpec, metrics: list[str], directory: Path) -> list[Path]:
    """``metric_vs_<key>.png`` per swept key (the seed is the replication, not a key to plot
    against) and ``distributions.png``. Failed points are left out."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    directory.mkdir(parents=True, exist_ok=True)
    ok = table[table["error"].isna()]
    metrics = [m for m in HEADLINE if m in metrics] + [m for m in metrics if m not in HEADLINE]
    drawn = [m for m in metrics if np.isfinite(ok[m].to_numpy(dtype=float)).any()]
    written: list[Path] = []
    if not drawn or ok.empty:
        return written
    rows, columns = _grid_shape(len(drawn))
    for key in [k for k in spec.keys if k != SEED_KEY or not spec.seeds]:
        figure, axes = plt.subplots(rows, columns, figsize=(4.2 * columns, 3.0 * rows),
                                    squeeze=False)
        raw = ok[key]
        numeric = all(
            isinstance(v, int | float) and not isinstance(v, bool) for v in raw
        )
        if numeric:
            x = raw.to_numpy(dtype=float)
            ticks = None
        else:  # choices and flags: one column of dots per value
            labels = sorted({str(v) for v in raw})
            x = np.array([labels.index(str(v)) for v in raw], dtype=float)
            ticks = labels
        for axis, metric in zip(axes.flat, drawn, strict=False):
            axis.scatter(x, ok[metric].to_numpy(dtype=float), s=8, alpha=0.6)
            axis.set_xlabel(key)
            axis.set_ylabel(metric)
            axis.grid(alpha=0.3)
            if ticks is not None:
                axis.set_xticks(range(len(ticks)), ticks)
        for axis in list(axes.flat)[len(drawn):]:
            axis.set_visible(False)
        figure.suptitle(f"{spec.path.stem}: metrics against {key} ({len(ok)} points)")
        figure.tight_layout()
        path = directory / f"metric_vs_{key.replace('.', '_')}.png"
        _save(figure, path)
        plt.close(figure)
        written.append(path)
    figure, axes = plt.subplots(rows, columns, figsize=(4.2 * columns, 3.0 * rows), squeeze=False)
    for axis, metric in zip(axes.flat, drawn, strict=False):
        values = ok[metric].to_numpy(dtype=float)
        values = values[np.isfinite(values)]
        axis.hist(values, bins=min(40, max(5, values.size // 5)), color="tab:blue", alpha=0.7)
        for q, value in zip(QUANTILES, np.quantile(values, QUANTILES), strict=True):
            axis.axvline(value, color="tab:red", linestyle="--" if q != 0.5 else "-", lw=1)
            axis.annotate(f"p{round(q * 100)}", (value, 1), xycoords=("data", "axes fraction"),
                          fontsize=7, va="top", color="tab:red")
        axis.set_xlabel(metric)
        axis.set_ylabel("points")
    for axis in list(axes.flat)[len(drawn):]:
        axis.set_visible(False)
    figure.suptitle(f"{spec.path.stem}: distributions (p10, median, p90)")
    figure.tight_layout()
    path = directory / "distributions.png"
    _save(figure, path)
    plt.close(figure)
    written.append(path)
    return written
