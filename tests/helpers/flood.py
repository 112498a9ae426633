"""A bounded, paced flood of foreign traffic on one ballbeam bus: the bus-noise test's third node.

    python tests/helpers/flood.py --channel ff11:... [--rate-hz 3000] [--max-frames 20000]
        [--max-seconds 3] [--seed 0] [--start-on command|sensor] [--wait 30] [--raw-weight 4]

It waits (at most ``--wait`` seconds) for its cue on the bus: the controller's first *enabled*
voltage command (``command``: the run is cycling) or the plant's first sensor frame
(``sensor``: the controller is still starting up); then it sends for at most
``--max-seconds`` and at most ``--max-frames`` frames, paced on absolute deadlines in 1 ms
bursts (never faster than ``--rate-hz``), and prints one JSON object: what it sent, by kind.

What it sends (seeded):

- ``foreign_id``: standard ids outside 0x100-0x104, any length 0-8, random bytes;
- ``bad_crc``: our five ids, 8 random bytes whose E2E CRC is made wrong on purpose (a random
  payload would pass the CRC-16 once in 65,536 frames: that is spoofing, not noise);
- ``wrong_length``: our five ids with 0-7 bytes;
- ``extended_id``: our five numeric ids as *extended* (29-bit) ids, carrying payloads whose CRC is
  right for the standard frame of that number (a real bus keeps the two id spaces apart; so must
  the receivers), with wild values (full-scale counts, ±5 V enabled commands);
- ``remote_frame`` and ``error_frame``: our ids with those flags set;
- ``raw_datagram``: UDP datagrams on the group that are not python-can frames at all (random
  bytes; msgpack that is not a frame; a frame whose id is not a number).

``--attack`` sends what an authenticated bus (protocol/secoc.py) must refuse instead, from a
process that does not hold the run's secret:

- ``forged_mac``: 24-byte CAN FD frames on our five ids with valid classic payloads (right CRC,
  wild values: ±5 V enabled commands, full-scale counts, truth at ±5 rad, plant counters at
  their ceiling), a fresh freshness
  value and a MAC under a key of its own;
- ``replayed``: authenticated frames of the run heard on the bus, sent again (old ones and the
  very latest, i.e. replayed and reordered), unchanged;
- ``classic_valid``: well-formed classic 8-byte frames on our ids (a right CRC, no MAC);
- ``random``: the noise kinds above, mixed.

Interface-local groups only (ff11::, scope 1), like the bench: nothing leaves the host.
"""

from __future__ import annotations

import argparse
import ipaddress
import json
import os
import random
import socket
import struct
import sys
import time
from collections import Counter

import can
import msgpack

from ballbeam.config import BusSection
from ballbeam.protocol.frames import (
    PLANT_STATUS_FIELDS,
    PLANT_STATUS_ID,
    PLANT_STATUS_VALUE_MAX,
    SENSOR_ID,
    TRUTH_ANGLE_ID,
    TRUTH_BALL_ID,
    VOLTAGE_COMMAND_ID,
    FrameContract,
    e2e_profile5_crc,
)
from ballbeam.protocol.secoc import FrameAuthenticator, is_authenticated_length
from ballbeam.runtime.bus import open_bus

OUR_IDS = (VOLTAGE_COMMAND_ID, SENSOR_ID, TRUTH_ANGLE_ID, TRUTH_BALL_ID, PLANT_STATUS_ID)
# Every standard identifier that is not ours, listed once: a flood draws thousands a second.
FOREIGN_IDS = tuple(i for i in range(0x800) if i not in OUR_IDS)
BURST_PERIOD_NS = 1_000_000
KINDS = (
    ("foreign_id", 30),
    ("bad_crc", 30),
    ("wrong_length", 15),
    ("extended_id", 15),
    ("remote_frame", 3),
    ("error_frame", 3),
    ("raw_datagram", 4),
)


ATTACK_KINDS = (("forged_mac", 30), ("replayed", 40), ("classic_valid", 15), ("random", 15))
REPLAY_KEPT = 4096


