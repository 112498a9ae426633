"""What the bus and the machine allow, before any of our code runs: the floors the lock-step
and real-time figures are measured against.

- ``exchange_floor``: two processes trade frames over the same python-can bus a run uses, in
  the same pattern as a lock-step cycle (the plant's frames out, one command back, each side
  skipping its own frames that the bus hands back), doing nothing else: no plant, no control
  law, no recording. Its cycle time is the fastest any lock-step run with that pattern can go.
- ``machine_stalls``: one process per CPU, pinned, reads the clock in a tight loop and counts
  the gaps in which it did not run. A stall the machine imposes on a bare clock loop is a
  stall no control loop on that CPU can ride through.
"""

from __future__ import annotations

import gc
import multiprocessing
import os
import struct
import time
from typing import Any

import can

from ballbeam.config import BusSection
from ballbeam.protocol.secoc import EXTENSION_BYTES, FrameAuthenticator
from ballbeam.runtime.bus import (
    free_udp_port,
    isolated_group,
    open_bus,
    resolve_auto,
    resolved_bus,
)

PLANT_BASE_ID = 0x600  # ids of our own, unrelated to the frame contract
COMMAND_ID = 0x700
RESEND_AFTER_S = 0.05  # udp_multicast may lose a frame: the plant side asks again
GIVE_UP_S = 5.0

_CONTEXT = multiprocessing.get_context("spawn")


def _private_bus(bus: BusSection) -> BusSection:
    """The same bus kind on a group and port of its own, as ``ballbeam run`` gives each run."""
    if bus.interface == "auto":
        bus = resolved_bus(bus, resolve_auto(bus, claim=False))
    if bus.interface != "udp_multicast":
        return bus
    return bus.model_copy(update={"channel": isolated_group(bus.channel), "port": free_udp_port()})


def _receive(opened: can.BusABC, poll: bool, timeout_s: float) -> can.Message | None:
    """The next frame within ``timeout_s``: blocking in the bus, or polling it without sleep."""
    if not poll:
        return opened.recv(timeout=timeout_s)
    give_up = time.monotonic() + timeout_s
    while time.monotonic() < give_up:
        message = opened.recv(timeout=0.0)
        if message is not None:
            return message
    return None


class _Frames:
    """Frames as the pattern's runs make and judge them: plain 8-byte data, or (``secret``)
    authenticated as a run's are (protocol/secoc.py: a MAC and freshness on every frame sent,
    every frame heard judged, a peer's by ``verify`` and one's own echo by ``own_frame``); the
    plant's frame then 64 bytes, as a sensor frame with its sample's truth is."""

    def __init__(self, secret: bytes | None) -> None:
        self.auth = FrameAuthenticator(secret) if secret is not None else None

    def make(self, arbitration_id: int, cycle: int) -> can.Message:
        payload = struct.pack("<Q", cycle)
        if self.auth is None:
            return can.Message(arbitration_id=arbitration_id, data=payload, is_extended_id=False)
        extension = bytes(EXTENSION_BYTES) if arbitration_id != COMMAND_ID else b""
        return can.Message(
            arbitration_id=arbitration_id,
            data=self.auth.protect(arbitration_id, payload, extension),
            is_extended_id=False, is_fd=True,
        )

    def cycle_of(self, message: can.Message, own_id: int) -> int | None:
        """The cycle a heard frame carries; None for one this side sent (its echo) or one
        that fails its judgement."""
        data = bytes(message.data)
        if self.auth is not None:
            if message.arbitration_id == own_id:
                self.auth.own_frame(own_id, data)
                return None
            if self.auth.verify(message.arbitration_id, data) != "ok":
                return None
        elif message.arbitration_id == own_id:
            return None
        return int(struct.unpack_from("<Q", data)[0])


def _plant_side(
    bus: BusSection, cycles: int, plant_frames: int, poll: bool, secret: bytes | None,
    cpu_s: Any,
) -> None:
    """Send this cycle's frames, wait for the command that answers them, next cycle; puts
    the CPU time all that took on ``cpu_s``."""
    opened = open_bus(bus)
    frames_of = _Frames(secret)
    started_cpu_s = time.process_time()
    try:
        for cycle in range(cycles):
            answered = False
            while not answered:
                for i in range(plant_frames):  # made again for each send, as a run's are
                    opened.send(frames_of.make(PLANT_BASE_ID + i, cycle))
                resend_at = time.monotonic() + RESEND_AFTER_S
                while not answered and time.monotonic() < resend_at:
                    message = _receive(opened, poll, RESEND_AFTER_S)
                    if message is None or message.arbitration_id != COMMAND_ID:
                        continue  # (a plant frame's own echo is not judged: none is needed)
                    answered = frames_of.cycle_of(message, own_id=-1) == cycle
        cpu_s.put(time.process_time() - started_cpu_s)
    finally:
        opened.shutdown()


