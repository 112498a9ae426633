"""Speed where users wait (issue 29, items 3 and 4): plan, synthesis, replay --verify and the
offline run, today's tree beside a baseline revision, in one run.

    .venv/bin/python bench/design_speed.py --baseline e1e0676 --log RUN60.mcap
    .venv/bin/python bench/design_speed.py --baseline main            # records a 60 s run first

Each figure is CPU time (``time.process_time``) in a child process of its own, baseline and
today's tree alternating, so the machine's other load falls on both alike; the table shows the
smallest of the rounds (the least disturbed). The baseline is ``git archive REV service``
unpacked into a temporary directory and put first on the child's ``sys.path``.

- plan / synthesis / plan + synthesis: the paper's start (``configs/paper.toml``) and the
  bang-bang path (whose plan costs nothing: synthesis alone, nearly). "one-shot" is a call that
  finds nothing kept from an earlier one (a run's own process, or the caches cleared); "again"
  is the same call repeated in one process (a sweep, the tests), where today's tree reuses
  what no plan changes and the plans it has made.
- verify: ``replay --verify``'s work (``evaluation.replay.verify``) on a recorded lock-step
  log; the 10-minute figure is ten times that of a 60 s log (an upper bound: the design's
  decoding and re-synthesis are paid once, not ten times).
- offline 4 s run: ``run_offline_with`` on a design made once (what a sweep's offline point
  costs its worker); runs a minute on 2 workers = 2 × 60 s / that CPU time.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

from ballbeam.entry import BLAS_THREAD_VARIABLES

REPO = Path(__file__).resolve().parents[1]

# Runs in the child: measures one figure with whichever ballbeam is first on sys.path.
CHILD = r"""
import json, sys, time
sys.path.insert(0, sys.argv[1])
what, configs, log = sys.argv[2], sys.argv[3], sys.argv[4]
import ballbeam.assembly as assembly
from ballbeam.config import load_config

def clear():
    # (a baseline from before the caches has nothing to clear)
    getattr(assembly, "clear_design_caches", lambda: None)()

def cpu(action, repeats, fresh):
    times = []
    for _ in range(repeats):
        if fresh:
            clear()
        started = time.process_time()
        action()
        times.append(time.process_time() - started)
    return min(times)

paper = load_config(configs + "/paper.toml", [])
bang = load_config(configs + "/paths/bang_bang.toml", ["tracker.horizon_s=8"])
out = {}
if what == "design":
    assembly.controller_design(paper)  # imports and first-call set-up out of the figures
    plan = assembly.make_plan(paper)
    for label, fresh in (("one_shot", True), ("again", False)):
        out[label] = {
            "plan_ms": 1e3 * cpu(lambda: assembly.make_plan(paper), 5, fresh),
            "synthesis_ms": 1e3 * cpu(lambda: assembly.controller_design(paper, plan), 5, fresh),
            "plan_synthesis_ms": 1e3 * cpu(lambda: assembly.controller_design(paper), 5, fresh),
            "bang_bang_ms": 1e3 * cpu(lambda: assembly.controller_design(bang), 5, fresh),
        }
elif what == "verify":
    from ballbeam.evaluation.replay import verify
    from ballbeam.logs.reader import read_log
    run_log = read_log(log)
    started = time.process_time()
    result = verify(run_log)
    out = {"verify_s": time.process_time() - started, "cycles": result.cycles_checked,
           "ok": result.ok, "resynthesis_max_rel_diff": result.resynthesis_difference}
elif what == "offline":
    config = load_config(configs + "/paper.toml", ["run.duration_s=4"])
    design = assembly.controller_design(config)
    t_star = assembly.minimum_time_s(config)
    out = {"offline_run_s": cpu(lambda: assembly.run_offline_with(config, design, t_star), 3,
                                False)}
