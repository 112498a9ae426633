"""Strangers on an authenticated bus (protocol/secoc.py): forged, replayed and random frames from
a separate process at 5 kHz are rejected and counted, none is obeyed or recorded as truth, and
the real run goes on as a clean one; a second holder of the run's secret writing the command id
is a fault that stops the run at 0 V; the secret is on no command line, in no environment and
in no log.
"""

from __future__ import annotations

import hashlib
import hmac
import json
import math
import os
import secrets
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import can
import numpy as np
import pytest

from ballbeam.config import DEFAULT_BUS_GROUP, BusSection, load_config
from ballbeam.logs.reader import read_log
from ballbeam.protocol.frames import PLANT_STATUS_FIELDS, VOLTAGE_COMMAND_ID, VoltageCommand
from ballbeam.protocol.secoc import RunKey
from ballbeam.runtime.bus import isolated_group, open_bus
from ballbeam.runtime.exit_codes import EXIT_PLANT_LOST, EXIT_SECOND_WRITER

from ..conftest import REPO, ballbeam_argv
from .harness import (
    CONTRACT,
    DEFAULTS,
    START_TIMEOUT_S,
    Bench,
    Outcome,
    assert_settles_like,
    decoded,
    events,
    faults,
    figure,
    finish_flood,
    one_error_line,
    run_to_end,
    set_args,
    summary_meta,
)

# On wall time: alone under pytest -n (tests/conftest.py).
pytestmark = pytest.mark.realtime

FLOOD = Path(__file__).resolve().parents[1] / "helpers" / "flood.py"
ATTACK_RATE_HZ = 5000
ATTACK_MAX_FRAMES = 15_000
PERIODS_TO_ZERO = 3  # a second writer: the plant at 0 V within this many control periods


def _rest_s(outcome: Outcome) -> float:
    rest = outcome.summary["rest_time_s"]
    assert rest is not None and math.isfinite(rest), outcome.summary
    return float(rest)


def run_attacked(tmp: Path, mode: str, seed: int) -> tuple[Outcome, dict[str, Any]]:
    """A run with the attack flood (tests/helpers/flood.py --attack) from its first command."""
    with Bench(tmp, mode, 4.0, watch=False) as bench:
        assert bench.config.bus.authenticated
        flood = subprocess.Popen(
            [
                sys.executable, str(FLOOD), "--attack",
                "--channel", bench.group, "--port", str(bench.port), "--seed", str(seed),
                "--rate-hz", str(ATTACK_RATE_HZ), "--max-frames", str(ATTACK_MAX_FRAMES),
                "--max-seconds", "3", "--start-on", "command", "--wait", str(START_TIMEOUT_S),
            ],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO,
        )
        flood_out, flood_err = finish_flood(flood)
        outcome = run_to_end(bench)
    assert flood.returncode == 0, flood_err
    sent: dict[str, Any] = json.loads(flood_out)
    assert 0 < sent["sent"] <= ATTACK_MAX_FRAMES, sent
    for kind in ("forged_mac", "replayed", "classic_valid"):
        assert sent["by_kind"].get(kind, 0) > 0, sent
    assert outcome.daemon_exit == 0, outcome.daemon_stderr[-2000:]
    assert outcome.summary["end_reason"] == "completed" and not outcome.summary["truncated"]
    meta = summary_meta(outcome.log)
    rejected = {
        k.removeprefix("rejected_"): int(v) for k, v in meta.items()
        if k.startswith("rejected_") and k != "rejected_total"
    }
    emulator = outcome.emulator
    figure(f"attack_{mode}", {
        "flood": sent,
        "daemon_rejected": rejected,
        "emulator": {k: emulator[k] for k in (
            "bad_mac", "replayed", "unauthenticated", "out_of_window", "commands_applied",
            "watchdog_trips", "missed_periods")},
    })
    # Counted by kind, at the daemon and at the plant.
    for reason in ("bad_mac", "replayed", "unauthenticated", "foreign_command"):
        assert rejected.get(reason, 0) > 0, (reason, rejected)
    for counter in ("bad_mac", "replayed", "unauthenticated"):
        assert emulator[counter] > 0, emulator
    # None obeyed or taken: the plant applied only the daemon's own commands, no stranger was
    # taken for a second writer, and the sensor stream was never desynchronised.
    assert meta["second_writer_frames"] == "0"
    assert emulator["commands_applied"] <= len(outcome.log.topics["/can/tx"])
    assert int(meta["sensor_frames_stale"]) == 0, meta
    sensor = outcome.log.topics["/sensor"].values
    taken = sensor["fresh"] >= 1  # on time or late
    assert np.abs(sensor["angle_counts"][taken]).max() < 32767
    # None recorded as truth: forged truth carries up to ±5 rad; the plant's stays inside its
    # hard stops, and its sample index never moves back.
    truth = outcome.log.topics["/truth"].values
    assert np.abs(truth["theta_rad"]).max() <= math.radians(DEFAULTS.plant.hard_stop_deg)
    assert (np.diff(truth["sample_index"]) >= 0).all()  # a lock-step resend repeats one
    # None recorded as the plant's counters: forged status frames carry counters at their
    # ceiling; the plant's only grow, and never past what it reported on exit.
    status = outcome.log.topics["/plant_status"].values
    assert len(status) >= 10  # every 100 ms of a 4 s run, lost frames aside
    for name in PLANT_STATUS_FIELDS:
        assert (np.diff(status[name]) >= 0).all(), name
        assert status[name].max() <= emulator[name], (name, emulator)
    return outcome, sent


