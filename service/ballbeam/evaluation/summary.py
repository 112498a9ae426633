"""What a recorded run says: metrics from plant truth, loop timing, frame statistics, faults.

Computed from the log alone, so ``ballbeam run`` and ``ballbeam replay`` report the same.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np

from ballbeam.core.metrics import compute_metrics
from ballbeam.core.task import Task
from ballbeam.errors import BallbeamError, LogFormatError
from ballbeam.logs.reader import RunLog
from ballbeam.logs.topics import LEGACY_STRUCT_TOPICS, STRUCT_TOPICS
from ballbeam.protocol.frames import (
    COUNTER_MODULUS,
    PLANT_STATUS_FIELDS,
    SENSOR_ID,
    VOLTAGE_COMMAND_ID,
    FrameContract,
)

REQUIRED_TOPICS = ("/command", "/reference", "/truth", "/timing")
SATURATION_TOLERANCE_V = 1e-6


@dataclass(frozen=True)
class RunSeries:
    """Time series of one run on the controller's clock (0 = first control cycle)."""

    truth_time_s: np.ndarray
    truth_states: np.ndarray  # (N, 4)
    cycle_time_s: np.ndarray
    voltage_v: np.ndarray
    reference_time_s: np.ndarray
    reference_states: np.ndarray  # (M, 4) at reference_time_s
    lateness_ns: np.ndarray  # behind schedule: lateness plus the periods skipped before


STATE_NAMES = ("theta_rad", "theta_rate_rad_s", "ball_velocity_m_s", "ball_position_m")


def check_layouts(run_log: RunLog, topics: Iterable[str]) -> None:
    """LogFormatError unless each of ``topics`` that the log has is in the ballbeam layout."""
    for topic in topics:
        found = run_log.topics.get(topic)
        accepted = (STRUCT_TOPICS[topic], *LEGACY_STRUCT_TOPICS.get(topic, ()))
        if found is not None and all(found.schema.fields != known.fields for known in accepted):
            raise LogFormatError(
                f"{run_log.path}: topic {topic!r} has layout {found.schema.name!r} "
                f"({', '.join(found.schema.field_names)}), not ballbeam's "
                f"{STRUCT_TOPICS[topic].name!r}"
            )


def run_series(run_log: RunLog) -> RunSeries:
    missing = [topic for topic in REQUIRED_TOPICS if len(run_log.topics.get(topic, ())) == 0]
    if missing:
        where = " (the file was cut short)" if run_log.truncated else ""
        raise LogFormatError(
            f"{run_log.path}: no {', '.join(missing)} messages{where}; nothing to analyse"
        )
    check_layouts(run_log, REQUIRED_TOPICS)
    command = run_log.topics["/command"]
    reference = run_log.topics["/reference"]
    truth = run_log.topics["/truth"]
    timing = run_log.topics["/timing"]
    origin_ns = int(command.log_time_ns[0])
    truth_time_s = (truth.log_time_ns - origin_ns) * 1e-9
    keep = truth_time_s >= -1e-6
    states = np.column_stack([truth.values[name] for name in STATE_NAMES])[keep]
    return RunSeries(
        truth_time_s=np.maximum(truth_time_s[keep], 0.0),
        truth_states=states,
        cycle_time_s=(command.log_time_ns - origin_ns) * 1e-9,
        voltage_v=np.asarray(command.values["voltage_v"], dtype=float),
        reference_time_s=(reference.log_time_ns - origin_ns) * 1e-9,
        reference_states=np.column_stack([reference.values[name] for name in STATE_NAMES]),
        lateness_ns=behind_schedule_ns(timing.values),
    )


def behind_schedule_ns(timing: np.ndarray) -> np.ndarray:
    """Each cycle's start less the first deadline it was due after the cycle before: its
    lateness plus the periods skipped before it (a cycle late by a period or more runs as the
    period it starts in, so its own lateness is under a period)."""
    lateness_ns = np.asarray(timing["lateness_ns"], dtype=np.int64)
    skipped = np.asarray(timing["skipped"], dtype=np.int64)
    deadlines_ns = np.asarray(timing["deadline_ns"], dtype=np.int64)
    steps_ns = np.diff(deadlines_ns) // (1 + skipped[1:])
    period_ns = int(np.median(steps_ns)) if steps_ns.size else 0
    return lateness_ns + skipped * period_ns


def _percentile_us(values_ns: np.ndarray, q: float) -> float:
    return float(np.percentile(values_ns, q)) * 1e-3 if values_ns.size else math.nan




