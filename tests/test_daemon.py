"""The daemon in-process on python-can's ``virtual`` bus: its parts one by one, then the whole
loop against the emulator in a thread, checked against the offline closed loop."""

from __future__ import annotations

import itertools
import secrets
import threading
import time
from pathlib import Path

import can
import numpy as np
import pytest

from ballbeam.assembly import run_offline
from ballbeam.config import Config, load_config
from ballbeam.evaluation import replay
from ballbeam.evaluation.summary import summarise
from ballbeam.logs.reader import read_log
from ballbeam.logs.recorder import Recorder
from ballbeam.logs.recording import RunRecording
from ballbeam.protocol.frames import (
    SENSOR_ID,
    TRUTH_ANGLE_ID,
    VOLTAGE_COMMAND_ID,
    FrameContract,
    SensorFrame,
    TruthAngle,
    TruthBall,
    VoltageCommand,
)
from ballbeam.protocol.secoc import FrameAuthenticator
from ballbeam.runtime.daemon.command_out import CommandOut
from ballbeam.runtime.daemon.intake import SensorIntake
from ballbeam.runtime.daemon.node import run_daemon
from ballbeam.runtime.stop import StopFlag
from ballbeam_emulator.node import PlantEmulator

CONTRACT = FrameContract.load()


def virtual_config(duration_s: float, *extra: str) -> Config:
    channel = f"ballbeam-test-{secrets.token_hex(4)}"  # a bus of its own
    return load_config(None, [
        "bus.interface='virtual'", f"bus.channel='{channel}'", f"run.duration_s={duration_s}",
        *extra,
    ])


def message(frame_id: int, data: bytes) -> can.Message:
    return can.Message(arbitration_id=frame_id, data=data, is_extended_id=False)


def framed(frame: SensorFrame | TruthAngle | TruthBall | VoltageCommand) -> can.Message:
    frame_id, data = CONTRACT.encode(frame)
    return message(frame_id, data)


@pytest.fixture
def recording(tmp_path: Path) -> RunRecording:
    recorder = Recorder(tmp_path / "parts.mcap", metadata={})
    yield RunRecording(recorder)
    recorder.close()


def test_intake_accepts_samples_in_order_and_judges_the_rest(recording: RunRecording) -> None:
    own = framed(VoltageCommand(0, 1.0, True, 7))
    intake = SensorIntake(
        CONTRACT, recording,
        own_frame=lambda data: "echo" if data == bytes(own.data) else "not_sent",
    )

    def sensor(counter: int) -> can.Message:
        return framed(SensorFrame(counter, 10, -20, 0))

    assert intake.handle(sensor(5), 0, 0) == "ok"
    assert intake.take() == SensorFrame(5, 10, -20, 0)
    assert intake.take() is None  # a sample is used once
    assert intake.handle(sensor(5), 0, 0) == "repeated"
    assert intake.handle(sensor(4), 0, 0) == "stale"
    assert intake.handle(sensor(7), 0, 0) == "ok"
    assert intake.sensor_check.lost == 1
    assert intake.handle(own, 0, 0) is None and intake.own_frames == 1
    # A command frame with our id that we did not send is counted; a valid one is a second
    # writer (on the classic bus a right CRC is all it takes).
    assert intake.handle(framed(VoltageCommand(9, 5.0, True, 7)), 0, 0) is None
    assert intake.second_writer_frames == 1 and intake.own_frames == 1
    bad = bytearray(own.data)
    bad[0] ^= 0xFF
    intake.handle(message(VOLTAGE_COMMAND_ID, bytes(bad)), 0, 0)
    assert intake.second_writer_frames == 1 and intake.rejected["not_ours"] == 2
    del intake.rejected["not_ours"]
    corrupt = bytearray(sensor(8).data)
    corrupt[0] ^= 0xFF
    intake.handle(message(SENSOR_ID, bytes(corrupt)), 0, 0)
    extended = can.Message(arbitration_id=SENSOR_ID, data=bytes(8), is_extended_id=True)
    intake.handle(extended, 0, 0)
    assert dict(intake.rejected) == {"stale": 1, "crc": 1, "foreign": 1}
    # Truth pairs by counter; an unpaired ball frame is dropped.
    intake.handle(framed(TruthBall(7, 0.1, 0.0)), 0, 0)
    intake.handle(framed(TruthAngle(7, 0.2, 0.0)), 0, 0)
    intake.handle(framed(TruthBall(7, 0.1, 0.0)), 0, 0)
    assert intake.latest == SensorFrame(7, 10, -20, 0)


