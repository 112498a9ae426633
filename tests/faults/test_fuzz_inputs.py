"""A standing fuzz of everything a user hands the bench (issue 28): generated TOML through config
and spec loading, and mutated MCAP bytes (from a real recorded log) through ``replay`` and
``recover``. Never a traceback: a result, or a BallbeamError (one line and exit 2 on the
command line); never more than 256 MiB on top of what a normal replay uses; and ``recover``
never loses an intact message that precedes the damage.

Reproducible: every test is derandomized with a fixed example count and no example database.
Most examples run in process (cheap: the parsers, the reader, the recovery); a few dozen run
the real command line in a child under an address-space cap.
"""

from __future__ import annotations

import contextlib
import json
import resource
import struct
import tempfile
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from ballbeam.config import load_config
from ballbeam.errors import BallbeamError
from ballbeam.logs.reader import read_log
from ballbeam.logs.recover import recover_log
from ballbeam.studies.spec import load_spec
from ballbeam.studies.tune import load_tune_spec

from ..conftest import PAPER
from .harness import one_error_line
from .hostile_inputs import (
    GIB,
    GOLDEN,
    MIB,
    OP_CHUNK,
    Baseline,
    Capped,
    baseline_of_a_normal_replay,
    chunk_record,
    lz4_bomb,
    run_capped,
    top_level_records,
    zstd_rle_frame,
)

GROWTH_BYTES = 256 * MIB


def fuzz_settings(examples: int) -> settings:
    return settings(
        max_examples=examples, deadline=None, derandomize=True, database=None,
        suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
    )


@contextlib.contextmanager
def address_space_cap(extra_bytes: int = GROWTH_BYTES) -> Iterator[None]:
    """This process may map ``extra_bytes`` more than it has now, for the duration: more
    raises MemoryError (a failure of the test) instead of eating the machine."""
    with open("/proc/self/status") as status:
        vm_size = next(int(line.split()[1]) * 1024 for line in status if line.startswith("VmSize"))
    soft, hard = resource.getrlimit(resource.RLIMIT_AS)
    cap = vm_size + extra_bytes
    resource.setrlimit(resource.RLIMIT_AS, (cap if hard == resource.RLIM_INFINITY else
                                            min(cap, hard), hard))
    try:
        yield
    finally:
        resource.setrlimit(resource.RLIMIT_AS, (soft, hard))


# ---- TOML -----------------------------------------------------------------------------------

SECTIONS = ["run", "plan", "tracker", "controller", "plant", "limits", "initial", "bus",
            "model", "observer", "expect", "sweep", "tune", "axis", "grid", "space"]
KEYS = ["duration_s", "kind", "rate_hz", "voltage_v", "theta_deg", "seed", "q", "r", "port",
        "interface", "log_dir", "base", "runner", "trials", "metric", "values", "min", "max",
        "step_s", "mode", "extends"]


def _toml_string(text: str) -> str:
    return json.dumps(text)  # a JSON string is a TOML basic string (lone surrogates aside)


def _key(name: str) -> str:
    bare = name and all(c.isascii() and (c.isalnum() or c in "_-") for c in name)
    return name if bare else _toml_string(name)


_keys = st.one_of(st.sampled_from(KEYS), st.text(max_size=12))
_scalars = st.one_of(
    st.integers(-(10**30), 10**30).map(str),
    st.integers(4290, 4400).map(lambda digits: "9" * digits),  # around int()'s digit limit
    st.sampled_from(["nan", "+nan", "-nan", "inf", "-inf", "1e999", "-1e999", "1e-999",
                     "0x7fffffffffffffff", "0o777", "0b1", "1_000", "true", "false",
                     "1979-05-27T07:32:00Z", "07:32:00", "1979-05-27"]),
    st.floats(width=64).map(repr).map(lambda text: text.replace("e+", "e")),
    st.text(max_size=40).map(_toml_string),
    st.integers(1_000, 30_000).map(lambda n: _toml_string("λ" * n)),  # long unicode
)


def _array(items: list[str]) -> str:
    return "[" + ", ".join(items) + "]"


def _inline_table(items: dict[str, str]) -> str:
    return "{" + ", ".join(f"{_key(k)} = {v}" for k, v in items.items()) + "}"


_values = st.recursive(
    _scalars,
    lambda children: st.one_of(
        st.lists(children, max_size=3).map(_array),
        st.dictionaries(_keys, children, max_size=3).map(_inline_table),
    ),
    max_leaves=8,
)
_deep = st.builds(
    lambda depth, opener: opener * depth + "1" + ("]" if opener == "[" else "}") * depth,
    st.integers(1, 3_000), st.sampled_from(["[", "{a = "]),
)
_any_value = st.one_of(_values, _deep)


