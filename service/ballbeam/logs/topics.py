"""The recorded channels of a run: topic names and fixed layouts (self-describing in the file).

High-rate channels are fixed-size CDR structs (ros2msg schemas) so Foxglove plots them with no
plugin and the reader decodes a whole channel at once; rare events are JSON.
"""

from __future__ import annotations

from ballbeam.logs.schema import StructSchema

CAN_FRAME = StructSchema(
    "ballbeam/CanFrame",
    (
        ("bus_time_s", "float64"),
        ("arbitration_id", "uint32"),
        ("dlc", "uint8"),
        ("data", "uint8[8]"),
    ),
)
SENSOR = StructSchema(
    "ballbeam/Sensor",
    (
        ("cycle", "int64"),
        ("fresh", "uint8"),
        ("counter", "uint8"),
        ("status", "uint8"),
        ("angle_counts", "int32"),
        ("position_counts", "int32"),
        ("theta_rad", "float64"),
        ("position_m", "float64"),
    ),
)
COMMAND = StructSchema(
    "ballbeam/Command",
    (
        ("cycle", "int64"),
        ("voltage_v", "float64"),
        ("requested_v", "float64"),
        ("enable", "uint8"),
        ("counter", "uint8"),
        ("sensor_counter", "uint8"),
    ),
)
STATE_FIELDS = (
    ("theta_rad", "float64"),
    ("theta_rate_rad_s", "float64"),
    ("ball_velocity_m_s", "float64"),
    ("ball_position_m", "float64"),
)
ESTIMATE = StructSchema("ballbeam/Estimate", (("cycle", "int64"), *STATE_FIELDS))
REFERENCE = StructSchema(
    "ballbeam/Reference", (("cycle", "int64"), *STATE_FIELDS, ("input_v", "float64"))
)
TRUTH = StructSchema("ballbeam/PlantTruth", (("counter", "uint8"), *STATE_FIELDS))
TIMING = StructSchema(
    "ballbeam/CycleTiming",
    (
        ("cycle", "int64"),
        ("deadline_ns", "int64"),
        ("start_ns", "int64"),
        ("end_ns", "int64"),
        ("lateness_ns", "int64"),
        ("skipped", "int64"),
    ),
)
EVENT_SCHEMA = {
    "type": "object",
    "properties": {
        "cycle": {"type": "integer"},
        "kind": {"type": "string"},
        "detail": {"type": "string"},
    },
    "required": ["cycle", "kind", "detail"],
}

STRUCT_TOPICS = {
    "/can/rx": CAN_FRAME,
    "/can/tx": CAN_FRAME,
    "/sensor": SENSOR,
    "/command": COMMAND,
    "/estimate": ESTIMATE,
    "/reference": REFERENCE,
    "/truth": TRUTH,
    "/timing": TIMING,
}
JSON_TOPICS = ("/faults", "/events")
