"""The config-driven regression suite: every scenario file (``configs/scenarios/*.toml``) is a
run plus bounds.

Each scenario runs over the real bus (two processes, lock-step unless it says real time),
several at once; the verdict is a table scenario × metric × bound × value × pass/fail.
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Callable, Iterable
from concurrent.futures import ThreadPoolExecutor, as_completed
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from xml.etree import ElementTree

from ballbeam.config import load_config, resolve_config_path, shipped_configs
from ballbeam.errors import BallbeamError, ConfigError, OutputExistsError
from ballbeam.files import write_new


@dataclass(frozen=True)
class Check:
    metric: str
    bound: str  # "<= 2.1", ">= 0", ...
    value: Any
    passed: bool


@dataclass(frozen=True)
class ScenarioResult:
    name: str
    path: Path
    checks: tuple[Check, ...]
    error: str | None  # the run itself failed
    log_path: str | None
    wall_time_s: float

    @property
    def passed(self) -> bool:
        return self.error is None and all(check.passed for check in self.checks)


def discover(locations: Iterable[str | Path] = ()) -> list[Path]:
    """Scenario files: each location is a file or a directory of ``*.toml`` files, on disk or
    shipped with the package (``scenarios``, ``scenarios/noise_heavy``); none: every shipped
    scenario."""
    found: list[Path] = []
    for location in list(locations) or [shipped_configs() / "scenarios"]:
        path = Path(location)
        if not path.exists() and (shipped_configs() / path).is_dir():
            path = shipped_configs() / path
        if path.is_dir():
            scenarios = sorted(path.glob("*.toml"))
            if not scenarios:
                raise ConfigError(f"no scenario files (*.toml) in {path}")
            found += scenarios
        else:
            found.append(resolve_config_path(path))
    return found


def evaluate(expect: dict[str, dict[str, float]], summary: dict[str, Any]) -> tuple[Check, ...]:
    """Each bound against the run's value; a missing or non-finite value fails its bound
    (a ball that never settled has no settle time, and must not pass ``max = 2.1``)."""
    checks = []
    for metric, bounds in sorted(expect.items()):
        value = summary.get(metric)
        number = float(value) if isinstance(value, int | float) else math.nan
        for kind, limit in sorted(bounds.items()):
            if kind == "max":
                passed = math.isfinite(number) and number <= limit
                checks.append(Check(metric, f"<= {limit:g}", value, passed))
            else:
                passed = math.isfinite(number) and number >= limit
                checks.append(Check(metric, f">= {limit:g}", value, passed))
    return tuple(checks)


def run_scenario(path: Path, overrides: Iterable[str] = ()) -> ScenarioResult:
    from ballbeam.evaluation.summary import summarise
    from ballbeam.logs.reader import read_log
    from ballbeam.runtime.launcher import launch_run

    started = time.monotonic()
    overrides = list(overrides)
    try:
        config = load_config(path, overrides)
        if not config.expect:
            raise ConfigError(f"{path}: a scenario needs an [expect] table of metric bounds")
        result = launch_run(str(path), overrides)
        summary = summarise(read_log(result.log_path), config.limits.theta_rad)
    except BallbeamError as error:
        return ScenarioResult(path.stem, path, (), str(error), None, time.monotonic() - started)
    return ScenarioResult(
        path.stem,
        path,
        evaluate(config.expect, summary),
        None,
        str(result.log_path),
        time.monotonic() - started,
    )


def run_all(
    paths: list[Path],
    jobs: int,
    overrides: Iterable[str] = (),
    on_done: Callable[[ScenarioResult], None] | None = None,
) -> list[ScenarioResult]:
    overrides = list(overrides)
    results: dict[Path, ScenarioResult] = {}
    with ThreadPoolExecutor(max_workers=max(1, jobs)) as pool:
        futures = {pool.submit(run_scenario, path, overrides): path for path in paths}
        for future in as_completed(futures):
            result = future.result()
            results[futures[future]] = result
            if on_done is not None:
                on_done(result)
    return [results[path] for path in paths]


def default_jobs() -> int:
    # Each scenario is two busy processes; more than one per core only adds contention.
    return max(1, (os.cpu_count() or 1))


def table(results: list[ScenarioResult]) -> str:
    rows = [("scenario", "metric", "bound", "value", "result")]
    for result in results:
        if result.error is not None:
            rows.append((result.name, "(run)", "-", "error, see below", "FAIL"))
            continue
        for check in result.checks:
            value = check.value
            shown = f"{value:.4g}" if isinstance(value, float) else str(value)
            rows.append(
                (
                    result.name,
                    check.metric,
                    check.bound,
                    "never" if value is None else shown,
                    "pass" if check.passed else "FAIL",
                )
            )
    widths = [max(len(row[column]) for row in rows) for column in range(5)]
    lines = [
        "  ".join(cell.ljust(width) for cell, width in zip(row, widths, strict=True))
        for row in rows
    ]
    lines.insert(1, "  ".join("-" * width for width in widths))
    for result in results:
        if result.error is not None:
            lines.append(f"\n{result.name}: {result.error}")
    passed = sum(result.passed for result in results)
    lines.append(f"\n{passed}/{len(results)} scenarios passed")
    return "\n".join(lines)


def as_json(results: list[ScenarioResult]) -> dict[str, Any]:
    return {
        "passed": all(result.passed for result in results),
        "scenarios": [
            {
                "name": result.name,
                "path": str(result.path),
                "passed": result.passed,
                "error": result.error,
                "log_path": result.log_path,
                "wall_time_s": result.wall_time_s,
                "checks": [
                    {
                        "metric": check.metric,
                        "bound": check.bound,
                        "value": check.value,
                        "passed": check.passed,
                    }
                    for check in result.checks
                ],
            }
            for result in results
        ],
    }


def write_junit(results: list[ScenarioResult], path: Path) -> None:
    suite = ElementTree.Element(
        "testsuite",
        name="ballbeam.evaluation.regress",
        tests=str(len(results)),
        failures=str(sum(not result.passed for result in results)),
    )
    for result in results:
        case = ElementTree.SubElement(
            suite,
            "testcase",
            classname="scenarios",
            name=result.name,
            time=f"{result.wall_time_s:.3f}",
        )
        if result.error is not None:
            ElementTree.SubElement(case, "error", message=result.error)
        for check in result.checks:
            if not check.passed:
                ElementTree.SubElement(
                    case, "failure", message=f"{check.metric} = {check.value} not {check.bound}"
                )
    try:
        write_new(
            path,
            lambda stream: ElementTree.ElementTree(suite).write(
                stream, encoding="utf-8", xml_declaration=True
            ),
        )
    except OutputExistsError:
        raise
    except OSError as error:
        raise BallbeamError(f"cannot write JUnit XML {path}: {error}") from error
