"""Run logs: the MCAP recorder and a fast, truncation-tolerant reader."""

from ballbeam.logs.reader import JsonTopic, RunLog, StructTopic, read_log
from ballbeam.logs.recorder import PROFILE, ChannelHandle, Recorder
from ballbeam.logs.schema import StructSchema, parse_ros2msg

__all__ = [
    "PROFILE",
    "ChannelHandle",
    "JsonTopic",
    "Recorder",
    "RunLog",
    "StructSchema",
    "StructTopic",
    "parse_ros2msg",
    "read_log",
]
