"""Hostile inputs (issue 28): TOML nested past the interpreter's stack, wherever TOML is read,
and decompression bombs, wherever a chunk is inflated (replay's reader and ``recover``).

Each answer is one error line and exit 2, never a traceback; a bomb is refused at the size its
chunk states, before it is inflated, and ``recover`` still keeps every intact message before it
(counted independently, with the official mcap library, on the log the bomb was spliced into).
"""

from __future__ import annotations

import contextlib
import io
import json
import tracemalloc
import zipfile
from collections.abc import Callable
from pathlib import Path

import pytest

from ballbeam import cli
from ballbeam.config import MAX_TOML_NESTING, load_config, parse_override
from ballbeam.errors import ConfigError, DecompressionBombError, LogFormatError
from ballbeam.logs.decompression import MAX_CHUNK_BYTES, decompress_chunk
from ballbeam.logs.design_record import decode_design
from ballbeam.logs.reader import read_log

from ..conftest import PAPER, ballbeam
from .harness import one_error_line
from .hostile_inputs import (
    GIB,
    MIB,
    Baseline,
    baseline_of_a_normal_replay,
    chunk_record,
    deep_array_toml,
    deep_table_toml,
    golden_prefix,
    lz4_bomb,
    messages_in_first_chunks,
    run_capped,
    write,
    zstd_rle_frame,
)
from .test_hostile_logs import write_log


def cli_in_process(*argv: str) -> tuple[int, str, str]:
    stdout, stderr = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
        code = cli.main(list(argv))
    return code, stdout.getvalue(), stderr.getvalue()


# ---- deep TOML ----------------------------------------------------------------------------

DEEP = {"arrays": deep_array_toml, "inline tables": deep_table_toml}


# Every command that reads a TOML file, and how it is handed the deep one.
COMMANDS: dict[str, Callable[[Path], list[str]]] = {
    "plan": lambda deep: ["plan", str(deep)],
    "simulate": lambda deep: ["simulate", str(deep)],
    "run": lambda deep: ["run", str(deep)],
    "daemon": lambda deep: ["daemon", str(deep)],
    "emulator": lambda deep: ["emulator", str(deep)],
    "sweep spec": lambda deep: ["sweep", str(deep)],
    "tune spec": lambda deep: ["tune", str(deep)],
}


@pytest.mark.parametrize("shape", list(DEEP))
@pytest.mark.parametrize("command", list(COMMANDS))
def test_deep_toml_is_one_error_line_for_every_command(
    tmp_path: Path, command: str, shape: str
) -> None:
    deep = write(tmp_path / "deep.toml", DEEP[shape]().encode())
    code, _, stderr = cli_in_process(*COMMANDS[command](deep))
    assert code == 2, stderr
    assert one_error_line(stderr) == stderr.strip()
    assert f"nested more than {MAX_TOML_NESTING} deep" in stderr and str(deep) in stderr


@pytest.mark.parametrize("shape", list(DEEP))
def test_a_config_extending_a_deep_one_is_refused(tmp_path: Path, shape: str) -> None:
    write(tmp_path / "deep.toml", DEEP[shape]().encode())
    child = write(tmp_path / "child.toml", b'extends = "deep.toml"\n[run]\nduration_s = 1.0\n')
    with pytest.raises(ConfigError, match="nested more than"):
        load_config(child)


@pytest.mark.parametrize(
    "value", ["[" * 50_000 + "]" * 50_000, "{a = " * 10_000 + "1" + "}" * 10_000],
    ids=["array", "inline table"],
)
def test_a_deep_set_value_is_refused(value: str) -> None:
    with pytest.raises(ConfigError, match="nested more than"):
        parse_override(f"run.duration_s={value}")
    code, _, stderr = cli_in_process("plan", "--set", f"run.duration_s={value}")
    assert code == 2 and one_error_line(stderr) == stderr.strip()


def test_numbers_python_will_not_read_are_refused_too(tmp_path: Path) -> None:
    huge = "1" + "0" * 5000  # past int()'s digit limit: tomllib raises a bare ValueError
    path = write(tmp_path / "huge.toml", f"[run]\nduration_s = {huge}\n".encode())
    with pytest.raises(ConfigError, match="not a usable TOML value"):
        load_config(path)
    with pytest.raises(ConfigError, match="not a usable TOML value"):
        parse_override(f"run.duration_s={huge}")


def test_nesting_up_to_the_bound_still_parses() -> None:
    # An unknown key, so the answer is the validator's, not the nesting bound's.
    value = "[" * (MAX_TOML_NESTING - 2) + "1" + "]" * (MAX_TOML_NESTING - 2)
    with pytest.raises(ConfigError, match="unknown key") as caught:
        load_config(None, [f"run.extra={value}"])
    assert "nested" not in str(caught.value)


def test_a_deep_scenario_fails_its_line_of_the_regression_table(tmp_path: Path) -> None:
    deep = write(tmp_path / "deep.toml", deep_array_toml().encode())
    code, stdout, stderr = cli_in_process("regress", str(deep), "--json")
    assert code == 1 and "Traceback" not in stderr, stderr
    (result,) = json.loads(stdout)["scenarios"]
    assert "nested more than" in result["error"]


def test_the_exact_report_as_a_process(tmp_path: Path) -> None:
    """The audit's command line: ``ballbeam run d.toml`` printed a 3,000-line traceback."""
    deep = write(tmp_path / "d.toml", deep_array_toml().encode())
    result = ballbeam("run", str(deep), timeout_s=120)
    assert result.returncode == 2, result.stderr[-2000:]
    assert one_error_line(result.stderr) == result.stderr.strip()


@pytest.mark.parametrize("flags", [[], ["--verify"], ["--report", "r.html"]],
                         ids=["replay", "verify", "report"])
