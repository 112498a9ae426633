"""Fixtures of the fault tests: the clean reference run, and the figures each module prints."""

from __future__ import annotations

import json
from collections.abc import Iterator

import pytest

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


# Each module prints the figures its tests gave, then starts afresh for the next module.
@pytest.fixture(autouse=True, scope="module")
def _print_figures() -> Iterator[None]:
    yield
    if FIGURES:
        print("\nfault-test figures:\n" + json.dumps(FIGURES, indent=2, default=str))
        FIGURES.clear()
