"""The Foxglove layout shipped with the package, and how to open a log with it.

``foxglove_layout.json`` (package data) lays out four plots and the faults: x with x_d, θ with θ_d
(in degrees, the y axis ending just beyond the ±52° limits), u with u_d, the loop's lateness and
skipped periods, and the ``/faults`` messages. Its message paths are the log's own topics and
fields, checked against a recorded log's schemas by the tests (:func:`layout_paths`).
"""

from __future__ import annotations

import contextlib
import json
import re
from importlib import resources
from pathlib import Path
from typing import Any

from ballbeam.errors import OutputExistsError
from ballbeam.files import write_new

LAYOUT_NAME = "foxglove_layout.json"
# A plot path: /topic.field, optionally followed by a Foxglove modifier such as .@degrees.
_PATH = re.compile(r"^(?P<topic>/[A-Za-z0-9_/]+)\.(?P<field>[A-Za-z_][A-Za-z0-9_]*)(\.@\w+)?$")


def layout_text() -> str:
    return resources.files("ballbeam.evaluation").joinpath(LAYOUT_NAME).read_text("utf-8")


def layout_paths() -> list[tuple[str, str | None]]:
    """(topic, field) of every path the layout plots or shows (field None: a whole topic)."""
    layout: dict[str, Any] = json.loads(layout_text())
    found: list[tuple[str, str | None]] = []
    for panel in layout["configById"].values():
        for path in panel.get("paths", ()):
            match = _PATH.match(path["value"])
            if match is None:
                raise ValueError(f"not a topic.field path: {path['value']!r}")
            found.append((match["topic"], match["field"]))
        if "topicPath" in panel:
            found.append((panel["topicPath"], None))
    return found


def how_to_open(log_path: str) -> str:
    """The steps to open ``log_path`` with the shipped layout (the layout is written next to
    the log as ``ballbeam.foxglove-layout.json`` if it is not there yet)."""
    layout_file = Path(log_path).resolve().with_name("ballbeam.foxglove-layout.json")
    # A new file, never through a link; one already there (an earlier replay's) is kept.
    with contextlib.suppress(OutputExistsError):
        write_new(layout_file, layout_text().encode("utf-8"))
    return "\n".join((
        "To look at this run in Foxglove (the app, or app.foxglove.dev):",
        f"  1. Open the log: File → Open local file… → {Path(log_path).resolve()}",
        f"  2. Load the layout: Layouts → Import from file… → {layout_file}",
        "     (x and x_d; θ and θ_d against the ±52° limits; u and u_d; lateness; faults)",
    ))
