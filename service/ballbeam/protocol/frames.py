"""The CAN frame contract: encode and decode the five ballbeam frames, check their counters.

The contract is defined once, in ``ballbeam.dbc`` beside this module (package data), and
loaded with cantools by both processes. :meth:`FrameContract.load` reads each signal's
position, sign, scale and range from the DBC and refuses a file that breaks the fixed parts
of the contract (ids, lengths, the E2E header). Encoding and decoding then run on those
precomputed layouts with plain integer arithmetic, because they run at 1 kHz in both
processes: cantools' own strict encode plus its E2E helper (crccheck) is several times
slower (README, benchmarks). The tests check that the bytes
are identical to cantools' ``Message.encode`` followed by ``apply_profile5_crc``.

Every frame: AUTOSAR E2E profile 5 CRC-16 in bytes 0-1 (little-endian, data id = frame id),
an 8-bit rolling counter in byte 2, payload from bit 24, reserved bits 0.
"""

from __future__ import annotations

import binascii
import dataclasses
import math
import operator
import struct
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Final, Literal, TypeAlias

import cantools
import numpy as np

from ballbeam.errors import FrameError

VOLTAGE_COMMAND_ID: Final = 0x100
SENSOR_ID: Final = 0x101
TRUTH_ANGLE_ID: Final = 0x102
TRUTH_BALL_ID: Final = 0x103
PLANT_STATUS_ID: Final = 0x104
FRAME_LENGTH: Final = 8
COUNTER_MODULUS: Final = 256
# A command's look-ahead (virtual CAN FD bus only; protocol/secoc.py): the commands for the
# periods after it, int16 little-endian at the Voltage signal's 1 mV, NO_LOOKAHEAD_RAW after
# the last one given.
LOOKAHEAD_SLOTS: Final = 20
LOOKAHEAD_MV_PER_V: Final = 1000
NO_LOOKAHEAD_RAW: Final = -32768
# A sensor frame's truth (authenticated CAN FD bus only): the truth frames' two payloads, as
# each would be sent alone, then zeros to the same 40 bytes as a look-ahead. One frame a
# sample instead of three: each frame a node reads costs it a share of its period.
TRUTH_EXTENSION_BYTES: Final = 2 * LOOKAHEAD_SLOTS

DBC_RESOURCE: Final = "ballbeam.dbc"  # package data of ballbeam.protocol

RejectReason: TypeAlias = Literal["unknown_id", "length", "crc", "range"]
CounterVerdict: TypeAlias = Literal["ok", "repeated", "stale"]

# Status bits of SensorFrame.status.
STATUS_WATCHDOG: Final = 0x01  # the watchdog has zeroed the voltage
STATUS_HELD: Final = 0x02  # plant held at its initial state, not started yet

# The emulator's counters a PlantStatus snapshot carries, by PlantStatusFrame.field (the DBC's
# VAL_ table for the Field signal names them in this order).
PLANT_STATUS_FIELDS: Final = (
    "samples_sent",
    "resends",
    "commands_applied",
    "rejected",
    "own_or_foreign",
    "dropped_by_injection",
    "watchdog_trips",
    "missed_periods",
    "peer_lost",
    "unauthenticated",
    "bad_mac",
    "replayed",
    "out_of_window",
)
PLANT_STATUS_VALUE_MAX: Final = 0xFFFF_FFFF  # a 32-bit Value: senders saturate


class FrameRejectedError(FrameError):
    """A frame was refused by :meth:`FrameContract.decode` or an ``encode_*`` method.

    ``reason`` is a fixed code so receivers can count rejections by kind without parsing
    messages; ``arbitration_id`` is the frame id concerned.
    """

    def __init__(self, reason: RejectReason, arbitration_id: int, detail: str) -> None:
        super().__init__(f"frame 0x{arbitration_id:03X} rejected ({reason}): {detail}")
        self.reason: RejectReason = reason
        self.arbitration_id = arbitration_id


