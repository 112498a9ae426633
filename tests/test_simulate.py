"""The offline closed loop on the paper's set-up: the issue's figures."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from numpy.testing import assert_array_equal

from ballbeam.assembly import make_plan, run_offline
from ballbeam.cli import main
from ballbeam.config import load_config
from ballbeam.errors import ConfigError

from .conftest import CONFIGS

PATHS = sorted((CONFIGS / "paths").glob("*.toml"))


@pytest.mark.parametrize("path", PATHS, ids=[path.stem for path in PATHS])
def test_every_paper_path_keeps_the_servo_within_52_degrees(path: Path) -> None:
    result = run_offline(load_config(path))
    assert result.metrics.theta_violation_s == 0.0
    assert result.metrics.max_abs_theta_deg <= 52.0 + 1e-9
    assert result.metrics.max_abs_u_v <= 5.0
    assert result.metrics.settle_time_s is not None


def test_time_optimal_path_settles_within_2_1_s_with_all_nonlinearities_on() -> None:
    config = load_config(CONFIGS / "paper.toml")
    assert config.plant.deadzone_v > 0 and config.plant.position_noise_m > 0
    metrics = run_offline(config).metrics
    assert metrics.settle_time_s is not None and metrics.settle_time_s <= 2.1


def test_plan_json_prints_the_bang_bang_duration(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["plan", str(CONFIGS / "paths" / "bang_bang.toml"), "--json"]) == 0
    payload = json.loads(capsys.readouterr().out)
    # Paper eq. 17: T = 1.4447 s; the constants of docs/design.md §2 give 2·sqrt(x0/(|γ|·θmax)).
    gamma = 5 * 9.81 / (7 * 17)
    assert payload["duration_s"] == pytest.approx(2 * math.sqrt(0.195 / (gamma * math.radians(52))))
    assert f"{payload['duration_s']:.3f}" == "1.444"


def test_simulate_json_and_plot(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    plot = tmp_path / "run.png"
    assert main(["simulate", "--set", "run.duration_s=2.5", "--json", "--plot", str(plot)]) == 0
    payload = json.loads(capsys.readouterr().out)
    for key in (
        "settle_time_s",
        "overshoot_mm",
        "max_abs_theta_deg",
        "theta_violation_s",
        "max_abs_u_v",
        "tracking_rms_mm",
    ):
        assert key in payload
    assert plot.stat().st_size > 10_000


def test_time_optimal_plan_is_shorter_than_any_rate_limited_one_at_its_own_voltage() -> None:
    """Sanity between planners: the full model under 5 V cannot beat the jerk-limited ideal
    with slope 5/β, and the 4.5 V plan is longer than the 5 V one."""
    full = make_plan(load_config(None, ["plan.voltage_margin_v=0", "plan.theta_margin_deg=0"]))
    ideal = make_plan(
        load_config(None, ["plan.kind=rate_limited", f"plan.servo_rate_limit_rad_s={5 / 0.5369}"])
    )
    margin = make_plan(load_config(None))
    assert ideal.duration_s < full.duration_s < margin.duration_s


def test_a_fixed_target_is_reached_as_from_the_shifted_start() -> None:
    """The linear model is the same under a shift of x: bringing the ball from 0.195 m to
    0.05 m is bringing it from 0.145 m to 0 (the sensors' quantisation aside)."""
    to_target = run_offline(load_config(None, ["task.target_m=0.05"]))
    shifted = run_offline(load_config(None, ["initial.ball_position_m=0.145"]))
    rest_s, shifted_rest_s = to_target.metrics.rest_time_s, shifted.metrics.rest_time_s
    assert rest_s is not None and shifted_rest_s is not None
    assert abs(rest_s - shifted_rest_s) <= 0.005
    assert to_target.metrics.rest_ratio == pytest.approx(shifted.metrics.rest_ratio, abs=0.005)
    trace = to_target.trace
    # Rest is judged from the target, from truth: |x − 0.05| <= 0.5 mm and |θ| <= 0.5°.
    rest_from = trace.time_s >= rest_s
    assert np.all(np.abs(trace.true_states[rest_from, 3] - 0.05) <= 5e-4)
    assert np.all(np.abs(trace.true_states[rest_from, 0]) <= math.radians(0.5))
    before = int(np.flatnonzero(rest_from)[0]) - 1  # the sample before rest is outside
    assert (abs(trace.true_states[before, 3] - 0.05) > 5e-4
            or abs(trace.true_states[before, 0]) > math.radians(0.5))
    # The recorded reference and estimate are in x, not from the target.
    assert trace.reference_states[-1, 3] == 0.05
    assert trace.reference_states[0, 3] == pytest.approx(0.195)
    assert trace.estimates[-1, 3] == pytest.approx(0.05, abs=1e-3)
    assert to_target.design.target_m == 0.05


def test_a_target_below_zero_is_reached_too() -> None:
    run = run_offline(load_config(None, ["task.target_m=-0.1", "run.duration_s=4"]))
    assert run.metrics.rest_time_s is not None
    assert abs(run.trace.true_states[-1, 3] + 0.1) <= 5e-4
    assert run.metrics.max_abs_theta_deg <= 52.0


@pytest.mark.parametrize(
    "task",
    ["task.setpoints=[[0.0, 0.0], [4.0, -0.1]]", "task.square={amplitude_m=0.05, period_s=4}",
     "task.sine={amplitude_m=0.04, period_s=10}"],
)
def test_changing_targets_need_the_replanning_controller(
    task: str, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(ConfigError, match="re-planning controller"):
        run_offline(load_config(None, [task]))
    assert main(["simulate", "--set", task]) == 2
    error = capsys.readouterr().err
    assert "re-planning controller" in error and error.count("\n") == 1


def test_an_offline_tap_jumps_the_balls_velocity_at_its_time() -> None:
    plain = run_offline(load_config(None, ["run.duration_s=3.5"]))
    tapped = run_offline(load_config(None, ["run.duration_s=3.5",
                                            "plant.disturbances=[[3.0, 0.05]]"]))
    difference = tapped.trace.true_states - plain.trace.true_states
    # Nothing differs before the tap; the state at 3.0 s (cycle 3000) has it and only it.
    assert not np.any(difference[:3000])
    assert_array_equal(difference[3000], [0.0, 0.0, 0.05, 0.0])
    # The rolling ball moves 0.05 m/s × 1 ms further in the next period.
    assert difference[3001, 3] == pytest.approx(0.05e-3, rel=1e-9)
    assert tapped.metrics.rest_time_s is None or tapped.metrics.rest_time_s > 3.0