@pytest.mark.bus
def test_an_attack_at_5khz_in_lockstep_leaves_the_run_bit_identical_to_a_clean_one(
    tmp_path: Path,
) -> None:
    """Lock-step runs are deterministic, so "unaffected" can be exact: every command of the
    attacked run is the clean run's, to the bit (rest time equal, not only within 10 ms)."""
    with Bench(tmp_path / "clean", "lockstep", 4.0, watch=False) as bench:
        clean = run_to_end(bench)
    assert clean.daemon_exit == 0, clean.daemon_stderr[-2000:]
    attacked, _ = run_attacked(tmp_path / "attacked", "lockstep", seed=12)
    clean_v = clean.log.topics["/command"].values["voltage_v"]
    attacked_v = attacked.log.topics["/command"].values["voltage_v"]
    assert len(attacked_v) == len(clean_v) == 4000
    assert np.array_equal(attacked_v, clean_v)
    assert _rest_s(attacked) == _rest_s(clean)
    figure("attack_lockstep_rest_s", {"attacked": _rest_s(attacked), "clean": _rest_s(clean)})


@pytest.mark.bus
def test_an_attack_at_5khz_in_real_time_is_refused_and_the_run_settles_like_a_clean_one(
    tmp_path: Path, clean_realtime: Outcome
) -> None:
    attacked, _ = run_attacked(tmp_path, "realtime", seed=11)
    rest_s, clean_s = _rest_s(attacked), _rest_s(clean_realtime)
    figure("attack_realtime_rest_s", {"attacked": rest_s, "clean": clean_s,
                                      "difference_ms": round((rest_s - clean_s) * 1e3, 2)})
    # The issue asks for rest within 10 ms of a clean run. Two real-time runs do not meet that
    # between themselves here, attacked or not (bench/secoc_attack.py --mode realtime, 7 clean
    # and 7 attacked runs, load average 5-6 from other jobs on this 2-core machine): rest times
    # fall at 1.762-1.771 s or at 1.82-1.83 s, clean runs included (one clean pair 1.764 s vs
    # 1.833 s with no missed plant period, overrun or sensor timeout in either), further out
    # when the machine stalls the plant (a clean run with 331 missed periods: 2.663 s). So the
    # exact comparison is the lock-step test's (equal to the bit); a real-time run is held to
    # the bound every real-time fault test uses, unless starved outright (sensor timeouts, as in
    # test_bus_noise). What was refused is asserted in run_attacked either way.
    if not faults(attacked.log, "sensor_timeout"):
        assert_settles_like(attacked, clean_realtime)


