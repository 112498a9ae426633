"""The re-planning law's planner: a process of its own beside the daemon's 1 kHz loop.

The daemon sends it the law's plan requests through a pipe and reads the answers without
blocking (real time) or waits for one before the cycle it is due (lock-step). The process is
started from a fresh interpreter (spawn), so it holds none of the daemon's sockets, threads or
scheduling, and imports only the core planning code. It ends when its pipe closes — the daemon
closing it, or dying (even by SIGKILL: the kernel closes the daemon's end) — and, since a solve
can take seconds, the kernel also kills it when the daemon dies (Linux: PR_SET_PDEATHSIG).
"""

from __future__ import annotations

import contextlib
import ctypes
import logging
import multiprocessing
import os
import signal
import time
from multiprocessing.connection import Connection, wait

from ballbeam.core.replanning import (
    DesignAnswer,
    DesignRequest,
    Identification,
    PlanAnswer,
    PlanRequest,
    Settings,
    solve_design_request,
    solve_plan_request,
)
from ballbeam.errors import PlanningError
from ballbeam.logs.plan_record import design_json
from ballbeam.runtime.ticker import leave_real_time

log = logging.getLogger("ballbeam.planner")

_PR_SET_PDEATHSIG = 1
READY = "ready"  # the planner's first message: warmed up, answering
# Encoded designs kept for answers not yet taken (one is outstanding at most; a few for
# answers that come after their request was dropped, never taken).
_DESIGNS_KEPT = 4

# How long the daemon waits for its planner to end after closing the pipe (a solve in
# progress finishes first) before it terminates it.
CLOSE_WAIT_S = 1.0


def serve(connection: Connection, parent_pid: int) -> None:
    """The planner process: answer each request until the pipe closes."""
    _die_with(parent_pid)
    leave_real_time()  # the loop's scheduling is not ours
    with contextlib.suppress(KeyboardInterrupt):
        _warm_up()
        try:
            connection.send(READY)
        except (BrokenPipeError, OSError):
            return
        while True:
            try:
                request = connection.recv()
            except (EOFError, OSError):
                return
            reply: PlanAnswer | tuple[DesignAnswer, bytes]
            if isinstance(request, DesignRequest):  # its failure ends us: the daemon's then
                answer = solve_design_request(request)
                # with its record's encoding: ~50 KB of JSON, milliseconds a cycle lacks
                reply = (answer, design_json(answer.design))
            else:
                reply = _answer_plan(request)
            try:
                connection.send(reply)
            except (BrokenPipeError, OSError):
                return


def _answer_plan(request: PlanRequest) -> PlanAnswer:
    """A plan, or none with the failure in words (the law keeps its plan)."""
    try:
        return solve_plan_request(request)
    except PlanningError as error:
        return PlanAnswer(request.cycle, None, error=f"no plan: {error}")
    except Exception as error:  # any failure of a solve is an answer of no plan
        return PlanAnswer(request.cycle, None, error=f"{type(error).__name__}: {error}")


def _warm_up() -> None:
    """One cold plan of the design's model and one re-design from every kind of window, so
    the run's first requests do not pay for the solvers' imports and first calls (a second
    or more on a loaded machine, which lock-step would wait for)."""
    s = Settings()
    request = PlanRequest(
        0, "cold", (0.3, 0.0, 0.0, 0.1), 0.0, s.prior_pole_per_s, s.prior_alpha,
        s.prior_gamma, 4.0, s.theta_limit_rad - s.plan_theta_margin_rad,
    )
    with contextlib.suppress(PlanningError):
        solve_plan_request(request)
    cycles = max(s.servo_window, s.ball_window, s.noise_window, s.identify_every)
    at_rest = (0.0,) * (cycles + 1)
    solve_design_request(DesignRequest(
        cycles, s, Identification.prior(s), 0, at_rest, at_rest, (1.0,) * cycles
    ))


def _die_with(parent_pid: int) -> None:
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(_PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0)
    except (OSError, AttributeError):
        pass
    if os.getppid() != parent_pid:  # it died before we asked
        os._exit(0)


class PlannerProcess:
    """The daemon's side: send requests, collect answers, end the process."""

    def __init__(self) -> None:
        context = multiprocessing.get_context("spawn")
        self._connection, child = context.Pipe(duplex=True)
        self.process = context.Process(
            target=serve, args=(child, os.getpid()), name="ballbeam-planner", daemon=True
        )
        self.process.start()
        child.close()  # only the planner holds its end: its death closes the pipe here
        self.sent_ns: dict[int, int] = {}  # request cycle → when it was sent (monotonic)
        self.alive = True
        # id of a design answered → the design (so the id stays its) and its record's JSON
        self._design_json: dict[int, tuple[object, bytes]] = {}

    def wait_ready(self, timeout_s: float) -> bool:
        """Wait until the planner is warmed up (its first message); False if it is not by
        then or has died (the run goes on: its requests wait, or are answered with none)."""
        wait([self._connection, self.process.sentinel], timeout_s)
        try:
            if self._connection.poll(0):
                return bool(self._connection.recv() == READY)
        except (EOFError, OSError):
            self.alive = False
        return False

    @property
    def pid(self) -> int | None:
        return self.process.pid

    def send(self, request: PlanRequest | DesignRequest) -> bool:
        """Send a request; False if the planner is gone."""
        if not self.alive:
            return False
        try:
            self._connection.send(request)
        except (BrokenPipeError, OSError):
            self.alive = False
            return False
        if isinstance(request, PlanRequest):
            self.sent_ns[request.cycle] = time.monotonic_ns()
        return True

    def receive(
        self, timeout_s: float | None = 0.0
    ) -> list[tuple[PlanAnswer | DesignAnswer, int]]:
        """The answers in (waiting up to ``timeout_s`` for the first; None: until one comes
        or the planner dies), each with its wait since the request [ns]. Sets ``alive``
        False if the planner has died."""
        answers: list[tuple[PlanAnswer | DesignAnswer, int]] = []
        if not self.alive:
            return answers
        if timeout_s != 0.0:
            wait([self._connection, self.process.sentinel], timeout_s)
        try:
            while self._connection.poll(0):
                reply: PlanAnswer | tuple[DesignAnswer, bytes] = self._connection.recv()
                if isinstance(reply, tuple):
                    answer: PlanAnswer | DesignAnswer = reply[0]
                    self._design_json[id(reply[0].design)] = (reply[0].design, reply[1])
                    while len(self._design_json) > _DESIGNS_KEPT:  # answers never taken
                        del self._design_json[next(iter(self._design_json))]
                else:
                    answer = reply
                sent_ns = (
                    self.sent_ns.pop(answer.request_cycle, None)
                    if isinstance(answer, PlanAnswer) else None
                )
                wait_ns = time.monotonic_ns() - sent_ns if sent_ns is not None else -1
                answers.append((answer, wait_ns))
        except (EOFError, OSError):
            self.alive = False
        if not answers and not self.process.is_alive():
            self.alive = False
        return answers

    def take_design_json(self, design: object) -> bytes | None:
        """The encoding of ``design`` for its record, made by the planner (None: not its)."""
        kept = self._design_json.pop(id(design), None)
        return kept[1] if kept is not None and kept[0] is design else None

    def close(self) -> None:
        """Close the pipe (the planner ends on it), wait for it briefly, else terminate."""
        self._connection.close()
        self.process.join(CLOSE_WAIT_S)
        if self.process.is_alive():
            self.process.kill()
            self.process.join(CLOSE_WAIT_S)
        self.alive = False