def sensor_to_command_latency_s(run_log: RunLog) -> np.ndarray:
    """For each enabled command: send time minus the kernel receive time of the sensor frame
    of the period it names (paired by the echoed counter, latest such frame before the send;
    none where that frame came half the counter's range or more before: a coasting cycle's
    period whose sample never came, paired with one a wrap earlier)."""
    rx, tx = run_log.topics.get("/can/rx"), run_log.topics.get("/can/tx")
    if rx is None or tx is None or not len(rx) or not len(tx):
        return np.empty(0)
    rx_values, tx_values = rx.values, tx.values
    contract = FrameContract.load()
    sensors = rx_values[rx_values["arbitration_id"] == SENSOR_ID]
    commands = tx_values[tx_values["arbitration_id"] == VOLTAGE_COMMAND_ID]
    enabled = contract.raw_signal(VOLTAGE_COMMAND_ID, "Enable", commands["data"]) == 1
    commands = commands[enabled]
    sensor_counters = contract.raw_signal(SENSOR_ID, "Counter", sensors["data"])
    answered = contract.raw_signal(VOLTAGE_COMMAND_ID, "SensorCounter", commands["data"])
    latencies = []
    received_s = np.sort(sensors["bus_time_s"])
    period_s = float(np.median(np.diff(received_s))) if received_s.size > 1 else math.inf
    wrap_s = period_s * COUNTER_MODULUS / 2
    for counter in np.unique(answered):
        received = np.sort(sensors["bus_time_s"][sensor_counters == counter])
        sent = commands["bus_time_s"][answered == counter]
        if not received.size:
            continue
        index = np.searchsorted(received, sent, side="right") - 1
        valid = index >= 0
        latency = sent[valid] - received[index[valid]]
        latencies.append(latency[latency < wrap_s])
    return np.concatenate(latencies) if latencies else np.empty(0)


def plant_missed_periods(run_log: RunLog) -> int | None:
    """Sample periods with no truth recorded between the first and the last: the plant
    overran them (its counters count periods) or their truth frames were lost. None for a log
    recorded before the plant's clock was in /truth."""
    truth = run_log.topics["/truth"]
    if "sample_index" not in truth.schema.field_names:
        return None
    steps = np.diff(np.asarray(truth.values["sample_index"], dtype=np.int64))
    return int(np.sum(np.maximum(steps - 1, 0)))


def plant_counters(run_log: RunLog) -> tuple[str, dict[str, int] | None]:
    """The emulator's own counters as the log recorded them (``/plant_status``): the last
    snapshot, and what it is: ``"final"`` (sent as the emulator stopped), ``"periodic ..."``
    (no final one reached the log) or ``"absent ..."`` (a log recorded before the topic, or a
    plant that sends none: a real rig)."""
    status = run_log.topics.get("/plant_status")
    if status is None or not len(status):
        return "absent (the log has no /plant_status snapshot)", None
    check_layouts(run_log, ("/plant_status",))
    values = status.values
    counters = {name: int(values[name][-1]) for name in PLANT_STATUS_FIELDS}
    if values["final"][-1]:
        return "final", counters
    at_s = (int(status.log_time_ns[-1]) - int(run_log.topics["/command"].log_time_ns[0])) * 1e-9
    return f"periodic, at {at_s:.3f} s (no final snapshot reached the log)", counters


