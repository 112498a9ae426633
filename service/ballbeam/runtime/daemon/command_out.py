"""Command out: voltage frames to the plant, each recorded as sent."""

from __future__ import annotations

import time

import can

from ballbeam.logs.recording import RunRecording
from ballbeam.logs.topics import CAN_TX, COMMAND, CommandRecord
from ballbeam.protocol.frames import (
    VOLTAGE_COMMAND_ID,
    FrameContract,
    encode_lookahead,
    next_counter,
)
from ballbeam.protocol.secoc import FrameAuthenticator
from ballbeam.runtime.daemon.intake import SentCommands, frame_record

SHUTDOWN_REPEATS = 3  # the final 0 V is sent a few times: a frame can be lost


class CommandOut:
    """Sends the voltage commands: SecOC-style frames with ``auth`` (protocol/secoc.py; the
    authenticator then remembers what was sent), classic 8-byte frames without (noted in
    ``sent`` for the intake to tell its echoes from someone else's frames)."""

    def __init__(
        self,
        bus: can.BusABC,
        contract: FrameContract,
        recording: RunRecording,
        sent: SentCommands | None = None,
        auth: FrameAuthenticator | None = None,
    ) -> None:
        self.bus = bus
        self.auth = auth
        self.sent = sent if sent is not None else SentCommands()
        self.contract = contract
        self.recording = recording
        self.counter = 0
        self.last_data: bytes | None = None  # lock-step answers a repeated sample with it
        self.last_extension = b""
        self.resends = 0

    def send(
        self,
        log_time_ns: int,
        cycle: int,
        voltage_v: float,
        requested_v: float,
        enable: bool,
        sensor_counter: int,
        lookahead_v: tuple[float, ...] = (),
    ) -> None:
        """``lookahead_v``: the commands for the periods after this one (authenticated bus
        only: they ride in the frame's extension, protocol/secoc.py)."""
        data = self.contract.encode_voltage_command(
            self.counter, voltage_v, enable, sensor_counter
        )
        extension = (
            encode_lookahead(lookahead_v) if lookahead_v and self.auth is not None else b""
        )
        self.last_data = data
        self.last_extension = extension
        self._send_bytes(data, log_time_ns, cycle, extension)
        self.recording.write(COMMAND, log_time_ns, CommandRecord(
            cycle, voltage_v, requested_v, int(enable), self.counter, sensor_counter
        ))
        self.counter = next_counter(self.counter)

    def resend_last(self, log_time_ns: int, cycle: int) -> None:
        if self.last_data is not None:
            self._send_bytes(self.last_data, log_time_ns, cycle, self.last_extension)
            self.resends += 1

    def shutdown(self, log_time_ns: int, cycle: int) -> None:
        """0 V, disabled."""
        for _ in range(SHUTDOWN_REPEATS):
            data = self.contract.encode_voltage_command(self.counter, 0.0, False, 0)
            self._send_bytes(data, log_time_ns, cycle)
            self.counter = next_counter(self.counter)

    def _send_bytes(
        self, data: bytes, log_time_ns: int, cycle: int, extension: bytes = b""
    ) -> None:
        if self.auth is not None:
            # A fresh freshness value each time: a lock-step resend is a new frame, not a replay.
            message = can.Message(
                arbitration_id=VOLTAGE_COMMAND_ID,
                data=self.auth.protect(VOLTAGE_COMMAND_ID, data, extension),
                is_extended_id=False,
                is_fd=True,
            )
        else:
            message = can.Message(
                arbitration_id=VOLTAGE_COMMAND_ID, data=data, is_extended_id=False
            )
            self.sent.note(data)  # before sending: the echo may come back at once
        try:
            self.bus.send(message)
        except can.CanError as error:
            self.recording.fault(log_time_ns, cycle, "send_failed", str(error))
            return
        message.timestamp = time.time()  # the clock the kernel stamps received frames with
        self.recording.write(CAN_TX, log_time_ns, frame_record(message))
