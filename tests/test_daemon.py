"""The daemon in-process on python-can's ``virtual`` bus: its parts one by one, then the whole
loop against the emulator in a thread, checked against the offline closed loop."""

from __future__ import annotations

import secrets
import threading
import time
from pathlib import Path
from typing import Any

import can
import numpy as np
import pytest

from ballbeam.assembly import run_offline
from ballbeam.config import Config, load_config
from ballbeam.evaluation import replay
from ballbeam.evaluation.summary import plant_missed_periods, summarise
from ballbeam.logs import design_record
from ballbeam.logs.reader import read_log
from ballbeam.logs.recorder import Recorder
from ballbeam.logs.recording import RunRecording
from ballbeam.logs.topics import TruthRecord
from ballbeam.protocol.frames import (
    SENSOR_ID,
    TRUTH_ANGLE_ID,
    VOLTAGE_COMMAND_ID,
    FrameContract,
    SensorFrame,
    TruthAngle,
    TruthBall,
    VoltageCommand,
    encode_lookahead,
)
from ballbeam.protocol.secoc import FrameAuthenticator
from ballbeam.runtime.daemon.command_out import CommandOut
from ballbeam.runtime.daemon.intake import SensorIntake, SentCommands
from ballbeam.runtime.daemon.loop import PERIOD_OFFSET_AGREEMENT, ControllerDaemon
from ballbeam.runtime.daemon.node import run_daemon
from ballbeam.runtime.planner import PlannerProcess
from ballbeam.runtime.stop import StopFlag
from ballbeam.runtime.ticker import Tick
from ballbeam_emulator.node import PlantEmulator, arrival_ns

# On wall time: alone under pytest -n (tests/conftest.py).
pytestmark = pytest.mark.realtime

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


def test_a_sample_read_behind_the_stream_is_told_as_late_as_it_is(
    recording: RunRecording,
) -> None:
    """Real time: the plant samples period i at its origin + i ms (its counters count periods).
    A starved daemon reading its socket behind the stream takes older samples; one 2 ms or more
    older than the freshest a sample has been is no measurement of now: it is given with the
    whole periods it is late (counted), for the law to take for its own period. A daemon late
    within its period is not fooled (the freshest relation comes from the least age, which
    lateness only adds to)."""
    intake = SensorIntake(CONTRACT, recording, late_sample_periods=2)
    ms = 1_000_000
    origin_ns = 5_000 * ms
    # (counter, the plant period it was sampled in, when the daemon takes it [ms after origin])
    reads = [
        (250, 250, 250.2),  # 0.2 ms old: the freshest relation
        (251, 251, 251.2),
        (252, 252, 253.1),  # the daemon 0.9 ms late within its period: 1.1 ms old, taken
        (253, 253, 253.3),
        (2, 258, 260.4),  # past the wrap: period 258 read at 260.4, 2.2 ms old: 2 late
        (3, 259, 264.3),  # 5.3 ms old: 5 late
        (4, 260, 261.5),  # 1.3 ms old: taken
        (7, 263, 263.2),  # in step again
    ]
    late = []
    for counter, _period, at_ms in reads:
        intake.handle(framed(SensorFrame(counter, 10, -20, 0)), 0, 0)
        taken = intake.take(origin_ns + round(at_ms * ms))
        assert taken is not None and taken[0].counter == counter
        late.append(taken[1])
    assert late == [0, 0, 0, 0, 2, 5, 0, 0]
    assert intake.late_samples == 2
    # Lock-step (no lateness bound): every sample is of now.
    lockstep = SensorIntake(CONTRACT, recording)
    lockstep.handle(framed(SensorFrame(3, 10, -20, 0)), 0, 50)
    assert lockstep.take(10**12) == (SensorFrame(3, 10, -20, 0), 0)