def test_command_out_counts_resends_and_shuts_down_at_zero(recording: RunRecording) -> None:
    channel = f"ballbeam-test-{secrets.token_hex(4)}"
    with can.Bus(interface="virtual", channel=channel) as sender, can.Bus(
        interface="virtual", channel=channel
    ) as plant:
        out = CommandOut(sender, CONTRACT, recording)
        out.resend_last(0, 0)  # nothing sent yet: nothing to resend
        out.send(0, 0, 1.25, 1.3, True, 9)
        out.send(1, 1, -0.5, -0.5, True, 10)
        out.resend_last(1, 1)
        out.shutdown(2, 2)
        heard = []
        while (received := plant.recv(timeout=0.1)) is not None:
            heard.append(CONTRACT.decode(received.arbitration_id, bytes(received.data)))
    assert [(c.counter, c.voltage_v, c.enable) for c in heard] == [
        (0, 1.25, True), (1, -0.5, True), (1, -0.5, True),
        (2, 0.0, False), (3, 0.0, False), (4, 0.0, False),
    ]
    assert out.resends == 1


def test_the_whole_daemon_in_process_runs_like_the_offline_loop(tmp_path: Path) -> None:
    config = virtual_config(1.5)
    stop_plant = StopFlag()
    plant_bus = can.Bus(interface="virtual", channel=config.bus.channel)
    # Authenticated frames (the default on the virtual bus), keyed by one run secret.
    assert config.bus.authenticated
    secret = secrets.token_bytes(32)
    emulator = PlantEmulator(config, plant_bus, CONTRACT, FrameAuthenticator(secret))
    plant = threading.Thread(target=emulator.run_lockstep, args=(stop_plant,), daemon=True)
    plant.start()
    log_path = tmp_path / "run.mcap"
    try:
        stats = run_daemon(config, log_path, None, secret)
    finally:
        stop_plant.set()
        plant.join(timeout=10)
        emulator.stop()
        plant_bus.shutdown()
    assert stats.end_reason == "completed" and stats.authenticated
    assert emulator.counters.bad_mac == emulator.counters.replayed == 0
    run_log = read_log(log_path)
    summary = summarise(run_log)
    assert summary["end_reason"] == "completed" and summary["cycles"] == 1500
    assert summary["frames_rejected"] == 0 and summary["frames_lost"] == 0
    assert replay.verify(run_log).ok
    # The voltage frame carries 1 mV, so the bus run is the offline loop up to that
    # resolution: the same path, though the guard may switch on other cycles.
    offline = run_offline(config)
    truth = run_log.topics["/truth"].values
    count = len(truth["theta_rad"])
    assert count >= 1490
    theta = np.asarray(truth["theta_rad"]) - offline.trace.true_states[:count, 0]
    position = np.asarray(truth["ball_position_m"]) - offline.trace.true_states[:count, 3]
    assert np.max(np.abs(theta)) < np.radians(0.5)
    assert np.max(np.abs(position)) < 1e-4
    assert summary["max_abs_theta_deg"] <= config.limits.theta_deg


def test_authenticated_intake_takes_only_fresh_frames_with_a_right_mac(
    recording: RunRecording,
) -> None:
    """Forged, replayed and reordered frames are rejected and counted without moving the
    stream: the real frames that follow are accepted."""
    secret = secrets.token_bytes(32)
    plant, daemon = FrameAuthenticator(secret), FrameAuthenticator(secret)
    stranger = FrameAuthenticator(secrets.token_bytes(32))
    sent: list[can.Message] = []

    def protected(node: FrameAuthenticator, frame: SensorFrame | VoltageCommand) -> can.Message:
        frame_id, data = CONTRACT.encode(frame)
        out = can.Message(arbitration_id=frame_id, data=node.protect(frame_id, data),
                          is_extended_id=False, is_fd=True)
        sent.append(out)
        return out

    intake = SensorIntake(CONTRACT, recording, daemon)
    assert intake.handle(protected(plant, SensorFrame(1, 1, 1, 0)), 0, 0) == "ok"
    first = sent[0]
    assert intake.handle(protected(plant, SensorFrame(2, 2, 2, 0)), 0, 0) == "ok"
    # A replay of the first frame, a stranger's frame, and a classic frame with a right CRC.
    assert intake.handle(first, 0, 0) is None
    assert intake.handle(protected(stranger, SensorFrame(3, 9, 9, 0)), 0, 0) is None
    assert intake.handle(framed(SensorFrame(3, 9, 9, 0)), 0, 0) is None
    forged = bytearray(sent[1].data)
    forged[4] ^= 0x01  # a changed payload with the CRC made right again would still fail the MAC
    assert intake.handle(can.Message(arbitration_id=SENSOR_ID, data=bytes(forged),
                                     is_extended_id=False, is_fd=True), 0, 0) is None
    assert dict(intake.rejected) == {"replayed": 1, "bad_mac": 2, "unauthenticated": 1}
    # The real stream goes on: counter 3 is the next sample, not a stale or repeated one.
    assert intake.handle(protected(plant, SensorFrame(3, 3, 3, 0)), 0, 0) == "ok"
    assert intake.latest == SensorFrame(3, 3, 3, 0) and intake.sensor_check.lost == 0
    # A 0x100 frame with a right MAC that the daemon did not send: a second writer.
    command = protected(plant, VoltageCommand(0, 5.0, True, 3))
    assert intake.handle(command, 0, 0) is None and intake.second_writer_frames == 1


