"""A log's integrity (issue 13, item 7): every log we write carries the data section's CRC, so a
chunk duplicated or removed is detected, never replayed as if whole; and a hostile chunk cannot
make replay allocate more than it says (a 4 MB lz4 chunk of a gigabyte of zeros)."""

from __future__ import annotations

import os
import struct
import sys
import zlib
from pathlib import Path

import lz4.frame
import pytest
from mcap.data_stream import RecordBuilder
from mcap.records import Chunk, Header
from mcap.writer import MCAP0_MAGIC

from ballbeam.errors import LogFormatError
from ballbeam.logs.reader import read_log

from ..conftest import ballbeam

CHUNK_OPCODE = 0x06
DATA_END_OPCODE = 0x0F
PEAK_MEMORY_LIMIT_MIB = 256


def records(data: bytes) -> list[tuple[int, int, int]]:
    """(opcode, start, end) of each record after the magic, up to the footer."""
    found = []
    position = len(MCAP0_MAGIC)
    while position + 9 <= len(data):
        opcode = data[position]
        (length,) = struct.unpack_from("<Q", data, position + 1)
        end = position + 9 + length
        found.append((opcode, position, end))
        position = end
        if opcode == 0x02:  # footer
            break
    return found


def test_our_logs_carry_a_correct_data_section_crc(lockstep_log: Path) -> None:
    data = lockstep_log.read_bytes()
    ((_, start, _),) = [r for r in records(data) if r[0] == DATA_END_OPCODE]
    (crc,) = struct.unpack_from("<I", data, start + 9)
    assert crc != 0 and crc == zlib.crc32(data[:start])
    read_log(lockstep_log)  # and the reader checks it without complaint


@pytest.mark.parametrize("damage", ["duplicate", "remove"])
def test_a_duplicated_or_removed_chunk_is_detected(
    lockstep_log: Path, tmp_path: Path, damage: str
) -> None:
    data = lockstep_log.read_bytes()
    chunks = [r for r in records(data) if r[0] == CHUNK_OPCODE]
    assert len(chunks) >= 2
    _, start, end = chunks[len(chunks) // 2]
    piece = data[start:end]
    if damage == "duplicate":
        damaged = data[:end] + piece + data[end:]
    else:
        damaged = data[:start] + data[end:]
    path = tmp_path / f"{damage}.mcap"
    path.write_bytes(damaged)
    with pytest.raises(LogFormatError):
        read_log(path)
    result = ballbeam("replay", str(path), timeout_s=120)
    assert result.returncode == 2 and "Traceback" not in result.stderr, result.stderr


def _record(record: Chunk | Header) -> bytes:
    builder = RecordBuilder()
    record.write(builder)
    data: bytes = builder.end()  # type: ignore[no-untyped-call]
    return data


def zeros_lz4(total_bytes: int) -> bytes:
    """An lz4 frame of ``total_bytes`` zeros, compressed in pieces (little memory here)."""
    compressor = lz4.frame.LZ4FrameCompressor()
    parts = [compressor.begin()]
    block = bytes(16 << 20)
    for _ in range(total_bytes // len(block)):
        parts.append(compressor.compress(block))
    parts.append(compressor.flush())
    return b"".join(parts)


@pytest.mark.parametrize("declared_bytes", [1 << 20, (1 << 30) - 1])
def test_a_decompression_bomb_is_refused_within_the_memory_bound(
    tmp_path: Path, declared_bytes: int
) -> None:
    """A chunk of 1 GiB of zeros (about 4 MB of lz4), declared as 1 MiB (it lies) or as the
    whole gigabyte (beyond what a chunk may be): refused, replay's peak memory bounded."""
    bomb = zeros_lz4(1 << 30)
    chunk = Chunk(
        message_start_time=0, message_end_time=0, uncompressed_size=declared_bytes,
        uncompressed_crc=0, compression="lz4", data=bomb,
    )
    path = tmp_path / "bomb.mcap"
    path.write_bytes(
        MCAP0_MAGIC + _record(Header(profile="ballbeam", library="bomb")) + _record(chunk)
    )
    code, peak_mib, stderr = peak_memory_mib(["-m", "ballbeam", "replay", str(path)])
    assert code == 2, stderr
    assert b"Traceback" not in stderr
    assert peak_mib < PEAK_MEMORY_LIMIT_MIB, f"replay peaked at {peak_mib:.0f} MiB"


def peak_memory_mib(argv: list[str]) -> tuple[int, float, bytes]:
    """Exit code, peak resident memory [MiB] and stderr of a child process."""
    read_end, write_end = os.pipe()
    pid = os.fork()
    if pid == 0:  # pragma: no cover - the child
        os.close(read_end)
        os.dup2(write_end, 2)
        os.execv(sys.executable, [sys.executable, *argv])
    os.close(write_end)
    with os.fdopen(read_end, "rb") as stream:
        stderr = stream.read()
    _, status, usage = os.wait4(pid, 0)
    return os.waitstatus_to_exitcode(status), usage.ru_maxrss / 1024, stderr
