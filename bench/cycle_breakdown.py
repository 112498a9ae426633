"""Where a lock-step cycle's microseconds go, on each side, from a profile.

    .venv/bin/python bench/cycle_breakdown.py [--short-s 1] [--long-s 4] [--json out.json]

Two ``ballbeam run``s in lock-step (the paper's task, its default bus and authentication), the
same but for their length, each with every process under ``cProfile`` (a ``sitecustomize`` on
``PYTHONPATH``). Each function's own time goes to a part of the cycle by the file it is in (a
built-in's to its caller's part, but for the socket calls, the MAC and start-up's own); the
longer run's time less the shorter's, over the cycles between them, is what a cycle costs: the
start-up, the planning and the shut-down are the same in both and cancel. A profile slows what
it measures (every call pays its hook), so the parts are also given as shares, and those shares
of the cycle time an unprofiled run of the same length measured beside them.
"""

from __future__ import annotations

import argparse
import json
import os
import pstats
import subprocess
import sys
import tempfile
from collections import Counter
from pathlib import Path
from typing import Any

from ballbeam.logs.reader import read_log

REPO = Path(__file__).resolve().parents[1]
BALLBEAM = [sys.executable, "-m", "ballbeam"]

SITECUSTOMIZE = """\
import atexit, cProfile, os, sys
_profile = cProfile.Profile()
_profile.enable()
def _dump():
    _profile.disable()
    out = os.environ["BALLBEAM_BENCH_PROFILE_DIR"]
    _profile.dump_stats(os.path.join(out, f"{os.getpid()}.prof"))
atexit.register(_dump)
"""

# Parts of a cycle by where the code is (first match wins); built-ins by name.
PARTS_BY_FILE = (
    ("MAC (SecOC)", ("protocol/secoc.py", "/hmac.py")),
    ("encode and decode", ("/protocol/", "/cantools/")),
    ("recording", ("/logs/", "/mcap/", "/zstandard/")),
    ("control law / plant physics", ("/core/",)),
    ("bus (python-can, sockets)", ("/can/", "runtime/bus.py", "/msgpack/")),
    ("loop (daemon, emulator)", ("runtime/daemon/", "ballbeam_emulator/", "runtime/")),
)
WAITING = "waiting for the other side (select)"
PARTS_BY_BUILTIN = (
    (WAITING, ("select.select", "select.poll", "method 'poll'")),
    ("MAC (SecOC)", ("hmac_digest", "compare_digest", "openssl_sha256")),
    ("bus (python-can, sockets)", ("recvmsg", "sendto", "recv_into", "posix.read")),
    ("start-up", ("marshal.", "builtins.exec", "builtins.compile", "__build_class__",
                  "_imp.", "posix.stat", "io.open_code")),
)
STARTUP = "start-up"
OTHER = "other"


def _part_of_file(filename: str) -> str | None:
    if "importlib" in filename or filename.startswith("<frozen"):
        return STARTUP
    for part, needles in PARTS_BY_FILE:
        if any(needle in filename for needle in needles):
            return part
    return None


def _parts(stats: dict[Any, Any]) -> Counter[str]:
    """Seconds of own time per part of the cycle (and per function, for the parts' contents,
    under keys ``"<part>: <function>"``)."""
    own: Counter[str] = Counter()
    for (filename, _line, name), (_cc, _nc, own_s, _cum_s, callers) in stats.items():
        part = _part_of_file(filename) if filename != "~" else None
        if filename == "~":
            part = next((p for p, needles in PARTS_BY_BUILTIN
                         if any(needle in name for needle in needles)), None)
            if part is None and callers:  # the caller that spent most in it
                caller = max(callers.items(), key=lambda item: item[1][2])[0]
                part = _part_of_file(caller[0]) if caller[0] != "~" else None
        own[part or OTHER] += own_s
        own[f"{part or OTHER}: {Path(filename).name}:{name}"] += own_s
    return own


def _side(stats: dict[Any, Any]) -> str | None:
    files = {filename for filename, _line, _name in stats}
    if any("ballbeam_emulator/node.py" in f for f in files):
        return "emulator"
    if any("runtime/daemon/loop.py" in f for f in files):
        return "daemon"
    return None  # the launcher


