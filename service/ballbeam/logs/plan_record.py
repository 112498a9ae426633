"""The ``/plans`` topic: each answer of its planner a re-planning law took, the cycle it took
it (the plan's first) and the cycle of the request it answers; the plan, or null where the
planner had none.

A plan is written field by field (``ArcPlan``'s), each float as ``float.hex``: the text gives
back the very same bits, so a replay can inject the recorded answers instead of solving and
re-run the law bit for bit on any machine (and whatever today's planner would solve).
A re-design taken carries the design itself (``made``: every field of
``replanning._Design``, its identified model and its guard; floats as ``float.hex``, arrays
with their shape): a replay takes it as the run did instead of solving its Riccati equations
again, whose last bits depend on the machine's LAPACK and BLAS kernel. The design the law
started with is one, taken at cycle 0 to a request of cycle 0.
``wait_ns``, where the daemon measured it: wall time from sending the request to reading the
answer (information; a replay does not use it).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from typing import Any

import numpy as np

from ballbeam.core.control import PlanTaken
from ballbeam.core.guard import AngleGuard, SoftCap
from ballbeam.core.planning.arcs import ArcPlan
from ballbeam.core.replanning import Identified, _Design
from ballbeam.errors import LogFormatError
from ballbeam.logs.reader import RunLog
from ballbeam.logs.recorder import encode_json

PLANS = "/plans"
_FLOAT_LISTS = ("input_v", "duration_s_each", "start")
_FLOATS = ("target_m", "voltage_limit_v", "theta_max_rad", "pole_per_s", "alpha", "gamma")
_HEX_LIST = {"type": "array", "items": {"type": "string"}}
PLAN_SCHEMA = {
    "type": "object",
    "properties": {
        "cycle": {"type": "integer"},
        "request_cycle": {"type": "integer"},
        "design": {"type": "boolean"},
        "wait_ns": {"type": "integer"},
        "made": {"type": "object"},
        "plan": {
            "type": ["object", "null"],
            "properties": {
                **{name: _HEX_LIST for name in _FLOAT_LISTS},
                "holds": {"type": "array", "items": {"type": "integer"}},
                **{name: {"type": "string"} for name in _FLOATS},
            },
            "required": [*_FLOAT_LISTS, "holds", *_FLOATS],
        },
    },
    "required": ["cycle", "request_cycle", "plan"],
}


def plan_message(
    taken: PlanTaken, wait_ns: int | None = None, made: bool = True
) -> dict[str, Any]:
    """The ``/plans`` message of an answer taken (``made``: with its design; a design's
    encoding made elsewhere, :func:`design_json`, is joined to it by the recording)."""
    message: dict[str, Any] = {
        "cycle": int(taken.cycle),
        "request_cycle": int(taken.request_cycle),
        "plan": None if taken.plan is None else _plan_fields(taken.plan),
    }
    if taken.design:
        message["design"] = True
        if made and taken.design_made is not None:
            message["made"] = encode_design(taken.design_made)
    if wait_ns is not None:
        message["wait_ns"] = int(wait_ns)
    return message


def _plan_fields(plan: ArcPlan) -> dict[str, Any]:
    fields: dict[str, Any] = {
        name: [float(value).hex() for value in getattr(plan, name)] for name in _FLOAT_LISTS
    }
    fields["holds"] = [int(hold) for hold in plan.holds]
    fields.update({name: float(getattr(plan, name)).hex() for name in _FLOATS})
    return fields


def plan_from_message(message: Mapping[str, Any]) -> PlanTaken:
    """The answer taken of a ``/plans`` message; ValueError where it is not one."""
    cycle, request_cycle = message["cycle"], message["request_cycle"]
    for value in (cycle, request_cycle):
        if not isinstance(value, int) or isinstance(value, bool) or value < 0:
            raise ValueError(f"cycle {value!r} is not a cycle")
    if request_cycle > cycle:
        raise ValueError(f"an answer taken at cycle {cycle} to a request of {request_cycle}")
    fields, design = message["plan"], message.get("design", False)
    if not isinstance(design, bool) or (design and fields is not None):
        raise ValueError("a re-design carries no plan")
    made = message.get("made")
    if made is not None and not design:
        raise ValueError("a plan carries no design")
    return PlanTaken(
        cycle, request_cycle, None if fields is None else _plan(fields), design,
        None if made is None else decode_design(made),
    )


def _plan(fields: Mapping[str, Any]) -> ArcPlan:
    lists = {name: tuple(_float(text) for text in fields[name]) for name in _FLOAT_LISTS}
    holds = tuple(fields["holds"])
    if not all(isinstance(hold, int) and not isinstance(hold, bool) for hold in holds):
        raise ValueError("holds must be integers")
    if len(lists["start"]) != 4 or not (
        len(lists["input_v"]) == len(lists["duration_s_each"]) == len(holds)
    ):
        raise ValueError("a plan needs a 4-state start and one input, duration and hold an arc")
    start = lists["start"]
    return ArcPlan(
        input_v=lists["input_v"],
        duration_s_each=lists["duration_s_each"],
        holds=holds,
        start=(start[0], start[1], start[2], start[3]),
        **{name: _float(fields[name]) for name in _FLOATS},
    )


def recorded_plans(run_log: RunLog) -> dict[tuple[int, bool], PlanTaken]:
    """The answers a run took, by the cycle it took each and whether it is a re-design (none:
    the log has no ``/plans``); LogFormatError for a message that is not one, or two of a
    kind at one cycle."""
    topic = run_log.json_topics.get(PLANS)
    plans: dict[tuple[int, bool], PlanTaken] = {}
    if topic is None:
        return plans
    for index, message in enumerate(topic.messages):
        try:
            taken = plan_from_message(message)
        except (KeyError, TypeError, ValueError) as error:
            raise LogFormatError(
                f"{run_log.path}: {PLANS} message #{index} is not a plan ({error})"
            ) from error
        key = (taken.cycle, taken.design)
        if key in plans:
            raise LogFormatError(f"{run_log.path}: {PLANS} has two plans at cycle {taken.cycle}")
        plans[key] = taken
    return plans


def _float(text: object) -> float:
    if not isinstance(text, str):
        raise ValueError(f"{text!r} is not a float written with float.hex")
    value = float.fromhex(text)
    if not math.isfinite(value):
        raise ValueError(f"{text} is not finite")
    return value


# -- a re-design, field by field ------------------------------------------------------------

_DESIGN_TYPES: dict[str, type] = {
    cls.__name__: cls for cls in (_Design, Identified, AngleGuard, SoftCap)
}


def encode_design(design: _Design) -> dict[str, Any]:
    """A design as JSON: each dataclass as its type's name and fields, floats as
    ``float.hex``, tuples as lists, arrays (float64) as their shape and values."""
    encoded = _encode(design)
    assert isinstance(encoded, dict)
    return encoded


def design_json(design: _Design) -> bytes:
    """:func:`encode_design` as the JSON text of a ``/plans`` message's ``made``."""
    return encode_json(encode_design(design))


