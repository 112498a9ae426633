"""The ticker's schedule against a fake clock: cycles stay tied to wall time."""

from __future__ import annotations

import numpy as np
import pytest

from ballbeam.runtime import ticker as ticker_module
from ballbeam.runtime.ticker import Ticker

PERIOD_NS = 1_000_000


class FakeClock:
    """monotonic_ns and sleep; a sleep may be 'preempted' and wake later than asked."""

    def __init__(self) -> None:
        self.now_ns = 0
        self.oversleep_ns: list[int] = []  # extra delay of each sleep, in order
        self.cpu_ns = 0  # the thread's CPU time: what a test says its cycles used
        self.slept_ns: list[int] = []

    def monotonic_ns(self) -> int:
        self.now_ns += 1_000  # each reading costs a microsecond, as spinning does
        return self.now_ns

    def thread_time_ns(self) -> int:
        return self.cpu_ns

    def sleep(self, seconds: float) -> None:
        extra_ns = self.oversleep_ns.pop(0) if self.oversleep_ns else 0
        self.slept_ns.append(round(seconds * 1e9))
        self.now_ns += round(seconds * 1e9) + extra_ns


@pytest.fixture
def clock(monkeypatch: pytest.MonkeyPatch) -> FakeClock:
    fake = FakeClock()
    monkeypatch.setattr(ticker_module, "time", fake)
    return fake


def test_on_time_cycles_follow_the_deadlines(clock: FakeClock) -> None:
    ticker = Ticker(PERIOD_NS, spin_ns=100_000, start_ns=0)
    ticks = [ticker.wait() for _ in range(5)]
    assert [t.cycle for t in ticks] == [0, 1, 2, 3, 4]
    assert all(t.skipped == 0 and 0 <= t.lateness_ns < 5_000 for t in ticks)
    assert ticker.overruns == 0


def test_a_cycle_that_overran_skips_the_periods_it_missed(clock: FakeClock) -> None:
    ticker = Ticker(PERIOD_NS, spin_ns=100_000, start_ns=0)
    ticker.wait()
    clock.now_ns += 3_400_000  # cycle 0's work took 3.4 ms
    tick = ticker.wait()
    assert (tick.cycle, tick.skipped) == (3, 2)
    assert tick.deadline_ns == 3 * PERIOD_NS and 0 <= tick.lateness_ns < PERIOD_NS
    assert ticker.overruns == 1


def test_a_wait_preempted_past_whole_periods_starts_the_period_it_wakes_in(
    clock: FakeClock,
) -> None:
    """Woken 3.7 ms after its deadline, the cycle is the one of the period it starts in, not
    the old one (which ran on the newest sensor sample as if it were the old period's: the
    servo looked 0.5° ahead of where it was)."""
    ticker = Ticker(PERIOD_NS, spin_ns=0, start_ns=0)
    ticker.wait()
    clock.oversleep_ns = [3_700_000]
    tick = ticker.wait()
    assert (tick.cycle, tick.skipped) == (4, 3)
    assert tick.deadline_ns == 4 * PERIOD_NS and 0 <= tick.lateness_ns < PERIOD_NS
    # Lateness plus skipped periods: how far behind its schedule the loop got, as before.
    assert tick.lateness_ns + tick.skipped * PERIOD_NS >= 3_700_000
    assert ticker.overruns == 1
    assert ticker.wait().cycle == 5


def test_catch_up_moves_a_cycle_preempted_after_its_start_to_the_present_period(
    clock: FakeClock,
) -> None:
    """A cycle that lost the CPU after it started, before it read its inputs, is moved to the
    period the clock is in: the periods between are skipped, the next wait follows on."""
    ticker = Ticker(PERIOD_NS, spin_ns=0, start_ns=0)
    tick = ticker.wait()
    assert ticker.catch_up(tick) == tick  # still its own period
    clock.now_ns += 2_500_000
    moved = ticker.catch_up(tick)
    assert (moved.cycle, moved.skipped, moved.deadline_ns) == (2, 2, 2 * PERIOD_NS)
    assert ticker.overruns == 1
    assert ticker.wait().cycle == 3


def test_a_logs_lateness_counts_the_periods_skipped_before_a_cycle() -> None:
    """A cycle that ran as the period it woke in has its own lateness under a period; how far
    behind its schedule the loop was is that plus the periods it skipped (summary, report)."""
    from ballbeam.evaluation.summary import behind_schedule_ns

    timing = np.zeros(5, dtype=[("deadline_ns", "i8"), ("lateness_ns", "i8"), ("skipped", "i8")])
    timing["deadline_ns"] = np.array([0, 1, 2, 6, 7]) * PERIOD_NS
    timing["skipped"] = [0, 0, 0, 3, 0]
    timing["lateness_ns"] = [10_000, 20_000, 30_000, 40_000, 50_000]
    assert behind_schedule_ns(timing).tolist() == [10_000, 20_000, 30_000, 3_040_000, 50_000]


def test_it_spins_only_while_the_loops_cpu_time_leaves_room(clock: FakeClock) -> None:
    """A spin is CPU time, and SCHED_FIFO tasks that use 95 % of a CPU for a second are stopped
    for the rest of it (kernel.sched_rt_runtime_us): once the loop's average CPU time a cycle
    and the spin would pass SPIN_CPU_SHARE of the period, the ticker sleeps to the deadline
    instead, and spins again once the average has come down."""
    spin_ns = 200_000
    ticker = Ticker(PERIOD_NS, spin_ns=spin_ns, start_ns=0)
    ticker.wait()

    def cycles(cpu_ns: int, count: int) -> list[bool]:
        spun = []
        for _ in range(count):
            clock.now_ns += cpu_ns  # the cycle's work, all of it on the CPU
            clock.cpu_ns += cpu_ns
            before = clock.now_ns
            tick = ticker.wait()
            slept_to_ns = before + clock.slept_ns[-1]
            assert tick.lateness_ns < 10_000
            # (each clock reading costs the fake a microsecond)
            spun.append(abs(slept_to_ns - (tick.deadline_ns - spin_ns)) < 5_000)
        return spun

    assert all(cycles(500_000, 200))  # 50 % and the spin: room
    busy = cycles(750_000, 200)  # 75 %: once the average passes 70 %, no spin
    assert busy[0] and not any(busy[150:])
    light = cycles(300_000, 200)
    assert not light[0] and all(light[100:])
    # an exponential average over CPU_AVERAGE_PERIODS: 200 periods on, the step has decayed
    left = (1 - 1 / ticker_module.CPU_AVERAGE_PERIODS) ** 200
    assert ticker.cycle_cpu_ns == pytest.approx(300_000 + left * 450_000, rel=0.01)
