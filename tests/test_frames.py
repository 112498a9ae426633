"""The frame contract: byte layout, E2E CRC, round trips, a fuzzed decoder, counters, DBC checks.

Expected values are computed here from the contract as written (factors, bit positions, the
AUTOSAR profile 5 CRC by a small bitwise implementation), not taken from cantools; cantools
only appears as a second opinion that our fast path produces its exact bytes.
"""

from __future__ import annotations

import dataclasses
import math
import random
import struct
from pathlib import Path

import numpy as np
import pytest
from cantools.autosar.end_to_end import apply_profile5_crc
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

import ballbeam.protocol
from ballbeam.errors import BallbeamError, FrameError
from ballbeam.protocol.frames import (
    PLANT_STATUS_FIELDS,
    PLANT_STATUS_ID,
    PLANT_STATUS_VALUE_MAX,
    SENSOR_ID,
    TRUTH_ANGLE_ID,
    TRUTH_BALL_ID,
    VOLTAGE_COMMAND_ID,
    CounterCheck,
    CounterUnwrap,
    Frame,
    FrameContract,
    FrameRejectedError,
    PlantStatusFrame,
    SensorFrame,
    TruthAngle,
    TruthBall,
    VoltageCommand,
    e2e_profile5_crc,
    next_counter,
)
from ballbeam.protocol.secoc import EXTENSION_BYTES

DBC_PATH = Path(ballbeam.protocol.__file__).parent / "ballbeam.dbc"
IDS = (VOLTAGE_COMMAND_ID, SENSOR_ID, TRUTH_ANGLE_ID, TRUTH_BALL_ID, PLANT_STATUS_ID)

# Factors and raw limits as the contract states them (symmetric ranges for the scaled signals).
VOLT_LSB = 1e-3
THETA_LSB, THETA_RATE_LSB = 1e-5, 1e-4
BALL_POS_LSB, BALL_VEL_LSB = 1e-6, 1e-5
INT16_MAX = 32767
INT20_MAX = (1 << 19) - 1


@pytest.fixture(scope="module")
def contract() -> FrameContract:
    return FrameContract.load()


# --- an independent reference for AUTOSAR E2E profile 5 ------------------------------------


def crc16_bitwise(data: bytes) -> int:
    """CRC-16/CCITT-FALSE bit by bit: poly 0x1021, init 0xFFFF, MSB first, no final xor."""
    crc = 0xFFFF
    for byte in data:
        crc ^= byte << 8
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1021) if crc & 0x8000 else (crc << 1)
            crc &= 0xFFFF
    return crc


def protect(frame_id: int, body: bytes) -> bytes:
    """Prefix bytes 2..7 with the profile 5 CRC: over body, then data id low, high; stored LE."""
    assert len(body) == 6
    crc = crc16_bitwise(body + bytes((frame_id & 0xFF, frame_id >> 8)))
    return crc.to_bytes(2, "little") + body


def cantools_protect(payload: bytes, frame_id: int) -> bytes:
    protected = apply_profile5_crc(payload, frame_id)
    assert protected is not None
    return bytes(protected)


def test_reference_crc_matches_the_published_check_value() -> None:
    # The catalogued check value of CRC-16/CCITT-FALSE (= AUTOSAR CRC16) over "123456789".
    assert crc16_bitwise(b"123456789") == 0x29B1


@given(st.binary(min_size=8, max_size=8), st.sampled_from(IDS))
def test_crc_matches_reference_and_cantools(payload: bytes, frame_id: int) -> None:
    ours = e2e_profile5_crc(payload, frame_id)
    assert ours == crc16_bitwise(payload[2:] + bytes((frame_id & 0xFF, frame_id >> 8)))
    assert ours.to_bytes(2, "little") == cantools_protect(payload, frame_id)[:2]


# --- hand-computed layouts ---------------------------------------------------------------


def test_sensor_frame_byte_layout(contract: FrameContract) -> None:
    # counter 0x2A; angle -100 = 0xFF9C; position 1234 = 0x04D2; status 2 (held); all LE.
    body = bytes([0x2A, 0x9C, 0xFF, 0xD2, 0x04, 0x02])
    expected = protect(0x101, body)
    assert contract.encode_sensor(0x2A, -100, 1234, 2) == expected
    assert contract.decode(0x101, expected) == SensorFrame(0x2A, -100, 1234, 2)