@dataclass(frozen=True, slots=True)
class VoltageCommand:
    """0x100, controller → plant. ``sensor_counter``: counter of the plant period the command
    is for (the sensor frame it answers; coasting in real time, the period its cycle is in)."""

    counter: int
    voltage_v: float
    enable: bool
    sensor_counter: int


@dataclass(frozen=True, slots=True)
class SensorFrame:
    """0x101, plant → controller: raw encoder and ball-track ADC counts, status bits."""

    counter: int
    angle_counts: int
    position_counts: int
    status: int


@dataclass(frozen=True, slots=True)
class TruthAngle:
    """0x102, emulator → recorder: true servo state; ``counter`` = its sample's sensor frame."""

    counter: int
    theta_rad: float
    theta_rate_rad_s: float


@dataclass(frozen=True, slots=True)
class TruthBall:
    """0x103, emulator → recorder: true ball state; ``counter`` = its sample's sensor frame."""

    counter: int
    position_m: float
    velocity_m_s: float


@dataclass(frozen=True, slots=True)
class PlantStatusFrame:
    """0x104, emulator → recorder: one counter of a snapshot of the emulator's counters.

    ``field`` indexes PLANT_STATUS_FIELDS; a snapshot is the frames with field 0..12 in order
    and consecutive ``counter`` values; ``final`` marks the snapshot sent as the emulator
    stops."""

    counter: int
    field: int
    final: bool
    value: int


Frame: TypeAlias = VoltageCommand | SensorFrame | TruthAngle | TruthBall | PlantStatusFrame


def next_counter(counter: int) -> int:
    """The rolling counter after ``counter``: (counter + 1) mod 256."""
    return (counter + 1) % COUNTER_MODULUS


def e2e_profile5_crc(payload: bytes | bytearray, data_id: int) -> int:
    """AUTOSAR E2E profile 5 CRC-16 of a frame, as cantools' ``compute_profile5_crc``.

    CRC-16 (poly 0x1021, init 0xFFFF, no reflection, no final xor) over ``payload[2:]``, then
    the data id's low byte and high byte. Stored little-endian in bytes 0-1 of the frame.
    ``binascii.crc_hqx`` is that CRC (the CCITT polynomial, MSB first, from a given start), in
    C: a table loop here in Python cost each frame a few microseconds of the loop's period.
    """
    return binascii.crc_hqx((data_id & 0xFFFF).to_bytes(2, "little"),
                            binascii.crc_hqx(payload[2:], 0xFFFF))


_FieldKind: TypeAlias = Literal["int", "bool", "float"]


@dataclass(frozen=True, slots=True)
class _Field:
    """One signal of a frame as read from the DBC, in raw-integer terms."""

    name: str
    start: int  # Intel start bit = least significant bit in the little-endian 64-bit word
    mask: int  # (1 << length) - 1
    sign_bit: int  # 1 << (length - 1) if signed, else 0 (no sign extension)
    raw_min: int  # the DBC's [min|max] converted to raw and clipped to the bit width
    raw_max: int
    value_min: float  # physical limits for encoding, widened by 1e-6 LSB as cantools does
    value_max: float
    scale: float
    offset: float
    kind: _FieldKind


@dataclass(frozen=True, slots=True)
class _Layout:
    frame_id: int
    name: str
    fields: tuple[_Field, ...]  # Counter first, then in the dataclass's field order
    reserved_mask: int  # bits no signal covers: must be 0
    frame_type: type[Frame]
    attributes: operator.attrgetter[tuple[object, ...]]  # reads a dataclass in field order


