"""Command out: voltage frames to the plant, each recorded as sent."""

from __future__ import annotations

import time
from collections import Counter, deque

import can

from ballbeam.logs.recording import RunRecording
from ballbeam.logs.topics import CAN_TX, COMMAND, CommandRecord
from ballbeam.protocol.frames import (
    VOLTAGE_COMMAND_ID,
    FrameContract,
    FrameRejectedError,
    next_counter,
)
from ballbeam.protocol.secoc import ECHOES_KEPT, FrameAuthenticator, OwnVerdict
from ballbeam.runtime.daemon.intake import frame_record

SHUTDOWN_REPEATS = 3  # the final 0 V is sent a few times: a frame can be lost


class CommandOut:
    """Sends the voltage commands; ``auth``: SecOC-style frames (None: the classic contract).

    It remembers what it sent so the intake can tell its own frames, looped back by the bus,
    from frames with the same id that someone else wrote (:meth:`own_frame`).
    """

    def __init__(
        self,
        bus: can.BusABC,
        contract: FrameContract,
        recording: RunRecording,
        auth: FrameAuthenticator | None = None,
    ) -> None:
        self.bus = bus
        self.contract = contract
        self.recording = recording
        self.auth = auth
        # Classic bus: the payloads sent lately, and those not heard back yet.
        self._sent: deque[bytes] = deque()
        self._recent: Counter[bytes] = Counter()
        self._pending: Counter[bytes] = Counter()
        self.counter = 0
        self.last_data: bytes | None = None  # lock-step answers a repeated sample with it
        self.resends = 0

    def send(
        self,
        log_time_ns: int,
        cycle: int,
        voltage_v: float,
        requested_v: float,
        enable: bool,
        sensor_counter: int,
    ) -> None:
        data = self.contract.encode_voltage_command(
            self.counter, voltage_v, enable, sensor_counter
        )
        self.last_data = data
        self._send_bytes(data, log_time_ns, cycle)
        self.recording.write(COMMAND, log_time_ns, CommandRecord(
            cycle, voltage_v, requested_v, int(enable), self.counter, sensor_counter
        ))
        self.counter = next_counter(self.counter)

    def resend_last(self, log_time_ns: int, cycle: int) -> None:
        if self.last_data is not None:
            self._send_bytes(self.last_data, log_time_ns, cycle)
            self.resends += 1

    def shutdown(self, log_time_ns: int, cycle: int) -> None:
        """0 V, disabled."""
        for _ in range(SHUTDOWN_REPEATS):
            data = self.contract.encode_voltage_command(self.counter, 0.0, False, 0)
            self._send_bytes(data, log_time_ns, cycle)
            self.counter = next_counter(self.counter)

    def own_frame(self, data: bytes) -> OwnVerdict:
        """Judge a 0x100 frame heard on the bus: ``"echo"`` (one this daemon sent, heard back
        the first time), ``"replayed"`` (one it sent, heard again), ``"not_sent"`` (valid,
        but not this daemon's: a second writer) or ``"invalid"`` (a stranger's)."""
        if self.auth is not None:
            return self.auth.own_frame(VOLTAGE_COMMAND_ID, data)
        if self._pending[data] > 0:
            self._pending[data] -= 1
            return "echo"
        if self._recent[data] > 0:
            return "replayed"
        try:
            self.contract.decode(VOLTAGE_COMMAND_ID, data)
        except FrameRejectedError:
            return "invalid"
        return "not_sent"

    def _remember(self, data: bytes) -> None:
        self._sent.append(data)
        self._pending[data] += 1
        self._recent[data] += 1
        if len(self._sent) > ECHOES_KEPT:
            old = self._sent.popleft()
            self._recent[old] -= 1
            if self._recent[old] <= 0:
                del self._recent[old]
                self._pending.pop(old, None)

    def _send_bytes(self, payload: bytes, log_time_ns: int, cycle: int) -> None:
        if self.auth is not None:
            message = can.Message(
                arbitration_id=VOLTAGE_COMMAND_ID,
                data=self.auth.protect(VOLTAGE_COMMAND_ID, payload),
                is_extended_id=False,
                is_fd=True,
            )
        else:
            self._remember(payload)
            message = can.Message(
                arbitration_id=VOLTAGE_COMMAND_ID, data=payload, is_extended_id=False
            )
        try:
            self.bus.send(message)
        except can.CanError as error:
            self.recording.fault(log_time_ns, cycle, "send_failed", str(error))
            return
        message.timestamp = time.time()  # the clock the kernel stamps received frames with
        self.recording.write(CAN_TX, log_time_ns, frame_record(message))
