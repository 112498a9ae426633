"""ballbeam benchmarks: how fast, how steady, how close to the limit. Prints a table and JSON.

    .venv/bin/python bench/bench.py            # everything (about 25 minutes)
    .venv/bin/python bench/bench.py --quick    # short runs (about 3 minutes)
    .venv/bin/python bench/bench.py --only plan,replay --json bench.json

Needs the test extras (``pip install -e '.[test]'``) for the Ruckig comparison. Figures are
measured side by side in one run; the machine is shared, so read ratios and percentiles.
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from floors import exchange_floor, machine_stalls

from ballbeam.assembly import (
    clear_design_caches,
    controller_design,
    make_plan,
    run_offline,
)
from ballbeam.config import load_config
from ballbeam.evaluation.summary import summarise
from ballbeam.logs.reader import RunLog, read_log
from ballbeam.plant_assembly import physical_constants
from ballbeam.protocol.frames import SENSOR_ID
from ballbeam.runtime.launcher import launch_run

REPO = Path(__file__).resolve().parents[1]
PAPER = str(REPO / "configs" / "paper.toml")
PATHS = {
    "bang_bang": str(REPO / "configs" / "paths" / "bang_bang.toml"),
    "rate_limited_9325": str(REPO / "configs" / "paths" / "rate_limited_9325.toml"),
    "rate_limited_8": str(REPO / "configs" / "paths" / "rate_limited_8.toml"),
    "time_optimal": str(REPO / "configs" / "paths" / "time_optimal.toml"),
}


class MemoryWatch:
    """Samples the children's resident memory (VmRSS) until they exit."""

    def __init__(self) -> None:
        self.samples: dict[str, list[tuple[float, int]]] = {}
        self._threads: list[threading.Thread] = []

    def __call__(self, processes: dict[str, subprocess.Popen[str]]) -> None:
        for name, process in processes.items():
            series: list[tuple[float, int]] = []
            self.samples[name] = series
            thread = threading.Thread(target=self._poll, args=(process, series), daemon=True)
            thread.start()
            self._threads.append(thread)

    @staticmethod
    def _poll(process: subprocess.Popen[str], series: list[tuple[float, int]]) -> None:
        started = time.monotonic()
        status = Path(f"/proc/{process.pid}/status")
        while process.poll() is None:
            try:
                for line in status.read_text().splitlines():
                    if line.startswith("VmRSS:"):
                        series.append((time.monotonic() - started, int(line.split()[1])))
            except OSError:
                break
            time.sleep(0.5)

    def report(self) -> dict[str, dict[str, float]]:
        result = {}
        for name, series in self.samples.items():
            if len(series) < 4:
                continue
            kib = np.array([value for _, value in series], dtype=float)
            minutes = np.array([at for at, _ in series]) / 60.0
            quarter = max(1, len(kib) // 4)
            # Growth after warm-up (the first quarter): the least-squares slope of RSS.
            slope_kib_per_min = np.polyfit(minutes[quarter:], kib[quarter:], 1)[0]
            result[name] = {
                "growth_mib_per_min": float(slope_kib_per_min / 1024),
                "peak_rss_mib": float(kib.max() / 1024),
                "rss_first_quarter_mib": float(kib[quarter : 2 * quarter].mean() / 1024),
                "rss_last_quarter_mib": float(kib[-quarter:].mean() / 1024),
            }
        return result


def bus_run(config: str, *overrides: str, memory: MemoryWatch | None = None) -> dict[str, Any]:
    with tempfile.TemporaryDirectory() as log_dir:
        result = launch_run(config, [f"run.log_dir='{log_dir}'", *overrides], on_started=memory)
        run_log = read_log(result.log_path)
    summary = summarise(run_log, result.config.limits.theta_rad)
    timing = run_log.topics["/timing"].values
    summary["loop_wall_s"] = (int(timing["end_ns"][-1]) - int(timing["start_ns"][0])) * 1e-9
    summary["wall_time_s"] = result.wall_time_s
    lateness = np.asarray(timing["lateness_ns"], dtype=float) * 1e-3
    summary["lateness_p999_us"] = float(np.percentile(lateness, 99.9))
    summary.update(_exchange_split_us(run_log))
    return summary


def _exchange_split_us(run_log: RunLog) -> dict[str, float]:
    """Where a cycle goes, from the kernel receive stamps of the sensor frames and the send
    stamps of the commands: the daemon's turnaround (sensor frame in → command out) and the
    emulator's plus the bus's (command out → next sensor frame in). Lock-step's split; in
    real time the second part also holds the wait for the next period."""
    rx = run_log.topics["/can/rx"].values
    sensor_in_s = np.asarray(rx["bus_time_s"][rx["arbitration_id"] == SENSOR_ID])
    command_out_s = np.asarray(run_log.topics["/can/tx"].values["bus_time_s"])
    n = min(len(sensor_in_s), len(command_out_s)) - 1
    daemon_us = (command_out_s[:n] - sensor_in_s[:n]) * 1e6
    emulator_us = (sensor_in_s[1 : n + 1] - command_out_s[:n]) * 1e6
    return {
        "daemon_turnaround_p50_us": float(np.median(daemon_us)),
        "emulator_and_bus_p50_us": float(np.median(emulator_us)),
        "cycle_mean_us": float(np.mean(daemon_us + emulator_us)),
    }


# -- 1. real-time loop ---------------------------------------------------------------------------
NORMAL = ("controller.realtime_priority=0", "plant.realtime_priority=0")  # no SCHED_FIFO
REALTIME_VARIANTS: dict[str, tuple[str, ...]] = {
    "sleep only": ("controller.spin_us=0", "controller.cpu=-1", "plant.cpu=-1", *NORMAL),
    "sleep + spin 200 µs": (
        "controller.spin_us=200", "controller.cpu=-1", "plant.cpu=-1", *NORMAL
    ),
    "spin + CPU affinity": ("controller.spin_us=200", "controller.cpu=1", "plant.cpu=0", *NORMAL),
    "spin + affinity + SCHED_FIFO": (
        "controller.spin_us=200",
        "controller.cpu=1",
        "plant.cpu=0",
        "controller.realtime_priority=50",
        "plant.realtime_priority=40",
    ),
}


def bench_machine_stalls(duration_s: float) -> dict[str, Any]:
    """The machine's own stalls, probed the way the daemon runs: pinned, normal and FIFO."""
    return {
        "normal": machine_stalls(duration_s),
        "SCHED_FIFO": machine_stalls(duration_s, fifo_priority=50),
    }


def bench_realtime(duration_s: float) -> list[dict[str, Any]]:
    rows = []
    for rate_hz in (1000, 2000):
        for variant, overrides in REALTIME_VARIANTS.items():
            summary = bus_run(
                PAPER,
                "run.mode='realtime'",
                f"run.duration_s={duration_s}",
                f"controller.rate_hz={rate_hz}",
                f"plant.sensor_rate_hz={rate_hz}",
                *overrides,
            )
            rows.append(
                {
                    "rate_hz": rate_hz,
                    "variant": variant,
                    "cycles": summary["cycles"],
                    "lateness_p50_us": summary["lateness_p50_us"],
                    "lateness_p99_us": summary["lateness_p99_us"],
                    "lateness_p999_us": summary["lateness_p999_us"],
                    "lateness_max_us": summary["lateness_max_us"],
                    "overruns": summary["overruns"],
                    "latency_p50_us": summary["latency_p50_us"],
                    "latency_p99_us": summary["latency_p99_us"],
                    "coasted_cycles": summary["coasted_cycles"],
                    "settle_time_s": summary["settle_time_s"],
                }
            )
            print(
                f"  realtime {rate_hz} Hz, {variant}: p99 {summary['lateness_p99_us']:.1f} µs,"
                f" overruns {summary['overruns']}",
                file=sys.stderr,
            )
    return rows


# -- 2. lock-step speed --------------------------------------------------------------------------
LOCKSTEP_VARIANTS: dict[str, tuple[str, ...]] = {
    "block in recv (default)": (),
    "poll 300 µs, then block": ("run.lockstep_poll_us=300",),
}


def bench_lockstep(duration_s: float) -> list[dict[str, Any]]:
    rows = []
    for variant, overrides in LOCKSTEP_VARIANTS.items():
        summary = bus_run(PAPER, f"run.duration_s={duration_s}", *overrides)
        simulated_s = summary["cycles"] * 1e-3
        rows.append(
            {
                "variant": variant,
                "simulated_s": simulated_s,
                "loop_wall_s": summary["loop_wall_s"],
                "speed_x_realtime": simulated_s / summary["loop_wall_s"],
                "process_wall_s": summary["wall_time_s"],
                **{
                    key: summary[key]
                    for key in ("daemon_turnaround_p50_us", "emulator_and_bus_p50_us",
                                "cycle_mean_us")
                },
            }
        )
    return rows


# Lock-step's frames: on the classic bus the sensor and two truth frames out of the plant, one
# command back; authenticated (a run's default on this bus), one 64-byte sensor frame that
# carries the truth, one command back, the same MACs made and checked.
FLOOR_PATTERNS = {
    "bare ping-pong (1 frame + 1), blocking": (1, False, False),
    "classic pattern (3 frames + 1), blocking": (3, False, False),
    "our pattern, authenticated (1 + 1), blocking": (1, False, True),
    "bare ping-pong (1 frame + 1), polling": (1, True, False),
    "classic pattern (3 frames + 1), polling": (3, True, False),
    "our pattern, authenticated (1 + 1), polling": (1, True, True),
}


def bench_exchange_floor(cycles: int) -> list[dict[str, Any]]:
    """The same bus with nothing but the frames: how fast lock-step could ever go."""
    bus = load_config(PAPER, []).bus
    return [
        {"pattern": pattern, **exchange_floor(bus, cycles, plant_frames, poll, authenticated)}
        for pattern, (plant_frames, poll, authenticated) in FLOOR_PATTERNS.items()
    ]


# -- 3. plan + synthesis -------------------------------------------------------------------------
def _median_s(
    action: Callable[[], object], repeats: int, before: Callable[[], None] = lambda: None
) -> float:
    times = []
    for _ in range(repeats):
        before()
        started = time.perf_counter()
        action()
        times.append(time.perf_counter() - started)
    return statistics.median(times)


def bench_plan(repeats: int) -> dict[str, Any]:
    import ruckig

    from ballbeam.core.planning.rate_limited import solve_jerk_profile

    rows: dict[str, Any] = {}
    for name, path in PATHS.items():
        config = load_config(path, ["tracker.horizon_s=8"])
        plan = make_plan(config)
        # One-shot: each call as a run's own process pays it (the assembly keeps plans and the
        # plan-free design pieces per process; cleared before each); "again": kept.
        rows[name] = {
            "duration_s": plan.duration_s,
            "plan_ms": 1e3
            * _median_s(lambda config=config: make_plan(config), repeats, clear_design_caches),
            "plan_plus_synthesis_ms": 1e3
            * _median_s(
                lambda config=config: controller_design(config), repeats, clear_design_caches
            ),
            "plan_plus_synthesis_again_ms": 1e3
            * _median_s(lambda config=config: controller_design(config), repeats),
        }
    # Rate-limited planner against Ruckig on the same inputs (paper start, both slopes).
    constants = physical_constants(load_config(PAPER))
    acceleration_max = abs(constants.gamma) * math.radians(52)
    start_accel = constants.gamma * math.radians(-52)
    for slope in (9.325, 8.0):
        jerk_max = abs(constants.gamma) * slope

        def ours(jerk_max: float = jerk_max) -> object:
            return solve_jerk_profile(0.195, 0.0, start_accel, acceleration_max, jerk_max)

        def theirs(jerk_max: float = jerk_max) -> float:
            generator = ruckig.Ruckig(1)
            params = ruckig.InputParameter(1)
            params.current_position, params.current_velocity = [0.195], [0.0]
            params.current_acceleration = [start_accel]
            params.target_position, params.target_velocity = [0.0], [0.0]
            params.target_acceleration = [0.0]
            params.max_velocity, params.max_acceleration = [1e3], [acceleration_max]
            params.max_jerk = [jerk_max]
            trajectory = ruckig.Trajectory(1)
            generator.calculate(params, trajectory)
            return float(trajectory.duration)

        rows[f"rate_limited_vs_ruckig_{slope}"] = {
            "ours_duration_s": ours().duration_s,  # type: ignore[attr-defined]
            "ruckig_duration_s": theirs(),
            "ours_us": 1e6 * _median_s(ours, repeats * 10),
            "ruckig_us": 1e6 * _median_s(theirs, repeats * 10),
        }
    return rows


# -- 4. replay -----------------------------------------------------------------------------------
def bench_replay(duration_s: float) -> dict[str, Any]:
    with tempfile.TemporaryDirectory() as log_dir:
        result = launch_run(PAPER, [f"run.log_dir='{log_dir}'", f"run.duration_s={duration_s}"])
        size_mb = result.log_path.stat().st_size / 1e6
        started = time.perf_counter()
        run_log = read_log(result.log_path)
        read_s = time.perf_counter() - started
        summarise(run_log)
        total_s = time.perf_counter() - started
        started = time.perf_counter()
        from ballbeam.evaluation.replay import verify

        verified = verify(run_log)
        verify_s = time.perf_counter() - started
    return {
        "run_duration_s": duration_s,
        "file_mb": size_mb,
        "messages": run_log.message_count,
        "read_s": read_s,
        "analyse_s": total_s,
        "messages_per_s": run_log.message_count / read_s,
        "verify_s": verify_s,
        "verify_ok": verified.ok,
    }


# -- 5. control quality against the physical limit -----------------------------------------------
QUALITY_FIGURES = (
    "rest_time_s", "rest_ratio", "input_tv_ratio", "dither_hz", "largest_step_v",
    "max_abs_theta_deg", "settle_time_s",
)


def bench_quality() -> dict[str, Any]:
    """Each path's run, offline and over the bus in lock-step, judged as docs/design.md §6 says:
    rest (0.5 mm, 0.5°) against the true minimum time T*, chatter, the angle; the paper's own
    design beside ours. (bench/control_quality.py runs the full sets of starts and seeds.)"""
    rows: dict[str, Any] = {}
    paths = {**PATHS, "paper_design": str(REPO / "configs" / "paths" / "paper_design.toml")}
    for name, path in paths.items():
        offline = run_offline(load_config(path)).metrics.as_dict()
        over_bus = bus_run(path)
        rows[name] = {
            "offline": {key: offline[key] for key in QUALITY_FIGURES},
            "bus": {key: over_bus[key] for key in QUALITY_FIGURES},
        }
    return rows


# -- 6. memory -----------------------------------------------------------------------------------
def bench_memory(duration_s: float) -> dict[str, Any]:
    memory = MemoryWatch()
    bus_run(PAPER, "run.mode='realtime'", f"run.duration_s={duration_s}", memory=memory)
    return {"duration_s": duration_s, **memory.report()}


def print_tables(figures: dict[str, Any]) -> None:
    """The headline figures as plain tables (the JSON follows for machines)."""
    if "plan" in figures:
        print("plan + synthesis, 8 s horizon at 1 kHz")
        for name, row in figures["plan"].items():
            if "plan_ms" in row:
                print(
                    f"  {name:<22} duration {row['duration_s']:.4f} s"
                    f"   plan {row['plan_ms']:7.2f} ms"
                    f"   plan+synthesis {row['plan_plus_synthesis_ms']:7.2f} ms"
                    f" (again {row['plan_plus_synthesis_again_ms']:6.2f} ms)"
                )
            else:
                print(
                    f"  {name:<22} ours {row['ours_duration_s']:.6f} s in {row['ours_us']:.1f} µs;"
                    f" Ruckig {row['ruckig_duration_s']:.6f} s in {row['ruckig_us']:.1f} µs"
                )
    if "lockstep" in figures:
        print("lock-step: variant, speed, cycle mean µs; p50 µs of daemon turnaround, emulator+bus")
        for row in figures["lockstep"]:
            print(
                f"  {row['variant']:<34} {row['speed_x_realtime']:5.2f}x"
                f" {row['cycle_mean_us']:7.1f} {row['daemon_turnaround_p50_us']:7.1f}"
                f" {row['emulator_and_bus_p50_us']:7.1f}"
            )
    if "exchange_floor" in figures:
        print(
            "lock-step floor: bare frame exchange over the same bus; µs a cycle, ceiling,"
            " CPU µs a cycle of controller and plant side"
        )
        for row in figures["exchange_floor"]:
            print(
                f"  {row['pattern']:<42} {row['cycle_us']:6.1f}"
                f"  {row['ceiling_x_realtime_at_1khz']:5.1f}x"
                f"  {row['controller_cpu_us_per_cycle']:6.1f} {row['plant_cpu_us_per_cycle']:6.1f}"
            )
    if "quality" in figures:
        print("control quality: rest ratio, input TV ratio, dither Hz, largest step V, max |θ|°")
        for name, row in figures["quality"].items():
            for where in ("offline", "bus"):
                q = row[where]
                rest = f"{q['rest_ratio']:.3f}" if q["rest_ratio"] is not None else "never"
                print(
                    f"  {name:<22} {where:<8} {rest:>6} {q['input_tv_ratio']:7.2f}"
                    f" {q['dither_hz']:5.1f} {q['largest_step_v']:6.2f}"
                    f" {q['max_abs_theta_deg']:8.3f}"
                )
    if "replay" in figures:
        row = figures["replay"]
        print(
            f"replay: {row['run_duration_s']:.0f} s run, {row['messages']} messages,"
            f" read {row['read_s']:.2f} s, metrics {row['analyse_s']:.2f} s,"
            f" verify {row['verify_s']:.2f} s"
        )
    if "realtime" in figures:
        print(
            "real time: rate  variant  lateness p50/p99/p99.9/max µs  overruns  latency p50/p99 µs"
        )
        for row in figures["realtime"]:
            print(
                f"  {row['rate_hz']:>5} Hz  {row['variant']:<30} {row['lateness_p50_us']:6.1f}"
                f" {row['lateness_p99_us']:7.1f} {row['lateness_p999_us']:7.1f}"
                f" {row['lateness_max_us']:8.1f}  {row['overruns']:>6}"
                f"  {row['latency_p50_us']:6.1f} {row['latency_p99_us']:6.1f}"
            )
    if "machine_stalls" in figures:
        print(
            "machine stalls: a pinned bare clock loop; stalls a minute >= 0.25 / 1 / 2 ms, longest"
        )
        for scheduling, probe in figures["machine_stalls"].items():
            for cpu, row in probe.items():
                if isinstance(row, dict):
                    print(
                        f"  {scheduling:<10} {cpu}  {row['stalls_over_250us_per_min']:6.1f}"
                        f" {row['stalls_over_1000us_per_min']:6.1f}"
                        f" {row['stalls_over_2000us_per_min']:6.1f}"
                        f"  {row['longest_stall_us']:7.0f} µs  ({row['scheduling']})"
                    )
    if "memory" in figures:
        for name, row in figures["memory"].items():
            if isinstance(row, dict):
                print(
                    f"memory {name}: peak {row['peak_rss_mib']:.1f} MiB, first quarter"
                    f" {row['rss_first_quarter_mib']:.1f}, last quarter"
                    f" {row['rss_last_quarter_mib']:.1f}, growth"
                    f" {row['growth_mib_per_min']:+.3f} MiB/min"
                )


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="short runs")
    parser.add_argument(
        "--only",
        default="realtime,machine_stalls,lockstep,exchange_floor,plan,replay,quality,memory",
    )
    parser.add_argument("--json", metavar="PATH", help="also write the figures as JSON")
    args = parser.parse_args()
    quick = args.quick
    selected = set(args.only.split(","))
    figures: dict[str, Any] = {}
    steps: list[tuple[str, Callable[[], Any]]] = [
        ("plan", lambda: bench_plan(5 if quick else 20)),
        ("lockstep", lambda: bench_lockstep(10.0 if quick else 60.0)),
        ("exchange_floor", lambda: bench_exchange_floor(5000 if quick else 30000)),
        ("quality", bench_quality),
        ("replay", lambda: bench_replay(60.0 if quick else 600.0)),
        ("realtime", lambda: bench_realtime(10.0 if quick else 60.0)),
        ("machine_stalls", lambda: bench_machine_stalls(10.0 if quick else 60.0)),
        ("memory", lambda: bench_memory(120.0 if quick else 600.0)),
    ]
    for name, step in steps:
        if name in selected:
            print(f"bench: {name} ...", file=sys.stderr)
            figures[name] = step()
    print_tables(figures)
    text = json.dumps(figures, indent=2, default=float)
    print(text)
    if args.json:
        Path(args.json).write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
