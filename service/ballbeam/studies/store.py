"""Where a sweep keeps its results: one JSON file per point, named by the point's content.

A point's id is a hash of what decides its result: the validated config it runs (less the
log directory) and the runner. The same spec run again finds its points done and skips them;
another spec that reaches the same config in the same directory reuses them too. Each record
is written whole (a temporary file renamed over), so a sweep stopped at any moment resumes.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import math
import os
import tempfile
from dataclasses import asdict
from pathlib import Path
from typing import Any

from ballbeam.config import config_from_data
from ballbeam.errors import BallbeamError, ConfigError
from ballbeam.studies.points import PointOutcome

STORE_VERSION = 1  # part of every id: a change of record layout starts afresh


def point_id(base_data: dict[str, Any], overrides: tuple[str, ...], runner: str) -> str:
    """The content address of a point (a config that does not validate: of its inputs)."""
    try:
        config = config_from_data(base_data, overrides)
        content: Any = config.model_dump(mode="json")
        content["run"].pop("log_dir")
    except BallbeamError:
        content = {"base": base_data, "overrides": list(overrides)}
    payload = json.dumps(
        {"version": STORE_VERSION, "runner": runner, "config": content}, sort_keys=True
    )
    return hashlib.sha256(payload.encode()).hexdigest()[:20]


def _json_ready(value: Any) -> Any:
    if isinstance(value, float) and not math.isfinite(value):
        return {"float": repr(value)}  # JSON has no inf/nan; they come back as floats
    if isinstance(value, dict):
        return {key: _json_ready(item) for key, item in value.items()}
    if isinstance(value, list | tuple):
        return [_json_ready(item) for item in value]
    return value


def _from_json(value: Any) -> Any:
    if isinstance(value, dict):
        if set(value) == {"float"}:
            return float(value["float"])
        return {key: _from_json(item) for key, item in value.items()}
    if isinstance(value, list):
        return [_from_json(item) for item in value]
    return value


class ResultStore:
    def __init__(self, directory: Path) -> None:
        self.directory = directory
        self.points = directory / "points"
        try:
            self.points.mkdir(parents=True, exist_ok=True)
        except OSError as error:
            raise ConfigError(f"cannot create the sweep directory {directory}: {error}") from error

    def path(self, identifier: str) -> Path:
        return self.points / f"{identifier}.json"

    def load(self, identifier: str) -> dict[str, Any] | None:
        try:
            record = json.loads(self.path(identifier).read_text(encoding="utf-8"))
        except (FileNotFoundError, json.JSONDecodeError):
            return None  # not done (a torn file cannot exist, but a hand-edited one can)
        result: dict[str, Any] = _from_json(record)
        return result

    def save(self, outcome: PointOutcome, values: dict[str, Any], runner: str) -> None:
        record = {**asdict(outcome), "values": values, "runner": runner}
        text = json.dumps(_json_ready(record), sort_keys=True, allow_nan=False)
        handle, temporary = tempfile.mkstemp(dir=self.points, prefix=".", suffix=".part")
        try:
            with os.fdopen(handle, "w", encoding="utf-8") as stream:
                stream.write(text)
            os.replace(temporary, self.path(outcome.point_id))
        except BaseException:
            with contextlib.suppress(OSError):
                os.unlink(temporary)
            raise
