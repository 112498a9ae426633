"""Issue 27's re-planning law (``replanning.py``) behind the controller seam (``law.py``), its
plans solved off the cycle.

The law never solves inside its step: when it wants a plan it issues a request (the state,
target, identified model and limits the solver would get; ``replanning.PlanRequest``), which
whoever runs it hands to a planner: ``solve_plan_request`` in this process (``ballbeam
simulate``), or the daemon's planner process (``runtime/planner.py``). The answer comes back
through :meth:`ReplanningLaw.offer` and is taken at the first step at least
``plan_delay_cycles`` after the request, or later if it came later (real time: the cycle it
arrived); the first plan, from the run's start, is asked for before the run and is due at its
first cycle. One request is outstanding at most; a plan wanted meanwhile is asked for afresh from
the state after the answer. So offline and lock-step (where the daemon waits for each answer
before the cycle it is due) take the same answers at the same cycles, whatever the solver's
speed.

Each answer taken is in the step's output (``PlanTaken``: the cycle, the request's cycle,
the plan or none), recorded on ``/plans``. A replay gives the law the recorded answers
(``recorded``): each is offered at the cycle the run took it, nothing is solved, and the
re-run follows the run's plans whatever today's planner would give. Each design the law takes
(the one it starts with, at cycle 0, and each re-design) is an answer too, recorded whole: its
Riccati equations' last bits are the machine's LAPACK's, so a replay takes the run's designs,
and the law's cycle is plain float arithmetic (``replanning.filter_step``): a run re-runs bit
for bit whatever the BLAS kernel.
If the re-run's request is not the one the recorded answer answered, the replay says so
(``plan_mismatch``).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping

import numpy as np

from ballbeam.core.control import CycleOutput, PlanTaken
from ballbeam.core.model import as_row4
from ballbeam.core.plant import SensorReading
from ballbeam.core.replanning import (
    DesignAnswer,
    DesignRequest,
    PlanAnswer,
    PlanRequest,
    ReplanningController,
    Settings,
    answer_with_design,
    solve_design_request,
)
from ballbeam.core.task import SineWave, Task

# The oldest sample the law takes late, in cycles back (older ones are history).
LATE_SAMPLE_RERUN_CYCLES = 8

# A step of the task takes effect at the first cycle at or after its instant: the cycle's time
# k·period is computed with rounding, so the instant is looked up this much later.
_CYCLE_TIME_SLACK_S = 1e-9

Request = PlanRequest | DesignRequest
Answer = PlanAnswer | DesignAnswer
Planner = Callable[[Request], Answer]


class ReplanningLaw:
    """:class:`~ballbeam.core.replanning.ReplanningController` as a :class:`ControlLaw`.

    ``encoder_step_rad`` and ``adc_step_m`` turn sensor counts into θ and x; ``task`` gives
    the target at each cycle's time; ``plan_delay_cycles``: the fewest cycles from a request
    to the step that takes its answer (≥ 1); ``planner``: solves requests in this process
    (None: the caller takes them, :meth:`take_request`, and offers the answers);
    ``recorded`` (a replay): the answers the run took, by the cycle it took each."""

    def __init__(
        self,
        settings: Settings,
        initial_state: np.ndarray,
        task: Task,
        encoder_step_rad: float,
        adc_step_m: float,
        *,
        plan_delay_cycles: int,
        planner: Planner | None = None,
        recorded: Mapping[tuple[int, bool], PlanTaken] | None = None,
    ) -> None:
        if plan_delay_cycles < 1:
            raise ValueError("a plan takes effect one cycle after its request at the soonest")
        # The identification's noise test, imported before the run, not by a cycle that must
        # learn windows itself (a daemon whose planner is lost): the import takes a second.
        import scipy.stats  # noqa: F401
        self.task = task
        self.encoder_step_rad = encoder_step_rad
        self.adc_step_m = adc_step_m
        self.plan_delay_cycles = plan_delay_cycles
        self.planner = planner
        self.recorded = recorded
        sine = (
            (task.amplitude_m, task.period_s, task.offset_m) if isinstance(task, SineWave)
            else None
        )
        self.controller = ReplanningController(
            settings, np.array(initial_state, dtype=float), target_m=task.target_at(0.0),
            sine=sine,
        )
        self.controller.deferred = True
        # The design the law starts with (its Riccati solutions are this machine's LAPACK's):
        # recorded as a re-design taken at cycle 0, and a replay starts from the run's.
        started = recorded.get((0, True)) if recorded is not None else None
        if recorded is not None:
            recorded = {key: taken for key, taken in recorded.items() if key != (0, True)}
            self.recorded = recorded
        if started is not None and started.design_made is not None:
            self.controller.design = started.design_made
        # The first plan is asked for now, from the run's start (the plant holds the ball
        # until the first command): it is due at the first cycle, so a runner solves it
        # before the run begins instead of the run starting with no plan.
        self.controller.request_plan(self.controller.initial_state)
        self._initial = self.controller.outstanding
        self._cycle = 0
        self._first_cycle = 0  # the law's cycle of the controller's first step
        # offered, by (a design's?, the request's cycle)
        self._answers: dict[tuple[bool, int], Answer] = {}
        self._issued: list[Request] = []  # for the caller to take
        self._taken: list[PlanTaken] = [  # since the last output
            PlanTaken(0, 0, None, design=True, design_made=self.controller.design)
        ]
        if recorded is None and self._initial is not None:
            if planner is not None:
                self.offer(planner(self._initial))
            else:
                self._issued.append(self._initial)
        # Set when a replayed cycle took a recorded answer to a request the re-run did not
        # make (or has none outstanding): the first such difference, in words.
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

    @property
    def late_reading_cycles(self) -> int:
        # Taking a late sample runs the filter again over every period since: its cost grows
        # with the sample's age, and a loop behind its sample stream would fall further
        # behind on older ones.
        return LATE_SAMPLE_RERUN_CYCLES

    def request_cycle(self, request: Request) -> int:
        """The law's cycle at which ``request`` was made."""
        return self.law_cycle(request.cycle)

    def law_cycle(self, controller_cycle: int) -> int:
        """The law's cycle of the controller's step ``controller_cycle`` (the law's count
        includes the periods coasted before the first reading)."""
        return controller_cycle + self._first_cycle

    def take_requests(self) -> list[Request]:
        """The requests the steps since the last call issued, for the caller's planner."""
        requests, self._issued = self._issued, []
        return requests

    def _due(self, request: Request) -> int:
        """The cycle from which the answer to ``request`` may be taken."""
        if request is self._initial:
            return 0
        return self.request_cycle(request) + self.plan_delay_cycles

    def _outstanding(self, design: bool) -> Request | None:
        return self.controller.design_outstanding if design else self.controller.outstanding

    @property
    def answer_due_cycle(self) -> int | None:
        """The first cycle whose step takes the answer to an outstanding request that is not
        in yet (lock-step waits for it before that step); None when nothing is awaited."""
        due = [
            self._due(request)
            for design in (True, False)
            if (request := self._outstanding(design)) is not None
            and (design, request.cycle) not in self._answers
        ]
        return min(due, default=None)

    def offer(self, answer: Answer) -> None:
        """The planner's answer to a request (taken at the first step it is due; one to a
        request no longer outstanding is dropped then)."""
        self._answers[isinstance(answer, DesignAnswer), answer.request_cycle] = answer

    def step(
        self, reading: SensorReading | None, lateness_ns: int = 0, age_cycles: int = 0
    ) -> CycleOutput:
        controller = self.controller
        if reading is not None and age_cycles > 0:
            # A sample of a cycle that went on without it: the filter takes it at its own
            # cycle and runs again to now (or, older than it takes, it is history); this
            # cycle has no sample of its own.
            if self.started and age_cycles <= self.late_reading_cycles:
                controller.take_late(
                    reading.angle_counts * self.encoder_step_rad,
                    reading.position_counts * self.adc_step_m, age_cycles,
                )
            reading = None
        if reading is None and not self.started:
            raise ValueError("the first control cycle needs a sensor reading")  # as the tracker
        if not self.started:
            self._first_cycle = self._cycle
        if controller.sine is None:
            target_m = self.task.target_at(self._cycle * self.period_s + _CYCLE_TIME_SLACK_S)
            if target_m != controller.target_m:
                controller.set_target(target_m)
        else:
            controller.sine_time_s = self._cycle * self.period_s
        self._take_answer()
        if reading is None:  # no sample: the filter predicts only
            record = controller.step(None, None)
        else:
            record = controller.step(
                reading.angle_counts * self.encoder_step_rad,
                reading.position_counts * self.adc_step_m,
            )
        self._issue()
        self._cycle += 1
        estimate = record.estimate if record.estimate is not None else controller.estimate
        taken, self._taken = tuple(self._taken), []
        return CycleOutput(
            record.command_v, record.plan_drive_v, as_row4(estimate), reading is not None,
            as_row4(record.plan_state), record.feedforward_v, taken,
        )

    def coast(
        self, held_voltage_v: float, count: int, lookahead_v: tuple[float, ...] = ()
    ) -> None:
        """Periods the law made no command for: the filter predicts each on what the plant
        drove (the look-ahead's entries, then its last; without one the held command) and
        the plan's clock runs on; before the first reading only the count advances. Nothing
        is decided in them: answers, targets and plans wait for the next step."""
        if not self.started:
            self._cycle += count
            return
        for index in range(count):
            if lookahead_v:
                applied_v = lookahead_v[min(index, len(lookahead_v) - 1)]
            else:
                applied_v = held_voltage_v
            self.controller.coast(applied_v)
            self._cycle += 1
        self._issue()

    def _issue(self) -> None:
        """The requests the controller made: to the planner, or for the caller to take."""
        controller = self.controller
        issued = [r for r in (controller.design_issued, controller.issued) if r is not None]
        controller.issued = controller.design_issued = None
        if self.recorded is None:  # (a replay answers from the log)
            for request in issued:
                if self.planner is not None:
                    self.offer(self.planner(request))
                else:
                    self._issued.append(request)

    def lookahead(self) -> tuple[float, ...]:
        return ()

    def _take_answer(self) -> None:
        """Before the step: the outstanding requests' answers that are in and due (the
        re-design first, as the plan is of the state after it)."""
        controller = self.controller
        if self.recorded is not None:
            self._offer_recorded()
        for design in (True, False):
            request = self._outstanding(design)
            for key in [key for key in self._answers if key[0] == design]:
                if request is None or key[1] < request.cycle:
                    del self._answers[key]  # to a request no longer outstanding
            if request is None:
                continue
            answer = self._answers.get((design, request.cycle))
            if answer is None or self._cycle < self._due(request):
                continue
            del self._answers[design, request.cycle]
            if isinstance(answer, DesignAnswer):
                controller.adopt_design(answer)
                taken = PlanTaken(
                    self._cycle, self.request_cycle(request), None, True, answer.design
                )
            else:
                controller.adopt(answer)
                taken = PlanTaken(self._cycle, self.request_cycle(request), answer.plan)
            self._taken.append(taken)

    def _offer_recorded(self) -> None:
        assert self.recorded is not None
        for design in (True, False):
            taken = self.recorded.get((self._cycle, design))
            if taken is None:
                continue
            request = self._outstanding(design)
            if request is None or self.request_cycle(request) != taken.request_cycle or (
                self._cycle < self._due(request)
            ):
                if self.plan_mismatch is None:
                    what = "re-design" if design else "plan"
                    self.plan_mismatch = (
                        f"the log records the {what} of a request of cycle "
                        f"{taken.request_cycle} taken at cycle {self._cycle}; the re-run's "
                        f"{what} request outstanding then is " + (
                            "none" if request is None
                            else f"of cycle {self.request_cycle(request)}"
                        )
                    )
                continue
            if isinstance(request, DesignRequest):
                # the run's design (a log from before has none: made again from the request)
                self.offer(
                    answer_with_design(request, taken.design_made)
                    if taken.design_made is not None
                    else solve_design_request(request)
                )
            else:
                self.offer(PlanAnswer(request.cycle, taken.plan))
