"""The typed recording front of a run: one write per topic record, events and faults.

The daemon records through this, never through raw tuples: each topic takes its own record
type (``logs/topics.py``), whose fields are the topic's layout.

Between a sensor frame and the command it answers the daemon *holds* the recording
(:meth:`RunRecording.hold`): records are kept as given and encoded at :meth:`release`, once
the command is on the bus, so that recording adds nothing to the loop's turnaround.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING, Any

from ballbeam.logs.plan_record import PLAN_SCHEMA, PLANS, plan_message
from ballbeam.logs.recorder import ChannelHandle, Recorder, encode_json
from ballbeam.logs.topics import (
    DISTURBANCE_SCHEMA,
    DISTURBANCES,
    EVENT_SCHEMA,
    EVENTS,
    FAULTS,
    JSON_TOPICS,
    STRUCT_TOPICS,
    R,
    StructTopic,
)

if TYPE_CHECKING:
    from ballbeam.core.control import PlanTaken


class RunRecording:
    def __init__(self, recorder: Recorder, plans: bool = False) -> None:
        """``plans``: the law adopts plans, recorded on ``/plans`` (a replay injects them)."""
        self.recorder = recorder
        self._handles: dict[str, ChannelHandle] = {
            name: recorder.add_struct_channel(name, schema)
            for name, schema in STRUCT_TOPICS.items()
        }
        self._handles.update(
            {name: recorder.add_json_channel(name, "ballbeam/Event", EVENT_SCHEMA)
             for name in JSON_TOPICS}
        )
        self._handles[DISTURBANCES] = recorder.add_json_channel(
            DISTURBANCES, "ballbeam/Disturbance", DISTURBANCE_SCHEMA
        )
        if plans:
            self._handles[PLANS] = recorder.add_json_channel(PLANS, "ballbeam/Plan", PLAN_SCHEMA)
        self._held: list[tuple[ChannelHandle, int, Any]] | None = None  # (channel, time, record)

    def hold(self) -> None:
        """Keep what is written from now on, in order, until :meth:`release` (records are
        immutable tuples, notes fresh mappings: kept as they are, encoded then)."""
        if self._held is None:
            self._held = []

    def release(self) -> None:
        """Encode what was held (in the order it was written) and write through again."""
        held, self._held = self._held, None
        if held:
            record = self.recorder.record
            for handle, log_time_ns, values in held:
                record(handle, log_time_ns, values)

    def _record(
        self, handle: ChannelHandle, log_time_ns: int, values: Sequence[Any] | Mapping[str, Any]
    ) -> None:
        if self._held is not None:
            self._held.append((handle, log_time_ns, values))
        else:
            self.recorder.record(handle, log_time_ns, values)

    def write(self, topic: StructTopic[R], log_time_ns: int, record: R) -> None:
        self._record(self._handles[topic.name], log_time_ns, record)

    def event(self, log_time_ns: int, cycle: int, kind: str, detail: str) -> None:
        self._note(EVENTS, log_time_ns, cycle, kind, detail)

    def fault(self, log_time_ns: int, cycle: int, kind: str, detail: str) -> None:
        self._note(FAULTS, log_time_ns, cycle, kind, detail)

    def tap(
        self, log_time_ns: int, cycle: int, time_s: float, plant_step: int, change_m_s: float
    ) -> None:
        """A tap on the ball at plant time ``time_s`` (physics step ``plant_step``)."""
        self._record(self._handles[DISTURBANCES], log_time_ns, {
            "cycle": cycle, "time_s": time_s, "plant_step": plant_step,
            "ball_velocity_change_m_s": change_m_s,
        })

    def plan(
        self, log_time_ns: int, taken: PlanTaken, wait_ns: int | None = None,
        made_json: bytes | None = None,
    ) -> None:
        """An answer of its planner the law took (``wait_ns``: request to answer, measured;
        ``made_json``: a design's encoding, made where it was solved: writing one here
        takes milliseconds of the cycle)."""
        if made_json is None or not taken.design:
            self._record(self._handles[PLANS], log_time_ns, plan_message(taken, wait_ns))
            return
        text = encode_json(plan_message(taken, wait_ns, made=False))
        self._record(
            self._handles[PLANS], log_time_ns, text[:-1] + b',"made":' + made_json + b"}"
        )

    def _note(self, topic: str, log_time_ns: int, cycle: int, kind: str, detail: str) -> None:
        self._record(
            self._handles[topic], log_time_ns, {"cycle": cycle, "kind": kind, "detail": detail}
        )
