"""The plant-emulator process: SRV02 physics behind the CAN frame contract.

Real time: free-running at the sensor rate on absolute deadlines; a command takes effect
when it arrives (the physics is advanced to that instant first), like a DAC update.
Lock-step: one control period per valid command answering the latest sample; with no answer
the sample is sent again, so a lost frame costs time, never determinism.
Either way a watchdog zeroes the voltage when valid commands stop.

Real time, a command may carry a look-ahead (the controller's commands for the periods after
its own, protocol/secoc.py): while no newer command comes, the plant drives its first entry
from the next sample instant on, the second from the one after, and so on, the last held
beyond; so a controller that misses periods is followed as it planned instead of by its last
command held.

With an authenticator (``bus.authenticate``) every frame sent is a SecOC-style CAN FD frame
and only commands with a right MAC and a fresh freshness value are obeyed (protocol/secoc.py);
the freshness, not the 8-bit counter, then orders the commands (across daemon restarts too).

Its own counters go to the run's log as PlantStatus frames: a snapshot every 100 ms of plant
time, one frame per sample sent (never a burst), and a final one as it stops. Under
``ballbeam run`` it stops when the daemon says the run is over (runtime/peer_link.py), while the
daemon still listens, so the log's final snapshot is what the emulator reports on exit.
"""

from __future__ import annotations

import logging
import os
import time
from collections import deque
from dataclasses import astuple, dataclass

import can
import numpy as np

from ballbeam.config import Config
from ballbeam.core.plant import PlantPhysics, initial_noise, next_noise, read_sensors
from ballbeam.errors import FrameError
from ballbeam.plant_assembly import plant_parameters, sensor_periods_per_cycle
from ballbeam.protocol.frames import (
    COUNTER_MODULUS,
    PLANT_STATUS_ID,
    PLANT_STATUS_VALUE_MAX,
    SENSOR_ID,
    STATUS_HELD,
    STATUS_WATCHDOG,
    TRUTH_ANGLE_ID,
    TRUTH_BALL_ID,
    VOLTAGE_COMMAND_ID,
    CounterCheck,
    FrameContract,
    VoltageCommand,
    decode_lookahead,
    next_counter,
)
from ballbeam.protocol.secoc import CLASSIC_LENGTH, FrameAuthenticator, extension_of
from ballbeam.runtime.bus import recv_frame
from ballbeam.runtime.peer_link import PeerLink
from ballbeam.runtime.stop import StopFlag
from ballbeam.runtime.ticker import Ticker, spin_ns_for_this_process

log = logging.getLogger("ballbeam.emulator")

STATUS_PERIOD_S = 0.1  # plant time between two snapshots of the counters
FINAL_STATUS_GAP_S = 100e-6  # between the final snapshot's frames: udp_multicast drops bursts


class AnswerTimer:
    """Lock-step: how long the emulator waits for the daemon's answer to a sample before it
    sends the sample again, and before its watchdog calls the daemon silent.

    A fixed 20 ms is two orders of magnitude above a round trip on an ordinary machine, but
    on an emulated CPU (a VM without hardware virtualisation) a round trip takes ~25 ms: a
    fixed wait resent about one sample in eight there and tripped the watchdog although
    nothing was lost. The wait is therefore TCP's retransmission timeout (RFC 6298): the
    smoothed round trip plus four times its variation, measured on samples answered at the
    first try (Karn), never below ``floor_s`` (``plant.lockstep_resend_ms``), doubled after
    each resend until an answer is measured again (else a peer slower than the floor would
    never be measured: every sample resent)."""

    __slots__ = ("backoff", "floor_s", "smoothed_s", "variation_s")
    # a slow peer up to 4 waits is measured; a dead one is still resent to every 4 waits (a
    # restarted daemon is answered soon)
    MAX_BACKOFF = 4

    def __init__(self, floor_s: float) -> None:
        self.floor_s = floor_s
        self.smoothed_s: float | None = None
        self.variation_s = 0.0
        self.backoff = 1

    def observe(self, round_trip_s: float) -> None:
        """A sample answered at the first try, ``round_trip_s`` after it was sent."""
        self.backoff = 1
        if self.smoothed_s is None:
            self.smoothed_s, self.variation_s = round_trip_s, round_trip_s / 2
            return
        self.variation_s += (abs(self.smoothed_s - round_trip_s) - self.variation_s) / 4
        self.smoothed_s += (round_trip_s - self.smoothed_s) / 8

    def resent(self) -> None:
        self.backoff = min(2 * self.backoff, self.MAX_BACKOFF)

    @property
    def timeout_s(self) -> float:
        return self._retransmission_s * self.backoff

    @property
    def silence_s(self) -> float:
        """When the daemon is silent: two waits, without the backoff (which grows while a dead
        daemon is resent to, and would put off the watchdog by up to 4 waits)."""
        return 2.0 * self._retransmission_s

    @property
    def _retransmission_s(self) -> float:
        measured_s = 0.0 if self.smoothed_s is None else self.smoothed_s + 4 * self.variation_s
        return max(self.floor_s, measured_s)


