"""The shipped Foxglove layout (issue 15, item 2): every topic and field it plots exists in a
recorded log, with a numeric type Foxglove can plot; and replay tells how to open a log with it."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

from mcap.reader import make_reader

from ballbeam.evaluation.foxglove import layout_paths, layout_text

from .conftest import ballbeam

GOLDEN = Path(__file__).resolve().parent / "data" / "golden_paper_1s.mcap"
NUMERIC = ("float64", "float32", "int64", "int32", "uint8", "uint32", "int8", "uint16", "int16")


def schema_fields(schema_text: str) -> dict[str, str]:
    """field → type of a ros2msg schema ("float64 theta_rad" lines)."""
    fields = {}
    for line in schema_text.splitlines():
        line = line.split("#", 1)[0].strip()
        if line:
            field_type, name = line.split()[:2]
            fields[name] = field_type
    return fields


def recorded_schemas(log: Path) -> dict[str, tuple[str, str]]:
    """topic → (schema encoding, schema text), as the log records them (official reader)."""
    with log.open("rb") as stream:
        summary = make_reader(stream).get_summary()
    assert summary is not None
    return {
        channel.topic: (
            summary.schemas[channel.schema_id].encoding,
            summary.schemas[channel.schema_id].data.decode(),
        )
        for channel in summary.channels.values()
    }


def test_every_layout_path_is_a_plottable_field_of_a_recorded_log() -> None:
    schemas = recorded_schemas(GOLDEN)
    paths = layout_paths()
    plotted = {(topic, field) for topic, field in paths if field is not None}
    assert {("/truth", "ball_position_m"), ("/reference", "ball_position_m"),
            ("/truth", "theta_rad"), ("/reference", "theta_rad"), ("/command", "voltage_v"),
            ("/reference", "input_v"), ("/timing", "lateness_ns")} <= plotted
    for topic, field in paths:
        encoding, text = schemas[topic]
        if field is None:
            assert encoding == "jsonschema", topic  # shown whole (the faults)
            continue
        assert encoding == "ros2msg", topic
        fields = schema_fields(text)
        assert fields.get(field) in NUMERIC, (topic, field, fields)


def test_the_layout_is_a_foxglove_layout() -> None:
    layout = json.loads(layout_text())
    assert set(layout) >= {"configById", "layout"}

    def leaves(node: object) -> list[str]:
        if isinstance(node, str):
            return [node]
        assert isinstance(node, dict) and node["direction"] in ("row", "column")
        return leaves(node["first"]) + leaves(node["second"])

    assert sorted(leaves(layout["layout"])) == sorted(layout["configById"])


def test_replay_says_how_to_open_the_log_with_the_layout(tmp_path: Path) -> None:
    log = tmp_path / "run.mcap"
    shutil.copy(GOLDEN, log)
    result = ballbeam("replay", str(log), "--foxglove")
    assert result.returncode == 0, result.stderr
    assert str(log) in result.stdout and "Import from file" in result.stdout
    written = tmp_path / "ballbeam.foxglove-layout.json"
    assert json.loads(written.read_text()) == json.loads(layout_text())
    as_json = ballbeam("replay", str(log), "--foxglove", "--json")
    assert as_json.returncode == 0 and json.loads(as_json.stdout)["log_path"] == str(log)
    assert "Import from file" in as_json.stderr
