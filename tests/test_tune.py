"""``ballbeam tune`` (issue 14, item 3) on a small space: the base's values are the first
trial, the tuned config is a loadable TOML that extends the base, and the before/after figures
on the held-out set equal the same runs made one by one through ``run_offline``."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from ballbeam.assembly import run_offline
from ballbeam.cli import main
from ballbeam.config import load_config
from ballbeam.errors import ConfigError
from ballbeam.studies.tune import load_tune_spec, run_tune

from .conftest import PAPER

pytest.importorskip("optuna")

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
    assert "extends" in outcome.tuned_path.read_text()
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