@st.composite
def toml_documents(draw: st.DrawFn) -> str:
    lines = [f"{_key(draw(_keys))} = {draw(_any_value)}" for _ in range(draw(st.integers(0, 2)))]
    for _ in range(draw(st.integers(0, 4))):
        section = draw(st.one_of(st.sampled_from(SECTIONS), _keys))
        double = draw(st.booleans()) and section in ("axis", "grid")
        lines.append(f"[[{_key(section)}]]" if double else f"[{_key(section)}]")
        lines += [f"{_key(draw(_keys))} = {draw(_any_value)}"
                  for _ in range(draw(st.integers(0, 3)))]
    if draw(st.booleans()):
        lines.insert(0, f"extends = {_toml_string(draw(st.sampled_from([str(PAPER), 'x.toml'])))}")
    return "\n".join(lines) + "\n"


def _loads_or_refuses(call: Callable[..., object], *args: object) -> None:
    """A result, or a BallbeamError whose message is one line (what the CLI prints)."""
    try:
        call(*args)
    except BallbeamError as error:
        message = str(error)
        assert message and "\n" not in message, message


@fuzz_settings(200)
@given(document=toml_documents())
def test_generated_toml_loads_or_is_refused_in_process(document: str) -> None:
    with tempfile.TemporaryDirectory() as directory, address_space_cap():
        path = Path(directory) / "x.toml"
        path.write_text(document, encoding="utf-8")
        _loads_or_refuses(load_config, path)
        _loads_or_refuses(load_spec, path)
        _loads_or_refuses(load_tune_spec, path)


@fuzz_settings(200)
@given(section=st.one_of(st.sampled_from(SECTIONS), _keys), key=_keys, value=_any_value)
def test_generated_set_values_load_or_are_refused(section: str, key: str, value: str) -> None:
    with address_space_cap():
        _loads_or_refuses(load_config, None, [f"{section}.{key}={value}"])


# ---- MCAP -----------------------------------------------------------------------------------

GOLDEN_BYTES = GOLDEN.read_bytes()
RECORDS = top_level_records(GOLDEN_BYTES)
CHUNKS = [(start, end) for opcode, start, end in RECORDS if opcode == OP_CHUNK]


@dataclass(frozen=True)
class Mutated:
    data: bytes = field(repr=False)  # a failure prints what was done, not half a megabyte
    intact_until: int  # no byte before this offset differs from the golden log
    what: str


def _chunk_fields(start: int) -> tuple[int, int]:
    """Offsets of a chunk record's uncompressed-size field and of its data-length field."""
    body = start + 9
    (n,) = struct.unpack_from("<I", GOLDEN_BYTES, body + 28)
    return body + 16, body + 32 + n


@st.composite
def mutations(draw: st.DrawFn) -> Mutated:
    data = bytearray(GOLDEN_BYTES)
    kind = draw(st.sampled_from(["flip", "truncate", "splice", "inflate", "bomb"]))
    if kind == "flip":
        offsets = draw(st.lists(st.integers(0, len(data) - 1), min_size=1, max_size=8))
        for offset in offsets:
            data[offset] ^= 1 << draw(st.integers(0, 7))
        return Mutated(bytes(data), min(offsets), f"flip at {sorted(offsets)}")
    if kind == "truncate":
        cut = draw(st.integers(0, len(data) - 1))
        return Mutated(bytes(data[:cut]), cut, f"cut at {cut}")
    if kind == "splice":
        source_start, source_end = draw(st.sampled_from(CHUNKS))
        _, at, _ = draw(st.sampled_from(RECORDS))
        replace = draw(st.booleans())
        end = next(e for _, s, e in RECORDS if s == at) if replace else at
        spliced = data[:at] + GOLDEN_BYTES[source_start:source_end] + data[end:]
        return Mutated(bytes(spliced), at, f"chunk {source_start} spliced at {at}")
    start, end = draw(st.sampled_from(CHUNKS))
    size_at, length_at = _chunk_fields(start)
    if kind == "inflate":
        field = draw(st.sampled_from(["uncompressed", "record length", "data length"]))
        value = draw(st.sampled_from([2**64 - 1, 2**63, 2**40, GIB, 64 * MIB + 1, 1 << 20]))
        at = {"uncompressed": size_at, "record length": start + 1, "data length": length_at}[field]
        struct.pack_into("<Q", data, at, value)
        return Mutated(bytes(data), start, f"{field} of chunk {start} set to {value}")
    (stated,) = struct.unpack_from("<Q", GOLDEN_BYTES, size_at)
    bomb = draw(st.sampled_from(["zstd", "zstd unstated", "lz4"]))
    if bomb == "lz4":
        payload = ("lz4", lz4_bomb(16 * MIB, state_size=draw(st.booleans())))
    else:
        payload = ("zstd", zstd_rle_frame(GIB, state_size=bomb == "zstd"))
    record = chunk_record(*payload, stated)
    return Mutated(bytes(data[:start]) + record + bytes(data[end:]), start, f"{bomb} bomb")


