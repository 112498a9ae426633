"""Runs a sweep's points on a Dask cluster: the ones not already in the store, in batches, with
a progress bar; every outcome is stored as it arrives (a stopped sweep resumes), then the whole
table is written as Parquet.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable, Sequence
from contextlib import AbstractContextManager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from ballbeam.config import read_config_data
from ballbeam.errors import ConfigError
from ballbeam.files import replace_file
from ballbeam.runtime.stop import INTERRUPT
from ballbeam.studies.points import PointOutcome, PointTask, evaluate_batch, log_dir_for, warm_up
from ballbeam.studies.spec import Point, SweepSpec, toml_value
from ballbeam.studies.store import ResultStore, point_id

TABLE_NAME = "results.parquet"
# Points per Dask task: enough that a 0.1 s offline point is not dominated by the scheduler's
# round trip, few enough that the progress bar moves and both workers stay busy to the end.
MAX_OFFLINE_BATCH = 8


@dataclass(frozen=True)
class SweepOutcome:
    table: Any  # pandas.DataFrame, one row a point
    table_path: Path
    total: int
    skipped: int  # already in the store
    ran: int
    failed: int  # of all points, stored earlier or now
    wall_time_s: float
    workers: int


def tasks_for(
    spec: SweepSpec, points: Sequence[Point], output: Path
) -> list[tuple[PointTask, Point]]:
    base = str(spec.base) if spec.base is not None else None
    base_data = read_config_data(spec.base) if spec.base is not None else {}
    log_dir = log_dir_for(output) if spec.runner != "offline" else None
    tasks = []
    for point in points:
        overrides = point.overrides
        if spec.runner != "offline":
            overrides = (*overrides, f"run.mode={toml_value(spec.runner)}")
        identifier = point_id(base_data, overrides, spec.runner)
        tasks.append(
            (PointTask(identifier, base, base_data, overrides, spec.runner, log_dir), point)
        )
    return tasks


def batches(tasks: list[PointTask], runner: str, workers: int) -> list[list[PointTask]]:
    if runner != "offline":
        return [[task] for task in tasks]  # a bus run is seconds: one per Dask task
    size = max(1, min(MAX_OFFLINE_BATCH, len(tasks) // (4 * max(workers, 1))))
    return [tasks[start : start + size] for start in range(0, len(tasks), size)]


def run_points(
    client: Any,
    tasks: list[PointTask],
    runner: str,
    on_outcome: Callable[[PointOutcome], None],
    progress: bool = True,
    description: str = "points",
) -> None:
    """Evaluate ``tasks`` on the cluster; ``on_outcome`` sees each as it arrives. A batch lost
    with its worker is recorded as failed points, like a run that failed."""
    from distributed import as_completed
    from tqdm import tqdm

    from ballbeam.studies.cluster import worker_count

    if not tasks:
        return
    workers = max(worker_count(client), 1)
    client.run(warm_up)  # imports on every worker before the clock and the ETA start
    groups = batches(tasks, runner, workers)
    futures = {
        client.submit(evaluate_batch, group, pure=False, key=f"ballbeam-{group[0].point_id}-"
                      f"{len(group)}-{time.monotonic_ns()}"): group
        for group in groups
    }
    with tqdm(total=len(tasks), unit="pt", desc=description, file=sys.stderr,
              disable=not progress, smoothing=0.1) as bar:
        for future in as_completed(futures):
            INTERRUPT.check()
            group = futures[future]
            try:
                outcomes: list[PointOutcome] = future.result()
            except Exception as error:  # the worker died or the task could not run
                outcomes = [
                    PointOutcome(task.point_id, {}, None, f"{type(error).__name__}: {error}",
                                 0.0, "lost")
                    for task in group
                ]
            for outcome in outcomes:
                on_outcome(outcome)
            bar.update(len(outcomes))
            future.release()


def run_sweep(
    spec: SweepSpec,
    output: Path,
    connect: Callable[[], AbstractContextManager[Any]],
    *,
    retry_failed: bool = False,
    progress: bool = True,
) -> SweepOutcome:
    started = time.monotonic()
    store = ResultStore(output)
    pairs = tasks_for(spec, spec.points(), output)
    records: dict[str, dict[str, Any]] = {}
    todo: dict[str, PointTask] = {}
    for task, _ in pairs:
        record = store.load(task.point_id)
        if record is not None and not (retry_failed and record.get("error")):
            records[task.point_id] = record
        else:
            todo[task.point_id] = task  # the same config twice in a spec runs once
    values_of = {task.point_id: point.as_dict() for task, point in pairs}

    def keep(outcome: PointOutcome) -> None:
        store.save(outcome, values_of[outcome.point_id], spec.runner)
        stored = store.load(outcome.point_id)
        records[outcome.point_id] = stored if stored is not None else {}

    from ballbeam.studies.cluster import worker_count

    skipped = len(pairs) - len(todo)
    workers = 0
    if todo:  # a finished sweep run again only rewrites its table: no cluster to start
        with connect() as client:
            workers = worker_count(client)
            run_points(client, list(todo.values()), spec.runner, keep, progress, spec.path.stem)
    table = results_table(spec, pairs, records)
    table_path = output / TABLE_NAME
    try:
        replace_file(table_path, lambda stream: table.to_parquet(stream, index=False))
    except OSError as error:  # the points are stored: a rerun writes the table without them
        raise ConfigError(f"cannot write the results table {table_path}: {error}") from error
    return SweepOutcome(
        table=table,
        table_path=table_path,
        total=len(pairs),
        skipped=skipped,
        ran=len(todo),
        failed=int(table["error"].notna().sum()),
        wall_time_s=time.monotonic() - started,
        workers=workers,
    )


def stored_points(spec: SweepSpec, output: Path) -> tuple[int, int]:
    """How many of the spec's points ``output`` holds a record of (run or failed: a rerun skips
    them), and how many points the spec has."""
    store = ResultStore(output)
    pairs = tasks_for(spec, spec.points(), output)
    return sum(store.path(task.point_id).is_file() for task, _ in pairs), len(pairs)


def results_table(
    spec: SweepSpec, pairs: list[tuple[PointTask, Point]], records: dict[str, dict[str, Any]]
) -> Any:
    """One row a point, in the spec's order: its id, the swept keys, every metric, the log
    path, the error (None if it ran), its wall and CPU time and worker."""
    import pandas as pd

    rows = []
    for task, point in pairs:
        record = records.get(task.point_id, {})
        rows.append(
            {
                "point_id": task.point_id,
                **point.as_dict(),
                **record.get("metrics", {}),
                "log_path": record.get("log_path"),
                "error": record.get("error"),
                "wall_time_s": record.get("wall_time_s"),
                "cpu_time_s": record.get("cpu_time_s"),
                "worker": record.get("worker"),
            }
        )
    table = pd.DataFrame(rows)
    for column in ("log_path", "error", "worker"):
        table[column] = table[column].astype(object).where(table[column].notna(), None)
    return table


def metric_columns(table: Any, spec: SweepSpec) -> list[str]:
    """The numeric metric columns of a results table (not the keys or the bookkeeping)."""
    import pandas as pd

    skip = {*spec.keys, "point_id", "log_path", "error", "wall_time_s", "cpu_time_s", "worker"}
    return [
        column
        for column in table.columns
        if column not in skip
        and pd.api.types.is_numeric_dtype(table[column])
        and not pd.api.types.is_bool_dtype(table[column])
    ]
