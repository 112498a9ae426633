"""``ballbeam tune`` (issue 14, item 3) on a small space: the base's values are the first
trial, the tuned config is a loadable TOML that extends the base, and the before/after figures
on the held-out set equal the same runs made one by one through ``run_offline``."""

from __future__ import annotations

import contextlib
import json
import shlex
import signal
import sqlite3
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from ballbeam.assembly import run_offline
from ballbeam.cli import main
from ballbeam.config import load_config
from ballbeam.errors import ConfigError
from ballbeam.studies.tune import load_tune_spec, run_tune

from .conftest import PAPER, ballbeam_argv

pytest.importorskip("optuna")
pd = pytest.importorskip("pandas")

SMALL_TUNE = f"""
[tune]
base = "{PAPER}"
set = ["run.duration_s=3.0"]
trials = 4
parallel = 2
seeds = [1]
holdout_seeds = [2]
holdout_seed = 9
holdout_samples = 2

[tune.constraints]
max_abs_theta_deg = {{ max = 52.0 }}

[space]
"tracker.q[3]" = {{ log_uniform = [3e3, 3e4] }}
"plan.theta_margin_deg" = {{ uniform = [0.3, 1.0] }}

[scenarios]
samples = 2
[scenarios.random]
"plant.ball_gain_scale" = {{ uniform = [0.9, 1.1] }}
"""


def test_a_small_tuning_on_a_local_cluster(tmp_path: Path, local_dask_client: Any) -> None:
    spec_path = tmp_path / "tune.toml"
    spec_path.write_text(SMALL_TUNE)
    spec = load_tune_spec(spec_path)
    outcome = run_tune(spec, tmp_path / "out", local_dask_client, progress=False)
    assert outcome.default_params == {"tracker.q[3]": 10000.0, "plan.theta_margin_deg": 0.5}
    assert len(outcome.trials) == 4
    assert outcome.trials.iloc[0]["params_tracker.q[3]"] == 10000.0  # trial 0: the base
    rows = {(row["set"], row["config"]): row for row in outcome.table}
    tuned_tuning = rows[("tuning", "tuned")]["rest_ratio worst"]
    assert tuned_tuning <= rows[("tuning", "default")]["rest_ratio worst"]
    # The tuned config: the base plus the chosen keys, loadable as any config.
    tuned = load_config(outcome.tuned_path)
    # The shipped base by its name, not by a path into this install's package: the file loads
    # the same from anywhere, with any install.
    assert 'extends = "paper"' in outcome.tuned_path.read_text().splitlines()
    moved = tmp_path / "elsewhere" / "tuned.toml"
    moved.parent.mkdir()
    moved.write_text(outcome.tuned_path.read_text())
    assert load_config(moved) == tuned
    assert tuned.tracker.q[3] == pytest.approx(outcome.best_params["tracker.q[3]"], rel=1e-15)
    assert tuned.plan.theta_margin_deg == outcome.best_params["plan.theta_margin_deg"]
    assert tuned.plant == load_config(PAPER).plant
    # Held-out figures, run one by one: the default and the tuned file.
    for label, config_path in (("default", PAPER), ("tuned", outcome.tuned_path)):
        worst = max(
            run_offline(load_config(config_path, point.overrides)).metrics.rest_ratio or 100.0
            for point in spec.holdout.points()
        )
        assert rows[("held-out", label)]["rest_ratio worst"] == worst, label
    assert (tmp_path / "out" / "before_after.md").read_text().startswith("| set | config |")