@dataclass
class EmulatorCounters:
    """The emulator's own counts; the fields, in order, are PLANT_STATUS_FIELDS (the frames'
    Field index)."""

    samples_sent: int = 0
    resends: int = 0
    commands_applied: int = 0
    rejected: int = 0
    own_or_foreign: int = 0
    dropped_by_injection: int = 0
    watchdog_trips: int = 0
    missed_periods: int = 0  # sample periods the emulator overran (real time): counter gaps
    peer_lost: int = 0  # times the launcher's link said the daemon died (voltage zeroed)
    # Authenticated bus: commands refused before the contract, by reason (also in rejected).
    unauthenticated: int = 0  # no MAC (a classic frame: a stranger's)
    bad_mac: int = 0
    replayed: int = 0  # right MAC, freshness not newer than the last accepted
    out_of_window: int = 0  # right MAC, freshness over a second from this host's clock


def arrival_ns(message: can.Message, now_ns: int) -> int:
    """When ``message`` reached this host on the monotonic clock: python-can stamps it with the
    kernel's receive time (SO_TIMESTAMPNS, wall clock). ``now_ns`` where there is no stamp or
    it is implausible (more than a second off)."""
    stamp_ns = round(message.timestamp * 1e9) - (time.time_ns() - time.monotonic_ns())
    return stamp_ns if 0 <= now_ns - stamp_ns <= 1_000_000_000 else now_ns


