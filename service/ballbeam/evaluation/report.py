"""``ballbeam replay LOG --report run.html``: one self-contained page a person reads.

The page holds the run's metrics (the headline ones first), the paper-style figure with the loop's
lateness, a histogram of that lateness, the faults and events, and the resolved config. Figures
are inline SVG, styles inline, no script and nothing fetched: the file opens the same from a mail
attachment, offline, years later.
"""

from __future__ import annotations

import html
import io
import json
import math
from collections import Counter
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np

from ballbeam.errors import BallbeamError, OutputExistsError
from ballbeam.evaluation.plots import plot_log
from ballbeam.evaluation.summary import run_series
from ballbeam.files import write_new
from ballbeam.logs.reader import RunLog

HEADLINE = (
    "rest_time_s", "rest_ratio", "input_tv_ratio", "dither_hz", "largest_step_v",
    "max_abs_theta_deg", "end_reason",
)
SHOWN_EVENTS = 200  # the first of each JSON topic, in full; the rest counted by kind

STYLE = """
body { font: 14px/1.45 system-ui, sans-serif; margin: 2em auto; max-width: 60em; color: #222; }
h1 { font-size: 1.5em; } h2 { font-size: 1.15em; margin-top: 2em; border-bottom: 1px solid #ccc; }
table { border-collapse: collapse; } td, th { padding: 2px 10px; text-align: left; }
tr:nth-child(even) { background: #f4f4f4; } td.value { font-family: monospace; }
pre { background: #f6f6f6; padding: 1em; overflow-x: auto; font-size: 12px; }
figure { margin: 1em 0; } svg { max-width: 100%; height: auto; }
.note { color: #a33; }
"""


def write_report(run_log: RunLog, summary: Mapping[str, Any], path: str | Path) -> None:
    """Write the page, a new file; OutputExistsError if anything is at ``path``, BallbeamError
    naming it if it cannot be written."""
    page = render_report(run_log, summary)
    try:
        write_new(path, page.encode("utf-8"))  # a new file only, never through a link
    except OutputExistsError:
        raise
    except OSError as error:
        raise BallbeamError(f"cannot write report {path}: {error.strerror or error}") from error


def render_report(run_log: RunLog, summary: Mapping[str, Any]) -> str:
    run_meta = run_log.metadata.get("run", {})
    title = (
        f"ballbeam run: {run_meta.get('plan_kind', '?')} path, "
        f"{run_meta.get('mode', '?')} mode"
    )
    parts = [
        "<!DOCTYPE html>",
        '<html lang="en"><head><meta charset="utf-8">',
        f"<title>{html.escape(title)}</title><style>{STYLE}</style></head><body>",
        f"<h1>{html.escape(title)}</h1>",
        f"<p>Log: <code>{html.escape(run_log.path)}</code></p>",
    ]
    if run_log.truncated:
        parts.append(
            f'<p class="note">The log was cut short ({html.escape(str(run_log.truncation_reason))})'
            "; what follows is what it holds.</p>"
        )
    parts += ["<h2>Headline</h2>", _table({key: summary.get(key) for key in HEADLINE})]
    parts += ["<h2>Figures</h2>", _figures(run_log)]
    others = {key: value for key, value in summary.items() if key not in HEADLINE}
    parts += ["<h2>All metrics</h2>", _table(others)]
    parts += ["<h2>Faults and events</h2>", _events(run_log)]
    parts += ["<h2>Run</h2>", _table(dict(run_meta)), _table(run_log.metadata.get("versions", {}))]
    parts += ["<h2>Resolved config</h2>", f"<pre>{html.escape(_config_text(run_log))}</pre>"]
    parts.append("</body></html>")
    return "\n".join(parts)


def _table(values: Mapping[str, Any]) -> str:
    rows = "".join(
        f'<tr><th>{html.escape(str(key))}</th><td class="value">{html.escape(_shown(value))}</td>'
        "</tr>"
        for key, value in values.items()
    )
    return f"<table>{rows}</table>"


def _shown(value: Any) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:.6g}" if math.isfinite(value) else str(value)
    return str(value)


def _figures(run_log: RunLog) -> str:
    paper_style = io.BytesIO()
    plot_log(paper_style, run_log, title="the run against its reference", file_format="svg")
    lateness_us = run_series(run_log).lateness_ns * 1e-3
    return (
        '<figure id="figure-run">' + _inline_svg(paper_style)
        + "<figcaption>Ball position x and its reference x_d; servo angle θ, θ_d and the "
        "limits; the command u; the loop's lateness.</figcaption></figure>"
        + '<figure id="figure-lateness">' + _lateness_histogram(lateness_us)
        + "<figcaption>How late each control cycle started (µs after its deadline)."
        "</figcaption></figure>"
    )


def _lateness_histogram(lateness_us: np.ndarray) -> str:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axis = plt.subplots(figsize=(8, 2.6))
    finite = lateness_us[np.isfinite(lateness_us)]
    if finite.size:
        axis.hist(finite, bins=80, log=True)
    axis.set_xlabel("lateness [µs]")
    axis.set_ylabel("cycles")
    axis.grid(True, alpha=0.3)
    figure.tight_layout()
    buffer = io.BytesIO()
    try:
        figure.savefig(buffer, format="svg")
    finally:
        plt.close(figure)
    return _inline_svg(buffer)


def _inline_svg(buffer: io.BytesIO) -> str:
    text = buffer.getvalue().decode("utf-8")
    return text[text.index("<svg"):]  # drop the XML prolog and doctype: inline in HTML


def _events(run_log: RunLog) -> str:
    parts = []
    for topic in ("/faults", "/events"):
        found = run_log.json_topics.get(topic)
        messages = found.messages if found is not None else ()
        kinds = Counter(str(message.get("kind")) for message in messages)
        parts.append(f"<h3>{html.escape(topic)}: {len(messages)}</h3>")
        if not messages:
            continue
        parts.append(_table(dict(sorted(kinds.items()))))
        rows = "".join(
            f"<tr><td>{html.escape(str(message.get('cycle', '')))}</td>"
            f"<td>{html.escape(str(message.get('kind', '')))}</td>"
            f"<td>{html.escape(str(message.get('detail', '')))}</td></tr>"
            for message in messages[:SHOWN_EVENTS]
        )
        more = len(messages) - SHOWN_EVENTS
        parts.append(
            f"<table><tr><th>cycle</th><th>kind</th><th>detail</th></tr>{rows}</table>"
            + (f"<p>… and {more} more.</p>" if more > 0 else "")
        )
    return "\n".join(parts)


def _config_text(run_log: RunLog) -> str:
    text = run_log.metadata.get("config", {}).get("json")
    if text is None:
        return "(the log holds no config)"
    try:
        return json.dumps(json.loads(text), indent=2, sort_keys=True)
    except (ValueError, RecursionError):  # not JSON, or nested past the interpreter's stack
        return text
