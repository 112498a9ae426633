"""Kill the daemon of real-time runs at random moments; every log must come back whole.

    .venv/bin/python bench/recover_soak.py              # 100 kills (about 5 minutes)
    .venv/bin/python bench/recover_soak.py --kills 10

Each run (paper set-up, real time) is killed with SIGKILL 0.2-2 s after its log appears;
``ballbeam run`` recovers its log. Prints how many logs the official mcap reader's
``get_summary`` opens, and how much log time was lost (the kill's wall time less the last
message's log time).
"""

from __future__ import annotations

import argparse
import random
import signal
import statistics
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

from mcap.reader import make_reader

from ballbeam.runtime.launcher import RunFailedError, launch_run


def kill_one(log_dir: Path, delay_s: float) -> tuple[bool, float | None, str]:
    killed_at_ns: list[int] = []

    def on_started(processes: dict[str, Any]) -> None:
        def kill() -> None:
            # From the moment the daemon has begun its log (`ballbeam run` creates it empty
            # before the daemon starts; the daemon's first write is its header).
            give_up = time.monotonic() + 60
            while not any(p.stat().st_size for p in log_dir.glob("*.mcap")) \
                    and time.monotonic() < give_up:
                time.sleep(0.01)
            time.sleep(delay_s)
            killed_at_ns.append(time.time_ns())
            processes["daemon"].send_signal(signal.SIGKILL)

        threading.Thread(target=kill, daemon=True).start()

    try:
        launch_run(
            None,
            ["run.mode='realtime'", "run.duration_s=5", f"run.log_dir='{log_dir}'"],
            on_started=on_started,
        )
        return False, None, "the run finished before the kill"
    except RunFailedError as error:
        message = str(error)
    logs = list(log_dir.glob("*.mcap"))
    if len(logs) != 1 or "made whole" not in message:
        return False, None, message.splitlines()[0]
    with logs[0].open("rb") as stream:
        summary = make_reader(stream).get_summary()
    if summary is None or summary.statistics is None or not killed_at_ns:
        return False, None, "no summary"
    return True, (killed_at_ns[0] - summary.statistics.message_end_time) / 1e6, ""


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--kills", type=int, default=100)
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args(argv)
    rng = random.Random(args.seed)
    recovered = 0
    lost_ms: list[float] = []
    with tempfile.TemporaryDirectory() as scratch:
        for attempt in range(args.kills):
            ok, lost, why = kill_one(Path(scratch) / str(attempt), rng.uniform(0.2, 2.0))
            if ok and lost is not None:
                recovered += 1
                lost_ms.append(lost)
            else:
                print(f"kill {attempt}: not recovered: {why}", file=sys.stderr)
    print(f"kills                 {args.kills}")
    print(f"logs recovered whole  {recovered}")
    if lost_ms:
        print(f"log time lost [ms]    median {statistics.median(lost_ms):.1f}, "
              f"max {max(lost_ms):.1f}")
    return 0 if recovered == args.kills else 1


if __name__ == "__main__":
    sys.exit(main())
