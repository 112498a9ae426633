"""``ballbeam sweep`` (issue 14): the spec, the points it expands to, and sweeps on Dask — an
embedded LocalCluster and a scheduler with two workers started as separate processes — each
checked against the same points run one by one through the existing paths (``run_offline``,
as ``ballbeam simulate`` runs it; ``launch_run``, as ``ballbeam run`` does)."""

from __future__ import annotations

import json
import math
import os
import shlex
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import nullcontext
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from ballbeam.assembly import run_offline
from ballbeam.cli import main
from ballbeam.config import load_config
from ballbeam.errors import ConfigError
from ballbeam.studies.engine import run_sweep
from ballbeam.studies.spec import SweepSpec, load_spec, spec_from_mapping

from .conftest import CONFIGS, PAPER, ballbeam, ballbeam_argv

pd = pytest.importorskip("pandas")

SWEEPS = sorted(set((CONFIGS / "sweeps").glob("*.toml")) - set((CONFIGS / "sweeps").glob("tune_*")))
TUNINGS = sorted((CONFIGS / "sweeps").glob("tune_*.toml"))
# Short runs: what is checked is that a point gives what it gives alone, not its control.
SMALL_SPEC = f"""
[sweep]
base = "{PAPER}"
set = ["run.duration_s=1.5"]
seeds = [1, 2]

[grid]
"plant.ball_gain_scale" = [0.9, 1.1, 0.05]   # 0.05 is below the key's range: a failing point
"""


