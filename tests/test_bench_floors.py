"""The benchmark's floors (bench/floors.py) do what the bench reports them as doing.

Not timed: these machines are noisy. They check that the bare exchange really trades the
frames it claims over a private ff11 bus, and that the stall probe probes every CPU.
"""

from __future__ import annotations

import importlib
import os
import sys
from pathlib import Path
from types import ModuleType

import pytest

from ballbeam.config import load_config

from .conftest import CONFIGS

BENCH = Path(__file__).resolve().parents[1] / "bench"


@pytest.fixture(scope="module")
def floors() -> ModuleType:
    # On the path, not loaded from its file: the spawned plant side imports it by name.
    if str(BENCH) not in sys.path:
        sys.path.insert(0, str(BENCH))
    return importlib.import_module("floors")


@pytest.mark.bus
@pytest.mark.parametrize(("plant_frames", "poll"), [(1, False), (3, True)])
def test_exchange_floor_answers_every_cycle(
    floors: ModuleType, plant_frames: int, poll: bool
) -> None:
    bus = load_config(CONFIGS / "paper.toml").bus
    row = floors.exchange_floor(bus, cycles=300, plant_frames=plant_frames, poll=poll)
    assert row["cycles"] == 300
    assert row["plant_frames"] == plant_frames
    assert row["cycle_us"] > 0
    assert row["ceiling_x_realtime_at_1khz"] == pytest.approx(1000 / row["cycle_us"])
    # Each side did its share of the work (a silent side would have timed the run out).
    assert row["controller_cpu_us_per_cycle"] > 0
    assert row["plant_cpu_us_per_cycle"] > 0


def test_exchange_floor_keeps_to_a_private_interface_local_group(floors: ModuleType) -> None:
    bus = load_config(CONFIGS / "paper.toml").bus
    private = floors._private_bus(bus)
    assert private.channel != bus.channel
    assert private.channel.startswith("ff11:")
    assert private.port != bus.port


def test_machine_stalls_probes_every_cpu(floors: ModuleType) -> None:
    report = floors.machine_stalls(0.2)
    for cpu in os.sched_getaffinity(0):
        row = report[f"cpu{cpu}"]
        assert row["scheduling"] == "normal"
        over = [row[f"stalls_over_{t}us_per_min"] for t in floors.STALL_THRESHOLDS_US]
        assert over == sorted(over, reverse=True)  # a longer stall is also a shorter one
        assert row["longest_stall_us"] >= 0