def test_command_frame_byte_layout(contract: FrameContract) -> None:
    # counter 7; -4.321 V = raw -4321 = 0xEF1F; Enable bit 40 = byte 5 bit 0; SensorCounter 6
    # in byte 6; byte 7 reserved.
    body = bytes([0x07, 0x1F, 0xEF, 0x01, 0x06, 0x00])
    expected = protect(0x100, body)
    assert contract.encode_voltage_command(7, -4.321, True, 6) == expected
    decoded = contract.decode(0x100, expected)
    assert isinstance(decoded, VoltageCommand)
    assert (decoded.counter, decoded.enable, decoded.sensor_counter) == (7, True, 6)
    assert decoded.voltage_v == pytest.approx(-4.321, abs=1e-12)


def test_truth_frame_byte_layout(contract: FrameContract) -> None:
    # Two 20-bit fields sharing byte 5: theta 1.23456 rad = raw 0x1E240 at bits 24..43,
    # rate -2.5 rad/s = raw -25000 = 0xF9E58 (20-bit two's complement) at bits 44..63.
    # Bits 24..63 = 0xF9E58 << 20 | 0x1E240 = 0xF9E581E240, LE: 40 E2 81 E5 F9.
    body = bytes([0xFF, 0x40, 0xE2, 0x81, 0xE5, 0xF9])
    expected = protect(0x102, body)
    assert contract.encode_truth_angle(0xFF, 1.23456, -2.5) == expected


# --- round trips ---------------------------------------------------------------------------

counters = st.integers(0, 255)
int16 = st.integers(-INT16_MAX - 1, INT16_MAX)


def physical(lsb: float, raw_max: int) -> st.SearchStrategy[float]:
    # The whole signal range [min|max] = ±raw_max·lsb.
    return st.floats(-raw_max * lsb, raw_max * lsb, allow_nan=False)


def assert_within_half_lsb(decoded: float, sent: float, lsb: float) -> None:
    raw = round(sent / lsb)  # what the contract says goes on the wire
    assert decoded == pytest.approx(raw * lsb, rel=0, abs=1e-9 * lsb)
    assert abs(decoded - sent) <= 0.5 * lsb * (1 + 1e-9)


@given(counters, physical(VOLT_LSB, INT16_MAX), st.booleans(), counters)
def test_voltage_command_round_trip(
    contract: FrameContract, counter: int, voltage_v: float, enable: bool, sensor_counter: int
) -> None:
    data = contract.encode_voltage_command(counter, voltage_v, enable, sensor_counter)
    assert len(data) == 8
    frame = contract.decode(0x100, data)
    assert isinstance(frame, VoltageCommand)
    assert (frame.counter, frame.enable, frame.sensor_counter) == (counter, enable, sensor_counter)
    assert type(frame.enable) is bool
    assert_within_half_lsb(frame.voltage_v, voltage_v, VOLT_LSB)


@given(counters, int16, int16, st.integers(0, 3))
def test_sensor_round_trip(
    contract: FrameContract, counter: int, angle: int, position: int, status: int
) -> None:
    data = contract.encode_sensor(counter, angle, position, status)
    assert contract.decode(0x101, data) == SensorFrame(counter, angle, position, status)


@given(counters, physical(THETA_LSB, INT20_MAX), physical(THETA_RATE_LSB, INT20_MAX))
def test_truth_angle_round_trip(
    contract: FrameContract, counter: int, theta: float, rate: float
) -> None:
    frame = contract.decode(0x102, contract.encode_truth_angle(counter, theta, rate))
    assert isinstance(frame, TruthAngle)
    assert frame.counter == counter
    assert_within_half_lsb(frame.theta_rad, theta, THETA_LSB)
    assert_within_half_lsb(frame.theta_rate_rad_s, rate, THETA_RATE_LSB)


@given(counters, physical(BALL_POS_LSB, INT20_MAX), physical(BALL_VEL_LSB, INT20_MAX))
def test_truth_ball_round_trip(
    contract: FrameContract, counter: int, position: float, velocity: float
) -> None:
    frame = contract.decode(0x103, contract.encode_truth_ball(counter, position, velocity))
    assert isinstance(frame, TruthBall)
    assert frame.counter == counter
    assert_within_half_lsb(frame.position_m, position, BALL_POS_LSB)
    assert_within_half_lsb(frame.velocity_m_s, velocity, BALL_VEL_LSB)


