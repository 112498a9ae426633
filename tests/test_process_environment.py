"""What the package does to the processes around it: importing it leaves the importer's
environment alone, while the processes that start from our entry points run BLAS on one thread
(read with threadpoolctl, which asks the loaded BLAS library itself); and the README's recipe for
a Dask cluster, started as written, listens on loopback only."""

from __future__ import annotations

import ipaddress
import json
import os
import re
import shlex
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from .conftest import PAPER, REPO

CLEAN_ENV = {"PATH": os.environ.get("PATH", "/usr/bin:/bin"), "LANG": "C.UTF-8"}


def _python(code: str, env: dict[str, str] | None = None) -> str:
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                            timeout=120, check=False, env=CLEAN_ENV if env is None else env)
    assert result.returncode == 0, result.stderr
    return result.stdout


@pytest.mark.parametrize("module", ["ballbeam", "ballbeam.cli", "ballbeam_emulator.main",
                                    "ballbeam.studies.tune"])
def test_importing_the_package_leaves_the_environment_alone(module: str) -> None:
    code = ("import json, os; before = dict(os.environ); "
            f"import {module}; "
            "print(json.dumps([before, dict(os.environ)]))")
    before, after = json.loads(_python(code))
    assert after == before


# The entry points as `ballbeam run` and a shell start them (the console script's module, and
# both `python -m`), run far enough to import everything a node imports (the command line loads
# numpy only for a command that reads a config: here a plan), then asked which BLAS thread count
# the loaded library uses.
ENTRY_POINTS = {
    "ballbeam command": f"from ballbeam.entry import main; sys.argv = ['ballbeam', 'plan', "
                        f"{str(PAPER)!r}]; main()",
    "python -m ballbeam": f"sys.argv = ['ballbeam', 'plan', {str(PAPER)!r}]; "
                          "runpy.run_module('ballbeam', run_name='__main__')",
    "python -m ballbeam_emulator": "sys.argv = ['ballbeam_emulator', '--help']; "
                                   "runpy.run_module('ballbeam_emulator', run_name='__main__')",
}


@pytest.mark.parametrize("entry", sorted(ENTRY_POINTS))
def test_a_process_started_from_an_entry_point_runs_blas_on_one_thread(entry: str) -> None:
    threadpoolctl = pytest.importorskip("threadpoolctl")
    del threadpoolctl
    code = (
        "import contextlib, io, json, runpy, sys\n"
        "with contextlib.redirect_stdout(io.StringIO()), contextlib.suppress(SystemExit):\n"
        f"    {ENTRY_POINTS[entry]}\n"
        "assert 'numpy' in sys.modules  # loaded by the entry point, not below\n"
        "import threadpoolctl\n"
        "print(json.dumps([pool['num_threads'] for pool in threadpoolctl.threadpool_info()\n"
        "                  if pool['user_api'] == 'blas']))\n"
    )
    counts = json.loads(_python(code))
    assert counts and set(counts) == {1}
    # What the same numpy does untouched on this machine (more than one on 2+ cores).
    untouched = json.loads(_python(
        "import json, numpy, threadpoolctl; print(json.dumps([pool['num_threads'] for pool in "
        "threadpoolctl.threadpool_info() if pool['user_api'] == 'blas']))"
    ))
    if len(os.sched_getaffinity(0)) > 1:
        assert max(untouched) > 1


def test_a_users_own_blas_thread_count_is_kept() -> None:
    code = ("import os, sys, runpy, contextlib, io\n"
            "sys.argv = ['ballbeam', '--help']\n"
            "with contextlib.redirect_stdout(io.StringIO()), contextlib.suppress(SystemExit):\n"
            "    runpy.run_module('ballbeam', run_name='__main__')\n"
            "print(os.environ['OPENBLAS_NUM_THREADS'])\n")
    assert _python(code, {**CLEAN_ENV, "OPENBLAS_NUM_THREADS": "2"}).strip() == "2"


# ---- the README's cluster recipe -----------------------------------------------------------

README_PORT = 8786  # the port the README's commands use; the test runs them on a free one
SMALL_SPEC = f"""
[sweep]
base = "{PAPER}"
set = ["run.duration_s=1.0"]
seeds = [1]

[grid]
"plant.ball_gain_scale" = [0.95, 1.05]
"""