@pytest.mark.parametrize(
    ("text", "fragment"),
    [
        (SMALL_TUNE.replace('"tracker.q[3]"', '"tracker.qq[3]"'), "'tracker.qq' is not a config"),
        (SMALL_TUNE.replace("holdout_seed = 9", "holdout_seed = 1"), "must differ"),
        (SMALL_TUNE.replace('max_abs_theta_deg = {', 'theta_max = {'), "not a metric"),
        (SMALL_TUNE.replace('"tracker.q[3]"', '"tracker.q[7]"'), "has no entry 7"),
    ],
)
def test_a_bad_tuning_spec_is_one_line_and_exit_2(
    tmp_path: Path, text: str, fragment: str, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "tune.toml"
    path.write_text(text)
    with pytest.raises(ConfigError) as caught:
        load_tune_spec(path)
    assert fragment in str(caught.value)
    assert main(["tune", str(path), "--output", str(tmp_path / "out")]) == 2
    error = capsys.readouterr().err
    assert error.count("\n") == 1 and fragment in error


def _interrupt_when(process: subprocess.Popen[str], ready: Callable[[], bool]) -> str:
    """SIGINT to ``process`` once ``ready()``, as Ctrl-C would; its stderr after it exits."""
    deadline = time.monotonic() + 240
    while not ready():
        assert process.poll() is None, process.communicate()[1][-3000:]
        assert time.monotonic() < deadline, "never got far enough to interrupt"
        time.sleep(0.2)
    process.send_signal(signal.SIGINT)
    _, errors = process.communicate(timeout=120)
    assert process.returncode == 130, errors[-3000:]
    return errors


def _resume_argv(errors: str) -> list[str]:
    """The command the interrupted study printed, run as `python -m ballbeam`."""
    command = errors.rsplit("resume with: ", 1)[1].strip().splitlines()[0]
    argv = shlex.split(command)
    assert argv[0] == "ballbeam"
    return [sys.executable, "-m", "ballbeam", *argv[1:]]


def _complete_trials(output: Path) -> list[Any]:
    """The whole trials of the study in ``output``, read once no tuning runs there."""
    import optuna
    from optuna.trial import TrialState

    study = optuna.load_study(study_name="ballbeam-tune",
                              storage=f"sqlite:///{output / 'study.db'}")
    return study.get_trials(states=(TrialState.COMPLETE,))


def _complete_count_while_running(output: Path) -> int:
    """The same count while the tuning writes: read-only SQL, which neither creates the schema
    nor waits for a write (Optuna's loader would do both, racing the tuning's own set-up)."""
    path = output / "study.db"
    if not path.is_file():
        return 0
    try:
        with contextlib.closing(sqlite3.connect(f"file:{path}?mode=ro", uri=True,
                                                timeout=0.1)) as db:
            (count,) = db.execute("SELECT count(*) FROM trials WHERE state = 'COMPLETE'").fetchone()
    except sqlite3.OperationalError:  # no table yet, or locked just now
        return 0
    return int(count)


def test_an_interrupted_tuning_resumes_with_the_trials_it_kept(tmp_path: Path) -> None:
    """Ctrl-C after two whole trials: exit 130, a line that says how many trials are kept and
    where, and the command that resumes; that command brings the study to --trials, the kept
    trials among them unchanged."""
    spec_path = tmp_path / "tune.toml"
    spec_path.write_text(SMALL_TUNE.replace("parallel = 2", "parallel = 1"))
    output = tmp_path / "out"
    process = subprocess.Popen(
        [*ballbeam_argv("tune", str(spec_path), "--output", str(output), "--workers", "1",
                        "--trials", "4", "--json")],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=tmp_path,
    )
    errors = _interrupt_when(process, lambda: _complete_count_while_running(output) >= 2)
    kept = {trial.number: (trial.params, trial.value) for trial in _complete_trials(output)}
    assert 2 <= len(kept) < 4
    assert (f"tune interrupted: {len(kept)} of 4 trials are saved in "
            f"{(output / 'study.db').absolute()}") in errors
    argv = _resume_argv(errors)
    assert argv[argv.index("--trials") + 1] == "4"
    resumed = subprocess.run([*argv, "--json"], capture_output=True, text=True, timeout=600,
                             check=False, cwd=tmp_path)
    assert resumed.returncode == 0, resumed.stderr[-3000:]
    final = _complete_trials(output)
    assert len(final) == 4
    assert {t.number: (t.params, t.value) for t in final if t.number in kept} == kept
    assert sum(bool(t.user_attrs.get("default")) for t in final) == 1  # the base, once
    report = json.loads(resumed.stdout)
    assert report["trials"] == 4
    assert len(pd.read_parquet(output / "trials.parquet")) == 4
    # Run again with more trials: it tunes on from the four.
    argv[argv.index("--trials") + 1] = "5"
    more = subprocess.run([*argv, "--json"],
                          capture_output=True, text=True, timeout=600, check=False,
                          cwd=tmp_path)
    assert more.returncode == 0, more.stderr[-3000:]
    assert len(_complete_trials(output)) == 5


def test_a_study_of_another_spec_is_not_resumed(tmp_path: Path, local_dask_client: Any) -> None:
    spec_path = tmp_path / "tune.toml"
    spec_path.write_text(SMALL_TUNE.replace("trials = 4", "trials = 1"))
    output = tmp_path / "out"
    run_tune(load_tune_spec(spec_path), output, local_dask_client, progress=False)
    spec_path.write_text(SMALL_TUNE.replace("[3e3, 3e4]", "[3e3, 5e4]"))
    with pytest.raises(ConfigError, match="another tuning"):
        run_tune(load_tune_spec(spec_path), output, local_dask_client, progress=False)