def test_intake_accepts_samples_in_order_and_judges_the_rest(recording: RunRecording) -> None:
    sent = SentCommands()
    intake = SensorIntake(CONTRACT, recording, sent)

    def sensor(counter: int) -> can.Message:
        return framed(SensorFrame(counter, 10, -20, 0))

    assert intake.handle(sensor(5), 0, 0) == "ok"
    assert intake.take() == (SensorFrame(5, 10, -20, 0), 0)
    assert intake.take() is None  # a sample is used once
    assert intake.handle(sensor(5), 0, 0) == "repeated"
    assert intake.handle(sensor(4), 0, 0) == "stale"
    assert intake.handle(sensor(7), 0, 0) == "ok"
    assert intake.sensor_check.lost == 1
    own = framed(VoltageCommand(0, 1.0, True, 7))
    sent.note(bytes(own.data))
    assert intake.handle(own, 0, 0) is None and intake.own_frames == 1
    # The same bytes again, or a command the daemon never sent: someone else's frame.
    assert intake.handle(own, 0, 0) is None and intake.own_frames == 1
    forged = framed(VoltageCommand(1, 5.0, True, 7))
    assert intake.handle(forged, 0, 0) is None and intake.own_frames == 1
    corrupt = bytearray(sensor(8).data)
    corrupt[0] ^= 0xFF
    intake.handle(message(SENSOR_ID, bytes(corrupt)), 0, 0)
    extended = can.Message(arbitration_id=SENSOR_ID, data=bytes(8), is_extended_id=True)
    intake.handle(extended, 0, 0)
    assert dict(intake.rejected) == {
        "stale": 1, "foreign_command": 2, "crc": 1, "foreign": 1
    }
    # Truth pairs by counter; an unpaired ball frame is dropped.
    intake.handle(framed(TruthBall(7, 0.1, 0.0)), 0, 0)
    intake.handle(framed(TruthAngle(7, 0.2, 0.0)), 0, 0)
    intake.handle(framed(TruthBall(7, 0.1, 0.0)), 0, 0)
    assert intake.latest == SensorFrame(7, 10, -20, 0)


def test_an_authenticated_intake_refuses_forged_replayed_and_reordered_frames_by_reason(
    recording: RunRecording,
) -> None:
    """The plant's frames under the run's key pass; a forger's key, a replay, a reorder, a
    tampered byte and a well-formed classic frame are each refused by reason, and none moves
    the sensor counter check or the truth (the real stream goes on being accepted)."""
    secret = secrets.token_bytes(32)
    plant, daemon = FrameAuthenticator(secret), FrameAuthenticator(secret)
    forger = FrameAuthenticator(secrets.token_bytes(32))
    intake = SensorIntake(CONTRACT, recording, auth=daemon)

    def fd(frame: SensorFrame | TruthAngle | TruthBall | VoltageCommand,
           key: FrameAuthenticator = plant) -> can.Message:
        frame_id, data = CONTRACT.encode(frame)
        return can.Message(arbitration_id=frame_id, data=key.protect(frame_id, data),
                           is_extended_id=False, is_fd=True)

    first = fd(SensorFrame(0, 1, 1, 0))
    assert intake.handle(first, 0, 0) == "ok"
    older = fd(SensorFrame(1, 2, 2, 0))
    newer = fd(SensorFrame(2, 3, 3, 0))
    assert intake.handle(newer, 0, 0) == "ok"
    assert intake.handle(older, 0, 0) is None  # reordered: refused before the counter check
    assert intake.handle(first, 0, 0) is None  # replayed
    assert intake.handle(fd(SensorFrame(200, 9, 9, 0), forger), 0, 0) is None
    tampered = bytearray(fd(SensorFrame(3, 4, 4, 0)).data)
    tampered[2] ^= 0x01
    assert intake.handle(message(SENSOR_ID, bytes(tampered)), 0, 0) is None
    assert intake.handle(framed(SensorFrame(3, 5, 5, 0)), 0, 0) is None  # no MAC
    # Forged truth is never paired into the record; the plant's is.
    intake.handle(fd(TruthAngle(2, 1.5, 0.0), forger), 0, 0)
    intake.handle(fd(TruthBall(2, 0.2, 0.0), forger), 0, 0)
    assert intake.handle(fd(SensorFrame(3, 6, 6, 0)), 0, 0) == "ok"  # the stream goes on
    assert intake.latest == SensorFrame(3, 6, 6, 0)
    assert intake.sensor_check.stale == 0
    assert dict(intake.rejected) == {"replayed": 2, "bad_mac": 4, "unauthenticated": 1}
    # A command frame with the run's key that the daemon never sent: a second writer.
    intake.handle(fd(VoltageCommand(0, 1.0, True, 3), plant), 0, 0)
    assert intake.second_writer_frames == 1 and intake.rejected["foreign_command"] == 1


