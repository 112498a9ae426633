"""Fixed-rate scheduling on absolute deadlines (``due += period``), never ``sleep(period)``.

Waiting sleeps until shortly before the deadline, then spins on the monotonic clock: the
kernel's wake-up jitter is tens of microseconds, the spin's is about one.
"""

from __future__ import annotations

import contextlib
import os
import time
from dataclasses import dataclass


@dataclass(frozen=True)
class Tick:
    cycle: int  # index of this period since start (skipped periods included)
    deadline_ns: int  # when the cycle was due
    start_ns: int  # when it actually started
    skipped: int  # whole periods skipped because the previous cycle overran

    @property
    def lateness_ns(self) -> int:
        return self.start_ns - self.deadline_ns


# The share of a period's CPU time [%] up to which the ticker spins, on average: a spin is CPU
# time, and under SCHED_FIFO Linux lets real-time tasks use 95 % of a CPU a second
# (kernel.sched_rt_runtime_us), then stops them for the rest of it. A loop spinning before
# every deadline beside cycles busy with a flood of frames got there, and stalled for tens of
# ms once a second while the servo ran into its end stop (docs/decisions.md).
SPIN_CPU_SHARE = 90
# The average is over about this many periods (an exponential one): the kernel's budget is
# a second's, and one long cycle must not stop the spin that the next ones can afford.
CPU_AVERAGE_PERIODS = 64


class Ticker:
    def __init__(self, period_ns: int, spin_ns: int = 200_000, start_ns: int | None = None):
        if period_ns <= 0:
            raise ValueError("period_ns must be positive")
        self.period_ns = period_ns
        self.spin_ns = max(0, min(spin_ns, period_ns))
        self.origin_ns = time.monotonic_ns() if start_ns is None else start_ns
        self._next_cycle = 0
        self.overruns = 0  # cycles that found their deadline already passed by a period
        self.spins_skipped = 0  # waits that slept to the deadline: the loop's CPU left no room
        self._cpu_at_return_ns = time.thread_time_ns()
        self.cycle_cpu_ns = 0.0  # the CPU time a cycle takes, on average (spins not counted)

    def wait(self) -> Tick:
        """Block until the next deadline. A cycle that starts a whole period or more after
        its deadline (the previous one overran, or this process lost the CPU while it
        waited) skips the missed periods (counted) and is the period it starts in: the cycle
        index stays tied to wall time instead of bursting to catch up, and what the cycle
        reads then (the latest sensor sample) is of its own period, not of a later one."""
        deadline_ns = self.origin_ns + self._next_cycle * self.period_ns
        now_ns = time.monotonic_ns()
        if now_ns - deadline_ns < self.period_ns:
            spin_ns = self.spin_ns
            used_ns = time.thread_time_ns() - self._cpu_at_return_ns
            self.cycle_cpu_ns += (used_ns - self.cycle_cpu_ns) / CPU_AVERAGE_PERIODS
            if spin_ns and (self.cycle_cpu_ns + spin_ns) * 100 > self.period_ns * SPIN_CPU_SHARE:
                spin_ns = 0
                self.spins_skipped += 1
            sleep_until_ns = deadline_ns - spin_ns
            if now_ns < sleep_until_ns:
                time.sleep((sleep_until_ns - now_ns) * 1e-9)
            while (now_ns := time.monotonic_ns()) < deadline_ns:
                pass
        tick = self.catch_up(Tick(self._next_cycle, deadline_ns, now_ns, 0))
        self._cpu_at_return_ns = time.thread_time_ns()
        return tick

    def catch_up(self, tick: Tick) -> Tick:
        """``tick`` while its period is the present one; once the clock is a whole period or
        more past its deadline, the tick of the period it is in now, the periods between
        skipped (counted). The loop asks again after reading its inputs: preempted before it
        read them, it would take the newest sample for its old period's."""
        # Preempted in the sleep, a loop woke 3–4 ms late and ran the old period on the
        # newest sample (20 times in 6 s beside two CPU hogs, unprivileged): it took the
        # servo for 0.5° ahead of where it was and cut the drive on the last swing.
        now_ns = time.monotonic_ns()
        behind = (now_ns - tick.deadline_ns) // self.period_ns
        if behind <= 0:
            self._next_cycle = tick.cycle + 1
            return tick
        if not tick.skipped:
            self.overruns += 1
        cycle = tick.cycle + behind
        self._next_cycle = cycle + 1
        return Tick(
            cycle=cycle, deadline_ns=tick.deadline_ns + behind * self.period_ns,
            start_ns=now_ns, skipped=tick.skipped + behind,
        )

def worst_lateness_ns(period_ns: int, duration_s: float, spin_ns: int) -> int:
    """Run an empty loop on this ticker's schedule for ``duration_s``: the worst lateness of a
    cycle's start [ns] (a skipped period counts as the time since its deadline). What the
    process's scheduling gets it on this machine now, measured the way the loop will run."""
    ticker = Ticker(period_ns, spin_ns=spin_ns)
    worst_ns = 0
    for _ in range(max(int(duration_s * 1e9 // period_ns), 1)):
        tick = ticker.wait()
        worst_ns = max(worst_ns, tick.lateness_ns + tick.skipped * period_ns)
    return worst_ns


def spin_ns_for_this_process(spin_us: int) -> int:
    """The spin before each deadline, where it pays: under SCHED_FIFO nothing of lower priority
    runs meanwhile, and it turns the kernel's wake-up jitter into about a microsecond. At normal
    priority the spin uses up the share of the CPU the scheduler grants next to CPU-bound jobs,
    which then preempt the loop right at its deadlines: with two of them running, an
    unprivileged run overran 560–740 times in 20 s spinning, 130–270 times not
    (bench/realtime_load.py)."""
    return spin_us * 1000 if scheduled_realtime() else 0


def scheduled_realtime() -> bool:
    """Does this process run under a real-time policy (SCHED_FIFO or SCHED_RR)?"""
    return os.sched_getscheduler(0) in (os.SCHED_FIFO, os.SCHED_RR)


def leave_real_time() -> None:
    """Put the calling thread (on Linux policy and CPU mask are a thread's) at normal
    scheduling on any CPU if it inherited the loop's real-time policy and CPU: work that
    serves the loop (its recorder's writer, its planner) must never hold the loop's CPU, nor
    be starved on it. At the loop's own SCHED_FIFO priority on its CPU, a thread keeps that
    CPU until it blocks: the loop's timer wakes it in vain, and it cannot even ask for the
    interpreter lock. At normal priority but still pinned there, it gets only what the loop
    and every other job on that CPU leave (a killed run's log then loses more than a flush).
    Where the system refuses, nothing changes; the kernel keeps the mask within the CPUs the
    process's cgroup allows."""
    with contextlib.suppress(OSError, AttributeError):
        if os.sched_getscheduler(0) != os.SCHED_OTHER:
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    with contextlib.suppress(OSError, AttributeError, TypeError):
        os.sched_setaffinity(0, range(os.cpu_count() or 1))