@given(counters, physical(THETA_LSB, INT20_MAX), physical(BALL_POS_LSB, INT20_MAX))
def test_a_sensor_frames_truth_is_the_two_truth_payloads_and_zeros(
    contract: FrameContract, counter: int, theta: float, position: float
) -> None:
    """On the authenticated bus the truth rides in the sensor frame's 40-byte extension:
    exactly the 0x102 and 0x103 payloads the truth frames would carry (their bits are pinned
    above), then zeros; it decodes to those frames."""
    angle_payload = contract.encode_truth_angle(counter, theta, -theta)
    ball_payload = contract.encode_truth_ball(counter, position, -position)
    extension = contract.encode_truth(counter, theta, -theta, position, -position)
    assert extension == angle_payload + ball_payload + bytes(24)
    assert len(extension) == EXTENSION_BYTES
    assert contract.decode_truth(extension, counter) == (
        contract.decode(0x102, angle_payload), contract.decode(0x103, ball_payload)
    )


def test_a_truth_extension_that_is_not_its_samples_is_refused(contract: FrameContract) -> None:
    extension = contract.encode_truth(7, 0.1, 0.2, 0.03, 0.04)
    cases = {
        "other sample": (extension, 8, "range"),
        "short": (extension[:-1], 7, "length"),
        "padding": (extension[:-1] + b"\x01", 7, "range"),
        "angle's CRC": (bytes([extension[0] ^ 1]) + extension[1:], 7, "crc"),
        "ball's CRC": (extension[:8] + bytes([extension[8] ^ 1]) + extension[9:], 7, "crc"),
        "two samples": (extension[:8] + contract.encode_truth_ball(8, 0.03, 0.04)
                        + extension[16:], 7, "range"),
    }
    for name, (data, counter, reason) in cases.items():
        with pytest.raises(FrameRejectedError) as refused:
            contract.decode_truth(data, counter)
        assert refused.value.reason == reason, name


def test_extremes_round_trip(contract: FrameContract) -> None:
    cases: list[Frame] = [
        VoltageCommand(0, INT16_MAX * VOLT_LSB, True, 255),
        VoltageCommand(255, -INT16_MAX * VOLT_LSB, False, 0),
        VoltageCommand(128, 0.0, False, 128),
        SensorFrame(0, -32768, 32767, 0),
        SensorFrame(255, 32767, -32768, 3),
        TruthAngle(0, INT20_MAX * THETA_LSB, -INT20_MAX * THETA_RATE_LSB),
        TruthAngle(255, -INT20_MAX * THETA_LSB, INT20_MAX * THETA_RATE_LSB),
        TruthBall(1, INT20_MAX * BALL_POS_LSB, -INT20_MAX * BALL_VEL_LSB),
        TruthBall(254, -INT20_MAX * BALL_POS_LSB, INT20_MAX * BALL_VEL_LSB),
    ]
    for frame in cases:
        frame_id, data = contract.encode(frame)
        back = contract.decode(frame_id, data)
        assert type(back) is type(frame)
        assert_close(back, frame)


def assert_close(a: Frame, b: Frame) -> None:
    for field in dataclasses.fields(a):
        x, y = getattr(a, field.name), getattr(b, field.name)
        assert x == pytest.approx(y, rel=1e-12, abs=1e-12), field.name


@given(counters, physical(VOLT_LSB, INT16_MAX), st.booleans(), counters)
def test_matches_cantools_bytes_and_values(
    contract: FrameContract, counter: int, voltage_v: float, enable: bool, sensor_counter: int
) -> None:
    message = contract.database.get_message_by_frame_id(0x100)
    signals = {
        "CRC": 0,
        "Counter": counter,
        "Voltage": voltage_v,
        "Enable": int(enable),
        "SensorCounter": sensor_counter,
    }
    reference = cantools_protect(message.encode(signals), 0x100)
    data = contract.encode_voltage_command(counter, voltage_v, enable, sensor_counter)
    assert data == reference
    decoded = message.decode_simple(data, decode_choices=False)
    frame = contract.decode(0x100, data)
    assert isinstance(frame, VoltageCommand)
    assert frame.voltage_v == decoded["Voltage"]


