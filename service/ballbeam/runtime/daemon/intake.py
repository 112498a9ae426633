"""Sensor intake: every frame the daemon hears, judged and recorded.

Sensor frames must pass the contract and their counter check to become the latest sample;
truth (in the sensor frame's extension on an authenticated bus, else in two frames paired by
counter, angle + ball) is recorded at its sample's time; the
emulator's status frames are gathered into whole snapshots of its counters (``/plant_status``); the
daemon's own commands looped back by the bus (the bytes it sent) are counted and dropped; a
command frame it did not send is someone else's: recorded and counted as rejected
(``rejected_foreign_command``); anything else is recorded as received and counted as rejected
(never fatal).

On an authenticated bus (protocol/secoc.py) every frame is judged by its MAC and freshness
first: forged (``rejected_bad_mac``), replayed or reordered (``rejected_replayed``,
``rejected_out_of_window``) and classic frames with no MAC (``rejected_unauthenticated``) are
refused before the contract and the counter check, so they move no state and never
desynchronise the real stream; truth comes only from authenticated frames. A command frame with
a right MAC that the daemon never sent was made by another holder of the run's secret: a
second writer (``second_writer_frames``; the loop stops the run). On a classic bus a command
frame with a right CRC that the daemon did not send lately counts the same way.
"""

from __future__ import annotations

from collections import Counter, deque

import can

from ballbeam.logs.recording import RunRecording
from ballbeam.logs.topics import (
    CAN_RX,
    PLANT_STATUS,
    TRUTH,
    CanFrameRecord,
    PlantStatusRecord,
    TruthRecord,
)
from ballbeam.protocol.frames import (
    PLANT_STATUS_FIELDS,
    VOLTAGE_COMMAND_ID,
    CounterCheck,
    CounterUnwrap,
    CounterVerdict,
    FrameContract,
    FrameRejectedError,
    PlantStatusFrame,
    SensorFrame,
    TruthAngle,
    TruthBall,
    next_counter,
)
from ballbeam.protocol.secoc import (
    CLASSIC_LENGTH,
    FrameAuthenticator,
    OwnVerdict,
    extension_of,
    is_authenticated_length,
)

MAX_RECORDED_REJECTIONS = 1000  # per reason: beyond this only the count grows (no log floods)


def frame_record(message: can.Message) -> CanFrameRecord:
    data = bytes(message.data).ljust(8, b"\0")[:8]
    return CanFrameRecord(message.timestamp, message.arbitration_id, message.dlc, data)


class SentCommands:
    """The payloads of the daemon's latest command frames, each claimed once by its echo.

    A bus that loops frames back (udp_multicast, SocketCAN with receive_own_messages) returns
    each command within a period or so; a bus that does not simply lets old entries fall off.
    """

    def __init__(self, keep: int = 64, recent: int = 512) -> None:
        self._pending: deque[bytes] = deque(maxlen=keep)
        # Classic bus: a frame that is one of these but already echoed is a replay of ours,
        # not a second writer's (half a second of commands at 1 kHz).
        self._recent: deque[bytes] = deque(maxlen=recent)

    def note(self, data: bytes) -> None:
        self._pending.append(data)
        self._recent.append(data)

    def sent_lately(self, data: bytes) -> bool:
        return data in self._recent

    def claim(self, data: bytes) -> bool:
        """True (and forgotten) if ``data`` is one of ours not yet echoed."""
        try:
            self._pending.remove(data)
        except ValueError:
            return False
        return True


class PlantStatusAssembler:
    """Whole snapshots from the emulator's PlantStatus frames: field 0 opens one; each next
    field must follow with the next counter and the same ``final``; the last field closes it.
    A lost or out-of-order frame discards the snapshot (the next comes 100 ms later)."""

    def __init__(self) -> None:
        self._values: list[int] = []
        self._final = False
        self._last_counter = 0
        self.snapshots = 0
        self.incomplete = 0  # snapshots begun and abandoned

    def add(self, frame: PlantStatusFrame) -> PlantStatusRecord | None:
        if frame.field == 0:
            if self._values:
                self.incomplete += 1
            self._values, self._final = [frame.value], frame.final
        elif (
            self._values
            and frame.field == len(self._values)
            and frame.final == self._final
            and frame.counter == next_counter(self._last_counter)
        ):
            self._values.append(frame.value)
        else:
            if self._values:
                self.incomplete += 1
            self._values = []
            return None
        self._last_counter = frame.counter
        if len(self._values) < len(PLANT_STATUS_FIELDS):
            return None
        record = PlantStatusRecord(int(self._final), *self._values)
        self._values = []
        self.snapshots += 1
        return record