def test_an_authenticated_sensor_frame_brings_its_samples_truth(
    recording: RunRecording, monkeypatch: pytest.MonkeyPatch
) -> None:
    """On the authenticated bus the plant sends one frame a sample, its truth in the extension:
    the sample is taken and its truth recorded at the sample's log time, as the two truth
    frames would be; a sensor frame whose truth is not its sample's is refused whole, and an
    extension on any other frame is refused for its length."""
    secret = secrets.token_bytes(32)
    plant = FrameAuthenticator(secret)
    intake = SensorIntake(CONTRACT, recording, auth=FrameAuthenticator(secret))
    truths: list[tuple[int, TruthRecord]] = []
    write = recording.write

    def spy(topic, log_time_ns, record):  # type: ignore[no-untyped-def]
        if isinstance(record, TruthRecord):
            truths.append((log_time_ns, record))
        write(topic, log_time_ns, record)

    monkeypatch.setattr(recording, "write", spy)

    def sample(counter: int, truth: bytes, frame_id: int = SENSOR_ID) -> can.Message:
        payload = CONTRACT.encode_sensor(counter, 10, -20, 0) if frame_id == SENSOR_ID else (
            CONTRACT.encode_truth_angle(counter, 0.0, 0.0)
        )
        return can.Message(arbitration_id=frame_id, data=plant.protect(frame_id, payload, truth),
                           is_extended_id=False, is_fd=True)

    assert intake.handle(sample(5, CONTRACT.encode_truth(5, 0.5, -1.0, 0.1, 0.2)), 123, 0) == "ok"
    assert intake.take() == (SensorFrame(5, 10, -20, 0), 0)
    assert [(at, r.counter) for at, r in truths] == [(123, 5)]
    assert truths[0][1][1:5] == pytest.approx((0.5, -1.0, 0.2, 0.1), abs=1e-5)  # quantised
    assert intake.handle(sample(6, CONTRACT.encode_truth(7, 0.5, -1.0, 0.1, 0.2)), 124, 1) is None
    assert intake.take() is None and len(truths) == 1
    wrong_id = sample(6, CONTRACT.encode_truth(6, 0.5, -1.0, 0.1, 0.2), TRUTH_ANGLE_ID)
    assert intake.handle(wrong_id, 125, 1) is None and len(truths) == 1
    assert dict(intake.rejected) == {"range": 1, "length": 1}


def test_a_classic_intake_takes_three_valid_commands_it_never_sent_for_a_second_writer(
    recording: RunRecording,
) -> None:
    sent = SentCommands()
    intake = SensorIntake(CONTRACT, recording, sent)
    ours = framed(VoltageCommand(0, 1.0, True, 7))
    sent.note(bytes(ours.data))
    intake.handle(ours, 0, 0)
    intake.handle(ours, 0, 0)  # a replay of ours: a stranger's, not a writer's
    corrupt = bytearray(framed(VoltageCommand(1, 5.0, True, 7)).data)
    corrupt[0] ^= 0xFF
    intake.handle(message(0x100, bytes(corrupt)), 0, 0)
    assert intake.second_writer_frames == 0
    intake.handle(framed(VoltageCommand(1, 5.0, True, 7)), 0, 0)
    assert intake.second_writer_frames == 1
    assert intake.own_frames == 1 and intake.rejected["foreign_command"] == 3


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


def run_in_process(config: Config, log_path: Path) -> str:
    """Daemon and emulator of one authenticated run, the emulator in a thread (real time or
    lock-step as ``config`` says); returns the daemon's end reason."""
    stop_plant = StopFlag()
    plant_bus = can.Bus(interface="virtual", channel=config.bus.channel)
    secret = secrets.token_bytes(32)
    emulator = PlantEmulator(config, plant_bus, CONTRACT, auth=FrameAuthenticator(secret))
    target = emulator.run_realtime if config.run.mode == "realtime" else emulator.run_lockstep
    plant = threading.Thread(target=target, args=(stop_plant,), daemon=True)
    plant.start()
    try:
        return run_daemon(config, log_path, None, secret=secret)
    finally:
        stop_plant.set()
        plant.join(timeout=10)
        emulator.stop()
        plant_bus.shutdown()


