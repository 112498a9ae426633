"""Lock-step on a slow machine: the emulator waits for the daemon's answer as long as answers
take (RFC 6298's timeout over the measured round trips), so a peer that answers every sample
in 30 ms, slower than the 20 ms floor, is neither flooded with resends nor called silent by
the watchdog (on the VM's emulated CPU a fixed 20 ms resent one sample in eight)."""

from __future__ import annotations

import secrets
import threading
import time

import can
import pytest

from ballbeam.config import load_config
from ballbeam.protocol.frames import SENSOR_ID, VOLTAGE_COMMAND_ID, FrameContract, next_counter
from ballbeam.runtime.stop import StopFlag
from ballbeam_emulator.node import AnswerTimer, PlantEmulator

CONTRACT = FrameContract.load()


def test_the_timeout_is_rfc_6298s_over_a_floor() -> None:
    timer = AnswerTimer(0.020)
    assert timer.timeout_s == 0.020  # nothing measured yet
    timer.observe(0.001)
    assert timer.timeout_s == 0.020  # 3 × 1 ms is under the floor
    timer = AnswerTimer(0.020)
    timer.observe(0.030)  # first measurement R: SRTT = R, RTTVAR = R/2, RTO = 3R
    assert timer.timeout_s == pytest.approx(0.090)
    timer.observe(0.030)  # RTTVAR = 3/4 · 15 ms + 1/4 · 0, SRTT stays 30 ms
    assert timer.timeout_s == pytest.approx(0.030 + 4 * 0.01125)
    timer.resent()
    timer.resent()
    assert timer.timeout_s == pytest.approx(4 * (0.030 + 4 * 0.01125))
    timer.observe(0.030)
    assert timer.backoff == 1


def _slow_daemon(channel: str, answer_after_s: float, samples: int, stop: StopFlag) -> None:
    """Answers each new sample once, ``answer_after_s`` after it came; stops the emulator
    after ``samples`` answers."""
    with can.Bus(interface="virtual", channel=channel) as bus:
        answered, counter, last = 0, 0, None
        deadline = time.monotonic() + 60
        while answered < samples:
            if time.monotonic() > deadline:
                break
            message = bus.recv(timeout=1.0)
            if message is None or message.arbitration_id != SENSOR_ID:
                continue
            sample = CONTRACT.decode(SENSOR_ID, bytes(message.data))
            if sample.counter == last:
                continue  # a resend of the sample already answered
            time.sleep(answer_after_s)
            bus.send(can.Message(
                arbitration_id=VOLTAGE_COMMAND_ID, is_extended_id=False,
                data=CONTRACT.encode_voltage_command(counter, 0.0, True, sample.counter),
            ))
            counter = next_counter(counter)
            last = sample.counter
            answered += 1
    stop.set("test over")


@pytest.mark.realtime
def test_a_peer_slower_than_the_floor_is_neither_flooded_nor_called_silent() -> None:
    channel = f"ballbeam-test-{secrets.token_hex(4)}"
    config = load_config(None, [
        "bus.interface='virtual'", f"bus.channel='{channel}'", "bus.authenticate=false",
        "plant.lockstep_resend_ms=20", "plant.watchdog_ms=20",
    ])
    samples = 25
    stop = StopFlag()
    with can.Bus(interface="virtual", channel=channel) as bus:
        emulator = PlantEmulator(config, bus, CONTRACT)
        daemon = threading.Thread(target=_slow_daemon, args=(channel, 0.030, samples, stop))
        daemon.start()
        emulator.run_lockstep(stop)
        daemon.join(timeout=60)
    counters = emulator.counters
    assert counters.commands_applied >= samples - 1
    # The first sample is resent (nothing measured yet, then backing off); a stall of the
    # test process on a loaded machine may cost one or two more.
    assert counters.resends <= 4, counters
    assert counters.watchdog_trips == 0, counters
