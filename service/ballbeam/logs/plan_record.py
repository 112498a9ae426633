"""The ``/plans`` topic: each plan a re-planning law adopted, and the cycle it took effect.

A plan is written field by field (``ArcPlan``'s), each float as ``float.hex``: the text gives
back the very same bits, so a replay can inject the recorded plans instead of solving and
re-run the law bit for bit on any machine (and whatever today's planner would solve).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

from ballbeam.core.planning.arcs import ArcPlan
from ballbeam.errors import LogFormatError
from ballbeam.logs.reader import RunLog

PLANS = "/plans"
_FLOAT_LISTS = ("input_v", "duration_s_each", "start")
_FLOATS = ("target_m", "voltage_limit_v", "theta_max_rad", "pole_per_s", "alpha", "gamma")
_HEX_LIST = {"type": "array", "items": {"type": "string"}}
PLAN_SCHEMA = {
    "type": "object",
    "properties": {
        "cycle": {"type": "integer"},
        "plan": {
            "type": "object",
            "properties": {
                **{name: _HEX_LIST for name in _FLOAT_LISTS},
                "holds": {"type": "array", "items": {"type": "integer"}},
                **{name: {"type": "string"} for name in _FLOATS},
            },
            "required": [*_FLOAT_LISTS, "holds", *_FLOATS],
        },
    },
    "required": ["cycle", "plan"],
}


def plan_message(cycle: int, plan: ArcPlan) -> dict[str, Any]:
    """The ``/plans`` message of ``plan``, adopted at ``cycle``."""
    fields: dict[str, Any] = {
        name: [float(value).hex() for value in getattr(plan, name)] for name in _FLOAT_LISTS
    }
    fields["holds"] = [int(hold) for hold in plan.holds]
    fields.update({name: float(getattr(plan, name)).hex() for name in _FLOATS})
    return {"cycle": int(cycle), "plan": fields}


def plan_from_message(message: Mapping[str, Any]) -> tuple[int, ArcPlan]:
    """(cycle, plan) of a ``/plans`` message; ValueError where it is not one."""
    cycle, fields = message["cycle"], message["plan"]
    if not isinstance(cycle, int) or isinstance(cycle, bool) or cycle < 0:
        raise ValueError(f"cycle {cycle!r} is not a cycle")
    lists = {name: tuple(_float(text) for text in fields[name]) for name in _FLOAT_LISTS}
    holds = tuple(fields["holds"])
    if not all(isinstance(hold, int) and not isinstance(hold, bool) for hold in holds):
        raise ValueError("holds must be integers")
    if len(lists["start"]) != 4 or not (
        len(lists["input_v"]) == len(lists["duration_s_each"]) == len(holds)
    ):
        raise ValueError("a plan needs a 4-state start and one input, duration and hold an arc")
    start = lists["start"]
    return cycle, ArcPlan(
        input_v=lists["input_v"],
        duration_s_each=lists["duration_s_each"],
        holds=holds,
        start=(start[0], start[1], start[2], start[3]),
        **{name: _float(fields[name]) for name in _FLOATS},
    )


def recorded_plans(run_log: RunLog) -> dict[int, ArcPlan]:
    """The plans a run adopted, by cycle (none: the log has no ``/plans``); LogFormatError for
    a message that is not a plan, or two at one cycle."""
    topic = run_log.json_topics.get(PLANS)
    plans: dict[int, ArcPlan] = {}
    if topic is None:
        return plans
    for index, message in enumerate(topic.messages):
        try:
            cycle, plan = plan_from_message(message)
        except (KeyError, TypeError, ValueError) as error:
            raise LogFormatError(
                f"{run_log.path}: {PLANS} message #{index} is not a plan ({error})"
            ) from error
        if cycle in plans:
            raise LogFormatError(f"{run_log.path}: {PLANS} has two plans at cycle {cycle}")
        plans[cycle] = plan
    return plans


def _float(text: object) -> float:
    if not isinstance(text, str):
        raise ValueError(f"{text!r} is not a float written with float.hex")
    value = float.fromhex(text)
    if not math.isfinite(value):
        raise ValueError(f"{text} is not finite")
    return value
