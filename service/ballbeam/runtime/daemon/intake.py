"""Sensor intake: every frame the daemon hears, judged and recorded.

Sensor frames must pass the contract and their counter check to become the latest sample;
truth frames are paired (angle + ball, same counter) and recorded at their sample's time; the
daemon's own commands looped back by the bus are counted and dropped; anything else is
recorded as received and counted as rejected (never fatal).

With an authenticator (``bus.authenticate``), a frame counts only if it carries a right MAC and
a fresh freshness value (protocol/secoc.py); forged, replayed and reordered frames are rejected
before the counter check, so they never move the real stream's state. A frame with the
daemon's own command id that the daemon did not send is recorded and counted
(``rejected_not_ours``); one that is valid all the same (a right MAC, or on the classic bus a
right CRC) was written by a second writer, which the loop treats as a fault.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable

import can

from ballbeam.logs.recording import RunRecording
from ballbeam.logs.topics import CAN_RX, TRUTH, CanFrameRecord, TruthRecord
from ballbeam.protocol.frames import (
    VOLTAGE_COMMAND_ID,
    CounterCheck,
    CounterVerdict,
    FrameContract,
    FrameRejectedError,
    SensorFrame,
    TruthAngle,
    TruthBall,
)
from ballbeam.protocol.secoc import (
    AUTHENTICATED_LENGTH,
    CLASSIC_LENGTH,
    FrameAuthenticator,
    OwnVerdict,
)

MAX_RECORDED_REJECTIONS = 1000  # per reason: beyond this only the count grows (no log floods)


def frame_record(message: can.Message) -> CanFrameRecord:
    data = bytes(message.data).ljust(8, b"\0")[:8]
    return CanFrameRecord(message.timestamp, message.arbitration_id, message.dlc, data)


def _never_sent(_data: bytes) -> OwnVerdict:
    return "not_sent"


class SensorIntake:
    def __init__(
        self,
        contract: FrameContract,
        recording: RunRecording,
        auth: FrameAuthenticator | None = None,
        own_frame: Callable[[bytes], OwnVerdict] = _never_sent,
    ) -> None:
        self.contract = contract
        self.recording = recording
        self.auth = auth
        self.own_frame = own_frame  # CommandOut.own_frame: was this 0x100 frame ours?
        self.second_writer_frames = 0  # valid frames with our command id we did not send
        self.truth_samples = 0
        self._last_truth_counter: int | None = None
        self.max_abs_truth_theta_rad = 0.0  # the plant's own |θ| (emulator truth), largest
        self.sensor_check = CounterCheck()
        self.latest: SensorFrame | None = None
        self.fresh = False  # a sample arrived that no cycle has used yet
        self.own_frames = 0
        self.rejected: Counter[str] = Counter()
        self._truth_angle: TruthAngle | None = None
        # (counter, log time) of the latest accepted sample: its truth is logged at that time.
        self._last_sample_log: tuple[int, int] | None = None

    def take(self) -> SensorFrame | None:
        """The latest sample if no cycle has used it yet."""
        sample = self.latest if self.fresh else None
        self.fresh = False
        return sample

    def reject(self, reason: str, detail: str, log_time_ns: int, cycle: int) -> None:
        self.rejected[reason] += 1
        if self.rejected[reason] <= MAX_RECORDED_REJECTIONS:
            self.recording.fault(log_time_ns, cycle, f"rejected_{reason}", detail)

    def handle(self, message: can.Message, log_time_ns: int, cycle: int) -> CounterVerdict | None:
        """Judge one frame; the sensor counter verdict, or None for any other frame."""
        # The contract is on standard-id data frames: an extended id that happens to have
        # the same number, a remote frame or an error frame is someone else's.
        foreign = message.is_extended_id or message.is_remote_frame or message.is_error_frame
        data = bytes(message.data)
        own: OwnVerdict | None = None
        if message.arbitration_id == VOLTAGE_COMMAND_ID and not foreign:
            own = self.own_frame(data)
            if own == "echo":
                self.own_frames += 1  # our own command looped back by the bus
                return None
        self.recording.write(CAN_RX, log_time_ns, frame_record(message))
        if foreign:
            kind = ("extended-id" if message.is_extended_id
                    else "remote" if message.is_remote_frame else "error")
            self.reject("foreign", f"{kind} frame 0x{message.arbitration_id:X}", log_time_ns,
                        cycle)
            return None
        if own is not None:
            self._not_ours(own, data, log_time_ns, cycle)
            return None
        auth = self.auth
        if auth is not None and len(data) == AUTHENTICATED_LENGTH:
            auth_verdict = auth.verify(message.arbitration_id, data)
            if auth_verdict != "ok":
                self.reject(auth_verdict, f"frame 0x{message.arbitration_id:03X}: {auth_verdict}",
                            log_time_ns, cycle)
                return None
            data = data[:CLASSIC_LENGTH]
            authenticated = True
        else:
            authenticated = auth is None
        try:
            frame = self.contract.decode(message.arbitration_id, data)
        except FrameRejectedError as error:
            self.reject(error.reason, str(error), log_time_ns, cycle)
            return None
        if not authenticated:
            # A well-formed classic frame on an authenticated bus: a stranger's.
            self.reject("unauthenticated", f"frame 0x{message.arbitration_id:03X} has no MAC",
                        log_time_ns, cycle)
            return None
        if isinstance(frame, SensorFrame):
            verdict = self.sensor_check.classify(frame.counter)
            if verdict == "ok":
                self.latest = frame
                self.fresh = True
                self._last_sample_log = (frame.counter, log_time_ns)
            elif verdict == "stale":
                self.reject("stale", f"sensor counter {frame.counter} is older than the last",
                            log_time_ns, cycle)
            return verdict
        if isinstance(frame, TruthAngle):
            self._truth_angle = frame
        elif isinstance(frame, TruthBall):
            angle = self._truth_angle
            if (
                angle is not None
                and angle.counter == frame.counter
                and frame.counter != self._last_truth_counter  # a lock-step resend: logged
            ):
                self._last_truth_counter = frame.counter
                # Truth follows its sensor frame: log it at the time of that sample (now, if
                # that sample's sensor frame never came: counters wrap, so no older match).
                sample = self._last_sample_log
                at_ns = sample[1] if sample and sample[0] == frame.counter else log_time_ns
                self.truth_samples += 1
                self.max_abs_truth_theta_rad = max(
                    self.max_abs_truth_theta_rad, abs(angle.theta_rad)
                )
                self.recording.write(TRUTH, at_ns, TruthRecord(
                    frame.counter, angle.theta_rad, angle.theta_rate_rad_s,
                    frame.velocity_m_s, frame.position_m,
                ))
                self._truth_angle = None
        else:
            self.reject("direction", f"unexpected {type(frame).__name__} frame", log_time_ns,
                        cycle)
        return None

    def _not_ours(self, own: OwnVerdict, data: bytes, log_time_ns: int, cycle: int) -> None:
        """A 0x100 frame the daemon did not send (this time): recorded by the caller and
        counted. ``"not_sent"`` is a valid frame (a right MAC; on a classic bus a right CRC):
        someone else writes our id."""
        if own == "not_sent" and self.auth is None:
            try:  # the default judge (no CommandOut) leaves validity to the contract
                self.contract.decode(VOLTAGE_COMMAND_ID, data)
            except FrameRejectedError:
                own = "invalid"
        detail = {
            "replayed": "a replay of a command this daemon sent",
            "invalid": "a stranger's (no valid MAC or CRC)",
            "not_sent": "valid, but not sent by this daemon: a second writer",
        }.get(own, own)
        self.reject("not_ours", f"0x{VOLTAGE_COMMAND_ID:03X} frame: {detail}", log_time_ns,
                    cycle)
        if own == "not_sent":
            self.second_writer_frames += 1