@pytest.mark.bus
def test_a_second_writer_stops_the_run_at_0v_within_three_periods(tmp_path: Path) -> None:
    with Bench(tmp_path, "realtime", 2.0) as bench:
        assert bench.watch is not None
        bench.wait_cycling()
        time.sleep(0.3)
        # Made with the run's own secret: only a second holder of the key can do this.
        insider = bench.authenticator()
        frames = [
            insider.protect(VOLTAGE_COMMAND_ID, CONTRACT.encode(VoltageCommand(n, 1.0, True, 0))[1])
            for n in range(3)
        ]
        bus = open_bus(BusSection(channel=bench.group, port=bench.port))
        try:
            for data in frames:
                bus.send(can.Message(arbitration_id=VOLTAGE_COMMAND_ID, data=data,
                                     is_extended_id=False, is_fd=True))
                time.sleep(0.001)
        finally:
            bus.shutdown()
        daemon_exit = bench.wait_daemon(START_TIMEOUT_S)
        time.sleep(0.1)
        assert bench.stop_emulator() == 0
        heard = list(bench.watch.frames)
        daemon_stderr = bench.stderr(bench.daemon)
        emulator_stderr = bench.stderr(bench.emulator)
        log_path = bench.log_path
        secret = bench.secret
        argv = [*bench.daemon.args, *bench.emulator.args]  # type: ignore[misc]
    # The run's secret is in no log, no command line and no message of the run.
    assert secret is not None
    raw = log_path.read_bytes()
    assert secret not in raw and secret.hex().encode() not in raw
    assert secret.hex() not in daemon_stderr + emulator_stderr
    assert all(secret.hex() not in str(arg) for arg in argv)
    log = read_log(log_path)
    assert log.metadata["run"]["authenticated"] == "true"
    assert daemon_exit == EXIT_SECOND_WRITER, daemon_stderr[-2000:]
    assert "second writer" in daemon_stderr
    assert summary_meta(log)["end_reason"] == "second_writer"
    assert len(faults(log, "second_writer")) == 1
    assert "reason=second_writer" in events(log, "daemon_stop")[0]["detail"]
    first_insider = next(h for h in heard if h.data in set(frames))
    daemon_after = [
        (h, c) for h in heard
        if h.arbitration_id == VOLTAGE_COMMAND_ID and h.data not in set(frames)
        and h.time_ns >= first_insider.time_ns
        and isinstance(c := decoded(h), VoltageCommand)
    ]
    enabled_after = [h for h, c in daemon_after if c.enable]
    stops = [(h, c) for h, c in daemon_after if not c.enable]
    # Counted in periods (commands), not timed: at most 3 more periods of drive, then 0 V.
    assert len(enabled_after) <= PERIODS_TO_ZERO, len(enabled_after)
    assert stops and all(c.voltage_v == 0.0 for _, c in stops)
    figure("second_writer", {
        "enabled_commands_after_first_insider_frame": len(enabled_after),
        "insider_to_0v_ms": round((stops[0][0].time_ns - first_insider.time_ns) / 1e6, 3),
    })


def test_the_launcher_hands_the_secret_through_a_pipe_and_never_in_argv_or_env(
    tmp_path: Path,
) -> None:
    """``ballbeam run`` on a lock-step bench, its children's argv and environment read from
    /proc while they run: each has --secret-fd N, and fd N holds 32 bytes nobody else saw."""
    from ballbeam.runtime import launcher

    seen: dict[str, tuple[list[str], dict[str, str]]] = {}

    def watch(processes: dict[str, subprocess.Popen[str]]) -> None:
        for name, process in processes.items():
            proc = Path(f"/proc/{process.pid}")
            environ = dict(
                item.split("=", 1) for item in
                (proc / "environ").read_bytes().decode(errors="replace").split("\0") if "=" in item
            )
            seen[name] = (list(process.args), environ)  # type: ignore[arg-type]

    drawn: list[bytes] = []
    keys: list[RunKey] = []

    class SpiedKey(RunKey):
        @classmethod
        def generate(cls) -> RunKey:
            keys.append(RunKey.generate())
            drawn.append(bytes(keys[-1].material))
            return keys[-1]

    group = isolated_group(DEFAULT_BUS_GROUP)
    overrides = ["run.mode='lockstep'", "run.duration_s=0.3", "bus.interface='udp_multicast'",
                 f"bus.channel='{group}'",
                 f"run.log_dir='{tmp_path}'"]
    launcher.RunKey = SpiedKey  # type: ignore[misc]
    try:
        result = launcher.launch_run(None, overrides, on_started=watch)
    finally:
        launcher.RunKey = RunKey  # type: ignore[misc]
    assert result.daemon_exit == 0
    assert len(drawn) == 1
    secret = drawn[0]
    # The launcher held it only to write the pipes: overwritten since.
    assert keys[0].wiped and keys[0]._buffer == bytearray(len(secret))
    for name, (argv, environ) in seen.items():
        assert "--secret-fd" in argv, (name, argv)
        blob = " ".join(argv) + json.dumps(environ)
        assert secret.hex() not in blob and secret.decode("latin-1") not in blob, name
    raw = result.log_path.read_bytes()
    assert secret not in raw and secret.hex().encode() not in raw
    assert read_log(result.log_path).metadata["run"]["authenticated"] == "true"


