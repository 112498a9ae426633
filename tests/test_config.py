"""The config loader: paper values, extends, overrides, and one clear error for bad input."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from ballbeam.config import Config, ModelSection, load_config, parse_override
from ballbeam.core.model import PhysicalConstants
from ballbeam.errors import ConfigError
from ballbeam.plant_assembly import physical_constants

from .conftest import CONFIGS


def test_paper_config_holds_the_papers_setup(paper_config_path: Path) -> None:
    config = load_config(paper_config_path)
    assert config.initial.theta_deg == -52.0
    assert config.initial.ball_position_m == 0.195
    assert config.limits.voltage_v == 5.0
    assert config.limits.theta_deg == 52.0
    constants = physical_constants(config)
    # α = km·kg/(Rm·Jm·kg²), β = km·kg, γ = −5 g r / (7 L), computed here from the paper's table.
    assert constants.alpha == pytest.approx(0.00767 * 70 / (2.6 * 3.87e-7 * 70**2), rel=1e-12)
    assert constants.alpha == pytest.approx(108.90, abs=0.01)
    assert constants.beta == pytest.approx(0.5369, rel=1e-12)
    assert constants.gamma == pytest.approx(-5 * 9.81 / (7 * 17), rel=1e-9)
    # The paper's 5 V slope: 5/β.
    assert constants.slew_rate_rad_s(5.0) == pytest.approx(9.3127, abs=1e-4)


def test_model_defaults_are_the_physical_constants() -> None:
    """The paper's constants have one home, ``PhysicalConstants``; the config only reads them."""
    assert ModelSection.model_fields.keys() == {
        field.name for field in dataclasses.fields(PhysicalConstants)
    }
    assert physical_constants(load_config(None)) == PhysicalConstants()


def test_defaults_equal_the_paper_file(paper_config_path: Path) -> None:
    from_file = load_config(paper_config_path)
    defaults = load_config(None)
    assert from_file.model == defaults.model
    assert from_file.initial == defaults.initial
    assert from_file.limits == defaults.limits


@pytest.mark.parametrize("path", sorted(CONFIGS.glob("paths/*.toml")))
def test_path_configs_load(path: Path) -> None:
    config = load_config(path)
    assert config.initial.ball_position_m == 0.195


def test_extends_merges_and_overrides(tmp_path: Path) -> None:
    (tmp_path / "base.toml").write_text("[plan]\nkind = 'bang_bang'\n[run]\nduration_s = 3.0\n")
    (tmp_path / "child.toml").write_text("extends = 'base.toml'\n[run]\nduration_s = 5.0\n")
    config = load_config(tmp_path / "child.toml")
    assert config.plan.kind == "bang_bang"
    assert config.run.duration_s == 5.0


def test_overrides_are_toml_values_validated_like_the_file() -> None:
    config = load_config(
        None, ["plan.kind=rate_limited", "tracker.q=[1, 2, 3, 4]", "run.duration_s=2"]
    )
    assert config.plan.kind == "rate_limited"
    assert config.tracker.q == (1.0, 2.0, 3.0, 4.0)
    assert config.run.duration_s == 2.0
    assert parse_override("a.b.c = 'x'") == {"a": {"b": {"c": "x"}}}


@pytest.mark.parametrize(
    ("overrides", "fragment"),
    [
        (["plan.kindd=bang_bang"], "unknown key 'plan.kindd'"),
        (["nosuch.key=1"], "unknown key 'nosuch'"),
        (["plan.kind=zigzag"], "'plan.kind'"),
        (["limits.voltage_v=-5"], "'limits.voltage_v'"),
        (["limits.theta_deg=-52"], "'limits.theta_deg'"),
        (["tracker.r=0"], "'tracker.r'"),
        (["tracker.q=[1, -2, 3, 4]"], "positive semi-definite"),
        (["tracker.q=[1, 2]"], "'tracker.q'"),
        (["controller.rate_hz=3000"], "controller.rate_hz"),
        (["controller.rate_hz=300"], "whole number of nanoseconds"),
        (["run.duration_s=abc"], "'run.duration_s'"),
        (["initial.theta_deg=70"], "hard stops"),
        (["plan.voltage_margin_v=5"], "leaves no voltage"),
        (["noequals"], "dotted.key=value"),
        (["=3"], "dotted.key=value"),
        (["expect.settle_time_s={ below = 2 }"], "expect.settle_time_s"),
    ],
)
def test_bad_values_name_the_key(overrides: list[str], fragment: str) -> None:
    with pytest.raises(ConfigError, match=None) as caught:
        load_config(None, overrides)
    assert fragment in str(caught.value)


def test_missing_file_and_bad_toml(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="not found"):
        load_config(tmp_path / "absent.toml")
    bad = tmp_path / "bad.toml"
    bad.write_text("[plan\nkind=")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_config(bad)
    with pytest.raises(ConfigError, match="directory"):
        load_config(tmp_path)