def test_frame_authenticator_protects_and_judges() -> None:
    secret = secrets.token_bytes(32)
    sender, receiver = FrameAuthenticator(secret), FrameAuthenticator(secret)
    _, payload = CONTRACT.encode(SensorFrame(1, 2, 3, 0))
    data = sender.protect(SENSOR_ID, payload)
    assert len(data) == 24 and data[:8] == payload  # a valid CAN FD length; classic first
    assert receiver.verify(SENSOR_ID, data) == "ok"
    assert receiver.verify(SENSOR_ID, data) == "replayed"
    assert receiver.verify(TRUTH_ANGLE_ID, data) == "bad_mac"  # the id is under the MAC
    assert receiver.verify(SENSOR_ID, payload) == "unauthenticated"
    old = sender.protect(SENSOR_ID, payload)
    assert FrameAuthenticator(secret).verify(SENSOR_ID, old, now_ns=10**18) == "out_of_window"
    # The sender knows its own frames: each comes back once; again, it is a replay.
    assert sender.own_frame(SENSOR_ID, data) == "echo"
    assert sender.own_frame(SENSOR_ID, data) == "replayed"
    assert sender.own_frame(SENSOR_ID, payload) == "invalid"
    # A right MAC on the sender's id that it never sent: another holder of the secret.
    other = FrameAuthenticator(secret).protect(SENSOR_ID, payload)
    assert sender.own_frame(SENSOR_ID, other) == "not_sent"
    assert receiver.own_frame(SENSOR_ID, old) == "not_sent"
    with pytest.raises(ValueError):
        FrameAuthenticator(b"short")


def test_the_emulators_sensor_counters_count_sample_periods() -> None:
    """A period the emulator misses (here: one 3.5 ms stall in a 1 ms loop) is a visible gap
    in the sensor counter, and the gaps add up to the emulator's own missed_periods."""
    config = virtual_config(1.0, "run.mode='realtime'", "bus.authenticate=false")
    plant_bus = can.Bus(interface="virtual", channel=config.bus.channel)
    listener = can.Bus(interface="virtual", channel=config.bus.channel)
    emulator = PlantEmulator(config, plant_bus, CONTRACT)
    send_sample = emulator._send_sample
    stop = StopFlag()
    samples = 0

    def stalling_send() -> None:
        nonlocal samples
        send_sample()
        samples += 1
        if samples == 50:
            time.sleep(0.0035)
        if samples >= 150:
            stop.set()

    emulator._send_sample = stalling_send  # type: ignore[method-assign]
    plant = threading.Thread(target=emulator.run_realtime, args=(stop,), daemon=True)
    plant.start()
    plant.join(timeout=30)
    counters = []
    while (received := listener.recv(timeout=0.1)) is not None:
        if received.arbitration_id == SENSOR_ID:
            counters.append(CONTRACT.decode(SENSOR_ID, bytes(received.data)).counter)
    plant_bus.shutdown()
    listener.shutdown()
    assert not plant.is_alive() and len(counters) == 150
    gaps = sum((b - a) % 256 - 1 for a, b in itertools.pairwise(counters))
    # (the last tick may skip periods after the last sample: counted, but no frame shows it)
    assert 2 <= gaps <= emulator.counters.missed_periods
