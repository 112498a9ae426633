"""The recorded topics of a run: names, typed records and their fixed layouts.

Each high-rate topic has one record type, a NamedTuple whose fields carry their ROS 2 type
(``Annotated[float, "float64"]``); the topic's schema is derived from it, so a value, its
fields and the layout in the file cannot drift apart. High-rate topics are fixed-size CDR
structs (ros2msg schemas), so Foxglove plots them with no plugin and the reader decodes a whole
channel at once; rare events are JSON.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, Any, Generic, NamedTuple, TypeVar, get_type_hints

from ballbeam.logs.schema import StructSchema

Int64 = Annotated[int, "int64"]
UInt8 = Annotated[int, "uint8"]
Float64 = Annotated[float, "float64"]


class CanFrameRecord(NamedTuple):
    bus_time_s: Float64
    arbitration_id: Annotated[int, "uint32"]
    dlc: UInt8
    data: Annotated[bytes, "uint8[8]"]


class SensorRecord(NamedTuple):
    cycle: Int64
    fresh: UInt8
    counter: UInt8
    status: UInt8
    angle_counts: Annotated[int, "int32"]
    position_counts: Annotated[int, "int32"]
    theta_rad: Float64
    position_m: Float64


class CommandRecord(NamedTuple):
    cycle: Int64
    voltage_v: Float64
    requested_v: Float64
    enable: UInt8
    counter: UInt8
    sensor_counter: UInt8


class EstimateRecord(NamedTuple):
    cycle: Int64
    theta_rad: Float64
    theta_rate_rad_s: Float64
    ball_velocity_m_s: Float64
    ball_position_m: Float64


class ReferenceRecord(NamedTuple):
    cycle: Int64
    theta_rad: Float64
    theta_rate_rad_s: Float64
    ball_velocity_m_s: Float64
    ball_position_m: Float64
    input_v: Float64


class TruthRecord(NamedTuple):
    counter: UInt8
    theta_rad: Float64
    theta_rate_rad_s: Float64
    ball_velocity_m_s: Float64
    ball_position_m: Float64
    # The plant's own clock: its sample-period index (the frame counter unwrapped; counters
    # count periods, so a period the plant missed is a step of 2) and that index's time.
    sample_index: Int64
    plant_time_s: Float64


class TruthRecordV1(NamedTuple):
    """/truth as logs recorded before the plant's clock was in it (still read)."""

    counter: UInt8
    theta_rad: Float64
    theta_rate_rad_s: Float64
    ball_velocity_m_s: Float64
    ball_position_m: Float64


class PlantStatusRecord(NamedTuple):
    """The emulator's own counters, one whole snapshot of its PlantStatus frames (fields after
    ``final`` are PLANT_STATUS_FIELDS, in order)."""

    final: UInt8  # 1: the snapshot the emulator sent as it stopped
    samples_sent: Int64
    resends: Int64
    commands_applied: Int64
    rejected: Int64
    own_or_foreign: Int64
    dropped_by_injection: Int64
    watchdog_trips: Int64
    missed_periods: Int64
    peer_lost: Int64
    unauthenticated: Int64
    bad_mac: Int64
    replayed: Int64
    out_of_window: Int64


class TimingRecord(NamedTuple):
    cycle: Int64
    deadline_ns: Int64
    start_ns: Int64
    end_ns: Int64
    lateness_ns: Int64
    skipped: Int64


R = TypeVar("R", bound=tuple[Any, ...])


def schema_of(name: str, record_type: type[tuple[Any, ...]]) -> StructSchema:
    """The fixed layout of a record type: its fields in order, with their ROS 2 types."""
    hints = get_type_hints(record_type, include_extras=True)
    fields = tuple((field, hints[field].__metadata__[0]) for field in hints)
    return StructSchema(name, fields)


@dataclass(frozen=True)
class StructTopic(Generic[R]):
    """A fixed-layout topic and the record type written to it."""

    name: str
    record_type: type[R]
    schema: StructSchema


def _topic(name: str, schema_name: str, record_type: type[R]) -> StructTopic[R]:
    return StructTopic(name, record_type, schema_of(schema_name, record_type))


CAN_RX = _topic("/can/rx", "ballbeam/CanFrame", CanFrameRecord)
CAN_TX = _topic("/can/tx", "ballbeam/CanFrame", CanFrameRecord)
SENSOR = _topic("/sensor", "ballbeam/Sensor", SensorRecord)
COMMAND = _topic("/command", "ballbeam/Command", CommandRecord)
ESTIMATE = _topic("/estimate", "ballbeam/Estimate", EstimateRecord)
REFERENCE = _topic("/reference", "ballbeam/Reference", ReferenceRecord)
TRUTH = _topic("/truth", "ballbeam/PlantTruth", TruthRecord)
TIMING = _topic("/timing", "ballbeam/CycleTiming", TimingRecord)
PLANT_STATUS = _topic("/plant_status", "ballbeam/PlantStatus", PlantStatusRecord)

EVENT_SCHEMA = {
    "type": "object",
    "properties": {
        "cycle": {"type": "integer"},
        "kind": {"type": "string"},
        "detail": {"type": "string"},
    },
    "required": ["cycle", "kind", "detail"],
}
FAULTS = "/faults"
EVENTS = "/events"
# The taps of [plant] disturbances, each logged at the first cycle whose sample shows it.
DISTURBANCES = "/disturbances"
DISTURBANCE_SCHEMA = {
    "type": "object",
    "properties": {
        "cycle": {"type": "integer"},
        "time_s": {"type": "number"},
        "plant_step": {"type": "integer"},
        "ball_velocity_change_m_s": {"type": "number"},
    },
    "required": ["cycle", "time_s", "plant_step", "ball_velocity_change_m_s"],
}

STRUCT_TOPICS: dict[str, StructSchema] = {
    topic.name: topic.schema
    for topic in (
        CAN_RX, CAN_TX, SENSOR, COMMAND, ESTIMATE, REFERENCE, TRUTH, TIMING, PLANT_STATUS
    )
}
JSON_TOPICS = (FAULTS, EVENTS)
# Earlier layouts a reader still accepts, per topic.
LEGACY_STRUCT_TOPICS: dict[str, tuple[StructSchema, ...]] = {
    TRUTH.name: (schema_of("ballbeam/PlantTruth", TruthRecordV1),),
}