def test_extends_cycle_is_refused(tmp_path: Path) -> None:
    (tmp_path / "a.toml").write_text("extends = 'b.toml'\n")
    (tmp_path / "b.toml").write_text("extends = 'a.toml'\n")
    with pytest.raises(ConfigError, match="extends"):
        load_config(tmp_path / "a.toml")


def test_config_is_immutable() -> None:
    config = load_config(None)
    with pytest.raises(Exception):  # noqa: B017 - pydantic's frozen error type is internal
        config.run.duration_s = 1.0  # type: ignore[misc]


_toml_scalars = st.one_of(
    st.integers(-(10**6), 10**6).map(str),
    st.floats(allow_nan=False, allow_infinity=False, width=32).map(repr),
    st.text(alphabet="abcxyz_", max_size=6).map(lambda text: f"'{text}'"),
    st.just("true"),
    st.just("[1, 2]"),
)
_keys = st.sampled_from(
    [
        "plan.kind",
        "plan.step_s",
        "tracker.r",
        "tracker.q",
        "run.duration_s",
        "plant.seed",
        "controller.rate_hz",
        "limits.voltage_v",
        "bus.port",
        "initial.theta_deg",
        "x.y",
        "plan",
    ]
)


@settings(max_examples=300, deadline=None)
@given(key=_keys, value=_toml_scalars)
def test_fuzzed_overrides_either_load_or_raise_config_error(key: str, value: str) -> None:
    try:
        config = load_config(None, [f"{key}={value}"])
    except ConfigError as error:
        assert str(error)
    else:
        assert isinstance(config, Config)
        assert math.isfinite(config.run.duration_s)


@pytest.mark.parametrize(
    ("override", "fragment"),
    [
        ("tracker.rest_theta_near_deg=5", "rest_theta_near_deg must be below"),
        ("tracker.rest_position_far_m=0.0002", "rest_position_near_m must be below"),
    ],
)
def test_rest_bands_must_be_ordered(override: str, fragment: str) -> None:
    with pytest.raises(ConfigError, match=fragment):
        load_config(None, [override])


def test_a_recorded_null_realtime_priority_reads_as_normal_scheduling() -> None:
    """Logs recorded before SCHED_FIFO became the default carry null (then: normal
    scheduling); 0 means that now, so their configs stay usable for replay --verify."""
    from ballbeam.config import config_from_mapping, load_config

    data = load_config(None, []).model_dump(mode="json")
    data["controller"]["realtime_priority"] = None
    data["plant"]["realtime_priority"] = None
    config = config_from_mapping(data, "old log")
    assert config.controller.realtime_priority == 0 and config.plant.realtime_priority == 0


# -- [task] and [plant] disturbances ---------------------------------------------------------


def test_the_default_task_is_the_papers() -> None:
    task = load_config(None).task
    assert (task.target_m, task.setpoints, task.square, task.sine) == (0.0, None, None, None)
    assert task.kind == "fixed"
    assert load_config(None).plant.disturbances == ()


def test_every_task_form_is_set_from_the_command_line() -> None:
    config = load_config(None, ["task.setpoints=[[0.0, 0.0], [4.0, -0.1]]"])
    assert config.task.setpoints == ((0.0, 0.0), (4.0, -0.1))
    assert config.task.kind == "steps"
    # Dotted keys build the nested table one key at a time, or an inline table at once.
    config = load_config(None, ["task.square.amplitude_m=0.05", "task.square.period_s=4"])
    assert config.task.square is not None
    assert (config.task.square.amplitude_m, config.task.square.period_s) == (0.05, 4.0)
    assert config.task.square.offset_m == 0.0 and config.task.kind == "steps"
    config = load_config(None, ["task.sine={amplitude_m=0.04, period_s=10, offset_m=-0.02}"])
    assert config.task.sine is not None and config.task.sine.offset_m == -0.02
    assert config.task.kind == "sine"
    assert load_config(None, ["task.target_m=-0.15"]).task.target_m == -0.15
    config = load_config(None, ["plant.disturbances=[[1.0, 0.1], [2.5, -0.2]]"])
    assert config.plant.disturbances == ((1.0, 0.1), (2.5, -0.2))


