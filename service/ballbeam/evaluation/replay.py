"""``replay --verify``: re-run the controller from a log and prove it explains the run.

The log carries the design the run used (``controller_design.npz``); the recorded sensor
readings (and the cycles where the daemon coasted, faulted or skipped) drive the same pure
control law, which is plain float arithmetic: every recorded voltage command must come out
identical, bit for bit, on any machine. A re-planning law (``controller.kind``) has no design:
it is rebuilt from the recorded config, and the plans it adopted (``/plans``) are injected at
their cycles instead of solved; the re-run must adopt a plan exactly where the run did.
Separately, today's code re-synthesises the tracker's design from the recorded config, and
the largest relative difference is reported (information: a different BLAS kernel or SciPy
moves the synthesis in its last bits, not the replay).
A log without a recorded design (older format) is verified against the re-synthesised one.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from ballbeam.assembly import control_law, controller_design
from ballbeam.config import Config, config_from_mapping
from ballbeam.core.control import ControllerDesign
from ballbeam.core.law import ControlLaw, TrackerLaw
from ballbeam.core.plant import SensorReading
from ballbeam.core.replanning_law import ReplanningLaw
from ballbeam.errors import BallbeamError, LogFormatError
from ballbeam.evaluation.summary import check_layouts
from ballbeam.logs import design_record
from ballbeam.logs.plan_record import recorded_plans
from ballbeam.logs.reader import RunLog

VERIFY_TOPICS = ("/sensor", "/command", "/timing")


@dataclass(frozen=True)
class Mismatch:
    index: int  # position among executed cycles
    cycle: int
    recorded_v: float
    replayed_v: float


@dataclass(frozen=True)
class VerifyResult:
    cycles_checked: int
    mismatch: Mismatch | None
    # "recorded" or "resynthesised" (a log without a recorded design); "recorded plans": a
    # re-planning law rebuilt from the recorded config with its recorded plans
    design_source: str
    # Today's synthesis against the recorded design: largest relative difference, or the
    # reason it could not be computed. None when there is no recorded design to compare.
    resynthesis_difference: float | str | None
    # A re-planning law: the first cycle at which the re-run adopted a plan where the log
    # records none, or none (or another) where it records one; in words.
    plan_mismatch: str | None = None

    @property
    def ok(self) -> bool:
        return self.mismatch is None and self.plan_mismatch is None


def verify(run_log: RunLog) -> VerifyResult:
    config: Config | None = None
    config_error = "no recorded config"
    text = run_log.metadata.get("config", {}).get("json")
    if text is not None:
        data = _recorded_config_data(run_log.path, text)
        controller = data.get("controller")
        if isinstance(controller, dict) and "lookahead_periods" not in controller:
            # Recorded before commands carried a look-ahead: the plant held the last one.
            data = {**data, "controller": {**controller, "lookahead_periods": 0}}
        try:
            config = config_from_mapping(data, f"{run_log.path} (recorded config)")
        except (ValueError, RecursionError) as error:  # refused today: another version
            config_error = f"recorded config unusable: {error}"
    if config is None and design_record.ATTACHMENT_NAME not in run_log.attachments:
        # Nothing to re-run: no design in the log, and no config to rebuild it from.
        raise LogFormatError(f"{run_log.path}: {config_error}, cannot re-run the controller")
    for topic in VERIFY_TOPICS:
        if topic not in run_log.topics:
            raise LogFormatError(f"{run_log.path}: no {topic} channel, cannot verify")
    check_layouts(run_log, VERIFY_TOPICS)
    sensor = run_log.topics["/sensor"].values
    command = run_log.topics["/command"].values
    timing = run_log.topics["/timing"].values
    count = min(len(sensor), len(command), len(timing))  # a truncated log: as far as it goes
    if count == 0:
        raise LogFormatError(f"{run_log.path}: no control cycle recorded, nothing to verify")
    if count and not (np.array_equal(sensor["cycle"][:count], command["cycle"][:count])):
        raise LogFormatError(f"{run_log.path}: /sensor and /command cycles do not line up")
    law: ControlLaw
    if config is not None and config.controller.kind != "tracker":
        law = control_law(config, recorded_plans=recorded_plans(run_log))
        source: str = "recorded plans"
        difference: float | str | None = None
    else:
        design, source, difference = _designs(run_log, config)
        law = TrackerLaw(design)
    held_v = 0.0
    commanded = False  # whether the last command was the law's (it then carried a look-ahead)
    period_ns = round(law.period_s * 1e9)
    # The columns as Python ints and floats, converted once (the same values bit for bit):
    # reading a NumPy element costs several times what the cycle's arithmetic does.
    skipped_all = timing["skipped"][:count].tolist()
    lateness_all = timing["lateness_ns"][:count].tolist()
    recorded_all = command["voltage_v"][:count].astype(np.float64).tolist()
    enabled_all = command["enable"][:count].tolist()
    cycles_all = command["cycle"][:count].tolist()
    fresh_all = sensor["fresh"][:count].tolist()
    angle_all = sensor["angle_counts"][:count].tolist()
    position_all = sensor["position_counts"][:count].tolist()
    for index in range(count):
        skipped = int(skipped_all[index])
        if skipped:
            lookahead_v = law.lookahead() if commanded else ()
            law.coast(held_v, skipped, lookahead_v)
        recorded_v = recorded_all[index]
        if enabled_all[index] == 0:
            # A fault cycle: the daemon sent 0 V and coasted its observer on it.
            replayed_v = 0.0
            law.coast(0.0, 1)
            commanded = False
        else:
            reading = None
            fresh = int(fresh_all[index])  # 1: of this period; 1 + n: of n cycles back
            if fresh:
                reading = SensorReading(int(angle_all[index]), int(position_all[index]))
            lateness_ns = int(lateness_all[index]) + skipped * period_ns
            output = law.step(reading, lateness_ns, max(fresh - 1, 0))
            replayed_v = output.voltage_v
            commanded = True
        plan_mismatch = law.plan_mismatch if isinstance(law, ReplanningLaw) else None
        if plan_mismatch is not None:
            return VerifyResult(index + 1, None, source, difference, plan_mismatch)
        if replayed_v != recorded_v or law.cycle - 1 != int(cycles_all[index]):
            mismatch = Mismatch(index, int(cycles_all[index]), recorded_v, replayed_v)
            return VerifyResult(index + 1, mismatch, source, difference)
        held_v = replayed_v
    if isinstance(law, ReplanningLaw):
        unused = [cycle for cycle, _ in recorded_plans(run_log) if cycle >= law.cycle]
        if unused and not run_log.truncated:
            return VerifyResult(count, None, source, difference, (
                f"the log records a plan at cycle {min(unused)}, after the last cycle re-run"
            ))
    return VerifyResult(count, None, source, difference)


def _not_finite(token: str) -> float:
    raise ValueError(f"{token} is not a number a run's config can hold")


def _finite(token: str) -> float:
    value = float(token)
    if not math.isfinite(value):
        raise ValueError(f"{token} overflows a float")
    return value


def _recorded_config_data(path: str, text: str) -> dict[str, Any]:
    """The recorded config's mapping; LogFormatError where it is not one a run could have
    written (not strict JSON, NaN or infinities, not an object): a damaged or altered log,
    whose commands nothing can vouch for. (A config today's code merely refuses is another
    version's: its recorded design still replays.)"""
    try:
        data = json.loads(text, parse_constant=_not_finite, parse_float=_finite)
    except (ValueError, RecursionError) as error:
        raise LogFormatError(
            f"{path}: the recorded config is damaged ({error}), cannot verify"
        ) from error
    if not isinstance(data, dict):
        raise LogFormatError(f"{path}: the recorded config is not a JSON object, cannot verify")
    return data


def _designs(
    run_log: RunLog, config: Config | None
) -> tuple[ControllerDesign, str, float | str | None]:
    """The design to replay, where it came from, and how today's synthesis compares (a log
    from another version verifies on its recorded design even where today's code refuses its
    config)."""
    data = run_log.attachments.get(design_record.ATTACHMENT_NAME)
    if data is None:
        assert config is not None  # verify() refuses a log with neither
        return controller_design(config), "resynthesised", None
    recorded = design_record.decode_design(data, f"{run_log.path}")
    if config is None:
        return recorded, "recorded", "cannot re-synthesise: the recorded config is unusable today"
    try:
        difference: float | str = design_record.design_difference(
            recorded, controller_design(config)
        )
    except BallbeamError as error:  # today's code refuses the recorded config
        difference = f"cannot re-synthesise: {error}"
    return recorded, "recorded", difference
