"""Bad invocations: every refused command line exits 2 with one error line, never a traceback.

The command-line fuzzing runs ``plan`` in-process on the rate-limited path, which plans in
microseconds.
"""

from __future__ import annotations

import contextlib
import io
import os
import random
import re
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from mcap.writer import Writer

from ballbeam import cli
from ballbeam.config import Config
from ballbeam.runtime.exit_codes import exit_code

from ..conftest import ballbeam

PLAN = "plan.kind='rate_limited'"


def _bad_invocations(tmp: Path) -> list[tuple[list[str], str, bool]]:
    random_bytes = tmp / "random.mcap"
    random_bytes.write_bytes(random.Random(3).randbytes(4096))
    foreign = tmp / "foreign.mcap"
    with foreign.open("wb") as stream:
        writer = Writer(stream)
        writer.start(profile="ros2", library="test")
        writer.finish()
    not_toml = tmp / "bad.toml"
    not_toml.write_text("[controller\nrate_hz = \n")
    loop = tmp / "loop.toml"
    loop.write_text('extends = "loop.toml"\n')
    missing = str(tmp / "missing.toml")
    fifo = tmp / "pipe"
    os.mkfifo(fifo)  # opening it would wait for a writer forever
    plan = ["plan", "--set", PLAN]
    return [
        ([*plan, "--set", "nosuch.key=1"], "unknown key", False),
        ([*plan, "--set", "controller.rate_hz='fast'"], "controller.rate_hz", False),
        ([*plan, "--set", "controller.rate_hz=1.5"], "controller.rate_hz", False),
        ([*plan, "--set", "tracker.q=[1,-1,0,0]"], "positive semi-definite", False),
        ([*plan, "--set", "tracker.q=[1,0,0]"], "4 diagonal entries", False),
        ([*plan, "--set", "tracker.r=0"], "tracker.r", False),
        ([*plan, "--set", "controller.rate_hz=3000"], "whole number of nanoseconds", False),
        ([*plan, "--set", "controller.rate_hz=400"], "must divide", False),
        ([*plan, "--set", "limits.voltage_v=-5"], "limits.voltage_v", False),
        ([*plan, "--set", "limits.theta_deg=-52"], "limits.theta_deg", False),
        ([*plan, "--set", "run.duration_s=nan"], "run.duration_s", False),
        ([*plan, "--set", "no-equals-sign"], "dotted.key=value", False),
        (["plan", missing], "not found", False),
        (["plan", str(not_toml)], "not valid TOML", False),
        (["plan", str(loop)], "extends", False),
        (["plan", str(tmp)], "directory", False),
        (
            [
                "run",
                "--set",
                PLAN,
                "--set",
                "bus.channel='ff02::1'",
                "--set",
                f"run.log_dir='{tmp}'",
            ],
            "leaves this host",
            False,
        ),
        (["replay", str(tmp / "missing.mcap")], "cannot open log", False),
        (["replay", str(random_bytes)], "not an MCAP file", False),
        (["replay", str(foreign)], "not a ballbeam log", False),
        (["replay", str(tmp)], "directory", False),
        # Found in the load campaign (issue 13): hangs, tracebacks and silent acceptance.
        (["plan", "/dev/zero"], "device, not a file", False),
        (["plan", str(fifo)], "pipe (FIFO), not a file", False),
        (["replay", "/dev/zero"], "device, not a file", False),
        (["replay", str(fifo)], "pipe (FIFO), not a file", False),
        ([*plan, "--set", "model.gravity_m_per_s2=inf"], "model.gravity_m_per_s2", False),
        ([*plan, "--set", "model.beam_length_m=1e-300"], "model.beam_length_m", False),
        ([*plan, "--set", "initial.ball_position_m=0.9"], "off the beam", False),
        ([*plan, "--set", "bus.options={bogus=1}"], "bogus not an option", False),
        (
            [
                "run", "--set", PLAN, "--set", "bus.channel='239.1.2.3'",
                "--set", "bus.allow_off_host=true", "--set", f"run.log_dir='{tmp}'",
            ],
            "bus.isolate_runs",  # refused before any socket is opened: nothing is sent
            False,
        ),
        # argparse: usage, then one "ballbeam ...: error:" line
        (["frobnicate"], "invalid choice", True),
        (["daemon", "--log"], "expected one argument", True),
        (["replay"], "required", True),
        (["regress", "--jobs", "0"], "must be at least 1", True),
        (["plan", "--bogus"], "unrecognized arguments", True),
    ]


def test_bad_invocations_exit_2_with_one_error_line(tmp_path: Path) -> None:
    cases = _bad_invocations(tmp_path)
    with ThreadPoolExecutor(max_workers=4) as pool:
        results = list(pool.map(lambda case: ballbeam(*case[0], timeout_s=60), cases))
    for (argv, needle, from_argparse), result in zip(cases, results, strict=True):
        where = f"ballbeam {' '.join(argv)}"
        assert result.returncode == 2, (where, result.returncode, result.stderr)
        assert "Traceback" not in result.stderr, (where, result.stderr)
        lines = [line for line in result.stderr.splitlines() if line.strip()]
        errors = [line for line in lines if re.match(r"ballbeam( \w+)?: error:", line)]
        assert len(errors) == 1, (where, result.stderr)
        assert needle in errors[0], (where, result.stderr)
        if from_argparse:  # its usage, then its one error line
            assert all(line.startswith(("usage:", " ")) for line in lines[:-1]), (where, lines)
            assert lines[-1] == errors[0]
        else:  # ours: the one line, nothing else
            assert lines == errors and errors[0].startswith("ballbeam: error:"), (where, lines)