@given(
    counters,
    st.integers(0, len(PLANT_STATUS_FIELDS) - 1),
    st.booleans(),
    st.integers(0, PLANT_STATUS_VALUE_MAX),
)
def test_plant_status_matches_cantools_bytes_and_round_trips(
    contract: FrameContract, counter: int, field: int, final: bool, value: int
) -> None:
    message = contract.database.get_message_by_frame_id(PLANT_STATUS_ID)
    signals = {"CRC": 0, "Counter": counter, "Field": field, "Final": int(final), "Value": value}
    reference = cantools_protect(message.encode(signals), PLANT_STATUS_ID)
    data = contract.encode_plant_status(counter, field, final, value)
    assert data == reference
    assert contract.decode(PLANT_STATUS_ID, data) == PlantStatusFrame(counter, field, final, value)


def test_the_dbc_names_the_plant_status_fields_as_the_code_does(contract: FrameContract) -> None:
    """The Field signal's value table is the contract for tools that read the DBC alone."""
    field = contract.database.get_message_by_frame_id(PLANT_STATUS_ID).get_signal_by_name("Field")
    assert dict(field.choices) == dict(enumerate(PLANT_STATUS_FIELDS))
    assert (field.minimum, field.maximum) == (0, len(PLANT_STATUS_FIELDS) - 1)


# --- encoding refuses what it cannot represent ----------------------------------------------


@pytest.mark.parametrize(
    ("frame_id", "args"),
    [
        (0x100, (0, 32.7675, True, 0)),  # would round to raw 32768: would wrap
        (0x100, (0, -32.768, True, 0)),  # raw -32768 is outside the symmetric range
        (0x100, (0, 32.7671, True, 0)),  # past the limit, though it would round onto it
        (0x100, (0, float("nan"), True, 0)),
        (0x100, (0, float("inf"), True, 0)),
        (0x100, (256, 0.0, True, 0)),
        (0x100, (0, 0.0, True, -1)),
        (0x101, (0, 32768, 0, 0)),
        (0x101, (0, 0, -32769, 0)),
        (0x101, (0, 0, 0, 4)),  # reserved status bit
        (0x102, (0, 5.24288, 0.0)),
        (0x102, (0, 0.0, -float("inf"))),
        (0x103, (0, 0.6, 0.0)),
        (0x103, (0, 0.0, float("nan"))),
        (0x104, (0, 13, False, 0)),  # no 14th counter
        (0x104, (0, 0, False, PLANT_STATUS_VALUE_MAX + 1)),  # the sender saturates
        (0x104, (0, 0, False, -1)),
    ],
)
def test_encode_refuses_out_of_range(
    contract: FrameContract, frame_id: int, args: tuple[float, ...]
) -> None:
    encoder = {
        0x100: contract.encode_voltage_command,
        0x101: contract.encode_sensor,
        0x102: contract.encode_truth_angle,
        0x103: contract.encode_truth_ball,
        0x104: contract.encode_plant_status,
    }[frame_id]
    with pytest.raises(FrameRejectedError) as info:
        encoder(*args)  # type: ignore[operator]
    assert info.value.reason == "range"
    assert info.value.arbitration_id == frame_id
    assert isinstance(info.value, FrameError)
    assert isinstance(info.value, ValueError)


def test_encode_accepts_the_limits_themselves(contract: FrameContract) -> None:
    for voltage_v in (32.767, -32.767, 32.767 + 1e-12):
        frame = contract.decode(0x100, contract.encode_voltage_command(0, voltage_v, True, 0))
        assert isinstance(frame, VoltageCommand)
        assert frame.voltage_v == pytest.approx(voltage_v, abs=1e-9)


def test_integer_fields_refuse_floats(contract: FrameContract) -> None:
    with pytest.raises(TypeError):
        contract.encode_sensor(0, 1.5, 0, 0)  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("frame_id", "body"),
    [
        (0x100, bytes([0, 0x00, 0x80, 0x01, 0x00, 0x00])),  # Voltage raw -32768
        (0x100, bytes([0, 0x00, 0x00, 0x03, 0x00, 0x00])),  # reserved bit 41 set
        (0x100, bytes([0, 0x00, 0x00, 0x01, 0x00, 0x01])),  # reserved byte 7
        (0x101, bytes([0, 0x00, 0x00, 0x00, 0x00, 0x04])),  # Status bit 2 is reserved
        (0x102, bytes([0, 0x00, 0x00, 0x08, 0x00, 0x00])),  # Theta raw -2**19
        (0x103, bytes([0, 0x00, 0x00, 0x00, 0x00, 0x80])),  # BallVelocity raw -2**19
    ],
)
def test_decode_refuses_values_outside_the_contract(
    contract: FrameContract, frame_id: int, body: bytes
) -> None:
    with pytest.raises(FrameRejectedError) as info:
        contract.decode(frame_id, protect(frame_id, body))
    assert info.value.reason == "range"


