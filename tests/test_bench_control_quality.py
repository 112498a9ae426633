"""bench/control_quality.py measures what it reports: the stratified draw, the matrix it builds,
and one tiny offline run end to end (its figures recomputed from the floor and rest it gives).

Not timed: nothing here bounds how long the bench takes."""

from __future__ import annotations

import json
import math
from pathlib import Path
from types import ModuleType

import pytest

from ballbeam.assembly import minimum_time_s
from ballbeam.config import load_config

from .conftest import PAPER, import_bench


@pytest.fixture(scope="module")
def quality() -> ModuleType:
    return import_bench("control_quality")


class SerialPool:
    @staticmethod
    def map(function, items):  # type: ignore[no-untyped-def]
        return [function(item) for item in items]


def test_the_draw_is_stratified_seeded_and_short_where_it_says(quality: ModuleType) -> None:
    starts = quality.draw_starts(5, 3, str(PAPER), [], 0.0, SerialPool())
    assert [s.kind for s in starts] == ["short", "rolling", "short rolling", "any", "any"]
    for start in starts:
        t_star = minimum_time_s(load_config(PAPER, start.overrides()))
        assert start.t_star_s == t_star  # the run's length and rest/T* use the design's T*
        if "short" in start.kind:
            assert t_star < quality.SHORT_T_STAR_S
        speed = abs(start.velocity_m_s)
        if "rolling" in start.kind:
            assert 0.05 <= speed <= 0.15
        else:
            assert speed == 0.0
        assert abs(start.theta_deg) <= 52.0 and abs(start.position_m) <= 0.2
    assert quality.draw_starts(5, 3, str(PAPER), [], 0.0, SerialPool()) == starts
    assert quality.draw_starts(5, 4, str(PAPER), [], 0.0, SerialPool()) != starts


def test_the_matrix_covers_the_issues_ranges(quality: ModuleType) -> None:
    sets = quality.plant_sets()
    values = {
        family: sorted(float(n.split(":")[1]) for n in sets if n.startswith(family + ":"))
        for family in ("ball_gain", "motor_gain", "deadzone", "nonlinear")
    }
    for family, count, ends in (
        ("ball_gain", 5, (0.7, 1.3)), ("motor_gain", 5, (0.8, 1.2)), ("deadzone", 4, (0.0, 0.4))
    ):
        assert len(values[family]) >= count, family  # not only the ends
        assert (values[family][0], values[family][-1]) == ends
    assert values["nonlinear"] == [0.9, 1.0, 1.1]
    assert "noise_5x" in sets
    paper = quality.Start("paper", -52.0, 0.195, 0.0, 1.746)
    drawn = [quality.Start("any", 10.0, 0.1 * i, 0.0, 1.0 + i) for i in range(1, 5)]
    chosen = {"nominal": [], "deadzone:0.4": ["plant.deadzone_v=0.4"]}
    cases = quality.build_cases(
        [paper, *drawn], chosen, ["tracker.r=0.1"], 5, 3, 2, [0.0], {0.0: []}
    )
    nominal = [c for c in cases if c.set_name == "nominal"]
    assert len(nominal) == 4 * 5  # every drawn start, every noise seed
    other = [c for c in cases if c.set_name != "nominal"]
    assert len(other) == 3 * 2 and other[0].start == paper
    for case in cases:
        duration = [o for o in case.overrides if o.startswith("run.duration_s=")]
        duration_s = float(duration[0].split("=")[1])
        assert duration_s == pytest.approx(case.start.t_star_s + 8.0, abs=1e-3)
        assert case.overrides[0] == "tracker.r=0.1"


def test_one_tiny_run_end_to_end(
    quality: ModuleType, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "quality.json"
    code = quality.main([
        "--only", "deadzone:0.0", "--starts", "1", "--seeds", "1", "--plant-starts", "1",
        "--processes", "1", "--json", str(out),
    ])
    assert code == 0
    report = json.loads(out.read_text())
    (run,) = report["runs"]
    assert run["set"] == "deadzone:0.0" and run["start_index"] == -1  # the paper's start
    assert run["floor_s"] == pytest.approx(1.746, abs=1e-9)  # no dead zone: the README's T*
    assert run["rest_floor"] == pytest.approx(run["rest_s"] / run["floor_s"])
    assert run["relapse_s"] == pytest.approx(run["rest_s"] - run["first_entry_s"])
    assert 0.0 <= run["relapse_s"] < math.inf
    assert run["theta_deg"] > 50.0  # the plan rides the limit arcs
    summary = report["summary"]["deadzone:0.0"]
    assert summary["runs"] == 1 and summary["rest_median"] == run["rest_floor"]
    printed = capsys.readouterr().out
    assert "med≤1.03" in printed and "≤50ms" in printed
    assert "ballbeam simulate" in printed and "--set 'plant.deadzone_v=0.0'" in printed
    assert ("PASS" in printed) == (summary["failed"] == [])


@pytest.mark.parametrize(
    "argv",
    [["--target", "0.3"], ["--set", "plant.deadzone_v=-1"], ["--only", "nosuch"], ["--seeds", "0"]],
)
def test_bad_input_is_one_line_and_exit_2(
    quality: ModuleType, argv: list[str], capsys: pytest.CaptureFixture[str]
) -> None:
    assert quality.main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("control_quality: ") and err.count("\n") == 1
