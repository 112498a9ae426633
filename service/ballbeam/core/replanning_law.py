"""Issue 27's re-planning law (``replanning.py``) behind the controller seam (``law.py``).

It is given the task's target schedule (a change of target re-plans from the state then) and,
in a replay, the plans the recorded run adopted: every solve of a cycle at which the run
adopted a plan returns that plan instead of solving, so the re-run follows the recorded plans
whatever the planner or its solver give today (the law's own filter and re-design still go
through BLAS: bit for bit on the kernel the run had, docs/decisions.md). A cycle at which
nothing was recorded solves as the run did; if the re-run then adopts a plan the run did not
(or does not adopt one it did), the replay says so (``plan_mismatch``).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any, TypeVar

import numpy as np

from ballbeam.core.control import CycleOutput
from ballbeam.core.model import as_row4
from ballbeam.core.planning.arcs import ArcPlan
from ballbeam.core.plant import SensorReading
from ballbeam.core.replanning import ReplanningController, Settings
from ballbeam.core.task import Task

T = TypeVar("T")
# A step of the task takes effect at the first cycle at or after its instant: the cycle's time
# k·period is computed with rounding, so the instant is looked up this much later.
_CYCLE_TIME_SLACK_S = 1e-9


class _Controller(ReplanningController):
    """The controller with its solves answered from recorded plans where there are some."""

    recorded: Mapping[int, ArcPlan] | None = None
    law_cycle: int = 0  # the cycle the law is stepping (the daemon's count)

    def _solve(self, solver: Callable[..., T], *args: Any, **kwargs: Any) -> T:
        if self.recorded is not None:
            plan = self.recorded.get(self.law_cycle)
            if plan is not None:
                return plan  # type: ignore[return-value]  # every solver's answer is a plan
        return super()._solve(solver, *args, **kwargs)


class ReplanningLaw:
    """:class:`~ballbeam.core.replanning.ReplanningController` as a :class:`ControlLaw`.

    ``encoder_step_rad`` and ``adc_step_m`` turn sensor counts into θ and x; ``task`` gives
    the target at each cycle's time; ``recorded_plans`` (a replay): the plan adopted at each
    cycle, by cycle."""

    def __init__(
        self,
        settings: Settings,
        initial_state: np.ndarray,
        task: Task,
        encoder_step_rad: float,
        adc_step_m: float,
        recorded_plans: Mapping[int, ArcPlan] | None = None,
    ) -> None:
        self.task = task
        self.encoder_step_rad = encoder_step_rad
        self.adc_step_m = adc_step_m
        self.controller = _Controller(
            settings, np.array(initial_state, dtype=float), target_m=task.target_at(0.0)
        )
        self.controller.recorded = recorded_plans
        self._cycle = 0
        self._adopted: list[tuple[int, ArcPlan]] = []  # since the last output
        # Set when a replayed cycle adopted a plan other than the recorded one, or none where
        # one was recorded: the first such difference, in words.
        self.plan_mismatch: str | None = None

    @property
    def period_s(self) -> float:
        return self.controller.settings.period_s

    @property
    def cycle(self) -> int:
        return self._cycle

    @property
    def started(self) -> bool:
        return self.controller.cycle > 0

    def step(self, reading: SensorReading | None, lateness_ns: int = 0) -> CycleOutput:
        controller = self.controller
        if reading is None and not self.started:
            raise ValueError("the first control cycle needs a sensor reading")  # as the tracker
        target_m = self.task.target_at(self._cycle * self.period_s + _CYCLE_TIME_SLACK_S)
        if target_m != controller.target_m:
            controller.set_target(target_m)
        if reading is None:
            # No sample: the law is told what its estimate expects (a measurement that
            # corrects nothing; the identification learns nothing new from it).
            theta_rad = float(controller.estimate[0])
            position_m = float(controller.estimate[3])
        else:
            theta_rad = reading.angle_counts * self.encoder_step_rad
            position_m = reading.position_counts * self.adc_step_m
        before = controller.plan
        controller.law_cycle = self._cycle
        record = controller.step(theta_rad, position_m)
        adopted = controller.plan if controller.plan is not before else None
        self._check_adoption(adopted)
        if adopted is not None:
            self._adopted.append((self._cycle, adopted))
        self._cycle += 1
        estimate = record.estimate if record.estimate is not None else controller.estimate
        plans, self._adopted = tuple(self._adopted), []
        return CycleOutput(
            record.command_v, record.plan_drive_v, as_row4(estimate), reading is not None,
            as_row4(record.plan_state), record.feedforward_v, plans,
        )

    def coast(
        self, held_voltage_v: float, count: int, lookahead_v: tuple[float, ...] = ()
    ) -> None:
        """Periods without a sample: each is stepped on the estimate's own expectation (the
        plan's clock runs on); before the first reading only the count advances. The law
        models its own commands through them, not the held one (its model of the drive is
        internal): a gap of a few periods costs a small correction afterwards. Plans adopted
        meanwhile come with the next step's output."""
        if not self.started:
            self._cycle += count
            return
        for _ in range(count):
            self._adopted = list(self.step(None).adopted_plans)  # kept for the next output

    def lookahead(self) -> tuple[float, ...]:
        return ()

    def _check_adoption(self, adopted: ArcPlan | None) -> None:
        recorded = self.controller.recorded
        if recorded is None or self.plan_mismatch is not None:
            return
        expected = recorded.get(self._cycle)
        if expected is not None and adopted is not expected:
            self.plan_mismatch = (
                f"the log records a plan adopted at cycle {self._cycle}; the re-run adopted "
                + ("none" if adopted is None else "another")
            )
        elif expected is None and adopted is not None:
            self.plan_mismatch = (
                f"the re-run adopts a plan at cycle {self._cycle}; the log records none there"
            )
