"""Nothing the CLI writes goes over a file or through a link: logs, recovered logs, reports,
plots, the Foxglove layout and JUnit XML are new files. An existing output (above all the log
a command reads) or a link planted where one will be written is refused with one line and
exit 2, and the file behind it is untouched; the run's own auto-named log is recorded safely
whatever is planted at its name. A missing log directory is made one level deep only.
"""

from __future__ import annotations

import hashlib
import shutil
import subprocess
from pathlib import Path
from typing import Any

import pytest

from ballbeam.config import DEFAULT_BUS_GROUP
from ballbeam.errors import BallbeamError
from ballbeam.logs import recover as recover_module
from ballbeam.logs.reader import read_log
from ballbeam.logs.recorder import Recorder
from ballbeam.logs.recover import recover_log
from ballbeam.runtime import launcher
from ballbeam.runtime.bus import isolated_group

from ..conftest import PAPER, REPO, ballbeam
from .harness import one_error_line, set_args

GOLDEN = REPO / "tests" / "data" / "golden_paper_1s.mcap"
PRECIOUS = b"precious: the only copy\n"
FAST_PLAN = "plan.kind='rate_limited'"


def _digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _refused(result: subprocess.CompletedProcess[str], *needles: str) -> str:
    assert result.returncode == 2, (result.returncode, result.stderr)
    line = one_error_line(result.stderr)
    assert len(result.stderr.strip().splitlines()) == 1, result.stderr
    for needle in needles:
        assert needle in line, line
    return line


@pytest.fixture
def log_copy(tmp_path: Path) -> Path:
    log = tmp_path / "r.mcap"
    shutil.copyfile(GOLDEN, log)
    return log


@pytest.fixture
def precious(tmp_path: Path) -> Path:
    target = tmp_path / "precious.txt"
    target.write_bytes(PRECIOUS)
    return target


# ---- the daemon's log ------------------------------------------------------------------------


def _daemon(log: Path) -> subprocess.CompletedProcess[str]:
    # Its own bus group, and a plant it stops waiting for soon (the old code opened the log,
    # then waited for one).
    overrides = [f"bus.channel='{isolated_group(DEFAULT_BUS_GROUP)}'",
                 "controller.start_timeout_s=1", FAST_PLAN]
    return ballbeam("daemon", str(PAPER), *set_args(overrides), "--log", str(log),
                    timeout_s=120)


@pytest.mark.bus
def test_daemon_refuses_a_log_file_that_exists_and_keeps_it(tmp_path: Path) -> None:
    log = tmp_path / "f.mcap"
    log.write_bytes(PRECIOUS)
    _refused(_daemon(log), str(log), "exists")
    assert log.read_bytes() == PRECIOUS


@pytest.mark.bus
def test_daemon_refuses_a_link_planted_at_its_log(tmp_path: Path, precious: Path) -> None:
    link = tmp_path / "run.mcap"
    link.symlink_to(precious)
    dangling = tmp_path / "dangling.mcap"
    dangling.symlink_to(tmp_path / "created-through-the-link.mcap")
    _refused(_daemon(link), str(link), "symbolic link")
    _refused(_daemon(dangling), str(dangling), "symbolic link")
    assert precious.read_bytes() == PRECIOUS and link.is_symlink()
    assert not (tmp_path / "created-through-the-link.mcap").exists()


def test_recorder_never_writes_through_a_link_planted_after_any_check(
    tmp_path: Path, precious: Path
) -> None:
    """What the daemon's open itself does, whatever was checked before it (a link planted
    between the check and the open)."""
    link = tmp_path / "run.mcap"
    link.symlink_to(precious)
    with pytest.raises(BallbeamError, match="symbolic link"):
        Recorder(link)
    existing = tmp_path / "existing.mcap"
    existing.write_bytes(PRECIOUS)
    with pytest.raises(FileExistsError, match="exists"):
        Recorder(existing)
    assert precious.read_bytes() == PRECIOUS and existing.read_bytes() == PRECIOUS


