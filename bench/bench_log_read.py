"""Write a synthetic run log the size of a 10-minute 1 kHz run, then read it back.

Channel mix per 1 ms cycle, as the controller daemon records it: 4 raw CAN frames (3 received
sensor/truth frames, 1 sent voltage frame) and 7 fixed-layout messages of 4-8 float64/int64
fields (sensor, command, estimate, reference, truth angle, truth ball, timing), plus a JSON
fault event now and then.

Prints the recorder's cost per record() call on the producing thread, write time, file size,
and the read time and rate of ``read_log`` for all topics and for a few.

    .venv/bin/python bench/bench_log_read.py [--minutes 10] [--out /tmp/bench.mcap]
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time

import numpy as np

from ballbeam.logs import Recorder, StructSchema, read_log

CAN_FRAME = StructSchema(
    "ballbeam_msgs/msg/CanFrame",
    (
        ("bus_time_s", "float64"),
        ("arbitration_id", "uint32"),
        ("dlc", "uint8"),
        ("data", "uint8[8]"),
    ),
)
STRUCTS: dict[str, StructSchema] = {
    "/sensor": StructSchema(
        "ballbeam_msgs/msg/Sensor",
        (
            ("counter", "int64"),
            ("angle_rad", "float64"),
            ("position_m", "float64"),
            ("bus_time_s", "float64"),
        ),
    ),
    "/command": StructSchema(
        "ballbeam_msgs/msg/Command",
        (
            ("counter", "int64"),
            ("voltage_v", "float64"),
            ("voltage_unclamped_v", "float64"),
            ("feedforward_v", "float64"),
            ("feedback_v", "float64"),
        ),
    ),
    "/estimate": StructSchema(
        "ballbeam_msgs/msg/Estimate",
        (
            ("angle_rad", "float64"),
            ("rate_rad_s", "float64"),
            ("ball_velocity_m_s", "float64"),
            ("ball_position_m", "float64"),
            ("innovation_angle_rad", "float64"),
            ("innovation_position_m", "float64"),
        ),
    ),
    "/reference": StructSchema(
        "ballbeam_msgs/msg/Reference",
        (
            ("angle_rad", "float64"),
            ("rate_rad_s", "float64"),
            ("ball_velocity_m_s", "float64"),
            ("ball_position_m", "float64"),
            ("plan_time_s", "float64"),
        ),
    ),
    "/truth/angle": StructSchema(
        "ballbeam_msgs/msg/TruthAngle",
        (
            ("angle_rad", "float64"),
            ("rate_rad_s", "float64"),
            ("current_a", "float64"),
            ("voltage_applied_v", "float64"),
        ),
    ),
    "/truth/ball": StructSchema(
        "ballbeam_msgs/msg/TruthBall",
        (
            ("position_m", "float64"),
            ("velocity_m_s", "float64"),
            ("acceleration_m_s2", "float64"),
            ("beam_angle_rad", "float64"),
        ),
    ),
    "/timing": StructSchema(
        "ballbeam_msgs/msg/Timing",
        (
            ("cycle", "int64"),
            ("due_ns", "int64"),
            ("wake_ns", "int64"),
            ("done_ns", "int64"),
            ("late_ns", "int64"),
            ("overruns", "int64"),
            ("skipped", "int64"),
            ("bus_rx", "int64"),
        ),
    ),
}
REAL_CHUNK_BYTES = 38_000  # uncompressed bytes of one 50 ms flush of this channel mix
FAULT_SCHEMA = {
    "type": "object",
    "properties": {"kind": {"type": "string"}, "cycle": {"type": "integer"}},
}


def write_log(path: str, cycles: int) -> tuple[float, float, int, int]:
    """Record ``cycles`` 1 ms cycles; returns (seconds, record() µs per call, messages, drops)."""
    rng = np.random.default_rng(1)
    noise = rng.standard_normal(4096).tolist()
    payloads = [bytes(rng.integers(0, 256, 8, dtype=np.uint8)) for _ in range(64)]
    record_s = 0.0
    count = 0
    start_s = time.perf_counter()
    with Recorder(
        path,
        metadata={"run": {"config": "bench", "cycles": str(cycles)}},
        attachments=[("config.toml", "application/toml", b"[bench]\nperiod_ns = 1000000\n")],
        queue_size=65_536,
        # This producer runs far faster than 1 kHz, so the 50 ms flushes would make few, large
        # chunks; cap chunks at what a 50 ms flush holds in a real run (~550 messages).
        chunk_size_bytes=REAL_CHUNK_BYTES,
    ) as rec:
        can_rx = rec.add_struct_channel("/can/rx", CAN_FRAME)
        can_tx = rec.add_struct_channel("/can/tx", CAN_FRAME)
        handles = {topic: rec.add_struct_channel(topic, s) for topic, s in STRUCTS.items()}
        fault = rec.add_json_channel("/fault", "ballbeam_msgs/Fault", FAULT_SCHEMA)
        sensor, command, estimate = handles["/sensor"], handles["/command"], handles["/estimate"]
        reference, truth_a = handles["/reference"], handles["/truth/angle"]
        truth_b, timing = handles["/truth/ball"], handles["/timing"]
        record = rec.record
        for k in range(cycles):
            t = 1_000_000_000 + k * 1_000_000
            x = noise[k & 4095]
            s = k * 1e-3
            data = payloads[k & 63]
            # Values are built before the clock starts: only record() is timed.
            msgs = (
                (can_rx, t, (s, 0x101, 8, data)),
                (can_rx, t + 1, (s, 0x102, 8, data)),
                (can_rx, t + 2, (s, 0x103, 8, data)),
                (sensor, t + 3, (k, x, 0.1 * x, s)),
                (estimate, t + 4, (x, 2 * x, 3 * x, 4 * x, 0.01 * x, 0.02 * x)),
                (reference, t + 5, (x, x, x, x, s)),
                (command, t + 6, (k, x, 1.1 * x, 0.5 * x, 0.6 * x)),
                (can_tx, t + 7, (s, 0x201, 8, data)),
                (truth_a, t + 8, (x, x, x, x)),
                (truth_b, t + 9, (x, x, x, x)),
                (timing, t + 10, (k, t, t + 20_000, t + 80_000, 20_000, 0, 0, 3)),
            )
            t0 = time.perf_counter()
            for handle, log_time_ns, values in msgs:
                record(handle, log_time_ns, values)
            record_s += time.perf_counter() - t0
            count += 11
            if k % 60_000 == 0:
                record(fault, t + 11, {"kind": "bench", "cycle": k})
                count += 1
            # A real loop waits 1 ms per cycle; this one runs flat out, so it must let the
            # writer keep up instead of overflowing the queue.
            while rec.queued > 40_000:
                time.sleep(0.002)
        dropped = rec.dropped
    return time.perf_counter() - start_s, record_s / count * 1e6, count, dropped


def paced_loop(path: str | None, seconds: float) -> tuple[np.ndarray, np.ndarray]:
    """A real 1 kHz absolute-deadline loop recording the same mix (or nothing if path is None).

    Returns wake-up lateness per cycle and record() cost per call, both in µs: the GIL is
    shared with the writer thread, so the recorder shows up as lateness, not only as cost.
    """
    period_ns = 1_000_000
    cycles = int(seconds * 1000)
    late_us = np.zeros(cycles)
    cost_us = np.zeros(cycles)
    data = bytes(8)
    rec = Recorder(path) if path is not None else None
    handles = []
    if rec is not None:
        can = rec.add_struct_channel("/can/rx", CAN_FRAME)
        handles = [(can, (0.0, 0x101, 8, data))] * 4 + [
            (rec.add_struct_channel(topic, s), (1,) + (0.5,) * (len(s.fields) - 1))
            for topic, s in STRUCTS.items()
        ]
    due_ns = time.monotonic_ns() + period_ns
    for k in range(cycles):
        while (wait_ns := due_ns - time.monotonic_ns()) > 0:
            if wait_ns > 200_000:
                time.sleep((wait_ns - 100_000) / 1e9)
        now_ns = time.monotonic_ns()
        late_us[k] = (now_ns - due_ns) / 1e3
        if rec is not None:
            t0 = time.perf_counter_ns()
            for handle, values in handles:
                rec.record(handle, now_ns, values)
            cost_us[k] = (time.perf_counter_ns() - t0) / 1e3 / len(handles)
        due_ns += period_ns
    if rec is not None:
        rec.close()
    return late_us, cost_us


def _pct(x: np.ndarray) -> str:
    p50, p99, p999 = np.percentile(x, [50, 99, 99.9])
    return f"p50 {p50:.2f}, p99 {p99:.2f}, p99.9 {p999:.2f}, max {x.max():.2f}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--minutes", type=float, default=10.0)
    parser.add_argument("--out", default=None, help="keep the log here (default: temp file)")
    parser.add_argument("--paced-s", type=float, default=5.0, help="seconds of real 1 kHz loop")
    args = parser.parse_args()
    cycles = int(args.minutes * 60_000)

    with tempfile.TemporaryDirectory() as tmp:
        if args.paced_s > 0:
            late_bare, _ = paced_loop(None, args.paced_s)
            late_rec, cost = paced_loop(os.path.join(tmp, "paced.mcap"), args.paced_s)
            print(f"1 kHz loop, {args.paced_s:g} s, 11 record() calls per cycle:")
            print(f"  record() cost, µs per call: {_pct(cost)}")
            print(f"  wake-up lateness without recorder, µs: {_pct(late_bare)}")
            print(f"  wake-up lateness with recorder, µs:    {_pct(late_rec)}")

        path = args.out or os.path.join(tmp, "bench.mcap")
        write_s, record_us, count, dropped = write_log(path, cycles)
        size = os.path.getsize(path)
        print(f"run: {args.minutes:g} min at 1 kHz, {count:,} messages, {dropped} dropped")
        print(f"record() in a flat-out producer: {record_us:.2f} µs per call (mean)")
        print(
            f"write: {write_s:.1f} s ({count / write_s:,.0f} msg/s, writer thread bound), "
            f"file {size / 1e6:.1f} MB ({size / count:.1f} B/msg)"
        )

        for label, topics in (
            ("all topics", None),
            ("3 topics", ["/sensor", "/command", "/estimate"]),
            ("CAN only", ["/can/rx", "/can/tx"]),
        ):
            best_s = float("inf")
            for _ in range(3):
                t0 = time.perf_counter()
                log = read_log(path, topics=topics)
                best_s = min(best_s, time.perf_counter() - t0)
            decoded = sum(len(t) for t in log.topics.values()) + sum(
                len(t) for t in log.json_topics.values()
            )
            print(
                f"read {label}: {best_s:.2f} s (best of 3), {decoded:,} messages decoded, "
                f"{decoded / best_s:,.0f} msg/s; truncated={log.truncated}"
            )


if __name__ == "__main__":
    main()