def test_classic_contract_for_real_can_and_authentication_on_the_virtual_buses() -> None:
    assert load_config(None, ["bus.interface='udp_multicast'"]).bus.authenticated
    assert load_config(None, ["bus.interface='virtual'"]).bus.authenticated
    assert not load_config(
        None, ["bus.interface='socketcan'", "bus.channel='vcan0'"]
    ).bus.authenticated
    assert not load_config(None, ["bus.authenticate=false"]).bus.authenticated


@pytest.mark.bus
def test_a_standalone_daemon_needs_the_run_secret_and_reads_it_from_an_fd(
    tmp_path: Path,
) -> None:
    group = isolated_group(DEFAULT_BUS_GROUP)
    sets = set_args(["bus.interface='udp_multicast'", f"bus.channel='{group}'",
                     "controller.start_timeout_s=0.5"])
    no_secret = subprocess.run(
        ballbeam_argv("daemon", *sets, "--log", str(tmp_path / "a.mcap")),
        capture_output=True, text=True, cwd=REPO, timeout=120, check=False,
    )
    assert no_secret.returncode == 2
    assert "secret" in one_error_line(no_secret.stderr)
    short = subprocess.run(
        ballbeam_argv("daemon", *sets, "--secret-fd", "0", "--log", str(tmp_path / "s.mcap")),
        input=b"too short", capture_output=True, cwd=REPO, timeout=120, check=False,
    )
    assert short.returncode == 2
    assert "32 bytes" in one_error_line(short.stderr.decode())
    alone = subprocess.run(
        ballbeam_argv("daemon", *sets, "--secret-fd", "0", "--log", str(tmp_path / "b.mcap")),
        input=secrets.token_bytes(32), capture_output=True, cwd=REPO, timeout=120, check=False,
    )
    assert alone.returncode == EXIT_PLANT_LOST, alone.stderr
    assert b"no sensor frame from the plant" in alone.stderr