def summarise(run_log: RunLog, theta_limit_rad: float | None = None) -> dict[str, Any]:
    """One flat dict: the core metrics plus timing, frames, faults and truncation."""
    series = run_series(run_log)
    if len(series.truth_time_s) < 2:
        raise LogFormatError(f"{run_log.path}: fewer than two plant-truth samples")
    if theta_limit_rad is None:
        theta_limit_rad = limit_from_log(run_log)
    task = task_from_log(run_log)
    # Truth after the last recorded reference: the reference beyond the plan, rest at the target.
    reference_at_truth = np.interp(
        series.truth_time_s, series.reference_time_s, series.reference_states[:, 3],
        right=float(task.target_at(float(series.truth_time_s[-1]))),
    )
    # u_d in force at each command (real time may skip cycles; a cut log may lack a few rows)
    reference_input_v = np.asarray(run_log.topics["/reference"].values["input_v"], dtype=float)
    index = np.searchsorted(series.reference_time_s, series.cycle_time_s, side="right") - 1
    input_at_commands = reference_input_v[np.clip(index, 0, len(reference_input_v) - 1)]
    metrics = compute_metrics(
        series.truth_time_s,
        series.truth_states,
        series.voltage_v,
        reference_at_truth,
        theta_limit_rad,
        reference_input_v=input_at_commands,
        minimum_time_s=minimum_time_from_log(run_log),
        voltage_time_s=series.cycle_time_s,
        target_m=task.target_at(series.truth_time_s),
    ).as_dict()
    timing = run_log.topics["/timing"]
    enabled = run_log.topics["/command"].values["enable"] == 1
    voltage_limit = voltage_limit_from_log(run_log)
    saturated = np.abs(series.voltage_v[enabled]) >= voltage_limit - SATURATION_TOLERANCE_V
    summary_meta = run_log.metadata.get("summary", {})
    latency_ns = sensor_to_command_latency_s(run_log) * 1e9
    faults = run_log.json_topics.get("/faults")
    fault_kinds: dict[str, int] = {}
    for message in faults.messages if faults is not None else ():
        fault_kinds[str(message.get("kind"))] = fault_kinds.get(str(message.get("kind")), 0) + 1

    plant_status, plant_counts = plant_counters(run_log)

    def counter(name: str) -> int | None:
        value = summary_meta.get(name)
        return int(value) if value is not None and value.lstrip("-").isdigit() else None

    return {
        **metrics,
        "cycles": len(timing),
        "saturation_fraction": float(np.mean(saturated)) if saturated.size else 0.0,
        "lateness_p50_us": _percentile_us(series.lateness_ns, 50),
        "lateness_p99_us": _percentile_us(series.lateness_ns, 99),
        "lateness_max_us": _percentile_us(series.lateness_ns, 100),
        "latency_p50_us": _percentile_us(latency_ns, 50),
        "latency_p99_us": _percentile_us(latency_ns, 99),
        "overruns": counter("overruns"),
        "frames_lost": counter("sensor_frames_lost"),
        "frames_rejected": counter("rejected_total"),
        "coasted_cycles": counter("coasted_cycles"),
        # Real time: samples read periods after their own (absent in older logs), and those
        # the law took for the period they are of (the rest: coasted over).
        "late_samples": counter("late_samples"),
        "late_readings": counter("late_readings"),
        "recorder_dropped": counter("recorder_dropped"),
        "plant_missed_periods": plant_missed_periods(run_log),
        # The emulator's own counts (its missed_periods among them: truth gaps above are those
        # plus truth frames lost on the bus).
        "plant_status": plant_status,
        "plant_counters": plant_counts,
        "faults": fault_kinds,
        "end_reason": summary_meta.get("end_reason", "unknown (no summary: run cut short)"),
        "truncated": run_log.truncated,
        "truncation_reason": run_log.truncation_reason,
        "last_time_s": (
            (run_log.last_complete_time_ns - int(run_log.topics["/command"].log_time_ns[0])) * 1e-9
            if run_log.last_complete_time_ns is not None
            else None
        ),
    }


def _resolved_config(run_log: RunLog) -> dict[str, Any]:
    import json

    text = run_log.metadata.get("config", {}).get("json")
    if text is None:
        raise LogFormatError(f"{run_log.path}: the log holds no resolved config")
    try:
        config = json.loads(text)
    except (ValueError, RecursionError) as error:
        raise LogFormatError(f"{run_log.path}: the recorded config is not JSON") from error
    if not isinstance(config, dict):
        raise LogFormatError(f"{run_log.path}: the recorded config is not a JSON object")
    return config


def _recorded_limit(run_log: RunLog, name: str) -> float:
    config = _resolved_config(run_log)
    try:
        value = float(config["limits"][name])
    except (KeyError, TypeError, ValueError) as error:
        raise LogFormatError(
            f"{run_log.path}: the recorded config has no usable limits.{name}"
        ) from error
    if not (math.isfinite(value) and value > 0):
        raise LogFormatError(f"{run_log.path}: the recorded config has limits.{name} = {value}")
    return value


def minimum_time_from_log(run_log: RunLog) -> float | None:
    """T* from the run's recorded start and limits (None where the config is not usable):
    as the daemon recorded it, else (an older log, or a value that is not one) computed
    from the recorded config."""
    recorded = run_log.metadata.get("run", {}).get("minimum_time_s")
    if recorded == "none":
        return None
    if recorded is not None:
        with contextlib.suppress(ValueError):
            value = float(recorded)
            if math.isfinite(value) and value > 0.0:
                return value
    from ballbeam.assembly import minimum_time_s
    from ballbeam.config import config_from_mapping

    try:
        return minimum_time_s(config_from_mapping(_resolved_config(run_log)))
    except BallbeamError:
        return None


def task_from_log(run_log: RunLog) -> Task:
    """The run's task, from its recorded ``[task]`` (a log from before the section: the
    paper's, x = 0); LogFormatError if the recorded section is not a valid one."""
    from pydantic import ValidationError

    from ballbeam.config import TaskSection

    section = _resolved_config(run_log).get("task", {})
    try:
        return TaskSection.model_validate(section).reference()
    except (ValidationError, BallbeamError) as error:
        raise LogFormatError(f"{run_log.path}: the recorded [task] is not usable") from error


def limit_from_log(run_log: RunLog) -> float:
    return math.radians(_recorded_limit(run_log, "theta_deg"))


def voltage_limit_from_log(run_log: RunLog) -> float:
    return _recorded_limit(run_log, "voltage_v")
