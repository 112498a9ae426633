"""The plant emulator's process: ``python -m ballbeam_emulator [CONFIG] [--set KEY=VALUE]``
(also ``ballbeam emulator``). It runs until SIGINT/SIGTERM (``ballbeam run`` stops it when its
daemon is done)."""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Sequence

import can

from ballbeam.config import Config
from ballbeam.errors import BallbeamError, BusError
from ballbeam.protocol.frames import FrameContract
from ballbeam.protocol.secoc import FrameAuthenticator, RunKey
from ballbeam.runtime.bus import check_before_start, open_bus
from ballbeam.runtime.owner_lock import EMULATOR_SLOT, OwnerLock
from ballbeam.runtime.peer_link import PeerLink
from ballbeam.runtime.process import (
    add_config_arguments,
    add_secret_argument,
    apply_scheduling,
    config_from_arguments,
    configure_logging,
    forbid_core_dumps,
    resolve_config_argument,
    secret_from_arguments,
    settle_heap,
)
from ballbeam.runtime.stop import StopFlag
from ballbeam_emulator.node import PlantEmulator

log = logging.getLogger("ballbeam.emulator")
EXIT_USAGE = 2


def run_emulator(config: Config, secret: RunKey | bytes | None = None) -> None:
    contract = FrameContract.load()
    auth = None
    if config.bus.authenticated:
        if secret is None:
            raise BusError(
                f"bus.authenticate is on ({config.bus.interface}) but the emulator has no run "
                "secret: `ballbeam run` hands one to both processes; alone, pass the same 32 "
                "bytes to both with --secret-fd N, or set bus.authenticate=false"
            )
        auth = FrameAuthenticator(secret)
    stop = StopFlag().install()
    if config.run.mode == "realtime":  # lock-step has no deadlines to protect
        apply_scheduling(
            config.plant.cpu, config.plant.realtime_priority, config.plant.fair_slice_us
        )
    peer_link = PeerLink.from_environment()
    own_lock = OwnerLock.from_environment(slot=EMULATOR_SLOT)  # held till death: for the daemon
    if own_lock is not None:
        own_lock.hold()
    bus = open_bus(config.bus)
    emulator = PlantEmulator(config, bus, contract, peer_link, auth)
    settle_heap()
    try:
        if config.run.mode == "lockstep":
            emulator.run_lockstep(stop)
        else:
            emulator.run_realtime(stop)
    finally:
        emulator.stop()
        try:
            emulator.send_final_status()  # the counters reported below, into the run's log
        except can.CanError as error:
            log.warning("the final status frames could not be sent: %s", error)
        finally:
            bus.shutdown()
        log.info("emulator stopped: %s", emulator.counters)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m ballbeam_emulator", description="The SRV02 ball-and-beam plant emulator."
    )
    add_config_arguments(parser)
    add_secret_argument(parser)
    args = parser.parse_args(argv)
    forbid_core_dumps()  # before the key is read: a core would hold it (runtime/process.py)
    configure_logging()
    secret = None
    try:
        resolve_config_argument(args)
        config = config_from_arguments(args)
        check_before_start(config.bus)
        secret = secret_from_arguments(args)
        run_emulator(config, secret)
    except BallbeamError as error:
        print(f"ballbeam-emulator: error: {error}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        return 130
    finally:
        if secret is not None:
            secret.wipe()
    return 0