def test_decode_accepts_bytearray_and_reports_reasons(contract: FrameContract) -> None:
    data = contract.encode_sensor(1, 2, 3, 1)
    assert contract.decode(0x101, bytearray(data)) == SensorFrame(1, 2, 3, 1)
    for frame_id, payload, reason in [
        (0x105, data, "unknown_id"),
        (0x101, data[:7], "length"),
        (0x101, data[:1] + bytes([data[1] ^ 0x80]) + data[2:], "crc"),
    ]:
        with pytest.raises(FrameRejectedError) as info:
            contract.decode(frame_id, payload)
        assert info.value.reason == reason
        assert f"0x{frame_id:03X}" in str(info.value)


# --- the decoder under fuzzing ---------------------------------------------------------------

any_id = st.one_of(st.sampled_from(IDS), st.integers(0, 0x7FF), st.integers(0, 0x1FFFFFFF))


def decode_or_reject(contract: FrameContract, frame_id: int, data: bytes) -> Frame | str:
    try:
        frame = contract.decode(frame_id, data)
    except FrameRejectedError as error:
        assert error.arbitration_id == frame_id
        return error.reason
    # Anything accepted is canonical: encoding it again gives the same bytes.
    assert contract.encode(frame) == (frame_id, bytes(data))
    return frame


@settings(max_examples=3000, suppress_health_check=[HealthCheck.too_slow])
@given(any_id, st.binary(min_size=0, max_size=16))
def test_random_frames_decode_or_raise_frame_error(
    contract: FrameContract, frame_id: int, data: bytes
) -> None:
    result = decode_or_reject(contract, frame_id, data)
    if frame_id not in IDS:
        assert result == "unknown_id"
    elif len(data) != 8:
        assert result == "length"


@settings(max_examples=2000)
@given(st.sampled_from(IDS), st.binary(min_size=6, max_size=6))
def test_random_frames_with_a_valid_crc_decode_or_fail_range(
    contract: FrameContract, frame_id: int, body: bytes
) -> None:
    # A correct CRC gets past the integrity check, so this reaches the range/reserved checks.
    result = decode_or_reject(contract, frame_id, protect(frame_id, body))
    assert result == "range" or not isinstance(result, str)


@st.composite
def valid_frames(draw: st.DrawFn) -> Frame:
    kind = draw(st.sampled_from((VoltageCommand, SensorFrame, TruthAngle, TruthBall)))
    counter = draw(counters)
    if kind is VoltageCommand:
        return VoltageCommand(
            counter, draw(physical(VOLT_LSB, INT16_MAX)), draw(st.booleans()), draw(counters)
        )
    if kind is SensorFrame:
        return SensorFrame(counter, draw(int16), draw(int16), draw(st.integers(0, 3)))
    if kind is TruthAngle:
        return TruthAngle(
            counter, draw(physical(THETA_LSB, INT20_MAX)), draw(physical(THETA_RATE_LSB, INT20_MAX))
        )
    return TruthBall(
        counter, draw(physical(BALL_POS_LSB, INT20_MAX)), draw(physical(BALL_VEL_LSB, INT20_MAX))
    )


