"""The benchmark's floors (bench/floors.py) do what the bench reports them as doing.

Not timed: these machines are noisy. They check that the bare exchange really trades the
frames it claims over a private ff11 bus, and that the stall probe probes every CPU.
"""

from __future__ import annotations

import os
import time
from types import ModuleType

import pytest

from ballbeam.config import load_config
from ballbeam.runtime.bus import INTERFACE_LOCAL_SCOPE, multicast_scope

from .conftest import PAPER, import_bench


@pytest.fixture(scope="module")
def floors() -> ModuleType:
    return import_bench("floors")  # the spawned plant side imports it by name


@pytest.mark.bus
@pytest.mark.parametrize(
    ("plant_frames", "poll", "authenticated"),
    [(1, False, False), (3, True, False), (1, False, True)],
)
def test_exchange_floor_answers_every_cycle(
    floors: ModuleType, plant_frames: int, poll: bool, authenticated: bool
) -> None:
    started = time.monotonic()
    row = floors.exchange_floor(
        load_config(PAPER).bus, cycles=300, plant_frames=plant_frames, poll=poll,
        authenticated=authenticated,
    )
    assert row["authenticated"] is authenticated
    elapsed_s = time.monotonic() - started
    # It returned, so every cycle was answered (a silent side raises). The timed part lies
    # inside the call, and one thread cannot use more CPU than the wall time it ran.
    assert 0 < row["cycle_us"] * 300 * 1e-6 <= elapsed_s
    assert 0 < row["controller_cpu_us_per_cycle"] <= row["cycle_us"] * 1.05
    assert row["plant_cpu_us_per_cycle"] > 0
    assert row["command_resends"] >= 0


def test_the_authenticated_floor_makes_and_judges_frames_as_a_run_does(
    floors: ModuleType,
) -> None:
    """A frame of the authenticated floor is a run's SecOC frame (CAN FD: the plant's 64 bytes,
    as a sensor frame with its truth, the command's 24); the peer with the secret reads its
    cycle, one with another secret refuses it, and a side's own frame heard back is its echo,
    not a cycle."""
    secret = bytes(range(32))
    plant, controller = floors._Frames(secret), floors._Frames(secret)
    frame = plant.make(floors.PLANT_BASE_ID, 41)
    assert frame.is_fd and len(frame.data) == 64
    assert controller.cycle_of(frame, own_id=floors.COMMAND_ID) == 41
    assert floors._Frames(bytes(32)).cycle_of(frame, own_id=floors.COMMAND_ID) is None
    command = controller.make(floors.COMMAND_ID, 41)
    assert command.is_fd and len(command.data) == 24
    assert controller.cycle_of(command, own_id=floors.COMMAND_ID) is None
    assert plant.cycle_of(command, own_id=-1) == 41
    plain = floors._Frames(None).make(floors.PLANT_BASE_ID, 7)
    assert not plain.is_fd and floors._Frames(None).cycle_of(plain, own_id=-1) == 7


def test_exchange_floor_keeps_to_a_private_interface_local_group(floors: ModuleType) -> None:
    bus = load_config(PAPER).bus
    private = floors._private_bus(bus)
    assert private.channel != bus.channel
    assert multicast_scope(private.channel) == INTERFACE_LOCAL_SCOPE
    assert private.port != bus.port


def test_machine_stalls_probes_every_cpu(floors: ModuleType) -> None:
    report = floors.machine_stalls(0.2)
    for cpu in os.sched_getaffinity(0):
        row = report[f"cpu{cpu}"]
        assert row["scheduling"] == "normal"
        over = [row[f"stalls_over_{t}us_per_min"] for t in floors.STALL_THRESHOLDS_US]
        assert over == sorted(over, reverse=True)  # a longer stall is also a shorter one
        assert row["longest_stall_us"] >= 0
