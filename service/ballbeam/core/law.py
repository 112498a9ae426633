"""What a controller must provide: the seam between a control law and whatever runs it.

The daemon (over the bus, lock-step or real time), the offline simulation and
``replay --verify`` drive a law only through :class:`ControlLaw`, one period at a time. A law
is made in its starting state (its constructor is the start) and then, each period, either
steps on the period's sensor reading or coasts through periods in which it commands nothing
of its own. Two laws implement it: :class:`TrackerLaw` (the paper's time-varying LQ tracker,
``control.py``) and ``replanning_law.ReplanningLaw`` (issue 27's identify-and-re-plan law).

A law must be deterministic in what it is given (no clock, no RNG, no I/O): replay re-runs it
from the recorded readings and must get every command back bit for bit.
"""

from __future__ import annotations

from typing import Protocol

from ballbeam.core.control import (
    ControllerDesign,
    ControllerState,
    CycleOutput,
    coast_cycles,
    control_cycle,
    late_correction,
    lookahead_voltages,
    starting_state,
)
from ballbeam.core.model import Row4
from ballbeam.core.plant import SensorReading


class ControlLaw(Protocol):
    """One control law, carrying its own state from period to period."""

    @property
    def period_s(self) -> float:
        """The control period [s]."""
        ...

    @property
    def cycle(self) -> int:
        """Periods stepped or coasted so far: the index of the next one."""
        ...

    @property
    def started(self) -> bool:
        """Whether a first reading has been taken (before it, a lost sensor is no fault)."""
        ...

    @property
    def late_reading_cycles(self) -> int:
        """The oldest reading ``step`` corrects its estimate by, in cycles back (0: none);
        through an older one it coasts, and the run counts the cycle as one without a
        sample."""
        ...

    def step(
        self, reading: SensorReading | None, lateness_ns: int = 0, age_cycles: int = 0
    ) -> CycleOutput:
        """One period: the command and what the log records of it (estimate, reference, an
        adopted plan). ``reading``: None when no valid sample came in time (the first step
        needs one); ``lateness_ns``: real time, how late the period began; ``age_cycles``:
        the reading is of the period that many cycles back (a loop that read its bus behind
        the stream), not of this one (0). A law that cannot use a late reading coasts."""
        ...

    def coast(
        self, held_voltage_v: float, count: int, lookahead_v: tuple[float, ...] = ()
    ) -> None:
        """``count`` periods with no command of the law's: skipped periods, or a fault's 0 V.
        The plant drove ``lookahead_v`` (sent with the last command) one a period, then held
        its last entry; without one it held ``held_voltage_v``."""
        ...

    def lookahead(self) -> tuple[float, ...]:
        """The commands of the next periods, sent with this one for a plant to drive if the
        next commands are late (real time); () for a law without them."""
        ...


# The coasted cycles a tracker remembers for a late reading (longer ago: it coasts on).
LATE_READING_CYCLES = 32


class TrackerLaw:
    """The paper's tracker (``control.py``) behind the seam: the functions it always ran,
    over its recorded design."""

    def __init__(self, design: ControllerDesign) -> None:
        self.design = design
        self.state: ControllerState = starting_state(design)
        # The predictions of the cycles coasted since the last reading, oldest first (the
        # first is cycle ``_coasted_from``'s): what a late reading corrects from.
        self._coasted: list[Row4] = []
        self._coasted_from = 0
        self._period_ns = round(design.period_s * 1e9)

    @property
    def period_s(self) -> float:
        return self.design.period_s

    @property
    def cycle(self) -> int:
        return self.state.cycle

    @property
    def started(self) -> bool:
        return self.state.prediction is not None

    @property
    def late_reading_cycles(self) -> int:
        return LATE_READING_CYCLES

    def step(
        self, reading: SensorReading | None, lateness_ns: int = 0, age_cycles: int = 0
    ) -> CycleOutput:
        if reading is not None and age_cycles > 0:
            if self._take_late(reading, age_cycles):
                # The estimate is a prediction over the sample's age: the angle guard looks
                # that much further ahead, as it does over the periods a late loop skipped.
                lateness_ns += age_cycles * self._period_ns
            reading = None
        prior = self.state.prediction
        self.state, output = control_cycle(self.design, self.state, reading, lateness_ns)
        if reading is None and prior is not None:
            self._remember([prior])
        else:
            self._coasted, self._coasted_from = [], self.state.cycle
        return output

    def coast(
        self, held_voltage_v: float, count: int, lookahead_v: tuple[float, ...] = ()
    ) -> None:
        priors: list[Row4] = []
        self.state = coast_cycles(
            self.design, self.state, held_voltage_v, count, lookahead_v, priors
        )
        self._remember(priors)

    def _remember(self, priors: list[Row4]) -> None:
        """Keep the priors of the cycles just coasted (they end at the law's cycle)."""
        if not self._coasted:
            self._coasted_from = self.state.cycle - len(priors)
        self._coasted += priors
        excess = len(self._coasted) - LATE_READING_CYCLES
        if excess > 0:
            del self._coasted[:excess]
            self._coasted_from += excess

    def _take_late(self, reading: SensorReading, age_cycles: int) -> bool:
        """Correct the estimate by a reading of ``age_cycles`` ago, if that cycle coasted
        and is remembered; else (a reading taken since is newer, or it is older than kept)
        it is history, and the cycle coasts. Whether it was taken."""
        index = self.state.cycle - age_cycles - self._coasted_from
        if not 0 <= index < len(self._coasted):
            return False
        self.state, later = late_correction(
            self.design, self.state, reading, self._coasted[index:]
        )
        self._coasted, self._coasted_from = list(later), self._coasted_from + index + 1
        return True

    def lookahead(self) -> tuple[float, ...]:
        return lookahead_voltages(self.design, self.state)