def write_spec(tmp_path: Path, text: str, name: str = "small.toml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def one_by_one_offline(spec: SweepSpec, overrides: tuple[str, ...]) -> dict[str, Any]:
    metrics: dict[str, Any] = run_offline(load_config(spec.base, overrides)).metrics.as_dict()
    return metrics


def assert_row_is(row: Any, expected: dict[str, Any]) -> None:
    for key, value in expected.items():
        got = row[key]
        if value is None:
            assert got is None or (isinstance(got, float) and math.isnan(got)), key
        else:
            assert got == value, key  # the same arithmetic: equal, not close


# --- the spec ----------------------------------------------------------------------------------


@pytest.mark.parametrize("path", SWEEPS, ids=[path.stem for path in SWEEPS])
def test_every_shipped_sweep_spec_loads_and_its_points_validate(path: Path) -> None:
    spec = load_spec(path)
    points = spec.points()
    assert points
    for point in points[:: max(1, len(points) // 10)]:
        load_config(spec.base, point.overrides)


@pytest.mark.parametrize("path", TUNINGS, ids=[path.stem for path in TUNINGS])
def test_every_shipped_tuning_spec_loads(path: Path) -> None:
    from ballbeam.studies.tune import defaults, load_tune_spec, overrides_for

    spec = load_tune_spec(path)
    assert spec.train.points() and spec.holdout.points()
    held_out = {point.overrides for point in spec.holdout.points()}
    assert not held_out & {point.overrides for point in spec.train.points()}
    # The base's own values, set back, give the base's config.
    keys = overrides_for(spec, defaults(spec))
    sets = [f"{key}={value!r}".replace("(", "[").replace(")", "]") for key, value in keys.items()]
    assert load_config(spec.base, sets) == load_config(spec.base)


def test_the_monte_carlo_example_is_200_points_drawn_in_range() -> None:
    spec = load_spec("sweeps/mismatch_monte_carlo")
    points = spec.points()
    assert len(points) == 200 == spec.samples * len(spec.seeds)
    ball = np.array([point.as_dict()["plant.ball_gain_scale"] for point in points])
    assert ball.min() >= 0.8 and ball.max() <= 1.2 and len(set(ball)) == spec.samples
    # Drawn again, the same points (a sweep resumes by its points' contents).
    assert [p.overrides for p in load_spec("sweeps/mismatch_monte_carlo").points()] == [
        p.overrides for p in points
    ]


def test_grid_ranges_distributions_and_seeds_expand(tmp_path: Path) -> None:
    spec = spec_from_mapping(
        {
            "sweep": {"seeds": 2, "samples": 3, "sample_seed": 7},
            "grid": {
                "plan.theta_margin_deg": {"start": 0.0, "stop": 1.0, "num": 3},
                "plant.deadzone_v": {"start": 0.1, "stop": 0.3, "step": 0.1},
            },
            "random": {
                "plant.motor_gain_scale": {"normal": [1.0, 0.05]},
                "plant.nonlinear_ball": {"choice": [False, True]},
                "plant.ball_gain_scale": {"uniform": [0.8, 1.2]},
            },
        },
        tmp_path / "spec.toml",
    )
    points = spec.points()
    assert len(points) == 3 * 3 * 3 * 2
    assert spec.keys[-1] == "plant.seed"
    assert sorted({p.as_dict()["plan.theta_margin_deg"] for p in points}) == [0.0, 0.5, 1.0]
    deadzones = sorted({p.as_dict()["plant.deadzone_v"] for p in points})
    assert deadzones == pytest.approx([0.1, 0.2, 0.3])
    assert {p.as_dict()["plant.nonlinear_ball"] for p in points} <= {False, True}
    # Every override parses back to the value drawn.
    point = points[5]
    config = load_config(None, point.overrides)
    assert config.plant.ball_gain_scale == point.as_dict()["plant.ball_gain_scale"]
    assert config.plant.nonlinear_ball == point.as_dict()["plant.nonlinear_ball"]


@pytest.mark.parametrize(
    ("text", "fragment"),
    [
        ('[grid]\n"plant.ball_gain" = [1.0]', "'plant.ball_gain' is not a config key"),
        ('[grid]\n"plant" = [1.0]', "names a config section"),
        ('[random]\n"plant.seed" = { uniform = [0, 1] }', "sweep.samples must be"),
        ('[sweep]\nsamples = 3\n[random]\n"plant.deadzone_v" = { gauss = [0, 1] }', "needs one of"),
        ('[sweep]\nrun = "fast"\nseeds = 2', "sweep.run must be one of"),
        ('[sweep]\nseeds = 0', "sweep.seeds must be a whole number >= 1"),
        ("[sweep]\nbase = 'paper'", "nothing to sweep"),
        ('[swep]\nseeds = 2', "unknown table"),
        ('[grid]\n"plant.deadzone_v" = { start = 0, stop = 1 }', "a range is"),
    ],
)
def test_a_bad_spec_is_one_line_and_exit_2(
    tmp_path: Path, text: str, fragment: str, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(ConfigError, match=None) as caught:
        load_spec(write_spec(tmp_path, text))
    assert fragment in str(caught.value)
    assert main(["sweep", str(tmp_path / "small.toml"), "--output", str(tmp_path / "out")]) == 2
    error = capsys.readouterr().err
    assert error.count("\n") == 1 and fragment in error and "Traceback" not in error


# --- sweeps on Dask ----------------------------------------------------------------------------


def test_a_sweep_on_a_local_cluster_equals_the_points_run_one_by_one(
    tmp_path: Path, local_dask_client: Any
) -> None:
    spec = load_spec(write_spec(tmp_path, SMALL_SPEC))
    output = tmp_path / "out"
    outcome = run_sweep(spec, output, lambda: nullcontext(local_dask_client), progress=False)
    table = pd.read_parquet(output / "results.parquet")
    assert outcome.total == len(table) == 6 and outcome.ran == 6 and outcome.workers == 2
    for point, (_, row) in zip(spec.points(), table.iterrows(), strict=True):
        assert row["plant.ball_gain_scale"] == point.as_dict()["plant.ball_gain_scale"]
        assert row["plant.seed"] == point.as_dict()["plant.seed"]
        if point.as_dict()["plant.ball_gain_scale"] == 0.05:
            # Recorded with its reason; the other points went on.
            assert "plant.ball_gain_scale" in row["error"] and np.isnan(row["rest_ratio"])
            continue
        assert pd.isna(row["error"]) and pd.isna(row["log_path"])
        assert_row_is(row, one_by_one_offline(spec, point.overrides))
    assert outcome.failed == 2

    # Run again: every point is found done (content-addressed), nothing runs, no cluster starts.
    def no_cluster() -> Any:
        raise AssertionError("a finished sweep must not start a cluster")

    again = run_sweep(spec, output, no_cluster, progress=False)
    assert again.ran == 0 and again.skipped == 6
    pd.testing.assert_frame_equal(pd.read_parquet(output / "results.parquet"), table)
    # --retry-failed: only the failed points run again (and fail again, for the same reason).
    retried = run_sweep(spec, output, lambda: nullcontext(local_dask_client), progress=False,
                        retry_failed=True)
    assert retried.ran == 2 and retried.skipped == 4 and retried.failed == 2


def test_a_stopped_sweep_resumes_with_the_points_not_done(
    tmp_path: Path, local_dask_client: Any
) -> None:
    spec = load_spec(write_spec(tmp_path, SMALL_SPEC.replace(", 0.05]", "]")))
    output = tmp_path / "out"
    outcome = run_sweep(spec, output, lambda: nullcontext(local_dask_client), progress=False)
    assert outcome.ran == 4
    done = sorted((output / "points").glob("*.json"))
    removed = done[0]
    removed.unlink()  # as if the sweep had been stopped before this point
    # A grown spec: one more grid value; the old points are kept, the new and lost ones run.
    grown = load_spec(write_spec(tmp_path, SMALL_SPEC.replace("0.05]", "1.0]")))
    resumed = run_sweep(grown, output, lambda: nullcontext(local_dask_client), progress=False)
    assert resumed.total == 6 and resumed.ran == 3 and resumed.skipped == 3
    assert removed.exists()


def test_an_interrupted_sweep_says_what_it_kept_and_how_to_resume(tmp_path: Path) -> None:
    """Ctrl-C once some points are stored: exit 130, how many points are kept and where, and
    the command that resumes; that command runs the rest only."""
    spec_path = write_spec(tmp_path, SMALL_SPEC.replace(
        "[0.9, 1.1, 0.05]", "{ start = 0.85, stop = 1.15, num = 6 }"))
    output = tmp_path / "out"
    process = subprocess.Popen(
        ballbeam_argv("sweep", str(spec_path), "--output", str(output), "--workers", "1",
                      "--no-plots"),
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=tmp_path,
    )
    deadline = time.monotonic() + 240
    while len(list((output / "points").glob("*.json"))) < 3:
        assert process.poll() is None, process.communicate()[1][-3000:]
        assert time.monotonic() < deadline
        time.sleep(0.1)
    process.send_signal(signal.SIGINT)
    _, errors = process.communicate(timeout=120)
    assert process.returncode == 130, errors[-3000:]
    kept = len(list((output / "points").glob("*.json")))
    assert 3 <= kept < 12
    assert (f"sweep interrupted: {kept} of 12 points are saved in "
            f"{(output / 'points').absolute()}") in errors
    command = shlex.split(errors.rsplit("resume with: ", 1)[1].splitlines()[0])
    assert command[:2] == ["ballbeam", "sweep"]
    resumed = subprocess.run([*ballbeam_argv(*command[1:]), "--json", "--no-plots"],
                             capture_output=True, text=True, timeout=300, check=False,
                             cwd=tmp_path)
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    report = json.loads(resumed.stdout)
    assert report["points"] == 12 and report["skipped_done"] == kept
    assert report["ran"] == 12 - kept


@pytest.fixture
def dask_processes(tmp_path: Path) -> Iterator[str]:
    """``dask scheduler`` and two ``dask worker`` processes on loopback; always stopped."""
    dask = str(Path(sys.executable).parent / "dask")
    scheduler_file = tmp_path / "scheduler.json"
    started: list[subprocess.Popen[bytes]] = []
    logs = tmp_path / "dask-logs"
    logs.mkdir()

    def start(name: str, *argv: str) -> None:
        with (logs / f"{name}.log").open("wb") as log:
            started.append(
                subprocess.Popen([dask, *argv], stdout=log, stderr=subprocess.STDOUT,
                                 start_new_session=True)
            )

    try:
        start("scheduler", "scheduler", "--host", "127.0.0.1", "--port", "0", "--no-dashboard",
              "--dashboard-address", "127.0.0.1:0", "--scheduler-file", str(scheduler_file))
        deadline = time.monotonic() + 60
        while not scheduler_file.exists() and time.monotonic() < deadline:
            time.sleep(0.1)
        assert scheduler_file.exists(), (logs / "scheduler.log").read_text()
        address = json.loads(scheduler_file.read_text())["address"]
        assert address.startswith("tcp://127.0.0.1:")
        for index in range(2):
            start(f"worker{index}", "worker", address, "--host", "127.0.0.1", "--nthreads", "1",
                  "--nworkers", "1", "--no-dashboard", "--dashboard-address", "127.0.0.1:0",
                  "--name", f"w{index}")
        from distributed import Client

        with Client(address, timeout="30s") as client:
            client.wait_for_workers(2, timeout=60)
        yield address
    finally:
        for process in started:
            if process.poll() is None:
                os.killpg(process.pid, signal.SIGTERM)
        for process in started:
            try:
                process.wait(timeout=10)
            except subprocess.TimeoutExpired:
                os.killpg(process.pid, signal.SIGKILL)
                process.wait()


def test_a_sweep_on_a_scheduler_and_two_worker_processes(
    tmp_path: Path, dask_processes: str
) -> None:
    spec_path = write_spec(tmp_path, SMALL_SPEC.replace(", 0.05]", "]"))
    output = tmp_path / "out"
    result = ballbeam("sweep", str(spec_path), "--scheduler", dask_processes, "--output",
                      str(output), "--json", timeout_s=240)
    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout)
    assert report["points"] == report["ran"] == 4 and report["workers"] == 2
    table = pd.read_parquet(output / "results.parquet")
    spec = load_spec(spec_path)
    for point, (_, row) in zip(spec.points(), table.iterrows(), strict=True):
        assert pd.isna(row["error"])
        assert_row_is(row, one_by_one_offline(spec, point.overrides))
    assert len(set(table["worker"])) == 2  # both workers ran points
    assert sorted(path.name for path in (output / "plots").iterdir()) == [
        "distributions.png", "metric_vs_plant_ball_gain_scale.png"
    ]


def test_an_unreachable_scheduler_is_one_line_and_exit_2(tmp_path: Path) -> None:
    from ballbeam.runtime.bus import free_udp_port

    spec_path = write_spec(tmp_path, SMALL_SPEC)
    result = ballbeam("sweep", str(spec_path), "--scheduler", f"tcp://127.0.0.1:{free_udp_port()}",
                      "--output", str(tmp_path / "out"), "--json", timeout_s=120)
    assert result.returncode == 2
    assert result.stderr.startswith("ballbeam: error: cannot reach the Dask scheduler")
    assert "Traceback" not in result.stderr


@pytest.mark.bus
def test_a_lockstep_bus_sweep_equals_the_runs_one_by_one(
    tmp_path: Path, local_dask_client: Any
) -> None:
    from ballbeam.evaluation.summary import summarise
    from ballbeam.logs.reader import read_log
    from ballbeam.runtime.launcher import launch_run

    spec = load_spec(write_spec(tmp_path, f"""
[sweep]
base = "{PAPER}"
set = ["run.duration_s=0.5"]
run = "lockstep"
seeds = [3]
"""))
    output = tmp_path / "out"
    outcome = run_sweep(spec, output, lambda: nullcontext(local_dask_client), progress=False)
    assert outcome.ran == 1 and outcome.failed == 0
    table = pd.read_parquet(output / "results.parquet")
    for point, (_, row) in zip(spec.points(), table.iterrows(), strict=True):
        assert Path(row["log_path"]).parent == output / "logs"
        alone = launch_run(str(spec.base), [*point.overrides, f"run.log_dir='{tmp_path}/alone'"])
        summary = summarise(read_log(alone.log_path), alone.config.limits.theta_rad)
        assert row["end_reason"] == summary["end_reason"] == "completed"
        # The commands are the same bit for bit (lock-step); the tracking error is not compared:
        # it interpolates the reference at the truth frames' receive times.
        for metric in ("rest_ratio", "settle_time_s", "input_tv_ratio", "max_abs_theta_deg",
                       "largest_step_v", "max_abs_u_v", "dither_hz"):
            assert_row_is(row, {metric: summary[metric]})


# --- the core import stays light ----------------------------------------------------------------

HEAVY = ("dask", "distributed", "pandas", "pyarrow", "optuna")


def test_only_the_studies_package_imports_dask_pandas_or_optuna() -> None:
    from .test_architecture import PACKAGE, imports_of

    for path in sorted(PACKAGE.rglob("*.py")):
        if "studies" in path.relative_to(PACKAGE).parts:
            continue
        heavy = {name for name in imports_of(path) if name.split(".")[0] in HEAVY}
        assert not heavy, f"{path} imports {heavy}"


def test_the_command_line_loads_without_them() -> None:
    probe = (
        "import sys, ballbeam.cli, ballbeam.assembly, ballbeam.studies.spec;"
        f"print(sorted({{m.split('.')[0] for m in sys.modules}} & set({HEAVY!r})))"
    )
    result = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True,
                            check=True, timeout=60)
    assert result.stdout.strip() == "[]"


@pytest.mark.parametrize("path", [*sorted(CONFIGS.glob("*/*.toml")), PAPER], ids=str)
def test_a_config_sent_to_a_worker_as_data_reads_back_the_same(path: Path) -> None:
    """Workers get the base's contents, not its path; bus points write them back as TOML."""
    import tomllib

    from ballbeam.config import read_config_data
    from ballbeam.studies.spec import toml_document

    if "sweeps" in path.parts:
        return
    data = read_config_data(path)
    assert tomllib.loads(toml_document(data)) == data


# --- the design cache's key ---------------------------------------------------------------------

# A changed value for every key the design does not read (assembly.design_key leaves them out).
NOT_DESIGN = {
    "plant.motor_gain_scale": 1.1, "plant.ball_gain_scale": 0.9, "plant.saturation_v": 6.0,
    "plant.position_noise_m": 3e-4, "plant.noise_bandwidth_hz": 100.0,
    "plant.nonlinear_ball": True, "plant.hard_stop_deg": 57.0, "plant.sensor_rate_hz": 2000,
    "plant.physics_substeps": 20, "plant.seed": 5, "plant.hold_until_enabled": False,
    "plant.watchdog_ms": 30.0, "plant.lockstep_resend_ms": 30.0, "plant.cpu": 1,
    "plant.realtime_priority": 10, "plant.fair_slice_us": 500, "plant.command_loss": 0.1,
    "plant.sensor_loss": 0.1, "plant.disturbances": [[1.0, 0.1]],
    "run.duration_s": 2.0, "run.log_dir": "elsewhere", "run.lockstep_poll_us": 5,
    "bus.port": 40000,
}


def test_configs_with_one_design_key_get_one_design() -> None:
    """The worker's cache is sound: every plant and run key but the dead zone and the mode
    leaves the design (and T*) as it is, and those two change it."""
    import pickle

    from ballbeam.assembly import controller_design, design_key, minimum_time_key
    from ballbeam.config import PlantSection, RunSection
    from ballbeam.studies.spec import toml_value

    assert {key.split(".")[1] for key in NOT_DESIGN if key.startswith("plant.")} == set(
        PlantSection.model_fields) - {"deadzone_v"}
    assert {key.split(".")[1] for key in NOT_DESIGN if key.startswith("run.")} == set(
        RunSection.model_fields) - {"mode"}
    base = load_config(PAPER)
    design = pickle.dumps(controller_design(base))
    for key, value in NOT_DESIGN.items():
        config = load_config(PAPER, [f"{key}={toml_value(value)}"])
        assert config != base
        assert design_key(config) == design_key(base), key
        assert minimum_time_key(config) == minimum_time_key(base), key
        assert pickle.dumps(controller_design(config)) == design, key
    for key, value in (("plant.deadzone_v", 0.4), ("run.mode", "realtime")):
        config = load_config(PAPER, [f"{key}={toml_value(value)}"])
        assert design_key(config) != design_key(base), key
        assert pickle.dumps(controller_design(config)) != design, key


def test_a_target_changes_the_design_and_t_star() -> None:
    from ballbeam.assembly import design_key, minimum_time_key

    base, moved = load_config(PAPER), load_config(PAPER, ["task.target_m=0.05"])
    assert design_key(moved) != design_key(base)
    assert minimum_time_key(moved) != minimum_time_key(base)