@pytest.mark.bus
def test_a_run_records_safely_whatever_is_planted_at_its_log_name(
    tmp_path: Path, precious: Path
) -> None:
    """The run's log name stands on the daemon's command line before the daemon records: a
    link planted there as soon as the processes start must not be written through. The log
    directory is missing and one level deep: it is made."""
    log_dir = tmp_path / "logs"
    planted: list[Path] = []

    def plant(processes: dict[str, subprocess.Popen[str]]) -> None:
        argv = [str(item) for item in processes["daemon"].args]  # type: ignore[union-attr]
        name = Path(argv[argv.index("--log") + 1])
        try:
            name.symlink_to(precious)
        except FileExistsError:
            return  # the name is a file already: nothing can be planted
        planted.append(name)

    result = launcher.launch_run(
        str(PAPER),
        ["run.mode='lockstep'", "run.duration_s=0.3", f"run.log_dir='{log_dir}'", FAST_PLAN],
        on_started=plant,
    )
    assert precious.read_bytes() == PRECIOUS
    assert result.daemon_exit == 0
    assert result.log_path.parent == log_dir and not result.log_path.is_symlink()
    assert result.log_path not in planted
    log = read_log(result.log_path)
    assert not log.truncated and len(log.topics["/command"]) > 0


@pytest.mark.bus
def test_a_log_directory_is_made_one_level_deep_only(tmp_path: Path) -> None:
    deep = tmp_path / "some" / "deep" / "new"
    result = ballbeam(
        "run", str(PAPER),
        *set_args(["run.mode='lockstep'", "run.duration_s=0.3", f"run.log_dir='{deep}'",
                   FAST_PLAN]),
        timeout_s=120,
    )
    _refused(result, str(deep), "does not exist")
    assert not (tmp_path / "some").exists()


# ---- replay's outputs --------------------------------------------------------------------------


@pytest.mark.parametrize("option", ["--report", "--plot"])
def test_replay_never_writes_over_the_log_it_reads(
    tmp_path: Path, log_copy: Path, option: str
) -> None:
    before = _digest(log_copy)
    _refused(ballbeam("replay", str(log_copy), option, str(log_copy)), "reads")
    link = tmp_path / "link.out"
    link.symlink_to(log_copy)
    _refused(ballbeam("replay", str(log_copy), option, str(link)), "reads")
    hard = tmp_path / "hard.out"
    hard.hardlink_to(log_copy)  # the same inode under another name
    _refused(ballbeam("replay", str(log_copy), option, str(hard)), "reads")
    assert _digest(log_copy) == before


def test_replay_refuses_an_output_that_exists_or_is_a_link(
    tmp_path: Path, log_copy: Path, precious: Path
) -> None:
    report = tmp_path / "report.html"
    report.write_bytes(PRECIOUS)
    _refused(ballbeam("replay", str(log_copy), "--report", str(report)), str(report), "exists")
    link = tmp_path / "plot.png"
    link.symlink_to(precious)
    _refused(ballbeam("replay", str(log_copy), "--plot", str(link)), str(link), "symbolic link")
    dangling = tmp_path / "dangling.html"
    dangling.symlink_to(tmp_path / "made-through-the-link.html")
    _refused(ballbeam("replay", str(log_copy), "--report", str(dangling)), "symbolic link")
    twice = tmp_path / "twice.html"
    _refused(ballbeam("replay", str(log_copy), "--plot", str(twice), "--report", str(twice)),
             "two outputs")
    assert report.read_bytes() == PRECIOUS and precious.read_bytes() == PRECIOUS
    assert not (tmp_path / "made-through-the-link.html").exists() and not twice.exists()


def test_replay_writes_new_outputs_whole(tmp_path: Path, log_copy: Path) -> None:
    report, plot = tmp_path / "report.html", tmp_path / "plot.png"
    result = ballbeam("replay", str(log_copy), "--report", str(report), "--plot", str(plot))
    assert result.returncode == 0, result.stderr
    assert report.read_text(encoding="utf-8").startswith("<!DOCTYPE html>")
    assert plot.read_bytes().startswith(b"\x89PNG\r\n\x1a\n")
    assert not list(tmp_path.glob(".*.part")), "a temporary file was left behind"