def test_the_mac_is_hmac_sha256_truncated_over_id_freshness_and_payload() -> None:
    """Against an HMAC computed here with hmac/hashlib, from the layout the README gives."""
    from ballbeam.protocol.secoc import FrameAuthenticator

    secret = os.urandom(32)
    sender, receiver = FrameAuthenticator(secret), FrameAuthenticator(secret)
    payload = CONTRACT.encode(VoltageCommand(3, 1.5, True, 7))[1]
    data = sender.protect(VOLTAGE_COMMAND_ID, payload)
    assert len(data) == 24 and data[:8] == payload
    freshness = data[8:16]
    assert abs(int.from_bytes(freshness, "little") - time.monotonic_ns()) < 1e9
    expected = hmac.new(
        secret, VOLTAGE_COMMAND_ID.to_bytes(4, "little") + freshness + payload, hashlib.sha256
    ).digest()[:8]
    assert data[16:] == expected
    assert receiver.verify(VOLTAGE_COMMAND_ID, data) == "ok"
    assert receiver.verify(VOLTAGE_COMMAND_ID, data) == "replayed"  # the same frame again
    later = sender.protect(VOLTAGE_COMMAND_ID, payload)
    newest = sender.protect(VOLTAGE_COMMAND_ID, payload)
    assert receiver.verify(VOLTAGE_COMMAND_ID, newest) == "ok"
    assert receiver.verify(VOLTAGE_COMMAND_ID, later) == "replayed"  # reordered: refused
    tampered = bytearray(sender.protect(VOLTAGE_COMMAND_ID, payload))
    tampered[4] ^= 0x01  # the voltage, MAC untouched
    assert receiver.verify(VOLTAGE_COMMAND_ID, bytes(tampered)) == "bad_mac"
    other_key = FrameAuthenticator(os.urandom(32)).protect(VOLTAGE_COMMAND_ID, payload)
    assert receiver.verify(VOLTAGE_COMMAND_ID, other_key) == "bad_mac"
    assert receiver.verify(VOLTAGE_COMMAND_ID, payload) == "unauthenticated"
    # A right MAC with a freshness 2 s old (a frame kept from a log) to a fresh receiver.
    old = (time.monotonic_ns() - 2_000_000_000).to_bytes(8, "little")
    stale = payload + old + hmac.new(
        secret, VOLTAGE_COMMAND_ID.to_bytes(4, "little") + old + payload, hashlib.sha256
    ).digest()[:8]
    assert FrameAuthenticator(secret).verify(VOLTAGE_COMMAND_ID, stale) == "out_of_window"
    # The sender's own view: its echo once, then a replay; a frame it never sent: a writer.
    assert sender.own_frame(VOLTAGE_COMMAND_ID, newest) == "echo"
    assert sender.own_frame(VOLTAGE_COMMAND_ID, newest) == "replayed"
    assert sender.own_frame(VOLTAGE_COMMAND_ID, receiver.protect(VOLTAGE_COMMAND_ID, payload)) \
        == "not_sent"
    assert sender.own_frame(VOLTAGE_COMMAND_ID, other_key) == "invalid"
    # One of its own frames with a byte changed (its freshness is the sender's own, which the
    # sender takes its very bytes for without a MAC): a stranger's, not an echo.
    assert sender.own_frame(VOLTAGE_COMMAND_ID, bytes(tampered)) == "invalid"
    assert sender.own_frame(VOLTAGE_COMMAND_ID, later[:8] + later[8:16] + bytes(8)) == "invalid"


def test_a_commands_lookahead_is_covered_by_the_same_mac() -> None:
    """The 64-byte frame: payload ‖ look-ahead ‖ freshness ‖ MAC over all three; a flipped
    look-ahead bit, a look-ahead cut off, or one moved onto a sensor frame, is refused."""
    from ballbeam.protocol.frames import decode_lookahead, encode_lookahead
    from ballbeam.protocol.secoc import FrameAuthenticator, extension_of

    secret = os.urandom(32)
    sender, receiver = FrameAuthenticator(secret), FrameAuthenticator(secret)
    payload = CONTRACT.encode(VoltageCommand(3, 1.5, True, 7))[1]
    lookahead = encode_lookahead((1.25, -4.5, 0.0))
    data = sender.protect(VOLTAGE_COMMAND_ID, payload, lookahead)
    assert len(data) == 64 and data[:8] == payload and extension_of(data) == lookahead
    freshness = data[48:56]
    expected = hmac.new(
        secret, VOLTAGE_COMMAND_ID.to_bytes(4, "little") + freshness + payload + lookahead,
        hashlib.sha256,
    ).digest()[:8]
    assert data[56:] == expected
    tampered = bytearray(data)
    tampered[9] ^= 0x01  # the first look-ahead value
    assert receiver.verify(VOLTAGE_COMMAND_ID, bytes(tampered)) == "bad_mac"
    cut = data[:8] + data[48:]  # the look-ahead removed, freshness and MAC kept
    assert receiver.verify(VOLTAGE_COMMAND_ID, cut) == "bad_mac"
    assert receiver.verify(VOLTAGE_COMMAND_ID + 1, data) == "bad_mac"  # the id is in the MAC
    assert receiver.verify(VOLTAGE_COMMAND_ID, data) == "ok"
    assert decode_lookahead(extension_of(data)) == (1.25, -4.5, 0.0)
    with pytest.raises(ValueError, match="extension is 40 bytes"):
        sender.protect(VOLTAGE_COMMAND_ID, payload, lookahead[:-2])