# The fixed part of the contract: id, dataclass, and (DBC signal, kind) per dataclass field
# after the counter. Integer fields must have scale 1 and offset 0 in the DBC; scales and
# ranges of the float fields are the DBC's to choose.
_CONTRACT: Final[dict[str, tuple[int, type[Frame], tuple[tuple[str, _FieldKind], ...]]]] = {
    "VoltageCommand": (
        VOLTAGE_COMMAND_ID,
        VoltageCommand,
        (("Voltage", "float"), ("Enable", "bool"), ("SensorCounter", "int")),
    ),
    "SensorMeasurement": (
        SENSOR_ID,
        SensorFrame,
        (("AngleCounts", "int"), ("PositionCounts", "int"), ("Status", "int")),
    ),
    "PlantTruthAngle": (
        TRUTH_ANGLE_ID,
        TruthAngle,
        (("Theta", "float"), ("ThetaRate", "float")),
    ),
    "PlantTruthBall": (
        TRUTH_BALL_ID,
        TruthBall,
        (("BallPosition", "float"), ("BallVelocity", "float")),
    ),
    "PlantStatus": (
        PLANT_STATUS_ID,
        PlantStatusFrame,
        (("Field", "int"), ("Final", "bool"), ("Value", "int")),
    ),
}
_HEADER: Final = (("CRC", 0, 16), ("Counter", 16, 8))  # (name, start bit, length): E2E P5


def _field_from_signal(
    signal: cantools.database.can.Signal, kind: _FieldKind, where: str
) -> _Field:
    if signal.byte_order != "little_endian" or signal.is_float:
        raise FrameError(f"{where}: signal {signal.name} must be an Intel integer signal")
    if signal.multiplexer_ids or signal.is_multiplexer:
        raise FrameError(f"{where}: signal {signal.name} must not be multiplexed")
    scale, offset = signal.scale, signal.offset
    if kind != "float" and (scale != 1 or offset != 0):
        raise FrameError(f"{where}: signal {signal.name} must be a raw integer (scale 1, offset 0)")
    if scale <= 0:
        raise FrameError(f"{where}: signal {signal.name} needs a positive scale")
    length = signal.length
    lo, hi = (
        (-(1 << (length - 1)), (1 << (length - 1)) - 1)
        if signal.is_signed
        else (0, (1 << length) - 1)
    )
    # [min|max] are physical; a tolerance of 1e-6 LSB absorbs their decimal rounding.
    if signal.minimum is not None:
        lo = max(lo, math.ceil((signal.minimum - offset) / scale - 1e-6))
    if signal.maximum is not None:
        hi = min(hi, math.floor((signal.maximum - offset) / scale + 1e-6))
    if lo > hi:
        raise FrameError(f"{where}: signal {signal.name} has an empty range")
    return _Field(
        name=signal.name,
        start=signal.start,
        mask=(1 << length) - 1,
        sign_bit=(1 << (length - 1)) if signal.is_signed else 0,
        raw_min=lo,
        raw_max=hi,
        value_min=(lo - 1e-6) * scale + offset,
        value_max=(hi + 1e-6) * scale + offset,
        scale=float(scale),
        offset=float(offset),
        kind=kind,
    )