@settings(max_examples=500)
@given(valid_frames())
def test_every_single_bit_flip_is_rejected_by_the_crc(
    contract: FrameContract, frame: Frame
) -> None:
    frame_id, data = contract.encode(frame)
    for bit in range(64):
        corrupted = bytearray(data)
        corrupted[bit // 8] ^= 1 << (bit % 8)
        assert decode_or_reject(contract, frame_id, bytes(corrupted)) == "crc"


@settings(max_examples=500)
@given(valid_frames(), st.integers(0, 0x7FF))
def test_a_valid_frame_under_another_id_is_rejected(
    contract: FrameContract, frame: Frame, other_id: int
) -> None:
    frame_id, data = contract.encode(frame)
    assume(other_id != frame_id)
    # The data id is in the CRC, so a frame never passes for another frame type.
    assert decode_or_reject(contract, other_id, data) in ("unknown_id", "crc")


@settings(max_examples=300)
@given(valid_frames(), st.integers(0, 16), st.binary(max_size=8))
def test_truncated_or_padded_frames_are_rejected_by_length(
    contract: FrameContract, frame: Frame, length: int, filler: bytes
) -> None:
    assume(length != 8)
    frame_id, data = contract.encode(frame)
    resized = (data + filler * 2 + bytes(16))[:length]
    assert decode_or_reject(contract, frame_id, resized) == "length"


def test_seeded_mass_fuzz(contract: FrameContract) -> None:
    # Cheaper than Hypothesis per case: 20,000 random and mutated frames in a plain loop.
    rng = random.Random(20240601)
    reasons: dict[str, int] = {}
    for _ in range(20_000):
        frame_id = rng.choice(IDS)
        roll = rng.random()
        if roll < 0.4:
            data = rng.randbytes(8)
        elif roll < 0.7:
            data = protect(frame_id, rng.randbytes(6))
        else:
            mutated = bytearray(protect(frame_id, rng.randbytes(6)))
            for _ in range(rng.randint(1, 4)):
                mutated[rng.randrange(8)] ^= 1 << rng.randrange(8)
            data = bytes(mutated)
        result = decode_or_reject(contract, frame_id, data)
        key = result if isinstance(result, str) else "ok"
        reasons[key] = reasons.get(key, 0) + 1
    assert set(reasons) <= {"ok", "crc", "range"}
    assert reasons["ok"] > 1000 and reasons["crc"] > 10_000


def test_counter_stream_through_decode(contract: FrameContract) -> None:
    # A sensor stream with a lost frame, a repeat and a late straggler, end to end.
    sent = [contract.encode_sensor(c % 256, c, -c, 0) for c in range(250, 262)]
    received = [sent[i] for i in (0, 1, 2, 4, 4, 5, 3, 6, 7, 8, 9, 10, 11)]
    check = CounterCheck()
    verdicts = []
    for data in received:
        frame = contract.decode(SENSOR_ID, data)
        verdicts.append(check.classify(frame.counter))
    assert verdicts == ["ok"] * 4 + ["repeated", "ok", "stale"] + ["ok"] * 6
    assert (check.accepted, check.lost, check.repeated, check.stale) == (11, 1, 1, 1)
    assert check.last == 261 % 256


# --- counters ----------------------------------------------------------------------------


def test_next_counter_wraps() -> None:
    assert next_counter(0) == 1
    assert next_counter(254) == 255
    assert next_counter(255) == 0


def classify_all(counters_in: list[int]) -> tuple[list[str], CounterCheck]:
    check = CounterCheck()
    return [check.classify(c) for c in counters_in], check


def test_counter_check_in_order_with_wrap() -> None:
    verdicts, check = classify_all([253, 254, 255, 0, 1])
    assert verdicts == ["ok"] * 5
    assert (check.accepted, check.lost, check.repeated, check.stale) == (5, 0, 0, 0)


def test_counter_check_gaps_across_the_wrap() -> None:
    verdicts, check = classify_all([250, 252, 3, 130])
    # 250→252: 1 lost; 252→3: delta 7, 6 lost; 3→130: delta 127, 126 lost.
    assert verdicts == ["ok"] * 4
    assert check.lost == 1 + 6 + 126
    assert check.accepted == 4


def test_counter_check_repeats_and_stale() -> None:
    verdicts, check = classify_all([10, 10, 11, 9, 11, 12, 139, 12])
    # 11→9: delta 254 → stale; 12→139: delta 127 → ok, 126 lost; 139→12: delta 129 → stale.
    assert verdicts == ["ok", "repeated", "ok", "stale", "repeated", "ok", "ok", "stale"]
    assert (check.accepted, check.lost, check.repeated, check.stale) == (4, 126, 2, 2)
    assert check.last == 139


def test_counter_check_half_circle_is_stale() -> None:
    verdicts, _ = classify_all([0, 128])
    assert verdicts == ["ok", "stale"]
    verdicts, _ = classify_all([200, 72])  # delta (72 - 200) mod 256 = 128
    assert verdicts == ["ok", "stale"]


def test_counter_check_reset_accepts_the_next_frame() -> None:
    check = CounterCheck()
    check.classify(100)
    assert check.classify(0) == "stale"  # e.g. the sender restarted
    check.reset()
    assert check.classify(0) == "ok"
    assert (check.accepted, check.stale) == (2, 1)


@given(
    st.integers(0, 255),
    st.lists(st.tuples(st.integers(0, 126), st.integers(0, 3)), min_size=1, max_size=200),
)
def test_counter_check_counts_losses_and_repeats(start: int, steps: list[tuple[int, int]]) -> None:
    # A lossy, duplicating (but not reordering) channel: before each delivered frame, `gap`
    # frames are dropped (≤ 126 in a row: delta ≤ 127), then it arrives 1 + `dups` times.
    check = CounterCheck()
    counter = start
    first = True
    dropped = duplicates = 0
    for gap, dups in steps:
        if not first:
            counter = (counter + 1 + gap) % 256
            dropped += gap
        first = False
        for copy in range(1 + dups):
            assert check.classify(counter) == ("ok" if copy == 0 else "repeated")
        duplicates += dups
    assert (check.accepted, check.lost, check.repeated, check.stale) == (
        len(steps),
        dropped,
        duplicates,
        0,
    )


# --- the contract file is checked at load ---------------------------------------------------


def test_default_path_is_the_repo_dbc() -> None:
    contract = FrameContract.load()
    assert Path(contract.path) == DBC_PATH
    assert "BO_ 256 VoltageCommand" in contract.dbc_text
    assert {node.name for node in contract.database.nodes} == {"Controller", "Emulator"}


def _edited(tmp_path: Path, old: str, new: str) -> Path:
    text = DBC_PATH.read_text(encoding="utf-8")
    assert old in text
    path = tmp_path / "edited.dbc"
    path.write_text(text.replace(old, new), encoding="utf-8")
    return path


def _without_message(tmp_path: Path, frame_id: int) -> Path:
    lines = DBC_PATH.read_text(encoding="utf-8").splitlines()
    kept, skipping = [], False
    for line in lines:
        if line.startswith("BO_ "):
            skipping = line.startswith(f"BO_ {frame_id} ")
        elif not line.startswith(" SG_"):
            skipping = False
        if skipping or (
            f" {frame_id} " in line and line.startswith(("CM_ BO_", "CM_ SG_", "VAL_"))
        ):
            continue
        kept.append(line)
    path = tmp_path / "missing.dbc"
    path.write_text("\n".join(kept) + "\n", encoding="utf-8")
    return path


@pytest.mark.parametrize(
    ("old", "new", "complaint"),
    [
        ("BO_ 257 SensorMeasurement: 8", "BO_ 261 SensorMeasurement: 8", "0x101"),
        ("BO_ 258 PlantTruthAngle: 8", "BO_ 2147483906 PlantTruthAngle: 8", "0x102"),  # extended
        ("BO_ 259 PlantTruthBall: 8", "BO_ 259 PlantTruthBall: 16", "8-byte"),  # CAN FD size
        (
            ' SG_ Counter : 16|8@1+ (1,0) [0|255] "" Controller',
            ' SG_ Counter : 16|7@1+ (1,0) [0|127] "" Controller',
            "Counter",
        ),
        ("SG_ Voltage : 24|16@1-", "SG_ Volts : 24|16@1-", "Voltage"),
        ("SG_ AngleCounts : 24|16@1- (1,0)", "SG_ AngleCounts : 24|16@1- (2,0)", "raw integer"),
        ("SG_ Status : 56|8@1+", "SG_ Status : 63|8@0+", "Intel"),  # same byte, Motorola
    ],
)
def test_a_dbc_that_breaks_the_contract_is_refused(
    tmp_path: Path, old: str, new: str, complaint: str
) -> None:
    path = _edited(tmp_path, old, new)
    with pytest.raises(FrameError, match=complaint) as info:
        FrameContract.load(path)
    assert str(path) in str(info.value)


@pytest.mark.parametrize("frame_id", IDS)
def test_a_dbc_missing_a_message_is_refused(tmp_path: Path, frame_id: int) -> None:
    path = _without_message(tmp_path, frame_id)
    with pytest.raises(FrameError, match="needs message"):
        FrameContract.load(path)


def test_missing_or_unparsable_dbc_is_refused(tmp_path: Path) -> None:
    missing = tmp_path / "nope.dbc"
    with pytest.raises(FrameError, match=r"nope\.dbc"):
        FrameContract.load(missing)
    garbage = tmp_path / "garbage.dbc"
    garbage.write_text("this is not a DBC\n", encoding="utf-8")
    with pytest.raises(BallbeamError, match=r"garbage\.dbc"):
        FrameContract.load(garbage)


def test_the_dbc_defines_scales_and_ranges(tmp_path: Path) -> None:
    # Scale and range live in the DBC only: a 10 mV, ±10 V voltage is honoured as written.
    path = _edited(
        tmp_path,
        'SG_ Voltage : 24|16@1- (0.001,0) [-32.767|32.767] "V"',
        'SG_ Voltage : 24|16@1- (0.01,0) [-10|10] "V"',
    )
    contract = FrameContract.load(path)
    data = contract.encode_voltage_command(1, 1.234, True, 0)
    assert data[3:5] == (123).to_bytes(2, "little", signed=True)
    with pytest.raises(FrameRejectedError, match="Voltage"):
        contract.encode_voltage_command(1, 10.01, True, 0)


def test_raw_signal_reads_many_recorded_frames_as_decode_reads_one() -> None:
    """The vectorised reader the log analysis uses agrees with decode, signed fields too."""
    contract = FrameContract.load()
    rng = random.Random(5)
    frames = [
        SensorFrame(
            rng.randrange(256),
            rng.randrange(-2000, 2000),
            rng.randrange(-30000, 30000),
            rng.randrange(4),
        )
        for _ in range(200)
    ]
    data = np.array([list(contract.encode(frame)[1]) for frame in frames], dtype=np.uint8)
    assert list(contract.raw_signal(SENSOR_ID, "Counter", data)) == [f.counter for f in frames]
    assert list(contract.raw_signal(SENSOR_ID, "AngleCounts", data)) == [
        f.angle_counts for f in frames
    ]
    assert list(contract.raw_signal(SENSOR_ID, "PositionCounts", data)) == [
        f.position_counts for f in frames
    ]
    with pytest.raises(FrameError, match="no signal"):
        contract.raw_signal(SENSOR_ID, "Nonexistent", data)


def test_counter_unwrap_follows_wraps_gaps_and_old_frames() -> None:
    """Counters count the plant's sample periods: unwrapped, a wrap is +1, a gap shows as a
    larger step, an old frame gets the index it had."""
    unwrap = CounterUnwrap()
    heard = [250, 251, 255, 0, 1, 3, 2, 130]
    assert [unwrap.index(counter) for counter in heard] == [250, 251, 255, 256, 257, 259, 258, 386]


def test_a_lookahead_round_trips_at_1_mv_and_refuses_what_the_contract_cannot_carry() -> None:
    from ballbeam.protocol.frames import (
        LOOKAHEAD_SLOTS,
        NO_LOOKAHEAD_RAW,
        decode_lookahead,
        encode_lookahead,
    )

    voltages = (4.5504, -4.5496, 0.0, 32.767, -32.767)
    encoded = encode_lookahead(voltages)
    assert len(encoded) == 2 * LOOKAHEAD_SLOTS
    raws = struct.unpack(f"<{LOOKAHEAD_SLOTS}h", encoded)
    assert raws[:5] == (4550, -4550, 0, 32767, -32767)
    assert set(raws[5:]) == {NO_LOOKAHEAD_RAW}
    assert decode_lookahead(encoded) == (4.55, -4.55, 0.0, 32.767, -32.767)
    assert decode_lookahead(encode_lookahead(())) == ()
    for bad in ((math.nan,), (32.768,), (0.0,) * (LOOKAHEAD_SLOTS + 1)):
        with pytest.raises(FrameRejectedError) as refused:
            encode_lookahead(bad)
        assert refused.value.reason == "range"
    gap = bytearray(encode_lookahead((1.0, 2.0)))
    gap[0:2] = NO_LOOKAHEAD_RAW.to_bytes(2, "little", signed=True)  # empty, then a value
    with pytest.raises(FrameRejectedError, match="gap"):
        decode_lookahead(bytes(gap))
    with pytest.raises(FrameRejectedError) as short:
        decode_lookahead(encoded[:-1])
    assert short.value.reason == "length"


@settings(
    max_examples=300, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(st.floats(min_value=-5.5, max_value=5.5, allow_nan=False))
def test_offline_drives_the_command_as_the_frame_carries_it(
    contract: FrameContract, voltage_v: float
) -> None:
    """The offline loop's rounding of a command is the codec's, to the bit (offline and
    lock-step runs are then the same run)."""
    from ballbeam.core.plant import command_as_received, lookahead_as_received
    from ballbeam.protocol.frames import decode_lookahead, encode_lookahead

    frame = contract.decode(
        VOLTAGE_COMMAND_ID, contract.encode_voltage_command(0, voltage_v, True, 0)
    )
    assert isinstance(frame, VoltageCommand)
    assert frame.voltage_v == command_as_received(voltage_v)
    assert decode_lookahead(encode_lookahead((voltage_v,))) == (lookahead_as_received(voltage_v),)
