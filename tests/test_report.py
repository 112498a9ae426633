"""``replay --report``: one self-contained HTML page (issue 15, item 3).

Checked twice: its structure, parsed (every section, both figures inline, nothing fetched); and
in a real headless browser (Debian's chromium, which .ci/run installs), which must render it with
both figures and no console errors.
"""

from __future__ import annotations

import re
import shutil
import subprocess
from html.parser import HTMLParser
from pathlib import Path

import pytest

from .conftest import ballbeam

GOLDEN = Path(__file__).resolve().parent / "data" / "golden_paper_1s.mcap"


class _Page(HTMLParser):
    def __init__(self) -> None:
        super().__init__()
        self.tags: list[tuple[str, dict[str, str | None]]] = []
        self.text: list[str] = []

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        self.tags.append((tag, dict(attrs)))

    def handle_data(self, data: str) -> None:
        self.text.append(data)


@pytest.fixture(scope="module")
def report(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("report") / "run.html"
    result = ballbeam("replay", str(GOLDEN), "--report", str(path))
    assert result.returncode == 0, result.stderr
    return path


def test_the_report_holds_every_section_and_fetches_nothing(report: Path) -> None:
    page = _Page()
    page.feed(report.read_text(encoding="utf-8"))
    text = " ".join(page.text)
    for heading in ("Headline", "Figures", "All metrics", "Faults and events", "Run",
                    "Resolved config"):
        assert heading in text
    for metric in ("rest_ratio", "input_tv_ratio", "dither_hz", "lateness_p99_us"):
        assert metric in text
    assert '"theta_deg"' in text  # the resolved config
    tags = [tag for tag, _ in page.tags]
    assert tags.count("svg") == 2
    assert {"figure-run", "figure-lateness"} <= {attrs.get("id") for _, attrs in page.tags}
    # Self-contained: no script, no stylesheet link, no image or frame from elsewhere.
    assert "script" not in tags and "link" not in tags and "iframe" not in tags
    for _, attrs in page.tags:
        for name in ("src", "href"):
            value = attrs.get(name) or ""
            assert not re.match(r"[a-z]+:", value) or value.startswith(("#", "data:")), value


def test_the_report_is_refused_where_it_cannot_be_written(tmp_path: Path) -> None:
    result = ballbeam("replay", str(GOLDEN), "--report", str(tmp_path / "missing" / "r.html"))
    assert result.returncode == 2 and "cannot write report" in result.stderr
    assert "Traceback" not in result.stderr


def test_the_report_renders_in_a_headless_browser(report: Path, tmp_path: Path) -> None:
    browser = shutil.which("chromium") or shutil.which("chromium-browser")
    if browser is None:
        pytest.skip(
            "no browser: install Debian's chromium (apt-get install chromium), as .ci/run does"
        )
    command = [
        browser, "--headless", "--no-sandbox", "--disable-gpu", "--enable-logging=stderr",
        "--v=0", f"--user-data-dir={tmp_path / 'profile'}",
    ]
    dom = subprocess.run(
        [*command, "--dump-dom", report.as_uri()], capture_output=True, text=True, timeout=120,
    )
    assert dom.returncode == 0, dom.stderr[-2000:]
    assert dom.stdout.count("<svg") == 2 and 'id="figure-lateness"' in dom.stdout
    console = [line for line in dom.stderr.splitlines() if "CONSOLE" in line]
    assert not console, console
    screenshot = tmp_path / "report.png"
    shot = subprocess.run(
        [*command, f"--screenshot={screenshot}", "--window-size=1100,2400", report.as_uri()],
        capture_output=True, text=True, timeout=120,
    )
    assert shot.returncode == 0 and screenshot.stat().st_size > 50_000, shot.stderr[-2000:]