print(json.dumps(out))
"""


def _child(tree: Path, what: str, configs: Path, log: str) -> dict[str, Any]:
    # One BLAS thread, as every process of the project runs (entry.limit_blas_threads): a
    # second one spins while it waits, and process_time counts its spinning.
    done = subprocess.run(
        [sys.executable, "-c", CHILD, str(tree), what, str(configs), log],
        check=True, capture_output=True, text=True,
        env={**os.environ, **{name: "1" for name in BLAS_THREAD_VARIABLES}},
    )
    result: dict[str, Any] = json.loads(done.stdout)
    return result


def _best(rounds: list[dict[str, Any]]) -> dict[str, Any]:
    """Each figure's smallest over the rounds (nested one level for the design figures)."""
    best: dict[str, Any] = dict(rounds[0])
    for other in rounds[1:]:
        for key, value in other.items():
            if isinstance(value, dict):
                best[key] = {k: min(best[key][k], v) for k, v in value.items()}
            elif isinstance(value, float) and key.endswith("_s"):
                best[key] = min(best[key], value)
    return best


def _record_60s(directory: str) -> str:
    from ballbeam.runtime.launcher import launch_run

    result = launch_run(
        str(REPO / "configs" / "paper.toml"), [f"run.log_dir='{directory}'", "run.duration_s=60"]
    )
    return str(result.log_path)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--baseline", default="main", help="git revision to compare with")
    parser.add_argument("--log", help="a recorded 60 s lock-step log (default: record one)")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--only", default="design,verify,offline")
    parser.add_argument("--json", metavar="PATH", help="also write the figures as JSON")
    args = parser.parse_args()
    selected = args.only.split(",")
    with tempfile.TemporaryDirectory() as scratch:
        old = Path(scratch) / "baseline"
        old.mkdir()
        archive = subprocess.run(
            ["git", "-C", str(REPO), "archive", args.baseline, "service", "configs"],
            check=True, capture_output=True,
        ).stdout
        subprocess.run(["tar", "-x", "-C", str(old)], input=archive, check=True)
        log = args.log or ("" if "verify" not in selected else _record_60s(scratch))
        trees = {
            "baseline": (old / "service", old / "configs"),
            "today": (REPO / "service", REPO / "configs"),
        }
        figures: dict[str, dict[str, Any]] = {name: {} for name in trees}
        for what in selected:
            rounds: dict[str, list[dict[str, Any]]] = {name: [] for name in trees}
            for _ in range(args.rounds):
                for name, (tree, configs) in trees.items():
                    rounds[name].append(_child(tree, what, configs, log))
            for name in trees:
                figures[name][what] = _best(rounds[name])
    _print(figures, args.baseline)
    text = json.dumps(figures, indent=2)
    print(text)
    if args.json:
        Path(args.json).write_text(text)
    return 0


def _print(figures: dict[str, dict[str, Any]], baseline: str) -> None:
    old, new = figures["baseline"], figures["today"]
    print(f"CPU time, smallest of the rounds: baseline {baseline} | today")
    if "design" in new:
        for label in ("one_shot", "again"):
            for key, text in (
                ("plan_ms", "plan, paper start"),
                ("synthesis_ms", "synthesis alone, paper start"),
                ("plan_synthesis_ms", "plan + synthesis, paper start"),
                ("bang_bang_ms", "plan + synthesis, bang-bang path"),
            ):
                a, b = old["design"][label][key], new["design"][label][key]
                print(f"  {label:<8} {text:<34} {a:8.1f} ms | {b:8.1f} ms  ({a / b:4.1f}x)")
    if "verify" in new:
        a, b = old["verify"], new["verify"]
        print(
            f"  verify, 60 s log ({b['cycles']} cycles)          {a['verify_s']:8.2f} s  |"
            f" {b['verify_s']:8.2f} s  (ok {a['ok']} / {b['ok']}; resynthesis max rel diff"
            f" {a['resynthesis_max_rel_diff']} / {b['resynthesis_max_rel_diff']})"
        )
        print(
            f"  verify, 10-minute equivalent (10 x)          {10 * a['verify_s']:8.1f} s  |"
            f" {10 * b['verify_s']:8.1f} s"
        )
    if "offline" in new:
        a, b = old["offline"]["offline_run_s"], new["offline"]["offline_run_s"]
        print(
            f"  offline 4 s run, one design                  {a:8.3f} s  | {b:8.3f} s"
            f"  (2 workers: {120 / a:5.0f} | {120 / b:5.0f} runs a minute)"
        )


if __name__ == "__main__":
    sys.exit(main())