def test_set_ups_that_cannot_run_are_refused_before_anything_starts(tmp_path: Path) -> None:
    """One line naming what is wrong, exit 2, and no log left behind. Before: each started
    both processes and ended seconds later in "no /command, ... messages; nothing to
    analyse" (or several lines from both processes) with a log in run.log_dir."""
    logs = tmp_path / "logs"
    run = ["run", "--set", PLAN, "--set", f"run.log_dir='{logs}'"]
    virtual = ["--set", "bus.interface='virtual'"]
    cases = [
        ([*run, *virtual], "in-process bus"),
        (["daemon", "--set", PLAN, "--set", f"run.log_dir='{logs}'", *virtual],
         "in-process bus"),
        (["emulator", "--set", PLAN, *virtual], "in-process bus"),
        ([*run, "--set", "bus.options={fd=false}"], "CAN FD"),
        ([*run, "--set", "run.duration_s=1e-9"], "shorter than one control cycle"),
        # No SocketCAN in this kernel, or (elsewhere) no such interface: before, both
        # processes started, each failed to open it, and the log stayed behind.
        ([*run, "--set", "bus.interface='socketcan'", "--set", "bus.channel='vcan_absent'"],
         "socketcan:vcan_absent"),
    ]
    with ThreadPoolExecutor(max_workers=3) as pool:
        results = list(pool.map(lambda case: ballbeam(*case[0], timeout_s=120), cases))
    for (argv, needle), result in zip(cases, results, strict=True):
        where = f"ballbeam {' '.join(argv)}"
        assert result.returncode == 2, (where, result.returncode, result.stderr)
        lines = [line for line in result.stderr.splitlines() if line.strip()]
        assert len(lines) == 1 and lines[0].startswith("ballbeam: error:"), (where, lines)
        assert needle in lines[0], (where, lines)
    assert not logs.exists() or not any(logs.iterdir()), sorted(logs.iterdir())


def _leaf_keys() -> list[str]:
    keys = []
    for section, field in Config.model_fields.items():
        annotation = field.annotation
        if isinstance(annotation, type) and hasattr(annotation, "model_fields"):
            keys += [f"{section}.{name}" for name in annotation.model_fields]
        else:
            keys.append(section)
    return [key for key in keys if key != "plan.kind"]  # the path stays the rate-limited one


TOML_VALUES = st.one_of(
    st.sampled_from(
        [
            "0",
            "1",
            "-1",
            "1e400",
            "-0.0",
            "nan",
            "inf",
            "-inf",
            "1e-300",
            "true",
            "'text'",
            '"x"',
            "[]",
            "[1,2,3]",
            "[1,0,100,1000]",
            "[0,0,0,0]",
            "{a = 1}",
            "1979-05-27",
            "",
            "[[",
            "'",
            "=",
            "0x10",
            "1_000",
            "[1,'a']",
            "9999999999999999999999",
            "'ff11::1'",
            "'udp_multicast'",
        ]
    ),
    st.integers(-(10**6), 10**6).map(str),
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.text(max_size=12),
)
ASSIGNMENTS = st.one_of(
    st.tuples(st.sampled_from(_leaf_keys()), TOML_VALUES).map(lambda kv: f"{kv[0]}={kv[1]}"),
    st.tuples(st.text(max_size=15), TOML_VALUES).map(lambda kv: f"{kv[0]}={kv[1]}"),
    st.text(max_size=20),
)


@settings(max_examples=120, deadline=None)
@given(st.lists(ASSIGNMENTS, min_size=1, max_size=3), st.booleans())
def test_random_overrides_exit_0_or_2_and_never_raise(assignments: list[str], glued: bool) -> None:
    argv = ["plan", "--set", PLAN]
    for assignment in assignments:
        argv += [f"--set={assignment}"] if glued else ["--set", assignment]
    stdout, stderr = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
        try:
            code = cli.main(argv)
        except SystemExit as exit_:  # argparse refusing the command line
            code = exit_.code  # type: ignore[assignment]
            assert code == 2, stderr.getvalue()
    assert code in (0, 2), (argv, stderr.getvalue())
    if code == 2 and stderr.getvalue().startswith("ballbeam: error:"):
        assert len(stderr.getvalue().strip().splitlines()) == 1, stderr.getvalue()


def test_a_run_that_breaks_its_angle_bound_exits_1(tmp_path: Path) -> None:
    """A start at −52° under a 50° bound: the run completes, but the plant's truth went beyond
    the bound, and ``ballbeam run`` says so (it exited 0 before)."""
    result = ballbeam(
        "run", "--set", "limits.theta_deg=50", "--set", "run.duration_s=0.5",
        "--set", f"run.log_dir='{tmp_path}'", timeout_s=120,
    )
    assert result.returncode == 1, result.stderr
    assert "bound 50.0°" in result.stderr and "exit 1" in result.stderr


@pytest.mark.parametrize(
    ("end_reason", "bound_broken", "code"),
    [
        ("completed", False, 0), ("SIGTERM", False, 0), ("completed", True, 1),
        ("recorder_failed", False, 1), ("plant_lost", False, 3), ("plant_silent", True, 3),
        ("second_writer", False, 4), ("second_writer", True, 4),
    ],
)
def test_exit_codes_follow_the_documented_table(
    end_reason: str, bound_broken: bool, code: int
) -> None:
    assert exit_code(end_reason, bound_broken) == code
