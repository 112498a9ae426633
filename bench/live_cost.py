"""What the live view (``ballbeam run --live``) costs a run, with a client connected and without.

    .venv/bin/python bench/live_cost.py                  # 4 real-time runs of 30 s (~2.5 min)
    .venv/bin/python bench/live_cost.py --duration 10 --repeat 2
    .venv/bin/python bench/live_cost.py --mode lockstep  # the same in lock-step (no overruns)

Side by side in one invocation, the paper's run over the bus: without ``--live``; with it and
no client; with a client subscribed to the shipped Foxglove layout's topics (what the app with
that layout asks for); with a client subscribed to every topic. Per run, from the log the daemon
wrote:

- the live path's cost to the daemon per control cycle: the CPU time its recorder's writer
  thread spends handing written chunks to the live server process (the log's "live" record;
  the loop thread does no work for it);
- the recorder's writer thread's whole CPU time per cycle (the log's "recorder" record), to
  compare with the run without ``--live``: what the view adds to that thread, however it adds
  it;
- the live server process's CPU time per cycle once serving (user + system, every thread, as
  the kernel counted it when the process ended, less what it had spent when it began serving:
  interpreter, SDK and server start-up, reported apart): the work moved out of the daemon;
- messages forwarded and received, chunks the view dropped, and the loop's overruns and
  lateness.

The client is a separate process (``websockets``, needs the test extras), as the Foxglove app is.
"""

from __future__ import annotations

import argparse
import json
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

SUBPROTOCOLS = ["foxglove.sdk.v1", "foxglove.websocket.v1"]
LAYOUT_TOPICS = ("/truth", "/reference", "/command", "/timing", "/faults")
EVERY_TOPIC = "*"
TARGET_US_PER_CYCLE = 5.0


# ---- the client (a process of its own) ----------------------------------------------------


def client_main(port: int, topics: str, give_up_s: float) -> None:
    """Connect (retrying until the server is up), subscribe, count messages until the server
    goes away; print one JSON line."""
    from websockets.exceptions import ConnectionClosed
    from websockets.sync.client import connect

    wanted = None if topics == EVERY_TOPIC else set(topics.split(","))
    deadline = time.monotonic() + give_up_s
    while True:
        try:
            connection = connect(
                f"ws://127.0.0.1:{port}", subprotocols=SUBPROTOCOLS, max_size=None,
                open_timeout=5,
            )
        except OSError:
            if time.monotonic() > deadline:
                print(json.dumps({"received": 0, "error": "no server"}))
                return
            time.sleep(0.02)
            continue
        break
    received = 0
    subscriptions = 0
    with connection:
        try:
            for frame in connection:
                if isinstance(frame, str):
                    message = json.loads(frame)
                    if message["op"] != "advertise":
                        continue
                    subscribe = []
                    for channel in message["channels"]:
                        if wanted is None or channel["topic"] in wanted:
                            subscriptions += 1
                            subscribe.append({"id": subscriptions, "channelId": channel["id"]})
                    if subscribe:
                        connection.send(json.dumps({"op": "subscribe", "subscriptions": subscribe}))
                elif frame[0] == 0x01:  # message data
                    received += 1
        except ConnectionClosed:
            pass
    print(json.dumps({"received": received, "subscriptions": subscriptions}))


# ---- the runs ----------------------------------------------------------------------------


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