def test_a_recorded_config_nested_past_the_stack(
    tmp_path: Path, flags: list[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)
    log = write_log(tmp_path / "deep.mcap", config_json="[" * 200_000 + "]" * 200_000)
    code, _, stderr = cli_in_process("replay", str(log), *flags)
    assert code == 2, stderr
    assert one_error_line(stderr) == stderr.strip()


# ---- bounded decompression ----------------------------------------------------------------

BOMBS: dict[str, Callable[[int], tuple[str, bytes]]] = {
    "zstd, size in the frame": lambda n: ("zstd", zstd_rle_frame(n, state_size=True)),
    "zstd, no size in the frame": lambda n: ("zstd", zstd_rle_frame(n, state_size=False)),
    "lz4, size in the frame": lambda n: ("lz4", lz4_bomb(n, state_size=True)),
    "lz4, no size in the frame": lambda n: ("lz4", lz4_bomb(n, state_size=False)),
}


@pytest.mark.parametrize("bomb", list(BOMBS))
def test_a_chunk_yields_exactly_its_stated_size_and_allocates_no_more(bomb: str) -> None:
    stated = 256 << 10
    compression, exact = BOMBS[bomb](stated)
    assert decompress_chunk(compression, exact, stated) == bytes(stated)
    # The same data against a smaller stated size, and a bomb far larger: refused, and the
    # peak of Python-visible allocation stays near the stated size.
    big = 1 * GIB if compression == "zstd" else 64 * MIB  # lz4 tops out near 255:1
    _, bomb_data = BOMBS[bomb](big)
    for data, claimed in ((exact, stated - 1), (bomb_data, stated)):
        tracemalloc.start()
        try:
            with pytest.raises(DecompressionBombError):
                decompress_chunk(compression, data, claimed)
            _, peak = tracemalloc.get_traced_memory()
        finally:
            tracemalloc.stop()
        assert peak < 2 * stated + MIB, (bomb, claimed, peak)


def test_a_chunk_claiming_more_than_the_bound_is_refused_before_inflating() -> None:
    with pytest.raises(DecompressionBombError, match="claims"):
        decompress_chunk("zstd", zstd_rle_frame(GIB, state_size=True), GIB)
    with pytest.raises(DecompressionBombError, match="claims"):
        decompress_chunk("", b"", MAX_CHUNK_BYTES + 1)


@pytest.fixture(scope="module")
def baseline() -> Baseline:
    return baseline_of_a_normal_replay()


KEPT_CHUNKS = 4


def bomb_log(tmp_path: Path, bomb: str) -> Path:
    """The golden log's first chunks, then a 1 GiB (zstd) or 512 MiB (lz4: 2 MiB of it) bomb
    in a chunk that states 1 KiB, then one more chunk (the file was never finished)."""
    compression, data = BOMBS[bomb](GIB if bomb.startswith("zstd") else 512 * MIB)
    return write(
        tmp_path / "bomb.mcap",
        golden_prefix(KEPT_CHUNKS) + chunk_record(compression, data, 1024)
        + chunk_record("zstd", zstd_rle_frame(64, state_size=True), 64),
    )


@pytest.mark.parametrize("bomb", list(BOMBS))
def test_recover_refuses_a_bomb_and_keeps_every_message_before_it(
    tmp_path: Path, bomb: str, baseline: Baseline
) -> None:
    log = bomb_log(tmp_path, bomb)
    out = tmp_path / "out.mcap"
    result = run_capped(["recover", str(log), "-o", str(out)], baseline.cap_bytes, timeout_s=60)
    assert result.returncode == 2, result.stderr[-3000:]
    line = one_error_line(result.stderr)
    assert "inflate" in line or "frame says" in line, line
    assert result.max_rss_bytes <= baseline.rss_peak_bytes + 256 * MIB, result.max_rss_bytes
    # Every message of the chunks before the bomb, counted on the golden log with the mcap
    # library; the recovered file is whole (the library reads its summary).
    from mcap.reader import make_reader

    with out.open("rb") as stream:
        summary = make_reader(stream).get_summary()
    assert summary is not None and summary.statistics is not None
    assert summary.statistics.message_count == messages_in_first_chunks(KEPT_CHUNKS) > 0


@pytest.mark.parametrize("bomb", ["zstd, size in the frame", "lz4, no size in the frame"])
def test_replay_refuses_a_bomb_even_in_the_last_chunk(tmp_path: Path, bomb: str) -> None:
    compression, data = BOMBS[bomb](64 * MIB)
    log = write(tmp_path / "bomb.mcap", golden_prefix(KEPT_CHUNKS) + chunk_record(
        compression, data, 1024
    ))
    with pytest.raises(DecompressionBombError):
        read_log(log)
    code, _, stderr = cli_in_process("replay", str(log))
    assert code == 2 and one_error_line(stderr) == stderr.strip()


def test_the_paper_config_still_loads() -> None:
    assert load_config(PAPER).run.duration_s > 0


def test_a_recorded_design_whose_array_header_claims_terabytes_is_refused() -> None:
    """An .npy header (NEP 1 format, written by hand) claiming 10**12 float64 values over no
    data: NumPy would allocate 8 TB before reading, and fail with MemoryError."""
    header = b"{'descr': '<f8', 'fortran_order': False, 'shape': (1000000000000,), }"
    header += b" " * (-(10 + len(header) + 1) % 64) + b"\n"
    npy = b"\x93NUMPY\x01\x00" + len(header).to_bytes(2, "little") + header
    archive = io.BytesIO()
    with zipfile.ZipFile(archive, "w") as writing:
        writing.writestr("format_version.npy", npy)
    with pytest.raises(LogFormatError, match="claims"):
        decode_design(archive.getvalue(), "hostile.mcap")