def _layout_from_message(
    database: cantools.database.can.Database, name: str, path: str
) -> _Layout:
    frame_id, frame_type, payload = _CONTRACT[name]
    try:
        message = database.get_message_by_name(name)
    except KeyError:
        raise FrameError(f"{path}: frame contract needs message {name}") from None
    where = f"{path}: message {name}"
    if message.frame_id != frame_id or message.is_extended_frame:
        raise FrameError(
            f"{where} must have standard id 0x{frame_id:03X}, has 0x{message.frame_id:X}"
            + (" (extended)" if message.is_extended_frame else "")
        )
    if message.length != FRAME_LENGTH or message.is_container:
        raise FrameError(f"{where} must be a plain {FRAME_LENGTH}-byte frame")
    signals = {signal.name: signal for signal in message.signals}
    for signal_name, start, length in _HEADER:
        signal = signals.get(signal_name)
        if signal is None or (signal.start, signal.length, signal.is_signed) != (
            start,
            length,
            False,
        ):
            raise FrameError(
                f"{where} needs unsigned {signal_name} at bit {start}, {length} bits"
                " (E2E profile 5 header)"
            )
    fields = [_field_from_signal(signals["Counter"], "int", where)]
    for signal_name, kind in payload:
        if signal_name not in signals:
            raise FrameError(f"{where} needs signal {signal_name}")
        field = _field_from_signal(signals[signal_name], kind, where)
        if field.start < 24:
            raise FrameError(f"{where}: payload signal {signal_name} must start at bit 24 or later")
        fields.append(field)
    extra = set(signals) - {name for name, _, _ in _HEADER} - {name for name, _ in payload}
    if extra:
        raise FrameError(f"{where} has signals outside the contract: {sorted(extra)}")
    covered = 0xFFFF  # the CRC
    for field in fields:
        covered |= field.mask << field.start
    return _Layout(
        frame_id=frame_id,
        name=name,
        fields=tuple(fields),
        reserved_mask=~covered & ((1 << (8 * FRAME_LENGTH)) - 1),
        frame_type=frame_type,
        attributes=operator.attrgetter(*(f.name for f in dataclasses.fields(frame_type))),
    )