def _controller_side(
    opened: can.BusABC,
    cycles: int,
    plant_frames: int,
    poll: bool,
    plant: multiprocessing.process.BaseProcess,
    frames_of: _Frames,
) -> tuple[float, float, int]:
    """Answer every complete set of plant frames with one command; (wall seconds, CPU
    seconds, resends)."""
    resends = 0
    heard: set[int] = set()
    cycle = 0
    started: float | None = None  # from the first frame: the plant side's start-up is not timed
    started_cpu_s = 0.0
    silent_since = time.monotonic()
    while cycle < cycles:
        message = _receive(opened, poll, RESEND_AFTER_S)
        if message is None:
            if not plant.is_alive():
                raise RuntimeError(
                    f"exchange floor: the plant side exited ({plant.exitcode}) at cycle {cycle}"
                )
            give_up_s = GIVE_UP_S * (10 if started is None else 1)
            if time.monotonic() - silent_since > give_up_s:
                raise TimeoutError(f"exchange floor: the plant side went silent at cycle {cycle}")
            continue
        silent_since = time.monotonic()
        if started is None:
            started, started_cpu_s = time.perf_counter(), time.process_time()
        frame_cycle = frames_of.cycle_of(message, own_id=COMMAND_ID)
        if frame_cycle is None:
            continue  # our own command, handed back by the bus
        if frame_cycle < cycle:  # our answer was lost and the plant asks again
            if message.arbitration_id == PLANT_BASE_ID:
                resends += 1
                opened.send(frames_of.make(COMMAND_ID, frame_cycle))
            continue
        heard.add(message.arbitration_id)
        if len(heard) == plant_frames:
            opened.send(frames_of.make(COMMAND_ID, cycle))
            heard.clear()
            cycle += 1
    assert started is not None
    return time.perf_counter() - started, time.process_time() - started_cpu_s, resends


def exchange_floor(
    bus: BusSection, cycles: int, plant_frames: int, poll: bool, authenticated: bool = False
) -> dict[str, Any]:
    """Microseconds per lock-step cycle of bare frame exchange, the speed that caps at 1 kHz,
    and the CPU each side spends a cycle (polling: all of it, by construction);
    ``authenticated``: every frame made and judged as an authenticated run's are."""
    bus = _private_bus(bus)
    opened = open_bus(bus)  # open before the plant side sends, so no first frame is missed
    plant_cpu_s = _CONTEXT.Queue()
    secret = os.urandom(32) if authenticated else None  # a bench's own, never a run's
    try:
        plant = _CONTEXT.Process(
            target=_plant_side, args=(bus, cycles, plant_frames, poll, secret, plant_cpu_s)
        )
        plant.start()
        try:
            elapsed_s, controller_cpu_s, resends = _controller_side(
                opened, cycles, plant_frames, poll, plant, _Frames(secret)
            )
            plant_cpu_per_cycle_us = plant_cpu_s.get(timeout=GIVE_UP_S) / cycles * 1e6
        finally:
            plant.join(timeout=GIVE_UP_S)
            if plant.is_alive():
                plant.terminate()
    finally:
        opened.shutdown()
    cycle_us = elapsed_s / cycles * 1e6
    return {
        "plant_frames": plant_frames,
        "poll": poll,
        "authenticated": authenticated,
        "cycles": cycles,
        "cycle_us": cycle_us,
        "ceiling_x_realtime_at_1khz": 1000.0 / cycle_us,
        "controller_cpu_us_per_cycle": controller_cpu_s / cycles * 1e6,
        "plant_cpu_us_per_cycle": plant_cpu_per_cycle_us,
        "command_resends": resends,
    }


STALL_THRESHOLDS_US = (250, 1000, 2000)
BUSY_CHUNK_S = 0.5  # under SCHED_FIFO a loop that never sleeps is throttled (95 % of each
REST_S = 0.05  # second by default), which would read as a stall of our own making


def _probe_cpu(cpu: int, duration_s: float, fifo_priority: int, results: Any) -> None:
    os.sched_setaffinity(0, {cpu})
    scheduling = "normal"
    if fifo_priority:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(fifo_priority))
            scheduling = f"SCHED_FIFO {fifo_priority}"
        except OSError as error:
            scheduling = f"SCHED_FIFO refused: {error.strerror}"
    gc.disable()  # the probe allocates nothing cyclic; a collection would be our own stall
    gaps_ns: list[int] = []
    threshold_ns = min(STALL_THRESHOLDS_US) * 1000
    clock = time.monotonic_ns
    busy_ns = 0
    while busy_ns < duration_s * 1e9:
        now = start = clock()
        end = start + int(BUSY_CHUNK_S * 1e9)
        while now < end:
            before = now
            now = clock()
            if now - before >= threshold_ns:
                gaps_ns.append(now - before)
        busy_ns += now - start
        time.sleep(REST_S)
    results.put((cpu, scheduling, busy_ns * 1e-9, gaps_ns))


def machine_stalls(duration_s: float, fifo_priority: int = 0) -> dict[str, Any]:
    """Per CPU: how often, and how long, a pinned bare clock loop did not run (rates per
    minute of probing); ``fifo_priority`` > 0 probes under SCHED_FIFO where permitted."""
    cpus = sorted(os.sched_getaffinity(0))
    results = _CONTEXT.Queue()
    probes = [
        _CONTEXT.Process(target=_probe_cpu, args=(cpu, duration_s, fifo_priority, results))
        for cpu in cpus
    ]
    for probe in probes:
        probe.start()
    reports = [results.get(timeout=duration_s * 2 + 30) for _ in probes]
    for probe in probes:
        probe.join()
    per_cpu: dict[str, Any] = {}
    for cpu, scheduling, busy_s, gaps_ns in sorted(reports):
        gaps_us = [gap / 1000 for gap in gaps_ns]
        per_cpu[f"cpu{cpu}"] = {
            "scheduling": scheduling,
            **{
                f"stalls_over_{threshold}us_per_min": sum(g >= threshold for g in gaps_us)
                * 60.0
                / busy_s
                for threshold in STALL_THRESHOLDS_US
            },
            "longest_stall_us": max(gaps_us, default=0.0),
        }
    return {"duration_s": duration_s, **per_cpu}