def test_foxglove_layout_is_not_written_through_a_link(tmp_path: Path, log_copy: Path) -> None:
    layout = tmp_path / "ballbeam.foxglove-layout.json"
    layout.symlink_to(tmp_path / "made-through-the-link.json")
    result = ballbeam("replay", str(log_copy), "--foxglove")
    assert result.returncode == 0, result.stderr
    assert not (tmp_path / "made-through-the-link.json").exists() and layout.is_symlink()


def test_simulate_refuses_a_plot_that_exists(tmp_path: Path) -> None:
    plot = tmp_path / "figure.png"
    plot.write_bytes(PRECIOUS)
    _refused(ballbeam("simulate", "--set", FAST_PLAN, "--plot", str(plot)), str(plot), "exists")
    assert plot.read_bytes() == PRECIOUS


def test_regress_refuses_a_junit_file_that_exists_before_running_anything(
    tmp_path: Path,
) -> None:
    junit = tmp_path / "junit.xml"
    junit.write_bytes(PRECIOUS)
    result = ballbeam("regress", str(tmp_path / "no-such-scenario.toml"), "--junit-xml",
                      str(junit))
    _refused(result, str(junit), "exists")
    assert junit.read_bytes() == PRECIOUS


# ---- recover -----------------------------------------------------------------------------------


def test_recover_never_writes_through_a_link_planted_at_its_temporary(
    tmp_path: Path, log_copy: Path, precious: Path
) -> None:
    out = tmp_path / "out.mcap"
    (tmp_path / ".out.mcap.part").symlink_to(precious)  # the name the old code wrote to
    result = ballbeam("recover", str(log_copy), "-o", str(out))
    assert result.returncode == 0, result.stderr
    assert precious.read_bytes() == PRECIOUS
    assert not out.is_symlink() and not read_log(out).truncated


def test_recover_refuses_a_destination_that_exists_or_appears(
    tmp_path: Path, log_copy: Path, precious: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    link = tmp_path / "out.mcap"
    link.symlink_to(precious)
    _refused(ballbeam("recover", str(log_copy), "-o", str(link)), str(link), "symbolic link")
    assert precious.read_bytes() == PRECIOUS and link.is_symlink()
    # One that appears while the log is recovered (after any check) is kept, not replaced.
    late = tmp_path / "late.mcap"
    real_copy = recover_module._copy_intact

    def copy_then_appear(*args: Any) -> Any:
        recovery = real_copy(*args)
        late.write_bytes(PRECIOUS)
        return recovery

    monkeypatch.setattr(recover_module, "_copy_intact", copy_then_appear)
    with pytest.raises(FileExistsError):
        recover_log(log_copy, late)
    assert late.read_bytes() == PRECIOUS
    assert not list(tmp_path.glob(".*.part")), "a temporary file was left behind"


# ---- a study's results directory -----------------------------------------------------------


def test_a_study_rewrites_its_own_plots_but_never_through_a_link(
    tmp_path: Path, precious: Path
) -> None:
    """A sweep run again rewrites its table and plots in its results directory (it resumes
    there by design), each whole; a link planted at one is replaced, its target untouched."""
    pd = pytest.importorskip("pandas")
    from types import SimpleNamespace

    from ballbeam.studies.report import plot_sweep

    table = pd.DataFrame({"tracker.r": [0.1, 0.2, 0.3], "rest_time_s": [1.9, 1.8, 2.0],
                          "error": [None, None, None]})
    spec = SimpleNamespace(keys=["tracker.r"], seeds=None, path=Path("study.toml"))
    plot = tmp_path / "distributions.png"
    plot.symlink_to(precious)
    written = plot_sweep(table, spec, ["rest_time_s"], tmp_path)  # type: ignore[arg-type]
    assert plot in written and not plot.is_symlink()
    assert plot.read_bytes().startswith(b"\x89PNG\r\n\x1a\n")
    assert precious.read_bytes() == PRECIOUS
    assert not list(tmp_path.glob(".*.part")), "a temporary file was left behind"