def test_the_whole_daemon_in_process_runs_like_the_offline_loop(tmp_path: Path) -> None:
    config = virtual_config(1.5)
    assert config.bus.authenticated  # the virtual bus: SecOC-style frames by default
    log_path = tmp_path / "run.mcap"
    end_reason = run_in_process(config, log_path)
    run_log = read_log(log_path)
    summary = summarise(run_log)
    assert end_reason == summary["end_reason"] == "completed" and summary["cycles"] == 1500
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


def test_a_samples_records_wait_until_its_command_is_on_the_bus(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Between a sample and its command the daemon only computes: the sample's frame, its
    sensor record and its truth are encoded after the command has gone out (RunRecording's
    hold), in the order they were written, and none is lost."""
    events: list[tuple[str, int]] = []  # (what, its cycle or log time)
    send_bytes, record = CommandOut._send_bytes, Recorder.record

    def sending(self, data, log_time_ns, cycle, extension=b""):  # type: ignore[no-untyped-def]
        events.append(("command", cycle))
        send_bytes(self, data, log_time_ns, cycle, extension)

    def recording_(self, handle, log_time_ns, values):  # type: ignore[no-untyped-def]
        if handle.topic in ("/sensor", "/truth") or (
            handle.topic == "/can/rx" and values[1] == SENSOR_ID  # not the plant's status
        ):
            events.append((handle.topic, log_time_ns))
        record(self, handle, log_time_ns, values)

    monkeypatch.setattr(CommandOut, "_send_bytes", sending)
    monkeypatch.setattr(Recorder, "record", recording_)
    config = virtual_config(0.3, "run.mode='lockstep'")
    assert run_in_process(config, tmp_path / "run.mcap") == "completed"
    period_ns = round(config.controller.period_s * 1e9)
    commands = [i for i, (kind, _) in enumerate(events) if kind == "command"]
    assert len(commands) >= 300
    origin_ns = next(t for kind, t in events if kind == "/sensor")  # cycle 0's log time
    for kind in ("/can/rx", "/truth", "/sensor"):
        at = [(i, (t - origin_ns) // period_ns) for i, (k, t) in enumerate(events) if k == kind]
        assert [cycle for _, cycle in at] == list(range(300)), kind
        # cycle k's records come after cycle k's command, before cycle k + 1's (the first
        # sample is read before the loop starts: no command waits for it)
        assert all(commands[cycle] < i < commands[cycle + 1] for i, cycle in at[1:]), kind
    run_log = read_log(tmp_path / "run.mcap")
    assert len(run_log.topics["/sensor"].values["cycle"]) == 300
    assert replay.verify(run_log).ok


def test_what_waits_for_a_command_is_written_before_the_daemon_waits_for_its_planner(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Lock-step waits for each plan the re-planning law is due; a wait has no turnaround to
    spare, so the sample's records held for the command are written before it (a held
    record would miss the recorder's flushes for as long as the planner takes)."""
    events: list[tuple[str, int]] = []
    waiting, record = ControllerDaemon._take_in_while_waiting, Recorder.record
    receive = PlannerProcess.receive
    polls = [0]

    def slow_planner(self, timeout_s=0.0):  # type: ignore[no-untyped-def]
        # every other poll the daemon waits on finds nothing yet: a planner slower than the
        # loop, whatever the machine's load (a loaded daemon gave its planner time enough)
        if timeout_s != 0.0:
            polls[0] += 1
            if polls[0] % 2:
                return []
        return receive(self, timeout_s)

    def wait(self):  # type: ignore[no-untyped-def]
        waiting(self)  # (its first poll of the bus is at once: what it records comes first)
        events.append(("wait", self.law.cycle))

    def recording_(self, handle, log_time_ns, values):  # type: ignore[no-untyped-def]
        if handle.topic == "/can/rx" and values[1] == SENSOR_ID:
            events.append(("sample", log_time_ns))
        record(self, handle, log_time_ns, values)

    monkeypatch.setattr(ControllerDaemon, "_take_in_while_waiting", wait)
    monkeypatch.setattr(Recorder, "record", recording_)
    monkeypatch.setattr(PlannerProcess, "receive", slow_planner)
    config = virtual_config(0.3, "run.mode='lockstep'", "controller.kind='replanning'")
    assert run_in_process(config, tmp_path / "run.mcap") == "completed"
    period_ns = round(config.controller.period_s * 1e9)
    first = next(i for i, (kind, _) in enumerate(events) if kind == "sample")
    origin_ns = events[first][1]  # cycle 0's log time
    # (the first plan may be waited for before any sample: nothing is held then)
    waits = [i for i, (kind, _) in enumerate(events) if kind == "wait" and i > first]
    assert waits, "the law waited for no plan"
    for i in waits:
        # the sample of the cycle that waits was read before the wait: it is recorded
        cycle = events[i][1]
        assert any(kind == "sample" and (t - origin_ns) // period_ns == cycle
                   for kind, t in events[:i]), (i, cycle)
    assert replay.verify(read_log(tmp_path / "run.mcap")).ok


def test_after_a_watchdog_trip_the_plant_obeys_a_restarted_daemon_at_once() -> None:
    """A restarted daemon counts its commands from 0 again; the old stream had reached 40.
    Without a reset at the trip, its frames looked stale for up to 128 periods (42–120 ms of
    ignored commands were measured in 4 of 8 restarts)."""
    config = virtual_config(1.0)
    bus = can.Bus(interface="virtual", channel=config.bus.channel)
    emulator = PlantEmulator(config, bus, CONTRACT)
    try:
        for counter in range(41):
            command = VoltageCommand(counter, 0.5, True, 0)
            assert emulator._accept_command(framed(command)) is not None
            emulator._apply(command, now_ns=counter * 1_000_000)
        emulator._check_watchdog(now_ns=40_000_000 + emulator.watchdog_ns + 1)
        assert emulator.watchdog_zeroed and emulator.voltage_v == 0.0
        restarted = emulator._accept_command(framed(VoltageCommand(0, 1.0, True, 0)))
        assert restarted is not None and restarted[0].voltage_v == 1.0
    finally:
        emulator.stop()
        bus.shutdown()


def test_a_command_acts_from_when_it_reached_the_host_not_when_the_emulator_got_to_it() -> None:
    """Real time: a command that waited 4 ms in the socket while the emulator was off the CPU
    drives the plant from its arrival (the kernel's receive stamp): the physics runs on the old
    voltage up to that moment only, and the watchdog counts from it."""
    config = virtual_config(1.0, "run.mode='realtime'")
    bus = can.Bus(interface="virtual", channel=config.bus.channel)
    emulator = PlantEmulator(config, bus, CONTRACT)
    try:
        emulator._apply(VoltageCommand(0, 0.0, True, 0), now_ns=0)  # enabled: physics runs
        now_ns = time.monotonic_ns()
        physics_ns, arrived_ns = now_ns - 10_000_000, now_ns - 4_000_000
        late = framed(VoltageCommand(1, 3.0, True, 0))
        late.timestamp = (arrived_ns + time.time_ns() - time.monotonic_ns()) * 1e-9  # wall clock
        assert abs(arrival_ns(late, time.monotonic_ns()) - arrived_ns) < 50_000
        before = emulator.state.copy()
        new_physics_ns = emulator._take_command(late, physics_ns, limit_ns=now_ns)
        substep_ns = emulator.substep_ns
        assert abs(new_physics_ns - arrived_ns) <= substep_ns + 50_000
        assert abs(emulator.last_command_ns - arrived_ns) < 50_000
        assert emulator.voltage_v == 3.0
        # The physics between: the old 0 V for the 6 ms up to the arrival, nothing after.
        steps = (new_physics_ns - physics_ns) // substep_ns
        expected = emulator.physics.advance(before, 0.0, steps)
        assert np.allclose(emulator.state, expected, rtol=0, atol=1e-12)
        # No stamp, or one more than a second off: the command counts from now.
        stampless = framed(VoltageCommand(2, 1.0, True, 0))
        stampless.timestamp = 0.0
        assert arrival_ns(stampless, now_ns) == now_ns
    finally:
        emulator.stop()
        bus.shutdown()


class SkippingTicker:
    """A ticker whose deadlines are given: the periods the emulator 'overran' are skipped
    (what Ticker.wait reports after an overrun), and it stops the run after the last."""

    def __init__(self, cycles: list[int], period_ns: int, stop: StopFlag) -> None:
        self.origin_ns, self.spin_ns, self.period_ns = 0, 0, period_ns
        self._cycles, self._stop, self._last = iter(cycles), stop, -1

    def wait(self) -> Tick:
        cycle = next(self._cycles, None)
        if cycle is None:
            self._stop.set()
            cycle = self._last + 1
        skipped, self._last = cycle - self._last - 1, cycle
        deadline_ns = cycle * self.period_ns
        return Tick(cycle=cycle, deadline_ns=deadline_ns, start_ns=deadline_ns, skipped=skipped)


def test_the_plants_counters_count_the_periods_it_missed(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """An emulator that overran periods 2–4 sends no sample for them, and its next sample's
    counter is 5: the gap is visible to every receiver (before, the counter was per frame)."""
    config = virtual_config(1.0, "run.mode='realtime'")
    stop = StopFlag()
    period_ns = 1_000_000_000 // config.plant.sensor_rate_hz
    monkeypatch.setattr(
        "ballbeam_emulator.node.Ticker",
        lambda *_args, **_kwargs: SkippingTicker([0, 1, 5, 6], period_ns, stop),
    )
    plant_bus = can.Bus(interface="virtual", channel=config.bus.channel)
    listener = can.Bus(interface="virtual", channel=config.bus.channel)
    emulator = PlantEmulator(config, plant_bus, CONTRACT)
    try:
        emulator.run_realtime(stop)
        counters = []
        while (received := listener.recv(timeout=0.05)) is not None:
            if received.arbitration_id == SENSOR_ID:
                frame = CONTRACT.decode(received.arbitration_id, bytes(received.data))
                counters.append(frame.counter)
    finally:
        emulator.stop()
        plant_bus.shutdown()
        listener.shutdown()
    assert counters == [0, 1, 5, 6]
    assert emulator.counters.missed_periods == 3


def test_truth_carries_the_plants_own_sample_clock(tmp_path: Path) -> None:
    """The recorder's /truth has the plant's period index (its counter unwrapped) and time;
    replay counts the periods with no truth between the first and the last."""
    path = tmp_path / "truth.mcap"
    recorder = Recorder(path, metadata={})
    intake = SensorIntake(CONTRACT, RunRecording(recorder), sample_period_s=1e-3)
    for counter in (254, 255, 0, 3, 4):  # periods 257 and 258 missed
        intake.handle(framed(TruthAngle(counter, 0.1, 0.0)), 0, 0)
        intake.handle(framed(TruthBall(counter, 0.05, 0.0)), 0, 0)
    recorder.close()
    run_log = read_log(path)
    truth = run_log.topics["/truth"]
    assert list(truth.values["sample_index"]) == [254, 255, 256, 259, 260]
    assert list(truth.values["plant_time_s"]) == pytest.approx([0.254, 0.255, 0.256, 0.259, 0.26])
    assert plant_missed_periods(run_log) == 2


def test_the_plant_drives_the_lookahead_of_a_command_while_no_newer_one_comes() -> None:
    """Real time, authenticated: a command that comes in period 0 carrying the commands for
    the next three drives 1 V up to the next sample instant, then 2, 3 and 4 V from each
    sample instant on, and 4 V beyond (its last word held). The physics is exactly the
    plant's at those voltages, switched at the instants. A newer command replaces the
    look-ahead; a stop (disabled) clears it, and so does the watchdog."""
    config = virtual_config(1.0, "run.mode='realtime'")
    bus = can.Bus(interface="virtual", channel=config.bus.channel)
    secret = secrets.token_bytes(32)
    sender = FrameAuthenticator(secret)
    emulator = PlantEmulator(config, bus, CONTRACT, auth=FrameAuthenticator(secret))

    def command(counter: int, voltage_v: float, lookahead_v: tuple[float, ...],
                enable: bool = True, period: int = 0) -> can.Message:
        _, data = CONTRACT.encode(VoltageCommand(counter, voltage_v, enable, period))
        extension = encode_lookahead(lookahead_v) if lookahead_v else b""
        return can.Message(
            arbitration_id=VOLTAGE_COMMAND_ID, is_extended_id=False, is_fd=True,
            data=sender.protect(VOLTAGE_COMMAND_ID, data, extension),
        )

    period_ns = emulator.sensor_period_ns
    try:
        emulator.realtime = True
        emulator.next_boundary_ns, emulator.next_boundary_index = 0, 0
        physics_ns = emulator._advance_until(0, 0)  # sample 0's instant
        accepted = emulator._accept_command(command(0, 1.0, (2.0, 3.0, 4.0)))
        assert accepted is not None and accepted[1] == (2.0, 3.0, 4.0)
        start = emulator.state.copy()
        emulator._apply(*accepted, now_ns=0)
        driven = []
        for k in range(5):
            physics_ns = emulator._advance_until(physics_ns, k * period_ns + period_ns // 2)
            driven.append(emulator.voltage_v)
        assert driven == [1.0, 2.0, 3.0, 4.0, 4.0]
        expected, half = start, (period_ns // 2) // emulator.substep_ns
        for voltage_v, steps in ((1.0, emulator.substeps), (2.0, emulator.substeps),
                                 (3.0, emulator.substeps), (4.0, emulator.substeps), (4.0, half)):
            expected = emulator.physics.advance(expected, voltage_v, steps)
        assert np.allclose(emulator.state, expected, rtol=0, atol=1e-12)
        newer = emulator._accept_command(command(1, -1.0, (-2.0,), period=4))
        assert newer is not None
        emulator._apply(*newer, now_ns=physics_ns)
        assert emulator.voltage_v == -1.0
        physics_ns = emulator._advance_until(physics_ns, 6 * period_ns + period_ns // 2)
        assert emulator.voltage_v == -2.0  # periods 5 and 6: its one entry, then held
        stopped = emulator._accept_command(command(2, 0.0, (), enable=False))
        assert stopped is not None
        emulator._apply(*stopped, now_ns=physics_ns)
        physics_ns = emulator._advance_until(physics_ns, 8 * period_ns)
        assert emulator.voltage_v == 0.0 and emulator.lookahead_v == ()
        again = emulator._accept_command(command(3, 1.0, (2.0, 3.0), period=8))
        assert again is not None
        emulator._apply(*again, now_ns=physics_ns)
        emulator._check_watchdog(now_ns=physics_ns + emulator.watchdog_ns + 1)
        physics_ns = emulator._advance_until(physics_ns, 11 * period_ns)
        assert emulator.voltage_v == 0.0 and emulator.lookahead_v == ()
        # A command for period 9 that comes in period 11 (its sender stalled between reading
        # and sending): it drives its entry for period 11 now, and the next from period 12.
        late = emulator._accept_command(command(4, 1.0, (2.0, 3.0, 4.0, 5.0), period=9))
        assert late is not None
        emulator._apply(*late, now_ns=physics_ns)
        assert emulator.voltage_v == 3.0
        emulator._advance_until(physics_ns, 12 * period_ns + period_ns // 2)
        assert emulator.voltage_v == 4.0
    finally:
        emulator.stop()
        bus.shutdown()


def test_a_command_heard_late_acts_from_its_arrival_when_the_physics_gets_there() -> None:
    """Real time: a command that came while the emulator was off the CPU (read under the limit
    of the period it stalled in) waits, and acts from its kernel receive stamp once the
    physics reaches it. Before, it acted from the limit: early by up to the stall, and its
    look-ahead started from the wrong period (traced: a plant two periods ahead)."""
    config = virtual_config(1.0, "run.mode='realtime'")
    bus = can.Bus(interface="virtual", channel=config.bus.channel)
    emulator = PlantEmulator(config, bus, CONTRACT)
    period_ns = emulator.sensor_period_ns
    try:
        base_ns = time.monotonic_ns() - 20 * period_ns
        emulator.realtime, emulator.started = True, True
        emulator.next_boundary_ns, emulator.next_boundary_index = base_ns, 0
        physics_ns = emulator._advance_until(base_ns, base_ns)  # sample 0's instant
        start = emulator.state.copy()
        arrived_ns = base_ns + 7 * emulator.substep_ns // 2  # mid-substep 3 (stamps: ±1 µs)
        message = framed(VoltageCommand(0, 1.0, True, 0))
        message.timestamp = (arrived_ns + time.time_ns() - time.monotonic_ns()) * 1e-9
        physics_ns = emulator._take_command(message, physics_ns, base_ns + emulator.substep_ns)
        assert emulator.voltage_v == 0.0 and len(emulator.pending) == 1
        physics_ns = emulator._advance_until(physics_ns, base_ns + period_ns // 2)
        assert emulator.voltage_v == 1.0 and not emulator.pending
        expected = emulator.physics.advance(start, 0.0, 3)
        expected = emulator.physics.advance(expected, 1.0, emulator.substeps // 2 - 3)
        assert np.allclose(emulator.state, expected, rtol=0, atol=1e-12)
    finally:
        emulator.stop()
        bus.shutdown()


def test_a_real_time_run_that_overran_replays_bit_for_bit_with_its_lookahead(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Daemon and emulator in real time (threads, virtual bus); the daemon stalls 6 ms at
    three points of the plan. Its commands carried a look-ahead, and after each stall it
    coasted on the commands the plant drove meanwhile: replay --verify, which recomputes
    that look-ahead from the log, gets every voltage bit for bit."""
    from ballbeam.runtime.ticker import Ticker

    class StallingTicker(Ticker):
        def wait(self) -> Tick:
            tick = super().wait()
            if tick.cycle in (600, 1200, 1700):
                time.sleep(0.006)
            return tick

    from ballbeam.runtime.daemon.command_out import CommandOut

    send = CommandOut.send

    def stalling_send(self: CommandOut, log_time_ns: int, cycle: int, *args: Any) -> None:
        if cycle in (900, 1500):  # the CPU lost between reading the sample and sending
            time.sleep(0.004)
        send(self, log_time_ns, cycle, *args)

    monkeypatch.setattr("ballbeam.runtime.daemon.loop.Ticker", StallingTicker)
    monkeypatch.setattr(CommandOut, "send", stalling_send)
    config = virtual_config(
        2.0, "run.mode='realtime'", "controller.realtime_priority=0", "controller.cpu=-1",
        "plant.cpu=-1", "plant.realtime_priority=0",
    )
    log_path = tmp_path / "run.mcap"
    run_in_process(config, log_path)
    run_log = read_log(log_path)
    skipped = run_log.topics["/timing"].values["skipped"]
    assert int(skipped.sum()) >= 3
    # Each command names its plant period (the plant aligns the look-ahead with it): the
    # cycle's plus the offset between the two clocks, which the samples give once
    # PERIOD_OFFSET_AGREEMENT measured cycles in a row agree on it (a cycle takes at times
    # the sample before or after its own; under load the phase can settle on either side).
    sensors, commands = run_log.topics["/sensor"].values, run_log.topics["/command"].values
    learned: dict[int, int] = {}
    offset: int | None = None
    candidate, agreement = -1, 0
    for cycle, fresh, counter in zip(
        sensors["cycle"].tolist(), sensors["fresh"].tolist(), sensors["counter"].tolist(),
        strict=True,
    ):
        if fresh >= 1:  # a sample taken: of its own period, or (1 + n) read n cycles late
            seen = (counter + fresh - 1 - cycle) % 256
            candidate, agreement = seen, (agreement + 1 if seen == candidate else 1)
            if agreement >= PERIOD_OFFSET_AGREEMENT:
                offset = candidate
        if offset is not None:
            learned[cycle] = offset
    enabled = (commands["enable"] == 1) & np.isin(commands["cycle"], list(learned))
    assert enabled.any()
    named = [(cycle + learned[cycle]) % 256 for cycle in commands["cycle"][enabled].tolist()]
    assert commands["sensor_counter"][enabled].tolist() == named
    assert not (sensors["fresh"][np.isin(sensors["cycle"], commands["cycle"][enabled])] != 0).all()
    result = replay.verify(run_log)
    assert result.ok and result.design_source == "recorded"
    decoded = design_record.decode_design(
        run_log.attachments[design_record.ATTACHMENT_NAME], "test"
    )
    assert decoded.lookahead_periods == 20
