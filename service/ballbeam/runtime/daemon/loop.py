"""The controller daemon: a fixed-rate loop (or lock-step) around the pure control law.

Each cycle: the latest valid sample (sensor intake) → control law (observer → tracker → guard)
→ command out; everything heard and done is recorded. It never dies on a bad frame (the
intake counts and records it); losing the plant commands 0 V and records a fault.
"""

from __future__ import annotations

import logging
import math
import time
from collections import Counter, deque
from dataclasses import dataclass, field

import can
import numpy as np

from ballbeam.assembly import counts_per_measurement
from ballbeam.config import Config
from ballbeam.core.control import CycleOutput, PlanTaken
from ballbeam.core.law import ControlLaw
from ballbeam.core.plant import SensorReading
from ballbeam.core.replanning import PlanAnswer, solve_design_request
from ballbeam.core.replanning_law import ReplanningLaw
from ballbeam.errors import BallbeamError
from ballbeam.logs.plan_record import design_json
from ballbeam.logs.recording import RunRecording
from ballbeam.logs.topics import (
    ESTIMATE,
    REFERENCE,
    SENSOR,
    TIMING,
    EstimateRecord,
    ReferenceRecord,
    SensorRecord,
    TimingRecord,
)
from ballbeam.plant_assembly import plant_parameters, sensor_periods_per_cycle
from ballbeam.protocol.frames import COUNTER_MODULUS, SENSOR_ID, CounterCheck, FrameContract
from ballbeam.protocol.secoc import FrameAuthenticator
from ballbeam.runtime.bus import ReceiveQueue, recv_frame
from ballbeam.runtime.daemon.command_out import CommandOut
from ballbeam.runtime.daemon.intake import SensorIntake, SentCommands
from ballbeam.runtime.owner_lock import OwnerLock
from ballbeam.runtime.peer_link import signal_run_over
from ballbeam.runtime.planner import PlannerProcess
from ballbeam.runtime.stop import StopFlag
from ballbeam.runtime.ticker import Ticker, spin_ns_for_this_process

log = logging.getLogger("ballbeam.daemon")

PHASE_PROBE_FRAMES = 20
PHASE_PROBE_S = 0.05
# Valid command frames this daemon never sent before the run ends as "second_writer": one on an
# authenticated bus (only a holder of the run's secret can make one), three on a classic bus
# (a random frame passes the CRC-16 once in 65,536 tries).
SECOND_WRITER_FRAMES_AUTHENTICATED = 1
SECOND_WRITER_FRAMES_CLASSIC = 3
# After the run, how long to listen for the emulator's final counters (it sends them within a
# sensor period or two of hearing that the run is over).
FINAL_STATUS_WAIT_S = 0.5
# Real time: a sample two control periods older than the freshest one was is not a measurement
# of now (a starved daemon reading its socket behind the stream); up to a period older is the
# loop's ordinary jitter (SensorIntake.take).
LATE_SAMPLE_CYCLES = 2
# Measured cycles in a row whose samples must agree on which plant period a cycle is.
PERIOD_OFFSET_AGREEMENT = 8
# Lock-step, waiting for a plan that is due: how often the stop flag is looked at [s].
PLAN_WAIT_POLL_S = 0.1
# ... and how many frames it judges between two looks.
TAKE_IN_WHILE_WAITING = 1000
# A cycle reads its socket for half a period at most, so that a flood cannot hold the loop; a
# daemon behind the stream reads on up to this share of the period [%] to catch up.
CATCH_UP_SHARE = 80


