"""``ballbeam regress``: table, exit status, JSON and JUnit reports, bad scenario files."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path
from xml.etree import ElementTree

import pytest

from ballbeam.evaluation.regress import evaluate

from .conftest import PAPER, ballbeam


def regress(*args: str) -> subprocess.CompletedProcess[str]:
    return ballbeam("regress", *args)


def test_evaluate_bounds_and_a_missing_value() -> None:
    checks = evaluate(
        {"settle_time_s": {"max": 2.1}, "overshoot_mm": {"min": 0.0, "max": 1.0}},
        {"settle_time_s": None, "overshoot_mm": 0.5},
    )
    verdicts = {(check.metric, check.bound): check.passed for check in checks}
    assert verdicts == {
        ("settle_time_s", "<= 2.1"): False,  # never settled must not pass a max bound
        ("overshoot_mm", ">= 0"): True,
        ("overshoot_mm", "<= 1"): True,
    }


@pytest.mark.bus
def test_regress_reports_pass_and_fail(tmp_path: Path) -> None:
    scenarios = tmp_path / "scenarios"
    scenarios.mkdir()
    common = f'extends = "{PAPER}"\n[run]\nduration_s = 2.5\nlog_dir = "{tmp_path}"\n'
    (scenarios / "good.toml").write_text(common + "[expect]\nsettle_time_s = { max = 2.1 }\n")
    (scenarios / "bad.toml").write_text(common + "[expect]\nsettle_time_s = { max = 0.5 }\n")
    junit = tmp_path / "report.xml"
    completed = regress(str(scenarios), "--json", "--junit-xml", str(junit))
    assert completed.returncode == 1, completed.stderr
    report = json.loads(completed.stdout)
    verdicts = {scenario["name"]: scenario["passed"] for scenario in report["scenarios"]}
    assert verdicts == {"bad": False, "good": True}
    suite = ElementTree.parse(junit).getroot()
    assert suite.get("tests") == "2" and suite.get("failures") == "1"
    failed = [case.get("name") for case in suite if case.find("failure") is not None]
    assert failed == ["bad"]


def test_a_scenario_with_an_unknown_metric_is_refused(tmp_path: Path) -> None:
    (tmp_path / "typo.toml").write_text("[expect]\nsettle_tim_s = { max = 2 }\n")
    completed = regress(str(tmp_path))
    assert completed.returncode == 1
    assert "unknown metric" in completed.stdout
    assert "Traceback" not in completed.stderr + completed.stdout


def test_an_empty_scenario_directory_is_one_clear_error(tmp_path: Path) -> None:
    completed = regress(str(tmp_path))
    assert completed.returncode == 2
    assert "no scenario files" in completed.stderr