class Attacker:
    """What ``--attack`` sends: forged and replayed authenticated frames, valid classic ones."""

    def __init__(self, rng: random.Random, contract: FrameContract) -> None:
        self.rng = rng
        self.contract = contract
        self.forger = FrameAuthenticator(rng.randbytes(32))  # not the run's secret
        self.heard: list[can.Message] = []

    def listen(self, bus: can.BusABC, limit: int) -> None:
        """Keep authenticated frames heard since the last call (at most ``limit``)."""
        for _ in range(limit):
            try:
                message = bus.recv(timeout=0.0)
            except can.CanOperationError:
                continue
            if message is None:
                return
            data = bytes(message.data)
            if (
                is_authenticated_length(len(data))  # 24 bytes, or 64 with a look-ahead
                and not message.is_extended_id
                and not self.forger.authentic(message.arbitration_id, data)  # not our own
            ):
                self.heard.append(message)
                if len(self.heard) > REPLAY_KEPT:
                    del self.heard[: REPLAY_KEPT // 2]

    def make(self, kind: str) -> tuple[str, can.Message | bytes]:
        rng = self.rng
        if kind == "replayed" and self.heard:
            # Half the time one of the latest frames (a reorder), else any older one.
            if rng.random() < 0.5:
                pick = self.heard[-rng.randrange(1, min(4, len(self.heard)) + 1)]
            else:
                pick = rng.choice(self.heard)
            return kind, can.Message(arbitration_id=pick.arbitration_id, data=bytes(pick.data),
                                     is_extended_id=False, is_fd=True)
        if kind in ("forged_mac", "replayed"):
            arbitration_id = rng.choice(OUR_IDS)
            payload = _valid_payload(rng, self.contract, arbitration_id)
            return "forged_mac", can.Message(
                arbitration_id=arbitration_id, data=self.forger.protect(arbitration_id, payload),
                is_extended_id=False, is_fd=True,
            )
        if kind == "classic_valid":
            arbitration_id = rng.choice(OUR_IDS)
            return kind, can.Message(arbitration_id=arbitration_id, is_extended_id=False,
                                     data=_valid_payload(rng, self.contract, arbitration_id))
        noise = rng.choice(("foreign_id", "bad_crc", "wrong_length", "extended_id"))
        return noise, make_frame(rng, self.contract, noise)


def _bad_crc_payload(rng: random.Random, arbitration_id: int) -> bytes:
    data = bytearray(rng.randbytes(8))
    good = e2e_profile5_crc(data, arbitration_id)
    if data[0] | data[1] << 8 == good:
        data[0] ^= 0x01
    return bytes(data)


def _valid_payload(rng: random.Random, contract: FrameContract, arbitration_id: int) -> bytes:
    counter = rng.randrange(256)
    if arbitration_id == VOLTAGE_COMMAND_ID:
        return contract.encode_voltage_command(
            counter, rng.choice((-5.0, 5.0)), True, rng.randrange(256)
        )
    if arbitration_id == SENSOR_ID:
        return contract.encode_sensor(
            counter, rng.choice((-32768, 32767)), rng.choice((-32768, 32767)), 0
        )
    if arbitration_id == TRUTH_ANGLE_ID:
        return contract.encode_truth_angle(counter, rng.uniform(-5, 5), rng.uniform(-50, 50))
    if arbitration_id == PLANT_STATUS_ID:  # a counter at its ceiling, final or not
        return contract.encode_plant_status(
            counter, rng.randrange(len(PLANT_STATUS_FIELDS)), rng.random() < 0.5,
            PLANT_STATUS_VALUE_MAX,
        )
    return contract.encode_truth_ball(counter, rng.uniform(-0.5, 0.5), rng.uniform(-5, 5))


def _raw_datagram(rng: random.Random) -> bytes:
    choice = rng.randrange(3)
    if choice == 0:
        return rng.randbytes(rng.randrange(1, 64))
    if choice == 1:
        return msgpack.packb([1, 2, 3])  # type: ignore[no-any-return]
    return msgpack.packb(  # type: ignore[no-any-return]
        {
            "timestamp": 0.0,
            "arbitration_id": "0x101",
            "is_extended_id": False,
            "is_remote_frame": False,
            "is_error_frame": False,
            "channel": None,
            "dlc": 8,
            "data": bytes(8),
            "is_fd": False,
            "bitrate_switch": False,
            "error_state_indicator": False,
        },
        use_bin_type=True,
    )


def make_frame(rng: random.Random, contract: FrameContract, kind: str) -> can.Message | bytes:
    """One piece of noise of ``kind``: a CAN message, or raw datagram bytes."""
    if kind == "raw_datagram":
        return _raw_datagram(rng)
    if kind == "foreign_id":
        arbitration_id = rng.choice(FOREIGN_IDS)
        return can.Message(
            arbitration_id=arbitration_id,
            is_extended_id=False,
            data=rng.randbytes(rng.randrange(9)),
        )
    arbitration_id = rng.choice(OUR_IDS)
    if kind == "bad_crc":
        return can.Message(
            arbitration_id=arbitration_id,
            is_extended_id=False,
            data=_bad_crc_payload(rng, arbitration_id),
        )
    if kind == "wrong_length":
        return can.Message(
            arbitration_id=arbitration_id,
            is_extended_id=False,
            data=rng.randbytes(rng.randrange(8)),
        )
    if kind == "extended_id":
        return can.Message(
            arbitration_id=arbitration_id,
            is_extended_id=True,
            data=_valid_payload(rng, contract, arbitration_id),
        )
    if kind == "remote_frame":
        return can.Message(
            arbitration_id=arbitration_id, is_extended_id=False, is_remote_frame=True, dlc=8
        )
    if kind == "error_frame":
        return can.Message(
            arbitration_id=arbitration_id,
            is_extended_id=False,
            is_error_frame=True,
            data=_bad_crc_payload(rng, arbitration_id),
        )
    raise ValueError(f"unknown kind {kind!r}")


def _wait_for_cue(bus: can.BusABC, contract: FrameContract, cue: str, timeout_s: float) -> bool:
    wanted = VOLTAGE_COMMAND_ID if cue == "command" else SENSOR_ID
    give_up = time.monotonic() + timeout_s
    while (remaining := give_up - time.monotonic()) > 0:
        try:
            message = bus.recv(timeout=min(remaining, 0.1))
        except can.CanOperationError:
            continue
        if message is None or message.arbitration_id != wanted or message.is_extended_id:
            continue
        data = bytes(message.data)[:8]  # an authenticated frame carries the classic one first
        try:
            frame = contract.decode(message.arbitration_id, data)
        except ValueError:
            continue
        if cue == "sensor" or getattr(frame, "enable", False):
            return True
    return False


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--channel", required=True, help="an interface-local ff11:: group")
    parser.add_argument("--port", type=int, default=43113)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--rate-hz", type=int, default=3000)
    parser.add_argument("--max-frames", type=int, default=20_000)
    parser.add_argument("--max-seconds", type=float, default=3.0)
    parser.add_argument("--start-on", choices=("command", "sensor"), default="command")
    parser.add_argument("--wait", type=float, default=30.0)
    parser.add_argument(
        "--attack", action="store_true",
        help="forged, replayed and valid-classic frames against an authenticated bus",
    )
    parser.add_argument(
        "--raw-weight",
        type=int,
        default=dict(KINDS)["raw_datagram"],
        help="relative weight of raw datagrams (the others sum to 96)",
    )
    args = parser.parse_args(argv)
    address = ipaddress.IPv6Address(args.channel)  # ValueError for anything but IPv6
    if not address.is_multicast or address.packed[1] & 0x0F != 1:
        parser.error(f"{args.channel} is not an interface-local (ff11::) multicast group")
    if not (
        0 < args.rate_hz <= 10_000
        and 0 < args.max_frames <= 20_000
        and 0 < args.max_seconds <= 3.0
        and 0 < args.wait <= 60
        and 0 <= args.raw_weight <= 1000
    ):
        parser.error("out of bounds: rate ≤ 10 kHz, ≤ 20k frames, ≤ 3 s, wait ≤ 60 s")

    rng = random.Random(args.seed)
    contract = FrameContract.load()
    bus = open_bus(BusSection(channel=args.channel, port=args.port))  # hears its group only
    raw = socket.socket(socket.AF_INET6, socket.SOCK_DGRAM)
    raw.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_MULTICAST_HOPS, struct.pack("@I", 1))
    sent: Counter[str] = Counter()
    try:
        if not _wait_for_cue(bus, contract, args.start_on, args.wait):
            print(json.dumps({"error": f"no {args.start_on} frame seen", "sent": 0}))
            return 1
        kinds = [kind for kind, _ in KINDS]
        weights = [args.raw_weight if kind == "raw_datagram" else weight for kind, weight in KINDS]
        attacker = Attacker(rng, contract) if args.attack else None
        if attacker is None:
            # Noise comes from another node on a real bus, not from the controller's CPU: this
            # process takes only time the run's processes leave idle (unprivileged on two
            # cores, competing with them it starved the loop it was meant to test).
            os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
        else:
            # Not niced: the rate is 5 kHz, and the run's processes are SCHED_FIFO in
            # real time, so the attacker cannot starve them (niced on a loaded 2-core machine
            # it reached 2.9 kHz).
            kinds = [kind for kind, _ in ATTACK_KINDS]
            weights = [weight for _, weight in ATTACK_KINDS]
        per_burst = max(1, args.rate_hz * BURST_PERIOD_NS // 1_000_000_000)
        start_ns = due_ns = time.monotonic_ns()
        stop_ns = start_ns + int(args.max_seconds * 1e9)
        total = 0
        while total < args.max_frames and due_ns < stop_ns:
            if attacker is not None:
                attacker.listen(bus, 64)
            for _ in range(min(per_burst, args.max_frames - total)):
                kind = rng.choices(kinds, weights)[0]
                if attacker is not None:
                    kind, item = attacker.make(kind)
                else:
                    item = make_frame(rng, contract, kind)
                try:
                    if isinstance(item, bytes):
                        raw.sendto(item, (args.channel, args.port))
                    else:
                        bus.send(item)
                except (OSError, can.CanError):
                    sent["send_failed"] += 1
                    continue
                sent[kind] += 1
                total += 1
            due_ns += BURST_PERIOD_NS
            if (sleep_ns := due_ns - time.monotonic_ns()) > 0:
                time.sleep(sleep_ns * 1e-9)
        elapsed_s = (time.monotonic_ns() - start_ns) * 1e-9
    finally:
        raw.close()
        bus.shutdown()
    print(
        json.dumps(
            {
                "sent": sum(v for k, v in sent.items() if k != "send_failed"),
                "by_kind": dict(sent),
                "elapsed_s": elapsed_s,
            }
        )
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
