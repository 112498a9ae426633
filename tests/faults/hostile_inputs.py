"""Builders of hostile inputs (deep TOML, decompression bombs, logs that carry them) and the
``ballbeam`` command line run under a memory cap, for the hostile-input and fuzz tests.

Bombs are built by hand from the formats' specifications, not with the libraries under test:
a zstd frame of RLE blocks (RFC 8878: each 4-byte block repeats one byte up to 128 KiB), so
that 1 GiB of output costs 32 KiB of input and no test ever holds the gigabyte.
"""

from __future__ import annotations

import io
import os
import resource
import struct
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

from ..conftest import REPO

GOLDEN = REPO / "tests" / "data" / "golden_paper_1s.mcap"
MAGIC = b"\x89MCAP0\r\n"
OP_CHUNK = 0x06
OP_DATA_END = 0x0F
GIB = 1 << 30
MIB = 1 << 20

# ---- deep TOML ----------------------------------------------------------------------------


def deep_array_toml(depth: int = 100_000) -> str:
    return "a = " + "[" * depth + "]" * depth + "\n"


def deep_table_toml(depth: int = 20_000) -> str:
    return "a = " + "{b = " * depth + "1" + "}" * depth + "\n"


# ---- bombs --------------------------------------------------------------------------------

_ZSTD_MAGIC = b"\x28\xb5\x2f\xfd"
_RLE_BLOCK_BYTES = 128 << 10  # the largest block zstd allows


def zstd_rle_frame(total_bytes: int, *, state_size: bool) -> bytes:
    """A zstd frame that inflates to ``total_bytes`` zero bytes; its header states that size
    (single segment, 8-byte content size) or states nothing (a 128 KiB window)."""
    if state_size:
        header = bytes([0xE0]) + struct.pack("<Q", total_bytes)  # FCS 8 bytes, single segment
    else:
        header = bytes([0x00, (17 - 10) << 3])  # no content size; window log 17
    blocks = []
    left = total_bytes
    while left > 0:
        size = min(left, _RLE_BLOCK_BYTES)
        left -= size
        block_header = (size << 3) | (1 << 1) | (1 if left == 0 else 0)  # RLE, last?
        blocks.append(struct.pack("<I", block_header)[:3] + b"\x00")
    return _ZSTD_MAGIC + header + b"".join(blocks)


def lz4_bomb(total_bytes: int, *, state_size: bool) -> bytes:
    """An lz4 frame of ``total_bytes`` zero bytes (lz4 cannot do better than ~255:1)."""
    import lz4.frame

    compressor = lz4.frame.LZ4FrameCompressor()
    parts = [compressor.begin(source_size=total_bytes if state_size else 0)]
    zeros = bytes(MIB)
    for start in range(0, total_bytes, MIB):
        parts.append(compressor.compress(zeros[: min(MIB, total_bytes - start)]))
    parts.append(compressor.flush())
    return b"".join(parts)


def chunk_record(compression: str, data: bytes, stated_size: int, crc: int = 0) -> bytes:
    """An MCAP chunk record (specification: start and end time, uncompressed size and CRC,
    compression, records) around ``data``."""
    body = (
        struct.pack("<QQQI", 0, 0, stated_size, crc)
        + struct.pack("<I", len(compression)) + compression.encode()
        + struct.pack("<Q", len(data)) + data
    )
    return struct.pack("<BQ", OP_CHUNK, len(body)) + body


def top_level_records(data: bytes) -> list[tuple[int, int, int]]:
    """(opcode, start, end) of each top-level record of an MCAP file, walked by hand."""
    records = []
    pos = len(MAGIC)
    while pos + 9 <= len(data) - len(MAGIC):
        opcode, length = struct.unpack_from("<BQ", data, pos)
        end = pos + 9 + length
        records.append((opcode, pos, end))
        pos = end
    return records


def golden_prefix(chunks_kept: int) -> bytes:
    """The golden log up to (not including) its chunk number ``chunks_kept`` (0-based): its
    header, metadata, attachments and the first ``chunks_kept`` chunks with their indexes."""
    data = GOLDEN.read_bytes()
    starts = [start for opcode, start, _ in top_level_records(data) if opcode == OP_CHUNK]
    return data[: starts[chunks_kept]]