class PlantEmulator:
    def __init__(
        self,
        config: Config,
        bus: can.BusABC,
        contract: FrameContract,
        peer_link: PeerLink | None = None,
        auth: FrameAuthenticator | None = None,
    ) -> None:
        self.config = config
        self.auth = auth
        self.peer_link = peer_link
        # The process that launched this one with the daemon (``ballbeam run``): when the daemon
        # and it are both gone, nothing will ever stop this process (see _check_peer).
        self.launcher_pid = os.getppid() if peer_link is not None else None
        self.bus = bus
        self.contract = contract
        params = plant_parameters(config)
        self.physics = PlantPhysics(params)
        self.rng = np.random.default_rng(config.plant.seed)
        # Fault injection draws from its own stream so it never perturbs the plant noise.
        self.fault_rng = np.random.default_rng([config.plant.seed, 1])
        self.state = config.initial.state()
        self.noise_m = initial_noise(params, self.rng)
        self.substeps = config.plant.physics_substeps
        self.sensor_period_ns = 1_000_000_000 // config.plant.sensor_rate_hz
        self.substep_ns = self.sensor_period_ns // self.substeps
        self.sensor_periods_per_command = sensor_periods_per_cycle(config)
        self.started = not config.plant.hold_until_enabled
        self.steps_done = 0  # physics steps since the ball's release: the taps' clock
        self.voltage_v = 0.0
        self.counter = 0
        # Real time: when the next sample period starts and its index, and the latest
        # command's look-ahead with the index of the period its first entry is for.
        self.realtime = False
        self.next_boundary_ns = 0
        self.next_boundary_index = 0
        self.lookahead_v: tuple[float, ...] = ()
        self.lookahead_from = 0
        # Commands heard that act once the physics reaches their arrival: (arrival, command,
        # look-ahead), in arrival order.
        self.pending: list[tuple[int, VoltageCommand, tuple[float, ...]]] = []
        self.command_check = CounterCheck()
        self.counters = EmulatorCounters()
        self.watchdog_ns = int(config.plant.watchdog_ms * 1e6)
        self.last_command_ns: int | None = None
        # Every frame that reached this host before this instant has been read. The watchdog
        # judges silence up to here, not up to now: commands queued while this process was
        # off the CPU (behind a flood, say) came in time; only reading them came late.
        self.heard_until_ns: int | None = None
        self.watchdog_zeroed = False
        # Status snapshots: frames waiting to go, one per sample sent; the first at the start.
        self.status_period_samples = max(1, round(STATUS_PERIOD_S * config.plant.sensor_rate_hz))
        self._periods_to_status = 0
        self._status_pending: deque[bytes] = deque()
        self.status_counter = 0

    # -- frames -------------------------------------------------------------------------------
    def _send(self, arbitration_id: int, data: bytes, extension: bytes = b"") -> None:
        """``extension``: authenticated bus only (protocol/secoc.py)."""
        if self.auth is None:
            message = can.Message(arbitration_id=arbitration_id, data=data, is_extended_id=False)
        else:
            message = can.Message(
                arbitration_id=arbitration_id,
                data=self.auth.protect(arbitration_id, data, extension),
                is_extended_id=False,
                is_fd=True,
            )
        self.bus.send(message)

    def _send_sample(self) -> None:
        """This sample's sensor frame and its truth, all with this sample's counter. On the
        authenticated (CAN FD) bus the truth rides in the sensor frame's extension, one frame
        for both; else, or when the sensor frame is lost, it follows in the two truth frames
        (the log keeps the truth of every sample)."""
        theta, theta_rate, velocity, position = (float(v) for v in self.state)
        loss = self.config.plant.sensor_loss
        truth = b""
        if loss and self.fault_rng.random() < loss:
            self.counters.dropped_by_injection += 1
        else:
            reading = read_sensors(self.physics.params, self.state, self.noise_m)
            status = (STATUS_WATCHDOG if self.watchdog_zeroed else 0) | (
                0 if self.started else STATUS_HELD
            )
            sensor = self.contract.encode_sensor(
                self.counter, reading.angle_counts, reading.position_counts, status
            )
            truth = b"" if self.auth is None else self.contract.encode_truth(
                self.counter, theta, theta_rate, position, velocity
            )
            self._send(SENSOR_ID, sensor, truth)
            self.counters.samples_sent += 1
        if not truth:
            self._send(
                TRUTH_ANGLE_ID, self.contract.encode_truth_angle(self.counter, theta, theta_rate)
            )
            self._send(
                TRUTH_BALL_ID, self.contract.encode_truth_ball(self.counter, position, velocity)
            )
        if self._status_pending:
            self._send(PLANT_STATUS_ID, self._status_pending.popleft())

    def _count_periods(self, periods: int) -> None:
        """``periods`` sample periods of plant time passed: a snapshot when one is due."""
        self._periods_to_status -= periods
        if self._periods_to_status <= 0:
            self._periods_to_status = self.status_period_samples
            self._queue_status(final=False)

    def _queue_status(self, final: bool) -> None:
        """A snapshot of the counters now, as PlantStatus payloads (an unsent older one is
        dropped: the receiver keeps whole snapshots only)."""
        self._status_pending.clear()
        for field_index, value in enumerate(astuple(self.counters)):
            self._status_pending.append(self.contract.encode_plant_status(
                self.status_counter, field_index, final, min(value, PLANT_STATUS_VALUE_MAX)
            ))
            self.status_counter = next_counter(self.status_counter)

    def send_final_status(self) -> None:
        """The counters as they stand, marked final, all at once (the loop is over)."""
        self._queue_status(final=True)
        while self._status_pending:
            self._send(PLANT_STATUS_ID, self._status_pending.popleft())
            if self._status_pending:
                time.sleep(FINAL_STATUS_GAP_S)

    def _recv(self, timeout_s: float, poll_s: float = 0.0) -> can.Message | None:
        """The next message within ``timeout_s``; datagrams that are no frame are counted."""
        message = recv_frame(self.bus, timeout_s, self._count_malformed, poll_s)
        now_ns = time.monotonic_ns()
        self.heard_until_ns = now_ns if message is None else arrival_ns(message, now_ns)
        return message

    def _count_malformed(self, _detail: str) -> None:
        self.counters.rejected += 1

    def _accept_command(
        self, message: can.Message
    ) -> tuple[VoltageCommand, tuple[float, ...]] | None:
        """A valid, fresh command frame and its look-ahead, or None (counted)."""
        if (
            message.arbitration_id != VOLTAGE_COMMAND_ID
            or message.is_extended_id  # the contract is on standard-id data frames only
            or message.is_remote_frame
            or message.is_error_frame
        ):
            self.counters.own_or_foreign += 1
            return None
        data = bytes(message.data)
        extension = b""
        if self.auth is not None:
            # Before the contract and the counter: a refused frame moves no state.
            verdict = self.auth.verify(VOLTAGE_COMMAND_ID, data)
            if verdict != "ok":
                setattr(self.counters, verdict, getattr(self.counters, verdict) + 1)
                self.counters.rejected += 1
                return None
            extension = extension_of(data)
            data = data[:CLASSIC_LENGTH]
        try:
            command = self.contract.decode(message.arbitration_id, data)
            lookahead_v = decode_lookahead(extension) if extension else ()
        except FrameError:
            self.counters.rejected += 1
            return None
        assert isinstance(command, VoltageCommand)
        loss = self.config.plant.command_loss
        if loss and self.fault_rng.random() < loss:
            self.counters.dropped_by_injection += 1
            return None
        # Authenticated, the freshness has ordered the commands already (across daemon
        # restarts too); the 8-bit counter is the classic contract's.
        if self.auth is None and self.command_check.classify(command.counter) != "ok":
            self.counters.rejected += 1
            return None
        return command, lookahead_v

    def _take_command(self, message: can.Message, physics_ns: int, limit_ns: int) -> int:
        """Real time: judge ``message``; a valid command acts on the physics from the moment it
        reached this host (the kernel's receive stamp, not when this process got to it). The
        physics goes at most up to ``limit_ns`` now: a command that came later (this process
        was off the CPU meanwhile) waits, and acts when the physics gets to its arrival.
        Returns the physics' new time."""
        accepted = self._accept_command(message)
        if accepted is None:
            return physics_ns
        now_ns = time.monotonic_ns()
        arrived_ns = min(max(arrival_ns(message, now_ns), physics_ns), now_ns)
        self.last_command_ns = arrived_ns  # heard: the watchdog counts from here
        self.pending.append((arrived_ns, *accepted))
        return self._advance_until(physics_ns, min(arrived_ns, limit_ns))

    def _apply(
        self, command: VoltageCommand, lookahead_v: tuple[float, ...] = (), *, now_ns: int
    ) -> None:
        self.last_command_ns = now_ns
        self.watchdog_zeroed = False
        self.voltage_v = command.voltage_v if command.enable else 0.0
        self.lookahead_v = lookahead_v if command.enable and self.realtime else ()
        # Its first entry is for the period after the one it names. A command that comes
        # periods late (its sender lost the CPU between reading and sending) drives its entry
        # for the period it lands in, not its own stale voltage (driven as on time, such
        # commands put 0.16 V on the brake where the law's entry was −4.5 V, and shifted
        # the look-ahead after them back by as many periods).
        late = self._periods_late(command.sensor_counter)
        self.lookahead_from = self.next_boundary_index - late
        if late and self.lookahead_v:
            self.voltage_v = self.lookahead_v[min(late, len(self.lookahead_v)) - 1]
        if command.enable:
            self.started = True
        self.counters.commands_applied += 1

    def _periods_late(self, period_counter: int) -> int:
        """Real time: how many periods ago the period a command names began (its 8-bit
        counter against the period the physics is in); 0 for one named for this period, or
        for one ahead of the physics (half the counter's range or more behind counts so)."""
        if not self.realtime:
            return 0
        late = (self.next_boundary_index - 1 - period_counter) % COUNTER_MODULUS
        return late if late < COUNTER_MODULUS // 2 else 0

    def _advance_until(self, physics_ns: int, until_ns: int) -> int:
        """Advance the physics from ``physics_ns`` to ``until_ns`` (whole substeps): the
        commands heard meanwhile act from their arrival on the way, and (real time) each
        sample period begun starts on the latest command's look-ahead for it, if any.
        Returns the physics' new time."""
        while True:
            # Commands waiting for the physics to reach their arrival act there, in order;
            # between them (real time) each sample instant switches to the look-ahead's entry.
            boundary_ns = self.next_boundary_ns if self.realtime else until_ns + 1
            if self.pending and self.pending[0][0] <= min(until_ns, boundary_ns - 1):
                arrived_ns, command, lookahead_v = self.pending.pop(0)
                physics_ns = self._advance_to(physics_ns, arrived_ns)
                self._apply(command, lookahead_v, now_ns=arrived_ns)
                continue
            if boundary_ns > until_ns:
                break
            physics_ns = self._advance_to(physics_ns, self.next_boundary_ns)
            ahead = self.next_boundary_index - self.lookahead_from
            if self.lookahead_v and not self.watchdog_zeroed and ahead >= 0:
                self.voltage_v = self.lookahead_v[min(ahead, len(self.lookahead_v) - 1)]
            self.next_boundary_ns += self.sensor_period_ns
            self.next_boundary_index += 1
        return self._advance_to(physics_ns, until_ns)

    def _advance_to(self, physics_ns: int, until_ns: int) -> int:
        """Whole substeps from ``physics_ns`` towards ``until_ns``; the physics' new time."""
        due = (until_ns - physics_ns) // self.substep_ns
        self._advance(due)
        return physics_ns + max(due, 0) * self.substep_ns

    def _check_watchdog(self, now_ns: int, floor_ns: int = 0) -> None:
        """Zero the drive once no valid command came for ``plant.watchdog_ms`` (at least
        ``floor_ns``)."""
        if self.last_command_ns is None or self.watchdog_zeroed:
            return
        if self.heard_until_ns is not None:
            now_ns = min(now_ns, self.heard_until_ns)
        if now_ns - self.last_command_ns > max(self.watchdog_ns, floor_ns):
            self.voltage_v = 0.0
            self.lookahead_v = ()
            self.watchdog_zeroed = True
            self.counters.watchdog_trips += 1
            # The commander went silent: whoever commands next (a restarted daemon counts from
            # 0) is judged from its first frame, not as stale against the old stream's counter.
            self.command_check.reset()
            log.warning("watchdog: no valid command for %.1f ms, voltage zeroed",
                        (now_ns - self.last_command_ns) / 1e6)

    def _check_peer(self, stop: StopFlag) -> None:
        """The launcher's link says the daemon's run is over: stop (0 V; the final counters
        go out while the daemon listens). It says the daemon died: no drive from this moment
        on (the sample's status shows it, as after a watchdog trip)."""
        if self.peer_link is None:
            return
        state = self.peer_link.state()
        if state == "run_over" and not stop.is_set():
            self._drop_drive()
            stop.set("run_over")
            log.info("the daemon's run is over: stopping")
            return
        if state == "gone" and self.launcher_pid is not None and os.getppid() != self.launcher_pid:
            # The launcher died too (killed with the daemon): no one is left to stop this
            # process, which would otherwise run on alone; it stops with 0 V.
            self._drop_drive()
            stop.set("launcher_gone")
            log.warning("the daemon and its launcher are gone: stopping")
            return
        # Once: a command heard since (a restarted daemon, by hand) is obeyed as usual.
        if state != "gone" or self.counters.peer_lost:
            return
        self._drop_drive()
        self.watchdog_zeroed = True
        self.counters.peer_lost += 1
        self.command_check.reset()
        log.warning("peer link closed: the daemon is gone; voltage zeroed at monotonic %d ns",
                    time.monotonic_ns())

    def _drop_drive(self) -> None:
        """0 V from now on: the command in force, its look-ahead and what waits to act."""
        self.voltage_v = 0.0
        self.lookahead_v = ()
        self.pending.clear()

    def _take_last_commands(self, message: can.Message | None, lockstep: bool) -> None:
        """The daemon's last frames, already on the bus when it said the run is over (its last
        command, its stop commands): judged and counted as usual; nothing advances any more."""
        while message is not None:
            accepted = self._accept_command(message)
            if accepted is not None:
                command = accepted[0]
                if lockstep and command.enable and command.sensor_counter != self.counter:
                    self.counters.rejected += 1  # answers an older sample: stale
                else:
                    self._apply(command, now_ns=time.monotonic_ns())
            message = self._recv(0.0)
        self.voltage_v = 0.0
        self.lookahead_v = ()

    def _advance(self, substeps: int) -> None:
        if self.started and substeps > 0:
            self.state = self.physics.advance(
                self.state, self.voltage_v, substeps, self.steps_done
            )
            self.steps_done += substeps

    # -- modes --------------------------------------------------------------------------------
    def run_lockstep(self, stop: StopFlag) -> None:
        answers = AnswerTimer(self.config.plant.lockstep_resend_ms * 1e-3)
        poll_s = self.config.run.lockstep_poll_us * 1e-6
        self._count_periods(0)
        self._send_sample()
        last_sent = first_sent = time.monotonic()
        resent = False  # this sample: its answer then says nothing of the round trip (Karn)
        while not stop.is_set():
            wait_s = max(0.0, last_sent + answers.timeout_s - time.monotonic())
            message = self._recv(wait_s, poll_s)
            now_ns = time.monotonic_ns()
            self._check_peer(stop)
            if stop.is_set():
                self._take_last_commands(message, lockstep=True)
                break
            # The plant stands still until the answer: silence is the daemon's only once it
            # outlasts a resend (AnswerTimer).
            self._check_watchdog(now_ns, round(answers.silence_s * 1e9))
            if message is None or (accepted := self._accept_command(message)) is None:
                if time.monotonic() - last_sent >= answers.timeout_s:
                    self._resend()
                    answers.resent()
                    last_sent, resent = time.monotonic(), True
                continue
            command = accepted[0]  # lock-step waits for every command: no look-ahead
            if command.sensor_counter != self.counter:
                if not command.enable:
                    # A stop (0 V, disabled) is obeyed whatever sample it answers; the plant
                    # does not advance on it.
                    self._apply(command, now_ns=now_ns)
                    continue
                self.counters.rejected += 1  # answers an older sample: stale
                continue
            self._apply(command, now_ns=now_ns)
            for _ in range(self.sensor_periods_per_command):
                self._advance(self.substeps)
                self.noise_m = next_noise(self.physics.params, self.noise_m, self.rng)
            if not resent:
                answers.observe(time.monotonic() - first_sent)
            self.counter = next_counter(self.counter)
            self._count_periods(self.sensor_periods_per_command)
            self._send_sample()
            last_sent = first_sent = time.monotonic()
            resent = False

    def _resend(self) -> None:
        self.counters.resends += 1
        # Same sample, same counters: the daemon answers a repeat with its cached command.
        self._send_sample()

    def run_realtime(self, stop: StopFlag) -> None:
        spin_ns = spin_ns_for_this_process(self.config.controller.spin_us)
        ticker = Ticker(self.sensor_period_ns, spin_ns=spin_ns)
        physics_ns = ticker.origin_ns
        self.realtime = True
        self.next_boundary_ns, self.next_boundary_index = ticker.origin_ns, 0
        tick = ticker.wait()
        while not stop.is_set():
            self._check_peer(stop)
            if stop.is_set():
                self._take_last_commands(None, lockstep=False)
                break
            # Commands that came while this process was off the CPU (or spinning) act from when
            # they came: the plant is physics, it does not wait for its emulator's turn. For
            # half a period at most: a flood must not hold the sample.
            catch_up_until_ns = tick.start_ns + self.sensor_period_ns // 2
            while (
                time.monotonic_ns() < catch_up_until_ns
                and (message := self._recv(0.0)) is not None
            ):
                physics_ns = self._take_command(message, physics_ns, tick.deadline_ns)
            # Advance to the deadline, then sample: the sensor reads the state at t_k.
            physics_ns = self._advance_until(physics_ns, tick.deadline_ns)
            # The counter counts sample periods, not frames: periods this process overran
            # (never sampled, never sent) are a visible gap to every receiver.
            for _ in range(tick.skipped):
                self.noise_m = next_noise(self.physics.params, self.noise_m, self.rng)
                self.counter = next_counter(self.counter)
            self.counters.missed_periods += tick.skipped
            self._count_periods(1 + tick.skipped)
            self.noise_m = next_noise(self.physics.params, self.noise_m, self.rng)
            self._send_sample()
            self.counter = next_counter(self.counter)
            next_deadline_ns = tick.deadline_ns + self.sensor_period_ns
            # Listen until just before the next deadline, applying commands as they arrive.
            while (remaining_ns := next_deadline_ns - time.monotonic_ns()) > ticker.spin_ns:
                message = self._recv((remaining_ns - ticker.spin_ns) * 1e-9)
                if message is None:
                    break
                physics_ns = self._take_command(message, physics_ns, next_deadline_ns)
            self._check_watchdog(time.monotonic_ns())
            tick = ticker.wait()

    def stop(self) -> None:
        """Leave the plant safe: zero volts."""
        self._drop_drive()
