"""Shared test fixtures."""

from __future__ import annotations

import importlib
import subprocess
import sys
from collections.abc import Iterator
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
