"""Fixtures of the fault tests: the clean reference run, and the figures each module prints."""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path

import pytest

from ballbeam.assembly import run_offline

from ..conftest import ballbeam
from .harness import FIGURES, SETTLE_TOLERANCE_S, Bench, Outcome, figure, run_to_end

CLEAN_ATTEMPTS = 2

# ---- the clean reference ------------------------------------------------------------------


# Session-wide: one clean run serves every module that compares with it (as when these tests
# were one module). A rerun of a failed test reuses it, so it must be a fair reference: one
# that itself settles like the offline run of its configuration. A host stall long enough to
# spoil it (this machine's VM host stalls even a real-time clock for milliseconds) makes it
# once more, rather than failing every comparison with it.
@pytest.fixture(scope="session")
def clean_realtime(tmp_path_factory: pytest.TempPathFactory) -> Outcome:
    spoiled: list[float] = []
    for attempt in range(CLEAN_ATTEMPTS):
        with Bench(tmp_path_factory.mktemp(f"clean{attempt}"), "realtime", 4.0) as bench:
            outcome = run_to_end(bench)
        assert outcome.daemon_exit == 0, outcome.daemon_stderr[-2000:]
        assert outcome.summary["end_reason"] == "completed"
        settle_s = outcome.summary["settle_time_s"]
        assert settle_s is not None
        offline_s = run_offline(bench.config).metrics.settle_time_s
        assert offline_s is not None
        if abs(settle_s - offline_s) <= SETTLE_TOLERANCE_S:
            figure("clean_settle_s", settle_s)
            figure("clean_runs_spoiled_settle_s", spoiled)
            return outcome
        spoiled.append(settle_s)
    pytest.fail(
        f"no clean real-time run settled within {SETTLE_TOLERANCE_S} s of the offline "
        f"{offline_s:.3f} s: {spoiled}; is the machine short of CPU?"
    )


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