class FrameContract:
    """The loaded frame contract: encode and decode the five frames.

    Encoders take physical values, round to the signal's resolution and refuse (with
    :class:`FrameRejectedError`, reason ``"range"``) a value outside the signal's DBC
    ``[min|max]`` (checked before rounding) or NaN, instead of wrapping: senders clamp first
    (the controller clamps its voltage, the emulator saturates its sensor counts). Integer
    arguments must be ints (``operator.index``; a float raises TypeError).
    """

    __slots__ = ("_by_id", "_by_type", "database", "dbc_text", "path")

    def __init__(self, path: str, dbc_text: str, database: cantools.database.can.Database) -> None:
        """Use :meth:`load`; this checks the contract and precomputes the layouts."""
        self.path = path
        self.dbc_text = dbc_text  # the exact contract text, e.g. for embedding in a run log
        self.database = database
        layouts = [_layout_from_message(database, name, path) for name in _CONTRACT]
        self._by_id = {layout.frame_id: layout for layout in layouts}
        self._by_type = {layout.frame_type: layout for layout in layouts}

    @classmethod
    def load(cls, path: Path | None = None) -> FrameContract:
        """Load and check the DBC at ``path`` (default: the one shipped with the package)."""
        source = resources.files("ballbeam.protocol") / DBC_RESOURCE if path is None else path
        where = str(source)
        try:
            text = source.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as exc:
            raise FrameError(f"{where}: cannot read the frame contract DBC: {exc}") from exc
        try:
            database = cantools.database.load_string(text, database_format="dbc")
        except Exception as exc:  # the DBC parser raises assorted types on malformed input
            raise FrameError(f"{where}: not a valid DBC file: {exc}") from exc
        if not isinstance(database, cantools.database.can.Database):
            raise FrameError(f"{where}: not a CAN database")
        return cls(where, text, database)

    # --- encoding ---------------------------------------------------------------------------

    def _encode(self, layout: _Layout, values: tuple[object, ...]) -> bytes:
        word = 0
        for field, value in zip(layout.fields, values, strict=True):
            if field.kind == "float":
                # Checked before rounding (as cantools' strict encode does), so a value past
                # the limit is refused even if it would round onto it; NaN fails both tests.
                if field.value_min <= value <= field.value_max:  # type: ignore[operator]
                    raw = round((value - field.offset) / field.scale)  # type: ignore[operator]
                else:
                    raw = None
            else:
                raw = operator.index(value)  # type: ignore[arg-type]
            if raw is None or not field.raw_min <= raw <= field.raw_max:
                raise FrameRejectedError(
                    "range",
                    layout.frame_id,
                    f"{layout.name}.{field.name} = {value!r} is outside "
                    f"[{field.raw_min * field.scale + field.offset:g}, "
                    f"{field.raw_max * field.scale + field.offset:g}]",
                )
            word |= (raw & field.mask) << field.start
        data = word.to_bytes(FRAME_LENGTH, "little")
        crc = e2e_profile5_crc(data, layout.frame_id)
        return bytes((crc & 0xFF, crc >> 8)) + data[2:]

    def encode_voltage_command(
        self, counter: int, voltage_v: float, enable: bool, sensor_counter: int
    ) -> bytes:
        """0x100 payload. ``voltage_v`` rounds to 1 mV; |voltage_v| ≤ 32.767 V else FrameError."""
        return self._encode(
            self._by_id[VOLTAGE_COMMAND_ID], (counter, voltage_v, enable, sensor_counter)
        )

    def encode_sensor(
        self, counter: int, angle_counts: int, position_counts: int, status: int
    ) -> bytes:
        """0x101 payload. Counts are int16; ``status`` uses only STATUS_WATCHDOG | STATUS_HELD."""
        return self._encode(
            self._by_id[SENSOR_ID], (counter, angle_counts, position_counts, status)
        )

    def encode_truth_angle(self, counter: int, theta_rad: float, theta_rate_rad_s: float) -> bytes:
        """0x102 payload. Resolution 1e-5 rad, 1e-4 rad/s (ranges ±5.24 rad, ±52.4 rad/s)."""
        return self._encode(self._by_id[TRUTH_ANGLE_ID], (counter, theta_rad, theta_rate_rad_s))

    def encode_truth_ball(self, counter: int, position_m: float, velocity_m_s: float) -> bytes:
        """0x103 payload. Resolution 1e-6 m, 1e-5 m/s (ranges ±0.524 m, ±5.24 m/s)."""
        return self._encode(self._by_id[TRUTH_BALL_ID], (counter, position_m, velocity_m_s))

    def encode_truth(
        self, counter: int, theta_rad: float, theta_rate_rad_s: float, position_m: float,
        velocity_m_s: float,
    ) -> bytes:
        """A sensor frame's truth extension: the 0x102 and 0x103 payloads of its sample, then
        zeros to TRUTH_EXTENSION_BYTES."""
        both = self.encode_truth_angle(counter, theta_rad, theta_rate_rad_s) + (
            self.encode_truth_ball(counter, position_m, velocity_m_s)
        )
        return both.ljust(TRUTH_EXTENSION_BYTES, b"\0")

    def decode_truth(self, extension: bytes, counter: int) -> tuple[TruthAngle, TruthBall]:
        """The truth a sensor frame with ``counter`` carries; FrameRejectedError (reasons as
        :meth:`decode`'s, the id the sensor's) unless it is the extension's length, each
        payload is valid, both are of ``counter`` and the rest is zeros."""
        if len(extension) != TRUTH_EXTENSION_BYTES:
            raise FrameRejectedError("length", SENSOR_ID, f"truth of {len(extension)} bytes, "
                                     f"expected {TRUTH_EXTENSION_BYTES}")
        if any(extension[2 * FRAME_LENGTH:]):
            raise FrameRejectedError("range", SENSOR_ID, "truth padding is not zeros")
        angle = self.decode(TRUTH_ANGLE_ID, extension[:FRAME_LENGTH])
        ball = self.decode(TRUTH_BALL_ID, extension[FRAME_LENGTH:2 * FRAME_LENGTH])
        assert isinstance(angle, TruthAngle) and isinstance(ball, TruthBall)
        if angle.counter != counter or ball.counter != counter:
            raise FrameRejectedError("range", SENSOR_ID, f"truth counters {angle.counter}, "
                                     f"{ball.counter} for sample {counter}")
        return angle, ball

    def encode_plant_status(self, counter: int, field: int, final: bool, value: int) -> bytes:
        """0x104 payload: counter ``field`` (an index of PLANT_STATUS_FIELDS) is ``value``
        (0..PLANT_STATUS_VALUE_MAX; the sender saturates)."""
        return self._encode(self._by_id[PLANT_STATUS_ID], (counter, field, final, value))

    def encode(self, frame: Frame) -> tuple[int, bytes]:
        """Any decoded frame back to ``(arbitration_id, payload)``, e.g. to replay a log."""
        layout = self._by_type[type(frame)]
        return layout.frame_id, self._encode(layout, layout.attributes(frame))

    # --- decoding ---------------------------------------------------------------------------

    def decode(self, arbitration_id: int, data: bytes | bytearray) -> Frame:
        """Check and decode one frame; :class:`FrameRejectedError` (with ``reason``) if refused.

        Checks in order: known standard id (``"unknown_id"``; the caller drops extended-id
        frames), exactly 8 bytes (``"length"``), E2E CRC (``"crc"``), reserved bits 0 and every
        signal inside its DBC range (``"range"``). The counter is not judged here: that is
        :class:`CounterCheck`'s job, one per stream.
        """
        layout = self._by_id.get(arbitration_id)
        if layout is None:
            raise FrameRejectedError("unknown_id", arbitration_id, "not in the frame contract")
        if len(data) != FRAME_LENGTH:
            raise FrameRejectedError(
                "length", arbitration_id, f"{len(data)} bytes, expected {FRAME_LENGTH}"
            )
        word = int.from_bytes(data, "little")
        if word & 0xFFFF != e2e_profile5_crc(data, arbitration_id):
            raise FrameRejectedError("crc", arbitration_id, "E2E profile 5 CRC mismatch")
        if word & layout.reserved_mask:
            raise FrameRejectedError("range", arbitration_id, "reserved bits set")
        values: list[object] = []
        for field in layout.fields:
            raw = (word >> field.start) & field.mask
            if raw & field.sign_bit:
                raw -= field.sign_bit << 1
            if not field.raw_min <= raw <= field.raw_max:
                raise FrameRejectedError(
                    "range", arbitration_id, f"{layout.name}.{field.name} raw {raw} out of range"
                )
            if field.kind == "float":
                values.append(raw * field.scale + field.offset)
            elif field.kind == "bool":
                values.append(bool(raw))
            else:
                values.append(raw)
        return layout.frame_type(*values)  # type: ignore[arg-type]

    def raw_signal(self, arbitration_id: int, signal: str, data: np.ndarray) -> np.ndarray:
        """One signal's raw values from many recorded frames at once: ``data`` (N, 8) uint8
        payloads of frames with ``arbitration_id`` → (N,) int64, sign-extended as the DBC says.
        No checks (the frames were judged when they were received); for analysis of logs."""
        layout = self._by_id.get(arbitration_id)
        field = next((f for f in layout.fields if f.name == signal), None) if layout else None
        if field is None:
            raise FrameError(f"frame 0x{arbitration_id:03X} has no signal {signal!r}")
        payload = np.ascontiguousarray(np.asarray(data, dtype=np.uint8).reshape(-1, FRAME_LENGTH))
        words = payload.view("<u8")[:, 0]
        raw = ((words >> np.uint64(field.start)) & np.uint64(field.mask)).astype(np.int64)
        if field.sign_bit:
            raw = np.where(raw & field.sign_bit, raw - (field.sign_bit << 1), raw)
        return raw


