"""A cut log is made whole (issue 13, item 5): ``ballbeam recover`` keeps every intact message
of a log cut anywhere, and ``ballbeam run`` recovers its own log when its daemon is killed.

Every intact message: a complete log is cut at seeded random offsets; the messages a recovery
must keep are counted independently, from the complete log's own chunk index (the chunks that
end before the cut), read with the official mcap reader.
"""

from __future__ import annotations

import contextlib
import io
import random
from pathlib import Path
from types import ModuleType

import pytest
import zstandard
from mcap.exceptions import EndOfFile
from mcap.reader import make_reader
from mcap.records import Chunk, Message
from mcap.stream_reader import StreamReader

from ballbeam.logs.recover import recover_log

from ..conftest import ballbeam, import_bench

CUTS = 40
KILLS = 4  # in the suite; bench/recover_soak.py kills 100 runs
MAX_LOST_MS = 50.0


def summary_of(path: Path):  # type: ignore[no-untyped-def]
    with path.open("rb") as stream:
        return make_reader(stream).get_summary()


def messages_per_chunk(log: Path) -> list[tuple[int, int]]:
    """(end offset, messages) of each chunk of a complete log, in file order: the library's
    chunk index for where each chunk ends, its stream reader for the chunks themselves."""
    summary = summary_of(log)
    assert summary is not None
    indexes = sorted(summary.chunk_indexes, key=lambda index: index.chunk_start_offset)
    with log.open("rb") as stream:
        chunks = [r for r in StreamReader(stream, emit_chunks=True).records if isinstance(r, Chunk)]
    assert len(chunks) == len(indexes)
    counted = []
    for index, chunk in zip(indexes, chunks, strict=True):
        records = zstandard.ZstdDecompressor().decompress(
            chunk.data, max_output_size=chunk.uncompressed_size
        )
        messages = 0
        with contextlib.suppress(EndOfFile):  # a chunk's records end without a footer
            for record in StreamReader(io.BytesIO(records), skip_magic=True).records:
                messages += isinstance(record, Message)
        counted.append((index.chunk_start_offset + index.chunk_length, messages))
    return counted


def test_every_intact_message_survives_a_cut_anywhere(lockstep_log: Path, tmp_path: Path) -> None:
    data = lockstep_log.read_bytes()
    chunks = messages_per_chunk(lockstep_log)
    rng = random.Random(13)
    for _ in range(CUTS):
        cut = rng.randrange(len(data) // 20, len(data))
        cut_path = tmp_path / "cut.mcap"
        cut_path.write_bytes(data[:cut])
        intact = sum(messages for end, messages in chunks if end <= cut)
        recovered = tmp_path / "recovered.mcap"
        recovered.unlink(missing_ok=True)
        recovery = recover_log(cut_path, recovered)
        whole = summary_of(recovered)
        assert whole is not None and whole.statistics is not None
        assert recovery.messages == whole.statistics.message_count == intact, cut
        assert recovery.attachments == len(whole.attachment_indexes)


def test_recover_refuses_to_overwrite_and_names_bad_input(
    lockstep_log: Path, tmp_path: Path
) -> None:
    existing = tmp_path / "exists.mcap"
    existing.write_bytes(b"keep me")
    refused = ballbeam("recover", str(lockstep_log), "-o", str(existing))
    assert refused.returncode == 2 and "exists" in refused.stderr
    assert existing.read_bytes() == b"keep me"
    not_mcap = tmp_path / "text.mcap"
    not_mcap.write_text("hello")
    result = ballbeam("recover", str(not_mcap), "-o", str(tmp_path / "out.mcap"))
    assert result.returncode == 2 and "not an MCAP file" in result.stderr
    assert "Traceback" not in result.stderr
    assert not (tmp_path / "out.mcap").exists() and not list(tmp_path.glob(".*.part"))


@pytest.fixture(scope="module")
def soak() -> ModuleType:
    """bench/recover_soak.py: the kill this test repeats a few times, the bench 100 times."""
    return import_bench("recover_soak")


@pytest.mark.realtime  # runs on wall time: a worker beside it starves the recorder's writer
def test_a_run_whose_daemon_is_killed_recovers_its_log(tmp_path: Path, soak: ModuleType) -> None:
    """SIGKILL the daemon of real-time runs at seeded random moments: ``ballbeam run`` makes
    each log whole (a seeking reader opens it) and loses at most about one recorder flush."""
    rng = random.Random(5)
    for attempt in range(KILLS):
        recovered, lost_ms, why = soak.kill_one(tmp_path / f"run{attempt}", rng.uniform(0.2, 2.0))
        assert recovered, why
        assert lost_ms <= MAX_LOST_MS, f"{lost_ms:.1f} ms of log lost"
