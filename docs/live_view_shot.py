"""Make docs/live_view.png: headless Chromium showing docs/live_view.html connected to a real
run's live view (``ballbeam run --live``), captured while the run goes.

    .venv/bin/python docs/live_view_shot.py [--out docs/live_view.png] [--at-s 4.5] [--set K=V]

Opens the page in Debian's ``chromium`` (headless, its DevTools endpoint on loopback), then
starts a real-time run with ``--live`` on a free loopback port, waits until the page has
received ``--at-s`` seconds of log time from the server, and captures the page through the
DevTools protocol (``Page.captureScreenshot``). Nothing is drawn from the log file: every
point on the picture came over the WebSocket.
"""

from __future__ import annotations

import argparse
import base64
import json
import shutil
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path
from typing import Any

from websockets.sync.client import ClientConnection, connect

DOCS = Path(__file__).resolve().parent
REPO = DOCS.parent
SUBPROTOCOLS = ["foxglove.sdk.v1", "foxglove.websocket.v1"]


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


class DevTools:
    """Just enough of the DevTools protocol: evaluate an expression, capture the page."""

    def __init__(self, ws: ClientConnection) -> None:
        self._ws = ws
        self._next = 0

    def call(self, method: str, **params: object) -> dict[str, Any]:
        self._next += 1
        self._ws.send(json.dumps({"id": self._next, "method": method, "params": params}))
        while True:
            reply = json.loads(self._ws.recv())
            if reply.get("id") == self._next:
                if "error" in reply:
                    raise RuntimeError(f"{method}: {reply['error']}")
                result: dict[str, Any] = reply["result"]
                return result

    def evaluate(self, expression: str) -> Any:
        result = self.call("Runtime.evaluate", expression=expression, returnByValue=True)
        return result["result"].get("value")  # none while the page loads


def page_target(devtools_port: int, give_up_s: float = 30.0) -> str:
    deadline = time.monotonic() + give_up_s
    while True:
        try:
            with urllib.request.urlopen(f"http://127.0.0.1:{devtools_port}/json") as reply:
                targets = json.load(reply)
            for target in targets:
                if target.get("type") == "page":
                    return str(target["webSocketDebuggerUrl"])
        except OSError:
            pass
        if time.monotonic() > deadline:
            raise SystemExit("chromium's DevTools endpoint never came up")
        time.sleep(0.1)


def wait_for_server(port: int, run: subprocess.Popen[str], give_up_s: float = 120.0) -> None:
    deadline = time.monotonic() + give_up_s
    while True:
        try:
            with connect(f"ws://127.0.0.1:{port}", subprotocols=SUBPROTOCOLS):  # type: ignore[arg-type]
                return
        except OSError:
            if run.poll() is not None or time.monotonic() > deadline:
                raise SystemExit("the run's live server never came up") from None
            time.sleep(0.02)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=DOCS / "live_view.png")
    parser.add_argument("--at-s", type=float, default=4.5, help="log time to capture at")
    parser.add_argument(
        "--set", action="append", default=[], metavar="KEY=VALUE",
        help="config override for the run, e.g. controller.realtime_priority=50",
    )
    args = parser.parse_args()
    browser = shutil.which("chromium") or shutil.which("chromium-browser")
    if browser is None:
        raise SystemExit("no browser: install Debian's chromium (apt-get install chromium)")
    live_port, devtools_port = free_port(), free_port()
    with tempfile.TemporaryDirectory(prefix="live_shot_") as tmp:
        # The page first, then the run.
        page = (DOCS / "live_view.html").as_uri() + f"?port={live_port}&window=6&autoconnect=0"
        chromium = subprocess.Popen(
            [browser, "--headless", "--no-sandbox", "--disable-gpu",
             "--disable-background-networking", "--hide-scrollbars",
             f"--user-data-dir={tmp}/profile", "--remote-debugging-address=127.0.0.1",
             f"--remote-debugging-port={devtools_port}", "--window-size=1040,1000", page],
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        )
        run: subprocess.Popen[str] | None = None
        try:
            with connect(page_target(devtools_port), max_size=None) as ws:
                devtools = DevTools(ws)
                while devtools.evaluate("document.readyState") != "complete":
                    time.sleep(0.05)
                run = subprocess.Popen(
                    [sys.executable, "-m", "ballbeam", "run", "--live", "--live-port",
                     str(live_port), "--set", "run.mode='realtime'", "--set", "run.duration_s=6",
                     "--set", f"run.log_dir='{tmp}'", *(f"--set={item}" for item in args.set)],
                    cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                )
                # The page connects once the server answers: it subscribes before the run's
                # first cycle (Chromium backs off from a server that refused it before).
                wait_for_server(live_port, run)
                devtools.evaluate("window.connect()")
                deadline = time.monotonic() + 120
                while float(devtools.evaluate("window.liveSeconds") or 0.0) < args.at_s:
                    if time.monotonic() > deadline or run.poll() is not None:
                        received = devtools.evaluate("window.liveSeconds")
                        raise SystemExit(
                            f"the page received {received} s of the run, not {args.at_s} s "
                            f"(run exit {run.poll()})"
                        )
                    time.sleep(0.05)
                time.sleep(0.15)  # one more redraw of the page (every 100 ms)
                height = int(devtools.evaluate("document.documentElement.scrollHeight"))
                shot = devtools.call(
                    "Page.captureScreenshot", format="png", captureBeyondViewport=True,
                    clip={"x": 0, "y": 0, "width": 1040, "height": height, "scale": 1},
                )
                args.out.write_bytes(base64.b64decode(str(shot["data"])))
            _, errors = run.communicate(timeout=120)
            print(f"wrote {args.out}; run exit {run.returncode}")
            if run.returncode != 0:
                print(errors, file=sys.stderr)
            return 0 if run.returncode == 0 else 1
        finally:
            chromium.terminate()
            chromium.wait(timeout=30)
            if run is not None and run.poll() is None:
                run.terminate()
                run.wait(timeout=30)


if __name__ == "__main__":
    sys.exit(main())