def test_a_file_task_takes_command_line_keys_into_its_table(tmp_path: Path) -> None:
    path = tmp_path / "square.toml"
    path.write_text("[task.square]\namplitude_m = 0.05\nperiod_s = 4.0\n"
                    "[plant]\ndisturbances = [[1.5, 0.05]]\n")
    config = load_config(path, ["task.square.period_s=8"])
    assert config.task.square is not None
    assert (config.task.square.amplitude_m, config.task.square.period_s) == (0.05, 8.0)
    assert config.plant.disturbances == ((1.5, 0.05),)


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (["task.target_m=0.1", "task.sine={amplitude_m=0.04, period_s=10}"],
         "not target_m and sine"),
        (["task.setpoints=[[0.0, 0.0]]", "task.square={amplitude_m=0.04, period_s=10}"],
         "not setpoints and square"),
        (["task.target_m=0.25"], "task.target_m"),
        (["task.setpoints=[[0.5, 0.1]]"], "first setpoint must be at time 0"),
        (["task.setpoints=[[0.0, 0.1], [2.0, 0.0], [2.0, 0.1]]"], "must ascend"),
        (["task.setpoints=[[0.0, 0.1], [2.0, -0.21]]"], "beyond ±0.2 m"),
        (["task.setpoints=[[0.0, nan]]"], "finite"),
        (["task.setpoints=[]"], "task.setpoints"),
        (["task.setpoints=[[0.0, 0.1, 3.0]]"], "task.setpoints"),
        (["task.square.amplitude_m=0.05"], "task.square.period_s"),
        (["task.square={amplitude_m=0.05, period_s=0.05}"], "task.square.period_s"),
        (["task.square={amplitude_m=0.15, period_s=4, offset_m=0.1}"], "goes beyond ±0.2 m"),
        (["task.sine={amplitude_m=0.15, period_s=10, offset_m=-0.1}"], "goes beyond ±0.2 m"),
        (["task.sine={amplitude_m=0.04, period_s=1e6}"], "task.sine.period_s"),
        (["task.sine={amplitude_m=0.04, period_s=10, phase=1}"], "unknown key"),
        (["plant.disturbances=[[6.0, 0.1]]"], "not within the run"),
        (["plant.disturbances=[[0.0, 0.1]]"], "after the start"),
        (["plant.disturbances=[[1.0, 1.5]]"], "within ±1 m/s"),
        (["plant.disturbances=[[1.0, 0.1], [0.5, 0.1]]"], "must ascend"),
        (["plant.disturbances=[[1.0]]"], "plant.disturbances"),
    ],
)
def test_bad_tasks_and_taps_are_refused_in_one_line(overrides: list[str], message: str) -> None:
    with pytest.raises(ConfigError) as caught:
        load_config(None, overrides)
    assert message in str(caught.value)
    assert "\n" not in str(caught.value)


def test_schedules_and_taps_are_bounded_in_count() -> None:
    many = ", ".join(f"[{k * 0.1:.1f}, 0.0]" for k in range(10_001))
    with pytest.raises(ConfigError, match=r"task\.setpoints"):
        load_config(None, [f"task.setpoints=[{many}]"])
    taps = ", ".join(f"[{(k + 1) * 1e-3:.3f}, 0.01]" for k in range(1_001))
    with pytest.raises(ConfigError, match=r"plant\.disturbances"):
        load_config(None, ["run.duration_s=10", f"plant.disturbances=[{taps}]"])
    ok = ", ".join(f"[{(k + 1) * 1e-3:.3f}, 0.01]" for k in range(1_000))
    assert len(load_config(None, [f"plant.disturbances=[{ok}]"]).plant.disturbances) == 1000


# Every size a config can ask for, each just past what a run can hold (config.py's MAX_*):
# (overrides, the key the refusal names).
_TOO_LARGE = [
    (["tracker.horizon_s=3600"], "tracker.horizon_s"),
    (  # 30 s is a fine horizon at 1 kHz, but 600,000 synthesis steps at 20 kHz
        ["controller.rate_hz=20000", "plant.sensor_rate_hz=20000", "tracker.horizon_s=30"],
        "tracker.horizon_s",
    ),
    (["plan.step_s=1e-6"], "plan.step_s"),
    (["run.duration_s=86400"], "run.duration_s"),
    (["plant.sensor_rate_hz=20000", "run.duration_s=600"], "run.duration_s"),
    (["plant.physics_substeps=1000"], "plant.physics_substeps"),
    (["plant.sensor_rate_hz=20000", "plant.physics_substeps=20"], "plant.physics_substeps"),
    ([f"observer.noise_levels={[float(level) for level in range(1, 18)]}"],
     "observer.noise_levels"),
    (["controller.sensor_timeout_periods=10001"], "controller.sensor_timeout_periods"),
    (["controller.sensor_timeout_alive_periods=10001"],
     "controller.sensor_timeout_alive_periods"),
    (["controller.lookahead_periods=21"], "controller.lookahead_periods"),
    (["controller.lateness_probe_s=11"], "controller.lateness_probe_s"),
    (["controller.guard_lateness_hold_s=61"], "controller.guard_lateness_hold_s"),
    (["controller.start_timeout_s=3601"], "controller.start_timeout_s"),
    (["controller.plant_lost_s=3601"], "controller.plant_lost_s"),
    (["controller.lockstep_timeout_s=3601"], "controller.lockstep_timeout_s"),
    (["tracker.rest_firm_s=61"], "tracker.rest_firm_s"),
    (["tracker.rest_blend_s=11"], "tracker.rest_blend_s"),
    (["tracker.rest_catch_s=11"], "tracker.rest_catch_s"),
    (["observer.noise_time_constant_s=61"], "observer.noise_time_constant_s"),
    (["plant.watchdog_ms=10001"], "plant.watchdog_ms"),
    (["plant.lockstep_resend_ms=10001"], "plant.lockstep_resend_ms"),
    (["run.lockstep_poll_us=100001"], "run.lockstep_poll_us"),
]