def _profiled_run(duration_s: float, log_dir: Path) -> tuple[dict[str, Counter[str]], int]:
    """Per side (daemon, emulator), seconds per part; and the cycles the run made."""
    with tempfile.TemporaryDirectory() as hook, tempfile.TemporaryDirectory() as out:
        Path(hook, "sitecustomize.py").write_text(SITECUSTOMIZE)
        env = {**os.environ, "PYTHONPATH": os.pathsep.join(
            [hook, *filter(None, [os.environ.get("PYTHONPATH")])]),
            "BALLBEAM_BENCH_PROFILE_DIR": out}
        summary = _run(duration_s, log_dir, env)
        sides: dict[str, Counter[str]] = {}
        for path in Path(out).glob("*.prof"):
            stats = pstats.Stats(str(path)).stats  # type: ignore[attr-defined]
            side = _side(stats)
            if side is not None:
                sides[side] = _parts(stats)
    return sides, int(summary["cycles"])


def _run(duration_s: float, log_dir: Path, env: dict[str, str] | None = None) -> dict[str, Any]:
    done = subprocess.run(
        [*BALLBEAM, "run", "--json", "--set", "run.mode='lockstep'",
         "--set", f"run.duration_s={duration_s}", "--set", f"run.log_dir='{log_dir}'"],
        capture_output=True, text=True, env=env, timeout=600, cwd=REPO,
    )
    if done.returncode != 0:
        raise RuntimeError(f"ballbeam run failed ({done.returncode}): {done.stderr[-2000:]}")
    summary: dict[str, Any] = json.loads(done.stdout)
    return summary


def cycle_breakdown(short_s: float = 1.0, long_s: float = 4.0) -> dict[str, Any]:
    with tempfile.TemporaryDirectory() as log_dir:
        plain = _run(long_s, Path(log_dir))
        timing = read_log(Path(plain["log_path"])).topics["/timing"].values
        loop_s = (int(timing["end_ns"][-1]) - int(timing["start_ns"][0])) * 1e-9
        plain_cycle_us = loop_s / int(plain["cycles"]) * 1e6
        short, short_cycles = _profiled_run(short_s, Path(log_dir))
        long, long_cycles = _profiled_run(long_s, Path(log_dir))
    cycles = long_cycles - short_cycles
    result: dict[str, Any] = {"cycles_between": cycles, "unprofiled_cycle_us": plain_cycle_us}
    for side in ("daemon", "emulator"):
        per_cycle_us = {
            key: (long[side][key] - short[side].get(key, 0.0)) / cycles * 1e6
            for key in long[side]
            if not key.startswith(STARTUP)
        }
        parts = {key: us for key, us in per_cycle_us.items() if ": " not in key}
        total = sum(parts.values())
        working = total - parts.get(WAITING, 0.0)
        result[side] = {
            part: {"profiled_us": us, "share": us / total}
            for part, us in sorted(parts.items(), key=lambda item: -item[1])
        }
        result[side + "_profiled_total_us"] = total
        result[side + "_profiled_working_us"] = working
        result[side + "_largest_functions_us"] = dict(sorted(
            ((key, us) for key, us in per_cycle_us.items() if ": " in key),
            key=lambda item: -item[1],
        )[:15])
    return result


def print_breakdown(result: dict[str, Any]) -> None:
    print(f"lock-step cycle breakdown (profiled, {result['cycles_between']} cycles between the "
          f"two runs; own time per part, a cycle)")
    for side in ("daemon", "emulator"):
        total, working = result[side + "_profiled_total_us"], result[side + "_profiled_working_us"]
        print(f"  {side}: {total:.1f} µs a cycle profiled, {working:.1f} µs of it working "
              f"(an unprofiled run: {result['unprofiled_cycle_us']:.1f} µs a cycle, both sides)")
        for part, row in result[side].items():
            print(f"    {part:<38} {row['profiled_us']:7.1f} µs  {100 * row['share']:5.1f} %")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--short-s", type=float, default=1.0)
    parser.add_argument("--long-s", type=float, default=4.0)
    parser.add_argument("--json")
    args = parser.parse_args(argv)
    if not 0 < args.short_s < args.long_s:
        print("cycle_breakdown: need 0 < --short-s < --long-s", file=sys.stderr)
        return 2
    result = cycle_breakdown(args.short_s, args.long_s)
    print_breakdown(result)
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