@pytest.fixture(scope="module")
def messages_by_chunk_end() -> list[tuple[int, int]]:
    """(end offset, messages) of each chunk of the golden log, counted with the mcap library."""
    import io

    from mcap.reader import make_reader
    from mcap.records import Chunk, Message
    from mcap.stream_reader import StreamReader, breakup_chunk

    with GOLDEN.open("rb") as stream:
        summary = make_reader(stream).get_summary()
    assert summary is not None
    counted = []
    for index in summary.chunk_indexes:
        raw = GOLDEN_BYTES[index.chunk_start_offset : index.chunk_start_offset + index.chunk_length]
        chunk = next(StreamReader(io.BytesIO(raw), skip_magic=True, emit_chunks=True).records)
        assert isinstance(chunk, Chunk)
        messages = sum(isinstance(record, Message) for record in breakup_chunk(chunk))
        counted.append((index.chunk_start_offset + index.chunk_length, messages))
    return counted


def intact_messages(counted: list[tuple[int, int]], mutated: Mutated) -> int:
    """Messages of the chunks that end before the first changed byte: no recovery may lose
    them (chunks are self-contained; the channels they use are defined before the first)."""
    return sum(messages for end, messages in counted if end <= mutated.intact_until)


@fuzz_settings(150)
@given(mutated=mutations())
def test_mutated_logs_read_or_are_refused_in_process(mutated: Mutated) -> None:
    with address_space_cap():
        try:
            run_log = read_log(mutated.data)
        except BallbeamError as error:
            assert str(error), mutated.what
        else:
            assert run_log.message_count >= 0


@fuzz_settings(30)
@given(mutated=mutations())
def test_mutated_logs_recover_every_intact_message_in_process(
    mutated: Mutated, messages_by_chunk_end: list[tuple[int, int]]
) -> None:
    with tempfile.TemporaryDirectory() as directory, address_space_cap():
        source = Path(directory) / "mutated.mcap"
        source.write_bytes(mutated.data)
        destination = Path(directory) / "recovered.mcap"
        try:
            recovery = recover_log(source, destination)
        except BallbeamError:
            # Only a file with nothing to recover: no header left intact.
            assert mutated.intact_until < RECORDS[0][2], mutated.what
            return
        assert recovery.messages >= intact_messages(messages_by_chunk_end, mutated), mutated.what
        assert read_log(destination).message_count == recovery.messages


# ---- the command line, in children under a memory cap ------------------------------------


@pytest.fixture(scope="module")
def baseline() -> Baseline:
    return baseline_of_a_normal_replay()


def _check_child(result: Capped, baseline: Baseline, what: str, codes: tuple[int, ...]) -> None:
    assert result.returncode in codes, (what, result.stderr[-3000:])
    assert "Traceback" not in result.stderr, what
    if result.returncode == 2:
        one_error_line(result.stderr)
    assert result.max_rss_bytes <= baseline.rss_peak_bytes + GROWTH_BYTES, (
        what, result.max_rss_bytes
    )


@fuzz_settings(8)
@given(mutated=mutations())
def test_mutated_logs_through_the_command_line(
    mutated: Mutated, baseline: Baseline, messages_by_chunk_end: list[tuple[int, int]]
) -> None:
    with tempfile.TemporaryDirectory() as directory:
        source = Path(directory) / "mutated.mcap"
        source.write_bytes(mutated.data)
        replayed = run_capped(["replay", str(source)], baseline.cap_bytes)
        _check_child(replayed, baseline, mutated.what, (0, 2))
        destination = Path(directory) / "recovered.mcap"
        recovered = run_capped(["recover", str(source), "-o", str(destination)],
                               baseline.cap_bytes)
        _check_child(recovered, baseline, mutated.what, (0, 2))
        if destination.exists():
            kept = read_log(destination).message_count
            assert kept >= intact_messages(messages_by_chunk_end, mutated), mutated.what


@fuzz_settings(6)
@given(document=toml_documents())
def test_generated_toml_through_the_command_line(document: str, baseline: Baseline) -> None:
    with tempfile.TemporaryDirectory() as directory:
        path = Path(directory) / "x.toml"
        path.write_text(document, encoding="utf-8")
        # The bang-bang planner: what is fuzzed is the loading, not the LP's running time.
        result = run_capped(
            ["plan", str(path), "--json", "--set", "plan.kind='bang_bang'"], baseline.cap_bytes
        )
        _check_child(result, baseline, document[:200], (0, 2))
