"""The package is whole: a wheel installed into a fresh venv runs, records, verifies and
regresses from an empty directory, with nothing from the repository but the wheel."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest

from .conftest import REPO

INSTALL_TIMEOUT_S = 900


def run(argv: list[str], cwd: Path, timeout_s: float = 300) -> subprocess.CompletedProcess[str]:
    env = {key: value for key, value in os.environ.items() if not key.startswith("PYTHON")}
    return subprocess.run(
        argv, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout_s, check=False
    )


@pytest.fixture(scope="module")
def installed(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The wheel built from this checkout, installed into a new venv whose dependencies are
    this environment's (installed from the same pyproject by the README's command; installing
    numpy, scipy and the rest a second time was most of the suite's longest set-up). The
    wheel's own declared dependencies must be met there (``pip check``), and the package
    must come from the wheel, not this environment's editable install (its hook is a .pth
    file, which a directory on the path does not run). Returns the venv's bin directory."""
    work = tmp_path_factory.mktemp("wheel")
    built = run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(work / "dist"),
         str(REPO)],
        cwd=work, timeout_s=INSTALL_TIMEOUT_S,
    )
    assert built.returncode == 0, built.stderr
    wheels = list((work / "dist").glob("ballbeam_hil-*.whl"))
    assert len(wheels) == 1, wheels
    venv = work / "venv"
    created = run([sys.executable, "-m", "venv", str(venv)], cwd=work)
    assert created.returncode == 0, created.stderr
    site_packages = next((venv / "lib").glob("python*/site-packages"))
    (site_packages / "this_environments_dependencies.pth").write_text(
        sysconfig.get_paths()["purelib"] + "\n"
    )
    pip = str(venv / "bin" / "pip")
    install = run([pip, "install", "-q", "--no-deps", str(wheels[0])], cwd=work,
                  timeout_s=INSTALL_TIMEOUT_S)
    assert install.returncode == 0, install.stderr
    checked = run([pip, "check"], cwd=work)
    assert checked.returncode == 0, checked.stdout + checked.stderr
    return venv / "bin"


@pytest.mark.bus
@pytest.mark.slow
def test_the_installed_wheel_runs_verifies_and_regresses_from_an_empty_directory(
    installed: Path, tmp_path: Path
) -> None:
    empty = tmp_path / "elsewhere"
    empty.mkdir()
    ballbeam = str(installed / "ballbeam")
    # The package is imported from the venv, not from this checkout.
    where = run([str(installed / "python"), "-c", "import ballbeam; print(ballbeam.__file__)"],
                cwd=empty)
    assert where.returncode == 0 and str(REPO) not in where.stdout, where.stdout

    ran = run([ballbeam, "run", "--json", "--set", "run.duration_s=0.5"], cwd=empty)
    assert ran.returncode == 0, ran.stderr
    summary = json.loads(ran.stdout)
    assert summary["end_reason"] == "completed" and summary["cycles"] == 500
    log = Path(summary["log_path"])
    assert log.is_file() and (empty / "logs") in log.parents

    verified = run([ballbeam, "replay", str(log), "--verify", "--json", "--foxglove"], cwd=empty)
    assert verified.returncode == 0, verified.stderr
    assert json.loads(verified.stdout)["verify_ok"] is True
    assert (log.parent / "ballbeam.foxglove-layout.json").is_file()  # the layout is package data

    listed = run([ballbeam, "configs"], cwd=empty)
    assert listed.returncode == 0 and "scenarios/noise_heavy" in listed.stdout, listed.stderr

    regressed = run([ballbeam, "regress", "scenarios/noise_heavy", "--json"], cwd=empty)
    assert regressed.returncode == 0, regressed.stdout + regressed.stderr
    report = json.loads(regressed.stdout)
    assert report["passed"] is True, report
    assert [scenario["name"] for scenario in report["scenarios"]] == ["noise_heavy"]
    assert sorted(path.name for path in empty.iterdir()) == ["logs"]  # nothing else written
