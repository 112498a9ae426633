"""Hostile logs: replay refuses them with one error line and executes nothing from them."""

from __future__ import annotations

import contextlib
import io
import json
import math
import os
import pickle
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import pytest
from mcap.writer import CompressionType, Writer

from ballbeam import cli
from ballbeam.logs import topics

from ..conftest import ballbeam
from .harness import DEFAULTS, PERIOD_NS, one_error_line

SENTINEL_NAME = "executed.txt"


class _Touch:
    """Unpickling this would create a file: proof that nothing is unpickled."""

    def __init__(self, path: str) -> None:
        self.path = path

    def __reduce__(self) -> tuple[Any, ...]:
        return (open, (self.path, "w"))


def _rows(topic: str, n: int) -> list[tuple[Any, ...]]:
    rows: list[tuple[Any, ...]] = []
    for k in range(n):
        x = 0.195 * math.exp(-k / 80)
        state = (0.0, 0.0, 0.0, x)
        if topic == "/command":
            rows.append((k, 0.1, 0.1, 1, k % 256, k % 256))
        elif topic == "/reference":
            rows.append((k, *state, 0.0))
        elif topic == "/truth":
            # /truth carries the plant's own clock since ef49084 (sample_index, plant_time_s)
            rows.append((k % 256, *state, k, k * PERIOD_NS * 1e-9))
        elif topic == "/timing":
            rows.append((k, k * PERIOD_NS, k * PERIOD_NS, k * PERIOD_NS + 1000, 0, 0))
        elif topic == "/sensor":
            rows.append((k, 1, k % 256, 0, 0, 0, 0.0, x))
        elif topic == "/estimate":
            rows.append((k, *state))
    return rows


def write_log(
    path: Path,
    *,
    config_json: str | None = None,
    schema_text: dict[str, str] | None = None,
    fault_payloads: Sequence[bytes] = (),
    evil_channel: bytes | None = None,
) -> Path:
    """A log written with the mcap library's Writer, shaped like ours, with parts replaced."""
    if config_json is None:
        config_json = json.dumps(DEFAULTS.model_dump(mode="json"))
    schema_text = schema_text or {}
    n = 300
    with path.open("wb") as stream:
        writer = Writer(stream, compression=CompressionType.ZSTD)
        writer.start(profile="ballbeam", library="hostile test")
        writer.add_metadata(
            "config", {"json": config_json, "note": "__import__('os').system('touch executed.txt')"}
        )
        for topic in ("/command", "/reference", "/truth", "/timing", "/sensor", "/estimate"):
            schema = topics.STRUCT_TOPICS[topic]
            text = schema_text.get(topic, schema.ros2msg)
            schema_id = writer.register_schema(schema.name, "ros2msg", text.encode())
            channel_id = writer.register_channel(topic, "cdr", schema_id)
            for k, row in enumerate(_rows(topic, n)):
                payload = schema.pack(row)
                if topic in schema_text:  # a layout of another size: same bytes, cut to fit
                    payload = payload[:12]
                t = 1_000_000_000 + k * PERIOD_NS
                writer.add_message(channel_id, t, payload, t)
        event_schema = writer.register_schema(
            "ballbeam/Event", "jsonschema", json.dumps(topics.EVENT_SCHEMA).encode()
        )
        faults_channel = writer.register_channel("/faults", "json", event_schema)
        for k, payload in enumerate(fault_payloads):
            writer.add_message(faults_channel, 1_000_000_000 + k, payload, 1_000_000_000 + k)
        if evil_channel is not None:
            evil = writer.register_channel("/evil", "pickle", 0)
            writer.add_message(evil, 1_000_000_000, evil_channel, 1_000_000_000)
        writer.finish()
    return path


def replay_in_process(*argv: str) -> tuple[int, str, str]:
    stdout, stderr = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
        code = cli.main(["replay", *argv])
    return code, stdout.getvalue(), stderr.getvalue()


def test_the_hostile_log_builder_makes_a_log_replay_accepts(tmp_path: Path) -> None:
    path = write_log(
        tmp_path / "fine.mcap", fault_payloads=[b'{"cycle": 1, "kind": "x", "detail": "y"}']
    )
    code, stdout, stderr = replay_in_process(str(path))
    assert code == 0, stderr
    assert "replay of" in stdout


HOSTILE: dict[str, tuple[dict[str, Any], str]] = {
    "command schema is garbage": (
        {"schema_text": {"/command": "this is ::: not a schema {\n"}},
        "schema",
    ),
    "command schema is another layout": (
        {"schema_text": {"/command": "float64 volts\n"}},
        "/command",
    ),
    "config is not JSON": ({"config_json": "{not json"}, "not JSON"),
    "config is a JSON list": ({"config_json": "[1, 2]"}, "config"),
    "config lacks the limits": ({"config_json": '{"run": {}}'}, "config"),
    "config limit is text": (
        {"config_json": '{"limits": {"theta_deg": "abc", "voltage_v": 5}}'},
        "config",
    ),
    "fault payload is not JSON": ({"fault_payloads": [b"\xff{not json"]}, "not JSON"),
    "fault payload nests deeply": (
        {"fault_payloads": [b"[" * 200_000 + b"]" * 200_000]},
        "not JSON",
    ),
    "fault payload is a list": ({"fault_payloads": [b"[1, 2, 3]"]}, "not an object"),
    "a pickled channel": ({"evil_channel": b""}, "/evil"),
}


@pytest.mark.parametrize("verify_flag", [False, True], ids=["replay", "replay-verify"])
@pytest.mark.parametrize("case", list(HOSTILE))
def test_replay_of_a_hostile_log_exits_2_and_executes_nothing(
    tmp_path: Path, case: str, verify_flag: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)
    options, needle = HOSTILE[case]
    if "evil_channel" in options:
        options = {"evil_channel": pickle.dumps(_Touch(str(tmp_path / SENTINEL_NAME)))}
    path = write_log(tmp_path / "hostile.mcap", **options)
    before = sorted(os.listdir(tmp_path))
    code, _, stderr = replay_in_process(str(path), *(["--verify"] if verify_flag else []))
    assert code == 2, stderr
    assert stderr.startswith("ballbeam: error:") and len(stderr.strip().splitlines()) == 1, stderr
    assert needle in stderr, stderr
    assert sorted(os.listdir(tmp_path)) == before  # nothing written, nothing executed
    assert not (tmp_path / SENTINEL_NAME).exists()


def test_replay_of_a_hostile_log_as_a_process_has_no_traceback(tmp_path: Path) -> None:
    paths = [
        write_log(tmp_path / "a.mcap", schema_text={"/command": "float64 volts\n"}),
        write_log(tmp_path / "b.mcap", config_json="[1, 2]"),
    ]
    for path in paths:
        result = ballbeam("replay", str(path), "--verify")
        assert result.returncode == 2, result.stderr
        one_error_line(result.stderr)
        assert len(result.stderr.strip().splitlines()) == 1
