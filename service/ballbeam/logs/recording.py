"""The typed recording front of a run: one write per topic record, events and faults.

The daemon records through this, never through raw tuples: each topic takes its own record
type (``logs/topics.py``), whose fields are the topic's layout.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

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

    def write(self, topic: StructTopic[R], log_time_ns: int, record: R) -> None:
        self.recorder.record(self._handles[topic.name], log_time_ns, record)

    def event(self, log_time_ns: int, cycle: int, kind: str, detail: str) -> None:
        self._note(EVENTS, log_time_ns, cycle, kind, detail)

    def fault(self, log_time_ns: int, cycle: int, kind: str, detail: str) -> None:
        self._note(FAULTS, log_time_ns, cycle, kind, detail)

    def tap(
        self, log_time_ns: int, cycle: int, time_s: float, plant_step: int, change_m_s: float
    ) -> None:
        """A tap on the ball at plant time ``time_s`` (physics step ``plant_step``)."""
        self.recorder.record(self._handles[DISTURBANCES], log_time_ns, {
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
            self.recorder.record(self._handles[PLANS], log_time_ns, plan_message(taken, wait_ns))
            return
        text = encode_json(plan_message(taken, wait_ns, made=False))
        self.recorder.record(
            self._handles[PLANS], log_time_ns, text[:-1] + b',"made":' + made_json + b"}"
        )

    def _note(self, topic: str, log_time_ns: int, cycle: int, kind: str, detail: str) -> None:
        self.recorder.record(
            self._handles[topic], log_time_ns, {"cycle": cycle, "kind": kind, "detail": detail}
        )