class WorkReserve:
    """The time a cycle's own work (law, commands, records) takes: the median of the last
    WORK_WINDOW cycles' and a quarter more, at most half a period (the loop always reads its
    bus for that long). A median, not a peak: the one long cycle after a stall (it coasts
    through the periods missed) kept a peak high for long after, while the loop read too
    little of its bus to catch up."""

    def __init__(self, period_ns: int) -> None:
        self._recent: deque[int] = deque(maxlen=WORK_WINDOW)
        self._most_ns = period_ns // 2
        self.reserve_ns = 0

    def took(self, work_ns: int) -> None:
        self._recent.append(work_ns)
        median_ns = sorted(self._recent)[len(self._recent) // 2]
        self.reserve_ns = min(median_ns + median_ns // 4, self._most_ns)


WORK_WINDOW = 9


class StandingQueue:
    """Whether the loop stays behind the stream: behind for SHORTEN_AFTER_CYCLES cycles in a
    row, its receive queue goes short; caught up for RESTORE_AFTER_CYCLES, long again. A
    stall's backlog is read in a few tens of cycles; a flood the loop cannot keep up with
    keeps it behind for good."""

    def __init__(self) -> None:
        self.short = False
        self._run = 0  # cycles in a row the other way than the queue is set for

    def update(self, behind: bool) -> bool:
        self._run = self._run + 1 if behind != self.short else 0
        if self._run >= (RESTORE_AFTER_CYCLES if self.short else SHORTEN_AFTER_CYCLES):
            self.short, self._run = not self.short, 0
        return self.short


SHORTEN_AFTER_CYCLES = 100
RESTORE_AFTER_CYCLES = 500


class PlantLostError(BallbeamError, TimeoutError):
    """The plant stopped sending sensor frames."""


@dataclass
class DaemonStats:
    cycles: int = 0
    measured_cycles: int = 0
    coasted_cycles: int = 0
    late_samples: int = 0  # real time: samples read periods after their own (the loop behind)
    late_readings: int = 0  # ... of them, those the law took for the period they are of
    fault_cycles: int = 0
    overruns: int = 0
    skipped_periods: int = 0
    spins_skipped: int = 0  # real time: waits that slept to the deadline, the CPU budget spent
    cycle_cpu_us: int = 0  # ... the CPU time of a cycle at the end (the ticker's average)
    receive_queue_bytes: str = ""  # ... the socket's queue, long / short (ReceiveQueue)
    queue_shortened: int = 0  # ... times the loop stayed behind the stream and cut it short
    command_resends: int = 0
    own_frames: int = 0
    theta_violation_events: int = 0
    authenticated: bool = False
    second_writer_frames: int = 0
    plant_status_snapshots: int = 0  # whole snapshots of the emulator's counters recorded
    plant_status_incomplete: int = 0  # snapshots with a frame lost or out of order
    plan_requests: int = 0  # re-planning law: requests sent to its planner
    plan_answers_taken: int = 0  # ... answers the law took (on /plans)
    plan_errors: int = 0  # ... answers with a failure of the planner's, or none (planner lost)
    rejected: Counter[str] = field(default_factory=Counter)
    end_reason: str = "completed"

    def as_metadata(self, sensor_check: CounterCheck) -> dict[str, str]:
        values: dict[str, object] = {
            key: value for key, value in vars(self).items() if key != "rejected"
        }
        values.update({f"rejected_{reason}": count for reason, count in self.rejected.items()})
        values["rejected_total"] = sum(self.rejected.values())
        values["sensor_frames_lost"] = sensor_check.lost
        values["sensor_frames_repeated"] = sensor_check.repeated
        values["sensor_frames_stale"] = sensor_check.stale
        return {key: str(value) for key, value in values.items()}


class ControllerDaemon:
    def __init__(
        self,
        config: Config,
        law: ControlLaw,
        bus: can.BusABC,
        contract: FrameContract,
        recording: RunRecording,
        stop: StopFlag,
        auth: FrameAuthenticator | None = None,
        run_over_fd: int | None = None,
        emulator_lock: OwnerLock | None = None,
        planner: PlannerProcess | None = None,
    ) -> None:
        """``run_over_fd``: the daemon's end of ``ballbeam run``'s peer link, to tell the
        emulator when the run is over and record its final counters; ``emulator_lock``: the
        robust mutex the emulator holds (runtime/owner_lock.py), to tell a late plant from a
        dead one. ``law``: the control law, in its starting state; ``planner``: a re-planning
        law's planner process (its requests go there, its answers come back each cycle)."""
        self.config = config
        self.run_over_fd = run_over_fd
        self.emulator_lock = emulator_lock
        self.law = law
        self.replanning = law if isinstance(law, ReplanningLaw) else None
        self.planner = planner
        self._plan_waits: dict[int, int] = {}  # request cycle (the law's) → ns to its answer
        # The starting design's record, encoded before the run (the planner encodes the rest)
        self._first_design_json = (
            design_json(self.replanning.controller.design) if self.replanning else None
        )
        self._planner_failing = False
        self._planner_gone = False
        self.angle_per_count, self.position_per_count = counts_per_measurement(config)
        self.bus = bus
        self.recording = recording
        self.stop = stop
        sent = SentCommands()  # what the daemon sent: its echoes are not someone else's
        # One plant sample per counter step: a sensor period in real time, a control period's
        # worth of them per lock-step exchange.
        sample_period_s = 1.0 / config.plant.sensor_rate_hz * (
            sensor_periods_per_cycle(config) if config.run.mode == "lockstep" else 1
        )
        realtime = config.run.mode == "realtime"
        self.intake = SensorIntake(
            contract, recording, sent, sample_period_s, auth,
            late_sample_periods=(
                LATE_SAMPLE_CYCLES * sensor_periods_per_cycle(config) if realtime else None
            ),
        )
        self.commands = CommandOut(bus, contract, recording, sent, auth)
        self.second_writer_limit = (
            SECOND_WRITER_FRAMES_AUTHENTICATED if auth is not None
            else SECOND_WRITER_FRAMES_CLASSIC
        )
        self.period_ns = config.controller.period_ns
        self.sample_periods_per_cycle = sensor_periods_per_cycle(config)
        self.n_cycles = round(config.run.duration_s * config.controller.rate_hz)
        self._stats = DaemonStats(authenticated=auth is not None)
        self.cycles_since_sensor = 0
        self.period_offset: int | None = None  # plant sample counter − cycle, mod 256
        self._offset_candidate, self._offset_agreement = -1, 0
        # Real time, one sample a cycle: commands name their plant period (the look-ahead is
        # aligned with it). Lock-step answers each sample and names it, as before.
        self.names_periods = (
            config.run.mode == "realtime" and sensor_periods_per_cycle(config) == 1
        )
        self.in_fault = False
        self.last_output: CycleOutput | None = None
        self.lookahead_v: tuple[float, ...] = ()  # sent with the last command
        self.wall_origin_ns = time.time_ns()
        self.mono_origin_ns = time.monotonic_ns()
        self.log_time_ns = self.wall_origin_ns
        self.theta_limit_rad = config.limits.theta_rad
        self.outside_limit = False
        # The plant's taps, to log at the first cycle whose sample shows each (the plant's
        # clock counts physics steps from the ball's release, the first cycle's command).
        plant = plant_parameters(config)
        steps_per_cycle = sensor_periods_per_cycle(config) * config.plant.physics_substeps
        self.taps_to_log = [
            (-(-step // steps_per_cycle), step, step * plant.substep_s, change_m_s)
            for step, change_m_s in plant.taps
        ]

    @property
    def stats(self) -> DaemonStats:
        """The run's counts so far (the intake's and the command side's included)."""
        self._stats.own_frames = self.intake.own_frames
        self._stats.rejected = self.intake.rejected
        self._stats.late_samples = self.intake.late_samples
        self._stats.command_resends = self.commands.resends
        self._stats.second_writer_frames = self.intake.second_writer_frames
        self._stats.plant_status_snapshots = self.intake.plant_status.snapshots
        self._stats.plant_status_incomplete = self.intake.plant_status.incomplete
        return self._stats

    @property
    def sensor_check(self) -> CounterCheck:
        return self.intake.sensor_check

    # -- frames -------------------------------------------------------------------------------
    def _recv(self, timeout_s: float, poll_s: float = 0.0) -> can.Message | None:
        """The next message within ``timeout_s``; datagrams that are no frame are rejected."""
        return recv_frame(
            self.bus,
            timeout_s,
            lambda detail: self.intake.reject(
                "malformed", detail, self.log_time_ns, self.law.cycle
            ),
            poll_s,
        )

    def _handle(self, message: can.Message) -> None:
        verdict = self.intake.handle(message, self.log_time_ns, self.law.cycle)
        if (
            self.intake.second_writer_frames >= self.second_writer_limit
            and not self.stop.is_set()
        ):
            # Someone else commands our plant: stop now (the loop ends this cycle and the
            # shutdown sends 0 V, disabled, at once).
            self._fault("second_writer",
                        f"{self.intake.second_writer_frames} valid command frame(s) this daemon "
                        "never sent: another writer commands the plant; stopping at 0 V")
            log.error("a second writer commands the plant: stopping the run at 0 V")
            self._stats.end_reason = "second_writer"
            self.stop.set("second_writer")
        if verdict == "repeated" and self.config.run.mode == "lockstep":
            # The plant resent a sample because our answer was lost: answer again without
            # advancing the controller (so determinism survives frame loss).
            self.commands.resend_last(self.log_time_ns, self.law.cycle)

    def _event(self, kind: str, detail: str) -> None:
        self.recording.event(self.log_time_ns, self.law.cycle, kind, detail)

    def _fault(self, kind: str, detail: str) -> None:
        self.recording.fault(self.log_time_ns, self.law.cycle, kind, detail)

    # -- one cycle ----------------------------------------------------------------------------
    def _cycle(self, lateness_ns: int = 0) -> None:
        recorder_error = self.recording.recorder.error
        if recorder_error is not None and not self.stop.is_set():
            # No run goes on unrecorded: this cycle still commands, then the loop stops at 0 V.
            log.error("recording failed (%s): stopping the run", recorder_error)
            self._stats.end_reason = "recorder_failed"
            self.stop.set("recorder_failed")
        cycle = self.law.cycle
        received = self.intake.take(time.monotonic_ns())
        reading = None
        age_cycles = 0
        if received is not None:
            sample, late_periods = received
            age_cycles = late_periods // self.sample_periods_per_cycle
            if age_cycles and not (
                self.law.started and age_cycles <= self.law.late_reading_cycles
            ):
                received, age_cycles = None, 0  # history: the cycle coasts
        if received is None:
            self.cycles_since_sensor += 1
        else:
            self._stats.late_readings += age_cycles > 0
            reading = SensorReading(sample.angle_counts, sample.position_counts)
            # A late sample still shows the plant alive, and the law takes it for the period
            # it is of: the estimate is of now again.
            self.cycles_since_sensor = 0
            if self.names_periods:
                # a sample read n cycles behind the stream is of the period n back: it tells
                # the offset as well (on a loaded host every sample can come so, for good)
                self._learn_period_offset(sample.counter + age_cycles, cycle)
        timeout = self._sensor_timeout_periods()
        self._take_plans()
        if self.law.started and self.cycles_since_sensor >= timeout:
            self._fault_cycle()
            self._send_plan_request()
            return
        if self.in_fault:
            self.in_fault = False
            self._event("sensor_frames_resumed", f"after {timeout}+ silent periods")
        self._record_sensor(cycle, reading, age_cycles)
        output = self.law.step(reading, lateness_ns, age_cycles)
        self._send_plan_request()
        self.last_output = output
        # What the plant is to drive if the next commands do not come in time (real time).
        self.lookahead_v = self.law.lookahead()
        self._stats.cycles += 1
        if reading is None:
            self._stats.coasted_cycles += 1
        else:
            self._stats.measured_cycles += 1
        self._command(cycle, output.voltage_v, output.requested_v, enable=True,
                      lookahead_v=self.lookahead_v)
        self.recording.release()  # the command is out: what waited is recorded now
        at_ns = self.log_time_ns
        self.recording.write(ESTIMATE, at_ns, EstimateRecord(cycle, *output.estimate))
        self.recording.write(
            REFERENCE, at_ns, ReferenceRecord(cycle, *output.reference, output.reference_input_v)
        )
        for taken in output.adopted_plans:
            self._stats.plan_answers_taken += 1
            wait_ns = None if taken.design else self._plan_waits.pop(taken.request_cycle, None)
            self.recording.plan(at_ns, taken, wait_ns, self._design_json(taken))
        self._watch_theta(output.estimate[0])
        while self.taps_to_log and self.taps_to_log[0][0] <= cycle:
            tap_cycle, step, time_s, change_m_s = self.taps_to_log.pop(0)
            self.recording.tap(at_ns, tap_cycle, time_s, step, change_m_s)

    # -- the re-planning law's planner ---------------------------------------------------------
    def _design_json(self, taken: PlanTaken) -> bytes | None:
        """A design's record as encoded before the cycle (None: the recording encodes it)."""
        if not taken.design or taken.design_made is None:
            return None
        if taken.cycle == 0 and taken.request_cycle == 0:
            made, self._first_design_json = self._first_design_json, None
            return made
        return self.planner.take_design_json(taken.design_made) if self.planner else None

    def _take_plans(self) -> None:
        """Hand the law its planner's answers; lock-step waits for the one due at this cycle
        (so the run equals the offline one), real time never waits (an answer is taken at
        the cycle it came in)."""
        law, planner = self.replanning, self.planner
        if law is None or planner is None:
            return
        lockstep = self.config.run.mode == "lockstep"
        while True:
            due = law.answer_due_cycle
            # (the first plan is waited for in real time too: the run has not begun)
            must_wait = (lockstep or not law.started) and due is not None and due <= law.cycle
            for answer, wait_ns in planner.receive(PLAN_WAIT_POLL_S if must_wait else 0.0):
                if isinstance(answer, PlanAnswer):
                    self._plan_waits[law.law_cycle(answer.request_cycle)] = wait_ns
                    self._planner_error(answer.error)
                law.offer(answer)
            if not planner.alive:
                self._planner_lost()
                return
            if not must_wait or law.answer_due_cycle is None or self.stop.is_set():
                return
            self._take_in_while_waiting()

    def _take_in_while_waiting(self) -> None:
        """Waiting on the planner: judge what the bus brought meanwhile while it is fresh (an
        authenticated frame is refused once it is older than the freshness window, and a
        slow solve can outlast it). The intake alone: a resent sample gets no command
        before the cycle it is for. What the recording held is written first: waiting, the
        loop has no turnaround to spare it, and a held record misses the recorder's flushes."""
        self.recording.release()
        for _ in range(TAKE_IN_WHILE_WAITING):  # bounded: a flood must not hold the wait
            message = self._recv(0.0)
            if message is None:
                return
            self.intake.handle(message, self.log_time_ns, self.law.cycle)

    def _send_plan_request(self) -> None:
        law = self.replanning
        if law is None:
            return
        for request in law.take_requests():
            self._stats.plan_requests += 1
            if self.planner is None or not self.planner.send(request):
                self._planner_lost()

    def _planner_error(self, error: str | None) -> None:
        """A failed solve is an answer of no plan (the law keeps its plan): a fault, once
        for a run of them."""
        if error is not None:
            self._stats.plan_errors += 1
            if not self._planner_failing:
                self._fault("planner_error", f"no plan from the planner ({error}); "
                            "the law keeps its plan")
                log.error("the planner failed: %s", error)
        self._planner_failing = error is not None

    def _planner_lost(self) -> None:
        """The planner process is gone: from now on every request is answered with no plan
        at once (the law keeps its plan and its terminal regulator; recorded as answers)."""
        law = self.replanning
        assert law is not None
        if not self._planner_gone:
            self._planner_gone = True
            pid = self.planner.pid if self.planner is not None else None
            self._fault("planner_lost", f"no planner process (pid {pid}); the law goes on "
                        "without new plans")
            log.error("the planner process ended: no new plans for the rest of the run")
            if self.planner is not None:
                self.planner.close()
                self.planner = None
        request = law.controller.outstanding
        if request is not None:
            self._stats.plan_errors += 1
            law.offer(PlanAnswer(request.cycle, None, error="planner lost"))
        design = law.controller.design_outstanding
        if design is not None:  # made here: a design's solve is tens of ms, not seconds
            law.offer(solve_design_request(design))

    def _learn_period_offset(self, sample_counter: int, cycle: int) -> None:
        """Plant periods and cycles both follow the clock, so the plant period of cycle k is
        k + offset. Now and then a cycle takes the sample of the period before (it came
        late) or after (the cycle started late), and the first cycles take the samples queued
        while the plant waited: an offset counts once PERIOD_OFFSET_AGREEMENT measured cycles
        in a row give it."""
        offset = (sample_counter - cycle) % COUNTER_MODULUS
        if offset == self._offset_candidate:
            self._offset_agreement += 1
        else:
            self._offset_candidate, self._offset_agreement = offset, 1
        if self._offset_agreement >= PERIOD_OFFSET_AGREEMENT:
            self.period_offset = offset

    def _command(
        self, cycle: int, voltage_v: float, requested_v: float, enable: bool,
        lookahead_v: tuple[float, ...] = (),
    ) -> None:
        # The command names the plant period it is for: its sample's, or, coasting, the one
        # the cycle's clock is in. The plant aligns the look-ahead with it, so a command that
        # comes late (this process lost the CPU between reading and sending) still drives its
        # entry for the period it lands in, not its own stale voltage.
        if self.period_offset is not None:
            period_counter = (cycle + self.period_offset) % COUNTER_MODULUS
        else:
            latest = self.intake.latest
            period_counter = latest.counter if latest is not None else 0
        self.commands.send(self.log_time_ns, cycle, voltage_v, requested_v, enable,
                           period_counter, lookahead_v)

    def _sensor_timeout_periods(self) -> int:
        """Silent periods before 0 V: ``sensor_timeout_periods``; with ``ballbeam run``'s link,
        more while the emulator is known alive (its samples are late, the plant is not lost:
        the model carries the estimate), and none once it is known dead."""
        controller = self.config.controller
        lock = self.emulator_lock
        if lock is None or self.cycles_since_sensor == 0:
            return controller.sensor_timeout_periods
        if lock.holder_gone():
            return 1
        if lock.taken:  # and not gone: alive
            return max(controller.sensor_timeout_periods, controller.sensor_timeout_alive_periods)
        return controller.sensor_timeout_periods

    def _record_sensor(
        self, cycle: int, reading: SensorReading | None, age_cycles: int = 0
    ) -> None:
        """``fresh``: 0 none, 1 a sample of this period, 1 + n one of n cycles back."""
        sample = self.intake.latest
        if reading is None or sample is None:
            record = SensorRecord(cycle, 0, 0, 0, 0, 0, math.nan, math.nan)
        else:
            measurement = (
                reading.angle_counts * self.angle_per_count,
                reading.position_counts * self.position_per_count,
            )
            record = SensorRecord(
                cycle, 1 + age_cycles, sample.counter, sample.status, reading.angle_counts,
                reading.position_counts,
                measurement[0] / self.config.model.angle_sensor_gain,
                measurement[1] / self.config.model.position_sensor_gain,
            )
        self.recording.write(SENSOR, self.log_time_ns, record)

    def _fault_cycle(self) -> None:
        """No sensor frame for too long: 0 V, disabled, coast the observer on 0 V."""
        if not self.in_fault:
            self.in_fault = True
            starved = self._starved_note()
            self._fault("sensor_timeout", f"no valid, current sensor frame for "
                        f"{self.cycles_since_sensor} periods; 0 V{starved}")
            log.error("sensor frames lost for %d periods: commanding 0 V%s",
                      self.cycles_since_sensor, starved)
        silent_s = self.cycles_since_sensor * self.period_ns * 1e-9
        if silent_s >= self.config.controller.plant_lost_s and not self.stop.is_set():
            self._fault("plant_lost",
                        f"no current sensor frame for {silent_s:.3f} s{self._starved_note()}")
            self._stats.end_reason = "plant_lost"
            self.stop.set("plant_lost")
        cycle = self.law.cycle
        self._record_sensor(cycle, None)
        self._command(cycle, 0.0, 0.0, enable=False)
        self.lookahead_v = ()  # the plant holds 0 V
        self.law.coast(0.0, 1)
        self._stats.cycles += 1
        self._stats.fault_cycles += 1

    def _starved_note(self) -> str:
        """Samples that came but were read too late to be taken for now: the daemon itself is
        short of CPU, not the plant silent; the user should hear which."""
        late = self.intake.late_samples
        if not late:
            return ""
        return (f" ({late} samples read too late to use so far: this process is short of CPU; "
                "README: real-time scheduling)")

    def _watch_theta(self, theta_estimate_rad: float) -> None:
        outside = abs(theta_estimate_rad) > self.theta_limit_rad + 1e-9
        if outside and not self.outside_limit:
            self._stats.theta_violation_events += 1
            self._event("theta_violation",
                        f"estimated |θ| = {math.degrees(abs(theta_estimate_rad)):.2f}° > "
                        f"{self.config.limits.theta_deg}°")
        self.outside_limit = outside

    def _record_timing(self, deadline_ns: int, start_ns: int, skipped: int) -> None:
        end_ns = time.monotonic_ns()
        self.recording.write(TIMING, self.log_time_ns, TimingRecord(
            self.law.cycle - 1, deadline_ns, start_ns, end_ns, start_ns - deadline_ns, skipped
        ))

    # -- loops --------------------------------------------------------------------------------
    def _wait_for_plant(self) -> int:
        """Block until the first valid sensor frame; its arrival time (monotonic ns)."""
        give_up = time.monotonic() + self.config.controller.start_timeout_s
        while not self.stop.is_set():
            remaining = give_up - time.monotonic()
            if remaining <= 0:
                raise PlantLostError(
                    f"no sensor frame from the plant within "
                    f"{self.config.controller.start_timeout_s} s on "
                    f"{self.config.bus.interface}:{self.config.bus.channel}; is the emulator "
                    "running on the same bus?"
                )
            message = self._recv(min(remaining, 0.1))
            if message is None:
                continue
            arrival_ns = time.monotonic_ns()
            self.log_time_ns = self._wall_ns()
            self._handle(message)
            if self.intake.fresh:
                return arrival_ns
        return time.monotonic_ns()

    def run(self) -> DaemonStats:
        self._event("daemon_start", f"mode={self.config.run.mode}")
        try:
            self._send_plan_request()  # the first plan, due at the first cycle: before the run
            self._take_plans()
            arrival_ns = self._wait_for_plant()
            if not self.stop.is_set():
                if self.config.run.mode == "lockstep":
                    self._run_lockstep()
                else:
                    self._run_realtime(arrival_ns)
        except PlantLostError:
            self._stats.end_reason = "plant_lost"
            raise
        finally:
            self._shutdown()
        return self.stats

    def _run_lockstep(self) -> None:
        silence_s = self.config.controller.lockstep_timeout_s
        poll_s = self.config.run.lockstep_poll_us * 1e-6
        self.wall_origin_ns = self.log_time_ns
        while not self.stop.is_set() and self.law.cycle < self.n_cycles:
            if self.intake.fresh:
                start_ns = time.monotonic_ns()
                self.log_time_ns = self.wall_origin_ns + self.law.cycle * self.period_ns
                self._cycle()
                self.recording.release()
                self._record_timing(start_ns, start_ns, 0)
                continue
            message = self._recv(silence_s, poll_s)
            # Whatever arrives now belongs to the sample of the coming cycle.
            self.log_time_ns = self.wall_origin_ns + self.law.cycle * self.period_ns
            if message is None:
                self._fault("plant_silent", f"no frame for {silence_s} s")
                self._stats.end_reason = "plant_silent"
                log.error("plant silent for %.1f s in lock-step: stopping", silence_s)
                return
            # A sample's records wait for its command (RunRecording.hold); anything else is
            # recorded at once.
            self.recording.hold()
            self._handle(message)
            if not self.intake.fresh:
                self.recording.release()

    def _sensor_phase_ns(self, first_arrival_ns: int) -> int:
        """Where in our period the plant's sensor frames land (monotonic ns mod period),
        from the kernel receive stamps of a few frames: the loop then starts each cycle
        just after a fresh frame instead of wherever the first one happened to be read."""
        phases = [first_arrival_ns % self.period_ns]
        give_up = time.monotonic() + PHASE_PROBE_S
        while len(phases) < PHASE_PROBE_FRAMES and time.monotonic() < give_up:
            message = self._recv(PHASE_PROBE_S)
            if message is None:
                break
            self.log_time_ns = self._wall_ns()
            self._handle(message)
            if message.arbitration_id == SENSOR_ID and self.intake.fresh:
                age_ns = time.time_ns() - int(message.timestamp * 1e9)
                phases.append((time.monotonic_ns() - age_ns) % self.period_ns)
        angles = np.array(phases) * (2 * math.pi / self.period_ns)
        mean = math.atan2(float(np.sin(angles).mean()), float(np.cos(angles).mean()))
        return int(mean % (2 * math.pi) * self.period_ns / (2 * math.pi))

    def _run_realtime(self, arrival_ns: int) -> None:
        phase_ns = self._sensor_phase_ns(arrival_ns)
        start_after_ns = time.monotonic_ns() + self.period_ns
        origin_ns = (
            start_after_ns - start_after_ns % self.period_ns + phase_ns
            + self.config.controller.phase_offset_us * 1000
        )
        spin_ns = spin_ns_for_this_process(self.config.controller.spin_us)
        ticker = Ticker(self.period_ns, spin_ns=spin_ns, start_ns=origin_ns)
        self.mono_origin_ns, self.wall_origin_ns = origin_ns, self._wall_ns_at(origin_ns)
        work = WorkReserve(self.period_ns)
        queue, standing = ReceiveQueue(self.bus), StandingQueue()
        self._stats.receive_queue_bytes = queue.sizes()
        try:
            self._realtime_cycles(ticker, work, queue, standing)
        finally:
            self._stats.queue_shortened = queue.shortened
            self._stats.spins_skipped = ticker.spins_skipped
            self._stats.cycle_cpu_us = round(ticker.cycle_cpu_ns / 1000)
            queue.close()

    def _realtime_cycles(
        self, ticker: Ticker, work: WorkReserve, queue: ReceiveQueue, standing: StandingQueue
    ) -> None:
        while not self.stop.is_set() and self.law.cycle < self.n_cycles:
            tick = ticker.wait()
            self.log_time_ns = self.wall_origin_ns + tick.cycle * self.period_ns
            # Read what has arrived, for half a period at most: a flood must not hold the loop
            # (the rest is read next cycle, or dropped by the kernel if its buffer overflows).
            # Behind the stream, read on, but never into the time the cycle's own work needs
            # before the next deadline: a catch-up that made the cycle overrun would put the
            # loop further behind at every period (under a flood it did).
            # (The ticker's spin gives way to reading: it spins only where the CPU allows.)
            catch_up_until_ns = min(
                tick.start_ns + self.period_ns * CATCH_UP_SHARE // 100,
                tick.deadline_ns + self.period_ns - work.reserve_ns,
            )
            drain_until_ns = min(tick.start_ns + self.period_ns // 2, catch_up_until_ns)
            self.recording.hold()  # until the cycle's command is out
            while (message := self._recv(0.0)) is not None:
                self._handle(message)
                if (now_ns := time.monotonic_ns()) >= drain_until_ns and (
                    # Behind the stream (after a stall, or under a flood): read on, to the
                    # present if the period allows, rather than take history for now.
                    now_ns >= catch_up_until_ns or not self.intake.behind(now_ns)
                ):
                    break
            queue.set_short(standing.update(self.intake.behind(time.monotonic_ns())))
            if self._stats.end_reason == "second_writer":
                break  # no further drive: the shutdown commands 0 V now
            # Preempted before it read the bus, the cycle is the period it is in now: the
            # sample it took is of this period, not a later one's taken for its own.
            tick = ticker.catch_up(tick)
            self.log_time_ns = self.wall_origin_ns + tick.cycle * self.period_ns
            if tick.skipped:
                self._stats.overruns += 1
                self._stats.skipped_periods += tick.skipped
                self._coast_skipped(tick.skipped)
            # The angle guard looks as far ahead as the loop has lately been late (replayed
            # from /timing: the same sum of its lateness and skipped periods).
            work_start_ns = time.monotonic_ns()
            self._cycle(tick.lateness_ns + tick.skipped * self.period_ns)
            self.recording.release()
            self._record_timing(tick.deadline_ns, tick.start_ns, tick.skipped)
            work.took(time.monotonic_ns() - work_start_ns)

    def _await_final_status(self) -> None:
        """Record what arrives until the emulator's final counters have (bounded wait)."""
        give_up = time.monotonic() + FINAL_STATUS_WAIT_S
        while not self.intake.final_status_seen:
            remaining_s = give_up - time.monotonic()
            if remaining_s <= 0:
                self._event("plant_status_missing",
                            f"no final status from the emulator within {FINAL_STATUS_WAIT_S} s")
                return
            message = self._recv(min(remaining_s, 0.05))
            if message is None:
                continue
            if self.config.run.mode == "realtime":  # lock-step's log clock is the cycle's
                self.log_time_ns = max(self.log_time_ns, self._wall_ns())
            # The intake alone: the run is over, so a repeated sample gets no command.
            self.intake.handle(message, self.log_time_ns, self.law.cycle)

    def _wall_ns(self) -> int:
        return self.wall_origin_ns + time.monotonic_ns() - self.mono_origin_ns

    def _wall_ns_at(self, monotonic_ns: int) -> int:
        return self.wall_origin_ns + monotonic_ns - self.mono_origin_ns

    def _coast_skipped(self, count: int) -> None:
        self.cycles_since_sensor += count  # skipped periods brought no sensor frame either
        held_v = self.last_output.voltage_v if self.last_output is not None else 0.0
        if self.in_fault:
            held_v = 0.0
        # The plant drove the look-ahead sent with the last command, then held its last entry.
        self._take_plans()
        self.law.coast(held_v, count, self.lookahead_v)
        self._send_plan_request()
        self._event("overrun", f"skipped {count} period(s), coasting on the model")

    def _shutdown(self) -> None:
        """0 V, disabled — sent a few times since a frame can be lost — then the stop event."""
        self.recording.release()
        self.commands.shutdown(self.log_time_ns, self.law.cycle)
        if self.run_over_fd is not None and signal_run_over(self.run_over_fd):
            self._await_final_status()
        reason = self.stop.signal_name if self.stop.signal_name else self._stats.end_reason
        if self.stop.signal_name in ("SIGINT", "SIGTERM"):
            self._stats.end_reason = self.stop.signal_name
        self._event("daemon_stop", f"reason={reason}; 0 V commanded")