def encode_lookahead(voltages_v: tuple[float, ...]) -> bytes:
    """A command's look-ahead extension: at most LOOKAHEAD_SLOTS voltages, each within
    ±32.767 V (the Voltage signal's range; FrameRejectedError "range" else), 1 mV each."""
    if len(voltages_v) > LOOKAHEAD_SLOTS:
        raise FrameRejectedError(
            "range", VOLTAGE_COMMAND_ID, f"{len(voltages_v)} look-ahead voltages, at most "
            f"{LOOKAHEAD_SLOTS}"
        )
    raws = []
    for voltage_v in voltages_v:
        raw = round(voltage_v * LOOKAHEAD_MV_PER_V) if abs(voltage_v) <= 32.767 else None
        if raw is None:  # NaN fails the test too
            raise FrameRejectedError(
                "range", VOLTAGE_COMMAND_ID, f"look-ahead voltage {voltage_v!r} V is outside "
                "[-32.767, 32.767]"
            )
        raws.append(raw)
    raws += [NO_LOOKAHEAD_RAW] * (LOOKAHEAD_SLOTS - len(raws))
    return struct.pack(f"<{LOOKAHEAD_SLOTS}h", *raws)


def decode_lookahead(extension: bytes) -> tuple[float, ...]:
    """The voltages of a command's look-ahead extension; FrameRejectedError unless it is
    LOOKAHEAD_SLOTS slots whose given values all come before the empty ones."""
    if len(extension) != 2 * LOOKAHEAD_SLOTS:
        raise FrameRejectedError(
            "length", VOLTAGE_COMMAND_ID,
            f"look-ahead of {len(extension)} bytes, expected {2 * LOOKAHEAD_SLOTS}",
        )
    raws = struct.unpack(f"<{LOOKAHEAD_SLOTS}h", extension)
    given = raws.index(NO_LOOKAHEAD_RAW) if NO_LOOKAHEAD_RAW in raws else LOOKAHEAD_SLOTS
    if any(raw != NO_LOOKAHEAD_RAW for raw in raws[given:]):
        raise FrameRejectedError("range", VOLTAGE_COMMAND_ID, "look-ahead has a gap")
    return tuple(raw / LOOKAHEAD_MV_PER_V for raw in raws[:given])