def messages_in_first_chunks(chunks_kept: int) -> int:
    """How many messages the golden log's first ``chunks_kept`` chunks hold, counted with the
    official mcap library (its chunk index, its chunk parser)."""
    from mcap.reader import make_reader
    from mcap.records import Chunk, Message
    from mcap.stream_reader import StreamReader, breakup_chunk

    data = GOLDEN.read_bytes()
    with GOLDEN.open("rb") as stream:
        summary = make_reader(stream).get_summary()
    assert summary is not None
    indexes = sorted(summary.chunk_indexes, key=lambda index: index.chunk_start_offset)
    count = 0
    for index in indexes[:chunks_kept]:
        raw = data[index.chunk_start_offset : index.chunk_start_offset + index.chunk_length]
        records = StreamReader(io.BytesIO(raw), skip_magic=True, emit_chunks=True).records
        chunk = next(records)
        assert isinstance(chunk, Chunk)
        count += sum(isinstance(record, Message) for record in breakup_chunk(chunk))
    return count


# ---- the command line under a memory cap ------------------------------------------------


@dataclass(frozen=True)
class Capped:
    returncode: int
    stdout: str
    stderr: str
    max_rss_bytes: int


def run_capped(args: list[str], address_space_bytes: int, timeout_s: float = 120) -> Capped:
    """``python -m ballbeam ARGS`` with its address space capped (RLIMIT_AS), and the child's
    own peak resident size (from wait4, not the sum over all children)."""

    def cap() -> None:
        resource.setrlimit(resource.RLIMIT_AS, (address_space_bytes, address_space_bytes))

    with tempfile.TemporaryFile() as out, tempfile.TemporaryFile() as err:
        process = subprocess.Popen(
            [sys.executable, "-m", "ballbeam", *args], stdout=out, stderr=err, cwd=REPO,
            preexec_fn=cap, env={**os.environ, "OPENBLAS_NUM_THREADS": "1"},
        )
        try:
            _, status, usage = _wait4(process.pid, timeout_s)
        except TimeoutError:
            process.kill()
            os.waitpid(process.pid, 0)
            raise
        process.returncode = os.waitstatus_to_exitcode(status)
        out.seek(0)
        err.seek(0)
        return Capped(
            process.returncode,
            out.read().decode(errors="replace"),
            err.read().decode(errors="replace"),
            usage.ru_maxrss * 1024,
        )


def _wait4(pid: int, timeout_s: float) -> tuple[int, int, resource.struct_rusage]:
    import time

    deadline = time.monotonic() + timeout_s
    while True:
        waited, status, usage = os.wait4(pid, os.WNOHANG)
        if waited == pid:
            return waited, status, usage
        if time.monotonic() > deadline:
            raise TimeoutError(f"ballbeam (pid {pid}) still running after {timeout_s} s")
        time.sleep(0.02)


@dataclass(frozen=True)
class Baseline:
    """A normal ``ballbeam replay`` of the golden log: its peak virtual size (what the
    interpreter, numpy and its BLAS reserve, plus a normal read) and its peak resident size."""

    vm_peak_bytes: int
    rss_peak_bytes: int

    @property
    def cap_bytes(self) -> int:
        """The address space a hostile input gets: a normal replay's and 256 MiB more (a
        child that needs more dies of MemoryError rather than eating the machine)."""
        return self.vm_peak_bytes + 256 * MIB


def baseline_of_a_normal_replay() -> Baseline:
    probe = (
        "import sys\n"
        "from ballbeam.cli import main\n"
        "code = main(['replay', sys.argv[1], '--json'])\n"
        "status = dict(l.split(':', 1) for l in open('/proc/self/status'))\n"
        "print(*(int(status[k].split()[0]) * 1024 for k in ('VmPeak', 'VmHWM')), "
        "file=sys.stderr)\n"
        "sys.exit(code)\n"
    )
    result = subprocess.run(
        [sys.executable, "-c", probe, str(GOLDEN)], capture_output=True, text=True, cwd=REPO,
        env={**os.environ, "OPENBLAS_NUM_THREADS": "1"}, timeout=120, check=False,
    )
    assert result.returncode == 0, result.stderr
    vm_peak, rss_peak = map(int, result.stderr.strip().splitlines()[-1].split())
    return Baseline(vm_peak, rss_peak)


def write(path: Path, data: bytes) -> Path:
    path.write_bytes(data)
    return path