def readme_cluster_commands() -> list[list[str]]:
    """The commands of the README's "On a cluster" block, comments dropped."""
    text = (REPO / "README.md").read_text(encoding="utf-8")
    section = text[text.index("**On a cluster.**"):]
    block = re.search(r"```sh\n(.*?)```", section, re.DOTALL)
    assert block is not None
    return [shlex.split(line, comments=True) for line in block[1].splitlines() if line.strip()]


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port: int = probe.getsockname()[1]
        return port


def _listening(pids: list[int]) -> list[tuple[int, str, int]]:
    """(pid, address, port) of every listening TCP socket of these processes and their
    children (psutil reads /proc/PID/net/tcp{,6} against the processes' descriptors)."""
    import psutil

    found = []
    for pid in pids:
        root = psutil.Process(pid)
        for process in [root, *root.children(recursive=True)]:
            for connection in process.net_connections(kind="tcp"):
                if connection.status == psutil.CONN_LISTEN:
                    found.append((process.pid, connection.laddr.ip, connection.laddr.port))
    return found


def test_the_readme_cluster_recipe_listens_on_loopback_only(tmp_path: Path) -> None:
    pytest.importorskip("distributed")
    pytest.importorskip("psutil")
    commands = readme_cluster_commands()
    assert [command[:2] for command in commands] == [
        ["dask", "scheduler"], ["dask", "worker"], ["ballbeam", "sweep"]
    ]
    port = str(_free_port())  # another cluster (or test) may hold the README's port
    commands = [[item.replace(str(README_PORT), port) for item in command]
                for command in commands]
    (tmp_path / "my_sweep.toml").write_text(SMALL_SPEC)
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}"
           f"{os.environ.get('PATH', '')}"}
    started: list[subprocess.Popen[bytes]] = []
    try:
        for name, command in zip(("scheduler", "worker"), commands[:2], strict=True):
            with (tmp_path / f"{name}.log").open("wb") as log:
                started.append(subprocess.Popen(command, cwd=tmp_path, env=env, stdout=log,
                                                stderr=subprocess.STDOUT,
                                                start_new_session=True))
            if name == "scheduler":
                deadline = time.monotonic() + 60
                while not any(p == int(port) for _, _, p in _listening([started[0].pid])):
                    assert started[0].poll() is None, (tmp_path / "scheduler.log").read_text()
                    assert time.monotonic() < deadline, "the scheduler never listened"
                    time.sleep(0.2)
        from distributed import Client

        workers = int(commands[1][commands[1].index("--nworkers") + 1])
        with Client(f"tcp://127.0.0.1:{port}", timeout="30s") as client:
            client.wait_for_workers(workers, timeout=90)
        sockets = _listening([process.pid for process in started])
        # Every process listens: the scheduler, the `dask worker` process (its nannies) and
        # each worker process.
        assert len({pid for pid, _, _ in sockets}) == 2 + workers, sockets
        outside = [entry for entry in sockets if not ipaddress.ip_address(entry[1]).is_loopback]
        assert not outside, f"listening beyond loopback: {outside}"
        # The third command, as written, runs the sweep on that cluster.
        result = subprocess.run(commands[2], cwd=tmp_path, env=env, capture_output=True,
                                text=True, timeout=240, check=False)
        assert result.returncode == 0, result.stderr[-2000:]
        assert (tmp_path / "sweep-results" / "my_sweep" / "results.parquet").is_file()
    finally:
        for process in reversed(started):
            if process.poll() is None:
                os.killpg(process.pid, signal.SIGTERM)
        for process in started:
            try:
                process.wait(timeout=15)
            except subprocess.TimeoutExpired:
                os.killpg(process.pid, signal.SIGKILL)
                process.wait()


# What a process loads before its work begins is paid at every start: every run starts two
# nodes, and the suite several hundred processes. The command line parses its arguments (and
# refuses bad ones) before the config stack loads; the emulator designs nothing, so the
# controller's design stack (SciPy's solvers, the planners) stays out of its imports.
@pytest.mark.parametrize(
    ("module", "absent"),
    [
        ("ballbeam.cli", ("numpy", "pydantic", "can", "scipy", "ballbeam.config")),
        ("ballbeam_emulator.main", ("ballbeam.assembly", "ballbeam.core.tracker",
                                    "ballbeam.core.planning", "scipy.optimize")),
    ],
)
def test_a_process_start_loads_only_what_it_needs(module: str, absent: tuple[str, ...]) -> None:
    code = (f"import sys, json; import {module}; "
            "print(json.dumps(sorted(sys.modules)))")
    loaded = json.loads(_python(code))
    found = [name for name in loaded if any(name == a or name.startswith(a + ".") for a in absent)]
    assert not found, f"importing {module} loads {found[:8]}"