def decode_design(value: object) -> _Design:
    """The design of :func:`encode_design`'s JSON, bit for bit; ValueError where it is not."""
    design = _decode(value)
    if not isinstance(design, _Design):
        raise ValueError("a recorded design is not a design")
    return design


def _encode(value: object) -> Any:
    if value is None or isinstance(value, bool):
        return value
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, float):
        return float(value).hex()
    if isinstance(value, tuple):
        return [_encode(item) for item in value]
    if isinstance(value, np.ndarray):
        if value.dtype != np.float64:
            raise TypeError(f"a design's array of {value.dtype}")
        return {"shape": list(value.shape), "array": [float(v).hex() for v in value.ravel()]}
    name = type(value).__name__
    if dataclasses.is_dataclass(value) and _DESIGN_TYPES.get(name) is type(value):
        return {
            "type": name,
            "fields": {f.name: _encode(getattr(value, f.name)) for f in dataclasses.fields(value)},
        }
    raise TypeError(f"a design holds a {name}")


def _decode(value: object) -> Any:
    if value is None or isinstance(value, (bool, int)):
        return value
    if isinstance(value, str):
        return _float_any(value)
    if isinstance(value, list):
        return tuple(_decode(item) for item in value)
    if isinstance(value, dict) and set(value) == {"shape", "array"}:
        shape, items = value["shape"], value["array"]
        if not (
            isinstance(shape, list) and isinstance(items, list)
            and all(isinstance(n, int) and not isinstance(n, bool) and n >= 0 for n in shape)
            and math.prod(shape) == len(items)
        ):
            raise ValueError("an array's shape does not match its values")
        return np.array([_float_any(item) for item in items], dtype=np.float64).reshape(shape)
    if isinstance(value, dict) and set(value) == {"type", "fields"}:
        cls = _DESIGN_TYPES.get(value["type"]) if isinstance(value["type"], str) else None
        fields = value["fields"]
        if cls is None or not isinstance(fields, dict):
            raise ValueError(f"{value['type']!r} is not a part of a design")
        names = {f.name for f in dataclasses.fields(cls)}
        if set(fields) != names:
            raise ValueError(f"a {cls.__name__} needs the fields {sorted(names)}")
        return cls(**{name: _decode(item) for name, item in fields.items()})
    raise ValueError(f"{value!r} is not part of a recorded design")


def _float_any(text: object) -> float:
    """A float written with float.hex (a design may hold infinities)."""
    if not isinstance(text, str):
        raise ValueError(f"{text!r} is not a float written with float.hex")
    return float.fromhex(text)
