"""Fixtures of the fault tests: the clean reference run, and the figures each module prints."""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path

import pytest

from ..conftest import ballbeam
from .harness import FIGURES, Bench, Outcome, figure, run_to_end

# ---- the clean reference ------------------------------------------------------------------


# Session-wide: one clean run serves every module that compares with it (as when these tests
# were one module).
@pytest.fixture(scope="session")
def clean_realtime(tmp_path_factory: pytest.TempPathFactory) -> Outcome:
    with Bench(tmp_path_factory.mktemp("clean"), "realtime", 4.0) as bench:
        outcome = run_to_end(bench)
    assert outcome.daemon_exit == 0, outcome.daemon_stderr[-2000:]
    assert outcome.summary["end_reason"] == "completed"
    assert outcome.summary["settle_time_s"] is not None
    figure("clean_settle_s", outcome.summary["settle_time_s"])
    return outcome


@pytest.fixture(scope="session")
def lockstep_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A whole log of a short lock-step run, written by this project's recorder (read only:
    tests that damage it work on copies)."""
    directory = tmp_path_factory.mktemp("lockstep-log")
    result = ballbeam(
        "run", "--set", "run.duration_s=1.0", "--set", f"run.log_dir='{directory}'",
        timeout_s=120,
    )
    assert result.returncode == 0, result.stderr
    (log,) = directory.glob("*.mcap")
    return log


# Each module prints the figures its tests gave, then starts afresh for the next module.
@pytest.fixture(autouse=True, scope="module")
def _print_figures() -> Iterator[None]:
    yield
    if FIGURES:
        print("\nfault-test figures:\n" + json.dumps(FIGURES, indent=2, default=str))
        FIGURES.clear()