@pytest.mark.parametrize(("overrides", "key"), _TOO_LARGE)
def test_every_size_is_bounded_by_what_a_run_can_hold(
    overrides: list[str], key: str, monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    """Refused while the config is validated, naming the key: nothing is planned or
    synthesised (before: a 3600 s horizon took 2.6 GB and 54 s to synthesise)."""
    import ballbeam.assembly
    from ballbeam import cli

    with pytest.raises(ConfigError) as caught:
        load_config(None, overrides)
    assert key in str(caught.value)

    def no_solve(*_args: object, **_kwargs: object) -> None:
        raise AssertionError("a solve started before the config was refused")

    for name in ("make_plan", "controller_design", "run_offline"):
        monkeypatch.setattr(ballbeam.assembly, name, no_solve)
    argv = ["simulate"] + [part for override in overrides for part in ("--set", override)]
    assert cli.main(argv) == 2
    error = capsys.readouterr().err
    assert error.count("\n") == 1 and key in error


@pytest.mark.parametrize(
    "overrides",
    [
        ["tracker.horizon_s=60"],  # 60,000 steps at 1 kHz
        ["controller.rate_hz=20000", "plant.sensor_rate_hz=20000", "tracker.horizon_s=26"],
        ["plan.step_s=5e-5"],
        ["run.duration_s=4000"],  # 4,000,000 samples
        ["plant.physics_substeps=200"],
        ["plant.sensor_rate_hz=20000", "plant.physics_substeps=10"],
        ["plant.sensor_rate_hz=2000", "plant.physics_substeps=20"],
        [f"observer.noise_levels={[float(level) for level in range(1, 17)]}"],
        ["run.duration_s=0.001"],  # one control cycle
    ],
)
def test_sizes_at_their_bounds_are_accepted(overrides: list[str]) -> None:
    load_config(None, overrides)


@pytest.mark.parametrize(
    ("overrides", "fragment"),
    [
        (["run.duration_s=1e-9"], "run.duration_s = 1e-09 is shorter than one control cycle"),
        (["run.duration_s=0.0004"], "shorter than one control cycle"),
        (["plant.physics_substeps=30"], "whole number of nanoseconds"),
        (["plant.sensor_rate_hz=3000", "controller.rate_hz=1000"],
         "whole number of nanoseconds"),
    ],
)
def test_set_ups_that_cannot_run_are_refused(overrides: list[str], fragment: str) -> None:
    """A run with no control cycle ended after seconds of start-up with an empty log; a
    physics step that is no whole number of nanoseconds drifts from the daemon's period."""
    with pytest.raises(ConfigError) as caught:
        load_config(None, overrides)
    assert fragment in str(caught.value)


@pytest.mark.parametrize(
    ("overrides", "refused"),
    [
        (["bus.options={fd=false}"], True),  # udp_multicast authenticates by default
        (["bus.options={fd=false}", "bus.authenticate=true"], True),
        # opened for CAN FD (runtime/bus.py; a classic interface is refused there, by its MTU)
        (["bus.interface='socketcan'", "bus.authenticate=true"], False),
        (["bus.interface='socketcan'", "bus.authenticate=true", "bus.options={fd=false}"], True),
        (["bus.options={fd=false}", "bus.authenticate=false"], False),
        (["bus.interface='socketcan'", "bus.authenticate=true", "bus.options={fd=true}"], False),
        (["bus.interface='socketcan'"], False),  # classic 8-byte E2E frames
        (["bus.interface='virtual'"], False),  # carries any frame (in-process tests)
    ],
)
def test_authenticated_frames_need_a_can_fd_bus(overrides: list[str], refused: bool) -> None:
    """Authenticated frames are 24 bytes, 64 with the look-ahead (protocol/secoc.py): a
    classic CAN bus cannot carry them (before: ~13 s, then "nothing to analyse")."""
    if not refused:
        load_config(None, overrides)
        return
    with pytest.raises(ConfigError) as caught:
        load_config(None, overrides)
    assert "bus.options.fd" in str(caught.value) and "CAN FD" in str(caught.value)
