"""Shared test fixtures."""

from __future__ import annotations

import fcntl
import importlib
import subprocess
import sys
import tempfile
from collections.abc import Generator, Iterator
from contextlib import contextmanager
from pathlib import Path
from types import ModuleType

import pytest

REPO = Path(__file__).resolve().parents[1]
CONFIGS = REPO / "configs"
PAPER = CONFIGS / "paper.toml"
BENCH = REPO / "bench"


def import_bench(name: str) -> ModuleType:
    """A bench/ script as a module. On the path, not loaded from its file: processes it spawns
    import it by name."""
    if str(BENCH) not in sys.path:
        sys.path.insert(0, str(BENCH))
    return importlib.import_module(name)


def ballbeam_argv(*args: str) -> list[str]:
    return [sys.executable, "-m", "ballbeam", *args]


def ballbeam(*args: str, timeout_s: float = 300) -> subprocess.CompletedProcess[str]:
    """The ``ballbeam`` command line, run from the repository as a user would."""
    return subprocess.run(
        ballbeam_argv(*args),
        capture_output=True,
        text=True,
        timeout=timeout_s,
        check=False,
        cwd=REPO,
    )


# ---- tests on wall time run alone -----------------------------------------------------------
#
# Under ``pytest -n`` (pytest-xdist) the workers share the machine's cores. A test marked
# ``realtime`` (a daemon and a plant on wall time, or bounds on how late a process may be)
# measures this machine's scheduling, so it runs while no other test does: every test holds a
# readers-writer lock of the run for its whole protocol (set-up to tear-down), shared, and a
# ``realtime`` one exclusive. A gate taken first keeps new shared holders from overtaking a
# waiting exclusive one (else the other worker's next test would always get in first).


class RunLock:
    def __init__(self, run_id: str) -> None:
        base = Path(tempfile.gettempdir()) / f"ballbeam-tests-{run_id}"
        self.gate_path, self.room_path = base.with_suffix(".gate"), base.with_suffix(".room")

    @contextmanager
    def held(self, exclusive: bool) -> Generator[None, None, None]:
        with self.gate_path.open("a") as gate, self.room_path.open("a") as room:
            fcntl.flock(gate, fcntl.LOCK_EX)
            try:
                fcntl.flock(room, fcntl.LOCK_EX if exclusive else fcntl.LOCK_SH)
            finally:
                fcntl.flock(gate, fcntl.LOCK_UN)
            try:
                yield
            finally:
                fcntl.flock(room, fcntl.LOCK_UN)


@pytest.hookimpl(wrapper=True)
def pytest_runtest_protocol(
    item: pytest.Item, nextitem: pytest.Item | None
) -> Generator[None, object, object]:
    worker = getattr(item.config, "workerinput", None)
    if worker is None:  # one process: nothing runs beside it
        return (yield)
    with RunLock(worker["testrunuid"]).held(item.get_closest_marker("realtime") is not None):
        return (yield)


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """A ``realtime`` test runs once more when it fails (pytest-rerunfailures; the rerun is
    reported): the shared machines these run on stall even a pinned SCHED_FIFO clock loop for
    milliseconds several times a minute (bench/bench.py --only machine_stalls), and a stall
    inside such a test's few seconds fails it whatever the code does. A failure of the code
    fails both runs."""
    for item in items:
        if item.get_closest_marker("realtime") is not None:
            item.add_marker(pytest.mark.flaky(reruns=1, reruns_delay=2))


@pytest.fixture
def paper_config_path() -> Path:
    return PAPER


@pytest.fixture(scope="session")
def local_dask_client() -> Iterator[object]:
    """One embedded Dask LocalCluster (2 worker processes, loopback) for the study tests: a
    cluster takes seconds to start."""
    pytest.importorskip("distributed")
    from ballbeam.studies.cluster import dask_client

    with dask_client(None, 2) as client:
        yield client
