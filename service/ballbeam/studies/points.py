"""One point of a study, evaluated where a Dask worker runs it.

Workers are long-lived processes, so what a point costs past its own simulation is paid once
per worker: the imports (``warm_up``), and the controller design and T*, cached here by the
config keys they read (``assembly.design_key``): points that differ only in the true plant,
the seed or the run's length share them. A failing point returns its error instead of raising,
so the sweep records it and goes on.
"""

from __future__ import annotations

import os
import socket
import tempfile
import time
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ballbeam.config import Config, config_from_data

DESIGN_CACHE_SIZE = 32  # designs a worker keeps (each a few MB of gain schedule)


@dataclass(frozen=True)
class PointTask:
    """What a worker needs to run a point: plain data, pickled to the worker."""

    point_id: str
    base: str | None  # the base config's name, as the driver found it (for messages)
    # The base's contents (its extends chain merged): workers on other hosts need no file.
    base_data: dict[str, Any]
    overrides: tuple[str, ...]
    runner: str  # offline | lockstep | realtime
    log_dir: str | None  # bus runs: where their logs go


@dataclass(frozen=True)
class PointOutcome:
    point_id: str
    metrics: dict[str, Any]
    log_path: str | None
    error: str | None
    wall_time_s: float
    worker: str
    cpu_time_s: float = 0.0  # this worker process's CPU (a bus run's two children not counted)


class _LeastRecentlyUsed:
    def __init__(self, size: int) -> None:
        self.size = size
        self.items: OrderedDict[str, Any] = OrderedDict()
        self.hits = 0
        self.misses = 0

    def get(self, key: str, make: Any) -> Any:
        if key in self.items:
            self.items.move_to_end(key)
            self.hits += 1
            return self.items[key]
        self.misses += 1
        value = make()
        self.items[key] = value
        if len(self.items) > self.size:
            self.items.popitem(last=False)
        return value


_DESIGNS = _LeastRecentlyUsed(DESIGN_CACHE_SIZE)
_MINIMUM_TIMES = _LeastRecentlyUsed(4 * DESIGN_CACHE_SIZE)


def warm_up() -> str:
    """Import what a point needs (once per worker, before the clock starts)."""
    import ballbeam.assembly
    import ballbeam.core.planning.time_optimal
    import ballbeam.evaluation.summary  # noqa: F401

    return f"{socket.gethostname()}:{os.getpid()}"


def cache_counts() -> dict[str, int]:
    """This worker's design cache: hits and misses (the bench reports them)."""
    return {"design_hits": _DESIGNS.hits, "design_misses": _DESIGNS.misses}


def offline_metrics(config: Config) -> dict[str, Any]:
    """``ballbeam simulate``'s metrics for ``config``, the design and T* from the cache."""
    from ballbeam import assembly

    design = (
        _DESIGNS.get(assembly.design_key(config), lambda: assembly.controller_design(config))
        if config.controller.kind == "tracker" else None  # another law has no design
    )
    minimum_time = _MINIMUM_TIMES.get(
        assembly.minimum_time_key(config), lambda: assembly.minimum_time_s(config)
    )
    run = assembly.run_offline_with(config, design, minimum_time)
    return {
        "plan_duration_s": design.plan_duration_s if design is not None else None,
        "t_star_s": minimum_time,
        **run.metrics.as_dict(),
    }


def bus_metrics(task: PointTask, config: Config) -> tuple[dict[str, Any], str]:
    """``ballbeam run``'s summary: two processes on a private ff11:: group of this host."""
    from ballbeam.evaluation.summary import summarise
    from ballbeam.logs.reader import read_log
    from ballbeam.runtime.launcher import launch_run
    from ballbeam.studies.spec import toml_document, toml_value

    overrides = list(task.overrides)
    if task.log_dir is not None:
        overrides.append(f"run.log_dir={toml_value(task.log_dir)}")
    # Both processes of the run read a file: the base's contents, written on this host.
    with tempfile.TemporaryDirectory(prefix="ballbeam-point-") as directory:
        base_path = Path(directory) / f"{Path(task.base or 'config').stem}.toml"
        base_path.write_text(toml_document(task.base_data) + "\n", encoding="utf-8")
        result = launch_run(str(base_path), overrides)
    summary = summarise(read_log(result.log_path), config.limits.theta_rad)
    # The table keeps numbers and flags; faults and reasons are summarised as strings.
    metrics = {
        key: value
        for key, value in summary.items()
        if isinstance(value, int | float | str | type(None)) and key != "truncation_reason"
    }
    metrics["faults"] = ",".join(f"{kind}={n}" for kind, n in sorted(summary["faults"].items()))
    metrics["daemon_wall_time_s"] = result.wall_time_s
    return metrics, str(result.log_path)


def evaluate(task: PointTask) -> PointOutcome:
    """Run one point; any failure (a config a draw made invalid, a run that failed) is
    returned as the point's error."""
    started = time.perf_counter()
    started_cpu_s = time.process_time()
    worker = f"{socket.gethostname()}:{os.getpid()}"
    log_path = None
    try:
        config = config_from_data(task.base_data, task.overrides, task.base or "config")
        if task.runner == "offline":
            metrics = offline_metrics(config)
        else:
            metrics, log_path = bus_metrics(task, config)
    except Exception as error:  # a point's failure is data, not the sweep's end
        message = str(error).strip().splitlines()
        return PointOutcome(
            task.point_id,
            {},
            log_path,
            f"{type(error).__name__}: {' / '.join(message)}"[:2000],
            time.perf_counter() - started,
            worker,
            time.process_time() - started_cpu_s,
        )
    return PointOutcome(
        task.point_id, metrics, log_path, None, time.perf_counter() - started, worker,
        time.process_time() - started_cpu_s,
    )


def evaluate_batch(tasks: list[PointTask]) -> list[PointOutcome]:
    """Several points in one Dask task: a 0.1 s point is then not dominated by the
    scheduler's per-task round trip."""
    return [evaluate(task) for task in tasks]


def log_dir_for(output: Path) -> str:
    return str((output / "logs").absolute())
