"""What frame authentication costs (protocol/secoc.py), per frame, in this interpreter.

    .venv/bin/python bench/secoc_cost.py            # 200,000 frames each
    .venv/bin/python bench/secoc_cost.py --frames 20000

Times ``protect`` (a sender's cost: freshness, HMAC-SHA256, truncation, the memory of what it
sent), ``verify`` of good frames (a receiver's), ``verify`` of forged frames (what a flood
costs: one HMAC each, refused) and ``own_frame`` (the daemon's test of its own echo), against
the classic contract's encode and decode of the same payload. Prints median of 5 repeats, µs
per frame.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time
from collections.abc import Callable

from ballbeam.protocol.frames import VOLTAGE_COMMAND_ID, FrameContract, VoltageCommand
from ballbeam.protocol.secoc import FrameAuthenticator

REPEATS = 5


def per_frame_us(action: Callable[[int], object], frames: int) -> float:
    times = []
    for _ in range(REPEATS):
        start = time.perf_counter_ns()
        for index in range(frames):
            action(index)
        times.append((time.perf_counter_ns() - start) / frames / 1e3)
    return round(statistics.median(times), 3)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=200_000)
    args = parser.parse_args()
    frames = args.frames
    contract = FrameContract.load()
    secret = os.urandom(32)
    payload = contract.encode(VoltageCommand(1, 1.25, True, 3))[1]
    sender = FrameAuthenticator(secret)
    protected = [sender.protect(VOLTAGE_COMMAND_ID, payload) for _ in range(frames)]
    forged = [FrameAuthenticator(os.urandom(32)).protect(VOLTAGE_COMMAND_ID, payload)] * frames

    def verify_good(index: int) -> object:
        return receivers[-1].verify(VOLTAGE_COMMAND_ID, protected[index])

    receivers: list[FrameAuthenticator] = []
    results: dict[str, float] = {}
    results["classic_encode_us"] = per_frame_us(
        lambda i: contract.encode_voltage_command(i & 0xFF, 1.25, True, 3), frames)
    results["classic_decode_us"] = per_frame_us(
        lambda i: contract.decode(VOLTAGE_COMMAND_ID, payload), frames)
    results["protect_us"] = per_frame_us(
        lambda i: FrameAuthenticator.protect(sender, VOLTAGE_COMMAND_ID, payload), frames)
    good = []
    for _ in range(REPEATS):  # each repeat a fresh receiver: every frame is new to it
        receivers.append(FrameAuthenticator(secret))
        start = time.perf_counter_ns()
        for index in range(frames):
            verify_good(index)
        good.append((time.perf_counter_ns() - start) / frames / 1e3)
    results["verify_good_us"] = round(statistics.median(good), 3)
    receiver = FrameAuthenticator(secret)
    results["verify_forged_us"] = per_frame_us(
        lambda i: receiver.verify(VOLTAGE_COMMAND_ID, forged[i]), frames)
    echo = FrameAuthenticator(secret)
    echoes = [echo.protect(VOLTAGE_COMMAND_ID, payload) for _ in range(min(frames, 50_000))]
    results["own_frame_us"] = per_frame_us(
        lambda i: echo.own_frame(VOLTAGE_COMMAND_ID, echoes[i % len(echoes)]), len(echoes))
    print(json.dumps({"frames": frames, **results}, indent=2))


if __name__ == "__main__":
    main()
