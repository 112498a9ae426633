"""Every configs/scenarios/*.toml is a test: a real two-process run over the bus, its metrics
checked against the file's [expect] bounds. A new scenario file is a new test."""

from __future__ import annotations

import tomllib
from pathlib import Path

import pytest

from ballbeam.evaluation.regress import discover, run_scenario, table

from .conftest import CONFIGS

SCENARIOS = discover([CONFIGS / "scenarios"])


def _on_wall_time(path: Path) -> bool:
    return tomllib.loads(path.read_text()).get("run", {}).get("mode") == "realtime"


@pytest.mark.bus
@pytest.mark.parametrize(
    "path",
    [
        pytest.param(
            path, id=path.stem, marks=[pytest.mark.realtime] if _on_wall_time(path) else []
        )
        for path in SCENARIOS
    ],
)
def test_scenario(path: Path, tmp_path: Path) -> None:
    result = run_scenario(path, [f"run.log_dir='{tmp_path}'"])
    assert result.error is None, result.error
    assert result.checks, "a scenario must bound at least one metric"
    assert result.passed, "\n" + table([result])