class CounterCheck:
    """Judges one stream's rolling counters: lost, repeated and stale frames.

    delta = (counter − last accepted) mod 256: 1 → ok; 0 → repeated; 2..127 → ok with
    delta − 1 frames lost; 128..255 → stale (older than the last accepted; reject it). The first
    frame, and the first after :meth:`reset`, is ok. Note that after an outage of 128 or more
    frames, or a sender restart, fresh frames look stale until the counter comes round (at most
    128 frames); a receiver that notices a long silence should :meth:`reset`.
    """

    __slots__ = ("accepted", "last", "lost", "repeated", "stale")

    def __init__(self) -> None:
        self.last: int | None = None  # counter of the last accepted frame
        self.accepted = 0
        self.lost = 0
        self.repeated = 0
        self.stale = 0

    def classify(self, counter: int) -> CounterVerdict:
        """Classify the counter (0..255) of the next received frame and update the counts."""
        last = self.last
        if last is None:
            self.last = counter
            self.accepted += 1
            return "ok"
        delta = (counter - last) % COUNTER_MODULUS
        if delta == 0:
            self.repeated += 1
            return "repeated"
        if delta >= COUNTER_MODULUS // 2:
            self.stale += 1
            return "stale"
        self.lost += delta - 1
        self.accepted += 1
        self.last = counter
        return "ok"

    def reset(self) -> None:
        """Forget the last counter (keep the counts): the next frame is accepted as the first."""
        self.last = None


class CounterUnwrap:
    """A rolling 8-bit counter unwrapped into an ever-growing index (the plant's sample-period
    index from its frames' counters). The first counter heard is taken as its own index (a
    plant heard from its start reads from 0); each next one moves the index on by the forward
    distance (counter − last) mod 256 when that is below 128, else it is an older frame and
    gets the index it had. Gaps of 128 periods or more cannot be told from old frames."""

    __slots__ = ("last",)

    def __init__(self) -> None:
        self.last: int | None = None  # the index of the newest counter heard

    def index(self, counter: int) -> int:
        if self.last is None:
            self.last = counter
            return counter
        delta = (counter - self.last) % COUNTER_MODULUS
        if delta >= COUNTER_MODULUS // 2:
            return self.last - (COUNTER_MODULUS - delta)
        self.last += delta
        return self.last