class SensorIntake:
    def __init__(
        self,
        contract: FrameContract,
        recording: RunRecording,
        sent: SentCommands | None = None,
        sample_period_s: float = 1e-3,
        auth: FrameAuthenticator | None = None,
        late_sample_periods: int | None = None,
    ) -> None:
        self.contract = contract
        self.recording = recording
        self.sent = sent if sent is not None else SentCommands()
        self.auth = auth
        self.second_writer_frames = 0  # valid command frames this daemon never sent
        self.sensor_check = CounterCheck()
        self.latest: SensorFrame | None = None
        self.fresh = False  # a sample arrived that no cycle has used yet
        self.own_frames = 0
        self.rejected: Counter[str] = Counter()
        self._truth_angle: TruthAngle | None = None
        self.plant_status = PlantStatusAssembler()
        self.final_status_seen = False
        # The plant's clock: its truth counters (one per sample period) unwrapped.
        self.plant_clock = CounterUnwrap()
        self.sample_period_s = sample_period_s
        self.sample_period_ns = round(sample_period_s * 1e9)
        # (counter, log time) of the latest accepted sample: its truth is logged at that time.
        self._last_sample_log: tuple[int, int] | None = None
        # Real time: a sample this many plant periods older than the freshest seen is no
        # measurement of now (see take); None: every sample counts.
        self.late_sample_periods = late_sample_periods
        self.sample_clock = CounterUnwrap()
        self._latest_index = 0
        self._freshest_offset_ns: int | None = None
        self.late_samples = 0

    def take(self, now_ns: int = 0) -> tuple[SensorFrame, int] | None:
        """The latest sample if no cycle has used it yet, with the plant periods it is late
        (0: it is of now).

        The plant samples its period ``i`` at its own ``origin + i·period``; ``now_ns − i·period``
        is then that origin plus the sample's age now. Its smallest value so far is the
        freshest a sample has ever been (the bus's own delay); a sample older than that by
        ``late_sample_periods`` periods or more is late by as many whole periods. A starved
        daemon reads its socket behind the stream (samples 29 ms old were read, and taken
        for now, while the servo ran to 53.6°): such a sample is of the past, and the law
        is told how far (counted)."""
        sample = self.latest if self.fresh else None
        self.fresh = False
        if sample is None:
            return None
        late_periods = self.late_periods(now_ns)
        if late_periods:
            self.late_samples += 1
        return sample, late_periods

    def behind(self, now_ns: int) -> bool:
        """Real time: is the latest sample late at ``now_ns`` (see :meth:`take`)? False before
        any sample, and in lock-step."""
        return self.late_periods(now_ns) > 0

    def late_periods(self, now_ns: int) -> int:
        """The whole plant periods the latest sample is late at ``now_ns``; 0 when it is
        less than ``late_sample_periods`` behind (the loop's ordinary jitter), before any
        sample, and in lock-step."""
        if self.latest is None or self.late_sample_periods is None:
            return 0
        offset_ns = now_ns - self._latest_index * self.sample_period_ns
        if self._freshest_offset_ns is None or offset_ns < self._freshest_offset_ns:
            self._freshest_offset_ns = offset_ns
        periods = (offset_ns - self._freshest_offset_ns) // self.sample_period_ns
        return periods if periods >= self.late_sample_periods else 0

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
        command = message.arbitration_id == VOLTAGE_COMMAND_ID and not foreign
        own: OwnVerdict | None = None
        if command:
            own = self._own(data)
            if own == "echo":
                self.own_frames += 1  # our own command looped back by the bus
                return None
        self.recording.write(CAN_RX, log_time_ns, frame_record(message))
        if own is not None:
            self._not_ours(own, data, log_time_ns, cycle)
            return None
        if foreign:
            kind = ("extended-id" if message.is_extended_id
                    else "remote" if message.is_remote_frame else "error")
            self.reject("foreign", f"{kind} frame 0x{message.arbitration_id:X}", log_time_ns,
                        cycle)
            return None
        auth = self.auth
        authenticated = auth is None  # a classic bus: the contract is all there is
        extension = b""
        if auth is not None and is_authenticated_length(len(data)):
            auth_verdict = auth.verify(message.arbitration_id, data)
            if auth_verdict != "ok":
                self.reject(auth_verdict, f"frame 0x{message.arbitration_id:03X}: {auth_verdict}",
                            log_time_ns, cycle)
                return None
            extension = extension_of(data)
            data = data[:CLASSIC_LENGTH]
            authenticated = True
        truth: tuple[TruthAngle, TruthBall] | None = None
        try:
            # Any other length is judged by the contract first, so noise keeps its reasons.
            frame = self.contract.decode(message.arbitration_id, data)
            if extension:  # only a sensor frame carries one here (its sample's truth)
                if not isinstance(frame, SensorFrame):
                    raise FrameRejectedError("length", message.arbitration_id,
                                             f"{len(extension)} bytes beyond its payload")
                truth = self.contract.decode_truth(extension, frame.counter)
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
                self._latest_index = self.sample_clock.index(frame.counter)
                self.fresh = True
                self._last_sample_log = (frame.counter, log_time_ns)
            elif verdict == "stale":
                self.reject("stale", f"sensor counter {frame.counter} is older than the last",
                            log_time_ns, cycle)
            if truth is not None:
                self._record_truth(*truth, log_time_ns)
            return verdict
        if isinstance(frame, PlantStatusFrame):
            # Authenticated (or, on a classic bus, contract-valid) frames only reach here.
            record = self.plant_status.add(frame)
            if record is not None:
                self.recording.write(PLANT_STATUS, log_time_ns, record)
                self.final_status_seen = self.final_status_seen or bool(record.final)
        elif isinstance(frame, TruthAngle):
            self._truth_angle = frame
        elif isinstance(frame, TruthBall):
            angle = self._truth_angle
            if angle is not None and angle.counter == frame.counter:
                self._record_truth(angle, frame, log_time_ns)
                self._truth_angle = None
        else:
            self.reject("direction", f"unexpected {type(frame).__name__} frame", log_time_ns,
                        cycle)
        return None

    def _record_truth(self, angle: TruthAngle, ball: TruthBall, log_time_ns: int) -> None:
        """A sample's truth (one counter), logged at the time of that sample: truth follows
        its sensor frame, or rides in it; now, if that sample's sensor frame never came
        (counters wrap, so no older match)."""
        sample = self._last_sample_log
        at_ns = sample[1] if sample and sample[0] == ball.counter else log_time_ns
        sample_index = self.plant_clock.index(ball.counter)
        self.recording.write(TRUTH, at_ns, TruthRecord(
            ball.counter, angle.theta_rad, angle.theta_rate_rad_s,
            ball.velocity_m_s, ball.position_m,
            sample_index, sample_index * self.sample_period_s,
        ))

    def _own(self, data: bytes) -> OwnVerdict:
        """Whose is this command frame: ``"echo"`` (ours, heard back once), ``"replayed"``
        (ours, heard again), ``"not_sent"`` (valid, never ours: a second writer) or
        ``"invalid"`` (no right MAC, or on a classic bus no right CRC: a stranger's)."""
        if self.auth is not None:
            return self.auth.own_frame(VOLTAGE_COMMAND_ID, data)
        if self.sent.claim(data):
            return "echo"
        if self.sent.sent_lately(data):
            return "replayed"
        try:
            self.contract.decode(VOLTAGE_COMMAND_ID, data)
        except FrameRejectedError:
            return "invalid"
        return "not_sent"

    def _not_ours(self, own: OwnVerdict, data: bytes, log_time_ns: int, cycle: int) -> None:
        """A command frame the daemon did not send (this time): recorded by the caller,
        counted here; a valid one counts towards a second writer."""
        detail = {
            "replayed": "a replay of a command this daemon sent",
            "invalid": "a stranger's (no valid MAC or CRC)",
            "not_sent": "valid, but never sent by this daemon: a second writer",
        }.get(own, own)
        self.reject("foreign_command", f"a command frame this daemon did not send ({detail}): "
                    f"{data.hex()}", log_time_ns, cycle)
        if own == "not_sent":
            self.second_writer_frames += 1