def one_run(
    variant: str, mode: str, duration_s: float, log_dir: Path, overrides: list[str]
) -> dict[str, Any]:
    from ballbeam.evaluation.summary import summarise
    from ballbeam.logs.reader import read_log
    from ballbeam.runtime.launcher import launch_run

    live = variant != "no --live"
    port = free_port() if live else None
    topics = {
        "client: layout topics": ",".join(LAYOUT_TOPICS),
        "client: every topic": EVERY_TOPIC,
    }.get(variant)
    client: subprocess.Popen[str] | None = None
    if topics is not None:
        client = subprocess.Popen(
            [sys.executable, __file__, "--client", str(port), "--topics", topics],
            stdout=subprocess.PIPE,
            text=True,
        )
    try:
        result = launch_run(
            None,
            [f"run.mode='{mode}'", f"run.duration_s={duration_s}", f"run.log_dir='{log_dir}'",
             *overrides],
            live_port=port,
        )
        received = None
        if client is not None:
            out, _ = client.communicate(timeout=60)
            received = json.loads(out.strip().splitlines()[-1])["received"]
    finally:
        if client is not None and client.poll() is None:
            client.kill()
            client.communicate()
    run_log = read_log(result.log_path)
    summary = summarise(run_log)
    cycles = int(summary["cycles"])
    live_record = run_log.metadata.get("live", {})
    writer_cpu_ns = run_log.metadata.get("recorder", {}).get("writer_cpu_ns")
    start_ns = run_log.topics["/timing"].values["start_ns"]
    # The loop's own pace: in lock-step, how fast the run goes (a slower loop shows here).
    cycle_us = float(start_ns[-1] - start_ns[0]) / (len(start_ns) - 1) / 1e3

    def per_cycle_us(key: str) -> float | None:
        value = live_record.get(key)
        return int(value) / cycles / 1e3 if live and value is not None else None

    return {
        "variant": variant,
        "cycles": cycles,
        "cycle_us": cycle_us,
        "live_us_per_cycle": per_cycle_us("daemon_cpu_ns"),
        "writer_thread_us_per_cycle": (
            int(writer_cpu_ns) / cycles / 1e3 if writer_cpu_ns is not None else None
        ),
        "server_process_us_per_cycle": (
            (int(live_record["server_cpu_ns"]) - int(live_record["server_startup_cpu_ns"]))
            / cycles / 1e3
            if live and "server_cpu_ns" in live_record and "server_startup_cpu_ns" in live_record
            else None
        ),
        "server_startup_cpu_ms": (
            int(live_record["server_startup_cpu_ns"]) / 1e6
            if "server_startup_cpu_ns" in live_record else None
        ),
        "forwarded": (
            int(live_record.get("server_messages_forwarded", 0)) if live else None
        ),
        "received": received,
        "chunks_dropped": int(live_record.get("chunks_dropped", 0)) if live else None,
        "live_failed": live_record.get("failed"),
        "overruns": summary["overruns"],
        "lateness_p99_us": summary["lateness_p99_us"],
        "lateness_max_us": summary["lateness_max_us"],
        "recorder_dropped": summary["recorder_dropped"],
        "end_reason": summary["end_reason"],
    }


VARIANTS = ("no --live", "--live, no client", "client: layout topics", "client: every topic")


def _cell(value: Any, digits: int = 2) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:.{digits}f}"
    return str(value)


def table(
    rows: list[dict[str, Any]], mode: str, duration_s: float, overrides: list[str]
) -> str:
    lines = [
        f"live view cost, paper run over the bus, {mode}, {duration_s:g} s a run"
        + "".join(f", --set {override}" for override in overrides)
        + " "
        f"(target <= {TARGET_US_PER_CYCLE:g} us a cycle, no extra overruns)",
        "| variant | live path (daemon) us/cycle | writer thread us/cycle "
        "| live server process us/cycle (start-up ms) | forwarded | received | view dropped chunks "
        "| loop us/cycle | overruns | lateness p99 / max [us] | recorder dropped |",
        "| --- | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for row in rows:
        dropped = _cell(row["chunks_dropped"])
        if row["live_failed"]:
            dropped += f" (view failed: {row['live_failed']})"
        lines.append(
            f"| {row['variant']} | {_cell(row['live_us_per_cycle'])} "
            f"| {_cell(row['writer_thread_us_per_cycle'])} "
            f"| {_cell(row['server_process_us_per_cycle'], 1)} "
            f"({_cell(row['server_startup_cpu_ms'], 0)}) "
            f"| {_cell(row['forwarded'])} | {_cell(row['received'])} | {dropped} "
            f"| {_cell(row['cycle_us'], 1)} | {_cell(row['overruns'])} "
            f"| {_cell(row['lateness_p99_us'], 1)} / {_cell(row['lateness_max_us'], 0)} "
            f"| {_cell(row['recorder_dropped'])} |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=30.0, help="seconds a run")
    parser.add_argument("--mode", choices=("realtime", "lockstep"), default="realtime")
    parser.add_argument("--repeat", type=int, default=1, help="rounds of the four variants")
    parser.add_argument("--json", metavar="PATH", help="also write the rows as JSON")
    parser.add_argument(
        "--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
        help="config override for every run, e.g. controller.realtime_priority=50",
    )
    parser.add_argument("--client", type=int, metavar="PORT", help=argparse.SUPPRESS)
    parser.add_argument("--topics", default=EVERY_TOPIC, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.client is not None:
        client_main(args.client, args.topics, give_up_s=120.0)
        return 0
    rows = []
    with tempfile.TemporaryDirectory(prefix="live_cost_") as tmp:
        for round_index in range(args.repeat):
            for variant in VARIANTS:  # interleaved: the machine's moods fall on every variant
                row = one_run(
                    variant, args.mode, args.duration, Path(tmp) / f"{round_index}",
                    args.overrides,
                )
                rows.append(row)
                print(f"  {variant}: {_cell(row['live_us_per_cycle'])} us/cycle in the "
                      f"daemon, {_cell(row['server_process_us_per_cycle'])} in the server, "
                      f"{row['overruns']} overruns", file=sys.stderr, flush=True)
    print(table(rows, args.mode, args.duration, args.overrides))
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
