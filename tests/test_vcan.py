"""The virtual SocketCAN bus, for real: runs over vcan interfaces, standard tools on them, and
what ``bus.interface = "auto"`` does.

The ``vcan``-marked tests need a kernel with SocketCAN and vcan interfaces that are up (one CAN
FD, MTU 72; one classic, MTU 16: ``sudo ballbeam bus setup`` and ``sudo ballbeam bus setup
--classic --prefix vcanc --count 1``) and can-utils. Where the kernel has none they skip, saying
so; CI then runs them in a VM (``.ci/vcan``), with ``BALLBEAM_VCAN_REQUIRED=1`` (missing
pieces fail instead) and ``BALLBEAM_VCAN_LOG_DIR`` (the runs' logs, verified afterwards on the
host by ``test_vm_logs_verify_on_the_host``).
"""

from __future__ import annotations

import json
import os
import re
import shutil
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import can
import cantools
import numpy as np
import pytest
from cantools.autosar.end_to_end import check_profile5_crc

from ballbeam.cli import main as cli_main
from ballbeam.config import DEFAULT_BUS_GROUP, BusSection
from ballbeam.errors import BusError
from ballbeam.logs.reader import read_log
from ballbeam.protocol.frames import SENSOR_ID, VOLTAGE_COMMAND_ID, FrameContract
from ballbeam.protocol.secoc import AUTHENTICATED_LENGTH, EXTENDED_LENGTH, MAC_BYTES
from ballbeam.runtime import bus as bus_module
from ballbeam.runtime.bus import (
    CanInterface,
    can_interfaces,
    claim_interface,
    open_bus,
    resolve_auto,
    setup_commands,
    socketcan_available,
)

from .conftest import PAPER, REPO, ballbeam_argv

REQUIRED = os.environ.get("BALLBEAM_VCAN_REQUIRED") == "1"
# Lock-step runs in the VM go ~25 times slower than on the host (an emulated CPU): short ones.
DURATION_S = 0.4
VM_LOGS_ENV = "BALLBEAM_VCAN_VM_LOGS"


def _missing(what: str) -> None:
    why = what if socketcan_available() else (
        "no SocketCAN in this kernel (socket(AF_CAN): errno 97); CI runs these in a VM: .ci/vcan"
    )
    if REQUIRED:
        pytest.fail(f"BALLBEAM_VCAN_REQUIRED, but {why}")
    pytest.skip(why)


def _vcan(fd: bool) -> str:
    for found in can_interfaces():
        if found.virtual and found.up and found.fd == fd and socketcan_available():
            return found.name
    _missing(
        f"no {'CAN FD (MTU 72)' if fd else 'classic (MTU 16)'} vcan interface that is up "
        f"(sudo ballbeam bus setup{'' if fd else ' --classic --prefix vcanc --count 1'})"
    )
    raise AssertionError("unreachable")


@pytest.fixture(scope="module")
def vcan_fd() -> str:
    return _vcan(fd=True)


@pytest.fixture(scope="module")
def vcan_classic() -> str:
    return _vcan(fd=False)


@pytest.fixture(scope="module")
def can_utils() -> None:
    if shutil.which("cansend") is None or shutil.which("candump") is None:
        _missing("can-utils (cansend, candump) not installed")


@pytest.fixture(scope="module")
def log_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Where the runs' logs go: the host verifies the VM's (BALLBEAM_VCAN_LOG_DIR)."""
    shared = os.environ.get("BALLBEAM_VCAN_LOG_DIR")
    return Path(shared) if shared else tmp_path_factory.mktemp("vcan-logs")


def _run(log_dir: Path, *overrides: str, wait: bool = True) -> subprocess.Popen[str]:
    argv = ballbeam_argv(
        "run", str(PAPER), "--json",
        *(item for override in (
            f"run.log_dir='{log_dir}'", "run.mode='lockstep'", f"run.duration_s={DURATION_S}",
            # On the VM's emulated CPU the two nodes take minutes to start and may stall for
            # seconds: timeouts meant to catch a dead peer, not a slow one.
            "controller.start_timeout_s=900", "controller.lockstep_timeout_s=60",
            *overrides,
        ) for item in ("--set", override)),
    )
    process = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                               cwd=REPO)
    if wait:
        process.wait(timeout=540)
    return process


def _summary(process: subprocess.Popen[str]) -> dict[str, object]:
    stdout, stderr = process.communicate(timeout=540)
    assert process.returncode == 0, stderr
    summary: dict[str, object] = json.loads(stdout)
    return summary


def _commands(summary: dict[str, object]) -> np.ndarray:
    values = read_log(Path(str(summary["log_path"]))).topics["/command"].values
    return np.asarray(values["voltage_v"])


def _emulator(summary: dict[str, object]) -> dict[str, int]:
    counters = summary["plant_counters"]
    assert isinstance(counters, dict), summary
    return {str(key): int(value) for key, value in counters.items()}


def _check_slow_machine_figures(summary: dict[str, object]) -> None:
    """Lock-step on a slow machine. Once the daemon answers, the emulator sends a sample again
    only when an answer takes far longer than the round trips before it (its wait is
    measured, plant.lockstep_resend_ms a floor under it), and its watchdog only trips after
    such a wait went unanswered too: a clean run on a machine of its own has neither
    (test_lockstep_answers.py). In the VM the two runs share two emulated CPUs, each with the
    other's three processes and the cansends, and on a loaded host those CPUs stop for over
    a second at times: measured 4-81 resends and 1-24 trips in 400 cycles (docs/decisions.md).
    Neither changes what a lock-step run computes (the two runs command alike bit for bit, and
    like the host's own run over udp_multicast). The bound, a quarter of the cycles each,
    catches a broken wait (a resend every cycle), not the VM's speed.
    (Before the daemon's first answer the emulator repeats its first sample, backing off;
    its own resend count includes those, which the daemon, not yet listening, never hears.)"""
    emulator = _emulator(summary)
    meta = read_log(Path(str(summary["log_path"]))).metadata["summary"]
    cycles = int(str(summary["cycles"]))
    print(f"{summary['bus']}: {cycles} cycles, {meta['sensor_frames_repeated']} samples "
          f"resent while the daemon listened, {emulator['resends']} resends in all, "
          f"{emulator['watchdog_trips']} watchdog trips, {summary['wall_time_s']:.0f} s")
    bound = cycles // 4
    assert emulator["watchdog_trips"] <= bound, emulator
    assert int(meta["sensor_frames_repeated"]) <= bound, meta


# -- over vcan ------------------------------------------------------------------------------
# Two runs (the VM's emulated CPU makes each costly): one under auto on the CAN FD vcan, one on
# the classic vcan, with standard tools writing and reading frames while they go.


# candump's socket buffer: the VM's emulated CPUs stall for seconds while the runs' processes
# start, and the default buffer (a few hundred frames) then overflows.
CANDUMP_BUFFER_BYTES = 8 << 20


@dataclass
class _Dump:
    """candump, its output read as it comes: unread, the pipe fills after ~1,400 lines, candump
    blocks on it and the frames still in its socket are lost when it is stopped."""

    process: subprocess.Popen[str]
    lines: list[str]
    reader: threading.Thread


def _candump(interface: str) -> _Dump:
    process = subprocess.Popen(
        ["candump", "-d", "-r", str(CANDUMP_BUFFER_BYTES), "-L", interface],
        stdout=subprocess.PIPE, text=True,
    )
    lines: list[str] = []
    assert process.stdout is not None
    reader = threading.Thread(target=lambda: lines.extend(process.stdout or ()), daemon=True)
    reader.start()
    time.sleep(0.5)  # it binds before the run starts
    return _Dump(process, lines, reader)


def _dumped(dump: _Dump) -> list[tuple[int, bytes]]:
    time.sleep(1.0)  # what the runs sent last reaches candump's socket and its output
    dump.process.terminate()
    dump.process.wait(timeout=10)
    dump.reader.join(timeout=10)
    frames = []
    for line in dump.lines:
        # -d: the kernel's count of frames the socket dropped, when it grows
        assert not line.startswith("DROPCOUNT"), f"candump lost frames: {line}"
        # "(1700000000.123456) vcan0 101#0A0B..." (classic) or "101##0..." (CAN FD, flags nibble)
        match = re.fullmatch(r"\(\S+\) \S+ ([0-9A-F]{3})#(#[0-9A-F])?([0-9A-F]*)", line.strip())
        assert match, line
        frames.append((int(match[1], 16), bytes.fromhex(match[3])))
    return frames


def _cansend(interface: str, arbitration_id: int, data: bytes, fd: bool) -> None:
    frame = f"{arbitration_id:03X}#{'#0' if fd else ''}{data.hex().upper()}"
    subprocess.run(["cansend", interface, frame], check=True, timeout=30)


def _sample_once_running(interface: str, fd: bool, run: subprocess.Popen[str]) -> bytes:
    """A sensor frame of ``run`` heard on ``interface`` after the daemon's first command: the
    daemon then listens (the emulator sends its first sample, again and again, while the
    daemon still starts: minutes on the VM's emulated CPU)."""
    commanded = False
    with can.Bus(interface="socketcan", channel=interface, fd=fd) as listener:
        while run.poll() is None:
            message = listener.recv(timeout=1.0)
            if message is None:
                continue
            commanded = commanded or message.arbitration_id == VOLTAGE_COMMAND_ID
            if commanded and message.arbitration_id == SENSOR_ID:
                return bytes(message.data)
    _, stderr = run.communicate()
    raise AssertionError(f"the run ended ({run.returncode}) before its daemon commanded on "
                         f"{interface}: {stderr[-2000:]}")


# On the VM's emulated CPU a run's three Python processes take minutes to start under load:
# the CI step's budget bounds these, not the suite's per-test one.
VM_TIMEOUT = pytest.mark.timeout(1500)


@dataclass(frozen=True)
class VcanRuns:
    """The two runs' outcomes: the one under auto on the CAN FD vcan, the one on the classic
    vcan with what candump recorded there, and the wrong-CRC frame cansend wrote on it."""

    fd: dict[str, object]
    classic: dict[str, object]
    classic_frames: list[tuple[int, bytes]]
    classic_wrong_crc: bytes


FD_CANSENDS = 9


@pytest.fixture(scope="module")
def vcan_runs(vcan_fd: str, vcan_classic: str, can_utils: None, log_dir: Path) -> VcanRuns:
    """Both runs at once (each is a lock-step ping-pong that keeps about one of the VM's two
    emulated CPUs busy; one after the other they took most of the CI step's budget).

    On the CAN FD vcan, under auto: can-utils' cansend writes forged (a zeroed MAC), replayed
    (an authentic frame heard earlier) and classic frames with a wrong CRC, three of each.
    On the classic vcan (named: socketcan's default contract is the classic one): candump
    records it, and cansend writes one sensor frame with a wrong CRC."""
    dump = _candump(vcan_classic)
    fd = _run(log_dir, wait=False)
    classic = _run(log_dir, "bus.interface='socketcan'", f"bus.channel='{vcan_classic}'",
                   wait=False)
    authentic = _sample_once_running(vcan_fd, fd=True, run=fd)
    assert len(authentic) == EXTENDED_LENGTH  # a sensor frame carries its sample's truth
    forged = authentic[:-MAC_BYTES] + bytes(MAC_BYTES)
    wrong_crc = bytes((authentic[0] ^ 0xFF,)) + authentic[1:8]
    for _ in range(FD_CANSENDS // 3):
        _cansend(vcan_fd, SENSOR_ID, forged, fd=True)
        _cansend(vcan_fd, SENSOR_ID, authentic, fd=True)  # its freshness is past
        _cansend(vcan_fd, SENSOR_ID, wrong_crc, fd=False)
    classic_authentic = _sample_once_running(vcan_classic, fd=False, run=classic)
    classic_wrong_crc = bytes((classic_authentic[0] ^ 0xFF,)) + classic_authentic[1:]
    _cansend(vcan_classic, SENSOR_ID, classic_wrong_crc, fd=False)
    fd_summary, classic_summary = _summary(fd), _summary(classic)
    return VcanRuns(fd_summary, classic_summary, _dumped(dump), classic_wrong_crc)


@pytest.fixture(scope="module")
def fd_run(vcan_runs: VcanRuns) -> dict[str, object]:
    return vcan_runs.fd


@pytest.fixture(scope="module")
def classic_run(vcan_runs: VcanRuns) -> tuple[dict[str, object], list[tuple[int, bytes]], bytes]:
    return vcan_runs.classic, vcan_runs.classic_frames, vcan_runs.classic_wrong_crc


@pytest.mark.vcan
@VM_TIMEOUT
def test_auto_runs_authenticated_on_the_fd_vcan_and_says_so(
    vcan_fd: str, fd_run: dict[str, object]
) -> None:
    assert fd_run["bus"] == f"socketcan:{vcan_fd}", fd_run["bus"]
    assert "CAN FD vcan" in str(fd_run["bus_choice"])
    run_log = read_log(Path(str(fd_run["log_path"])))
    assert run_log.metadata["run"]["authenticated"] == "true"
    assert run_log.metadata["run"]["bus"] == fd_run["bus"]
    assert run_log.metadata["run"]["bus_choice"] == fd_run["bus_choice"]
    received = run_log.topics["/can/rx"].values
    authenticated = received["dlc"] != 8  # 8: cansend's classic frames
    # SecOC, CAN FD lengths: a sensor frame with its truth, the plant's status frames
    assert set(np.unique(received["dlc"][authenticated])) == {EXTENDED_LENGTH, AUTHENTICATED_LENGTH}
    assert np.count_nonzero(~authenticated) == 3
    _check_slow_machine_figures(fd_run)


@pytest.mark.vcan
@VM_TIMEOUT
def test_cansend_frames_on_the_fd_vcan_are_refused_and_counted(
    fd_run: dict[str, object],
) -> None:
    counts = read_log(Path(str(fd_run["log_path"]))).metadata["summary"]
    assert int(counts["rejected_bad_mac"]) == 3, counts
    # A frame older than the last taken is a replay, whenever it comes (out-of-window ones are
    # the emulator's own, read over a second late on a stalled VM).
    assert int(counts["rejected_replayed"]) == 3, counts
    # A classic frame is judged by the contract first: its wrong CRC.
    assert int(counts.get("rejected_crc", 0)) + int(counts.get("rejected_unauthenticated", 0)) == 3


@pytest.mark.vcan
@VM_TIMEOUT
def test_classic_vcan_carries_the_e2e_contract_that_candump_and_cantools_read(
    classic_run: tuple[dict[str, object], list[tuple[int, bytes]], bytes],
) -> None:
    """socketcan defaults to the DBC's classic contract (real adapters): every frame candump
    records is 8 bytes with a right AUTOSAR E2E profile 5 CRC and decodes with the shipped
    DBC through cantools, the commands as the log has them; a frame with a wrong CRC from
    cansend is refused and counted."""
    summary, frames, wrong_crc = classic_run
    run_log = read_log(Path(str(summary["log_path"])))
    assert run_log.metadata["run"]["authenticated"] == "false"
    assert int(run_log.metadata["summary"]["rejected_crc"]) == 1
    _check_slow_machine_figures(summary)
    logged_v = _commands(summary)
    database = cantools.database.load_file(str(FrameContract.load().path))
    ours = [(frame_id, data) for frame_id, data in frames if data != wrong_crc]
    assert len(ours) == len(frames) - 1
    assert len(ours) >= 4 * len(logged_v)  # a sensor, two truth and a command a cycle
    voltages, last_counter = [], None
    for frame_id, data in ours:
        assert len(data) == 8
        assert check_profile5_crc(data, frame_id), (hex(frame_id), data.hex())
        # choices as numbers: a named value ("MotorOff") is truthy whatever it names
        decoded = database.decode_message(frame_id, data, decode_choices=False)
        # A lock-step resend repeats a command (same counter): each command once.
        if frame_id == VOLTAGE_COMMAND_ID and decoded["Enable"] and (
            decoded["Counter"] != last_counter
        ):
            voltages.append(float(decoded["Voltage"]))
            last_counter = decoded["Counter"]
    assert len(voltages) == len(logged_v)
    np.testing.assert_allclose(voltages, logged_v, atol=0.5e-3)  # the DBC's 1 mV


@pytest.mark.vcan
@VM_TIMEOUT
def test_both_vcan_runs_command_alike_bit_for_bit(
    fd_run: dict[str, object],
    classic_run: tuple[dict[str, object], list[tuple[int, bytes]], bytes],
) -> None:
    """Authenticated or classic, attacked or not: one design, one machine, the same commands
    (against udp_multicast on the host: test_vm_logs_verify_on_the_host)."""
    assert np.array_equal(_commands(fd_run), _commands(classic_run[0]))


def test_an_authenticated_socketcan_bus_on_a_classic_interface_is_refused(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    classic = CanInterface("vcanc0", 16, True, True)
    monkeypatch.setattr(bus_module, "can_interfaces", lambda: [classic])
    with pytest.raises(BusError, match=r"classic CAN .*mtu 72"):
        open_bus(BusSection(interface="socketcan", channel="vcanc0", authenticate=True))


# -- the VM's logs, on the host ---------------------------------------------------------------


def test_vm_logs_verify_on_the_host(tmp_path: Path) -> None:
    """Each log the VM wrote re-runs bit for bit here on its recorded design; against the
    same run over udp_multicast here, its commands differ only by the design: the VM's
    emulated CPU synthesises the gains a few 1e-12 apart (BLAS kernels, docs/design.md §5),
    and the commands follow by ~1e-9 V."""
    from ballbeam.evaluation.replay import verify

    where = os.environ.get(VM_LOGS_ENV)
    if not where:
        pytest.skip(f"no VM logs to verify ({VM_LOGS_ENV} unset; .ci/vcan sets it)")
    logs = sorted(Path(where).glob("*.mcap"))
    assert logs, f"no logs in {where}"
    host = _summary(_run(tmp_path, "bus.interface='udp_multicast'", wait=False))
    for path in logs:
        run_log = read_log(path)
        result = verify(run_log)
        assert result.ok, (path, result.mismatch)
        assert result.design_source == "recorded"
        difference = result.resynthesis_difference
        assert isinstance(difference, float) and difference < 1e-9, (path, difference)
        vm_v = np.asarray(run_log.topics["/command"].values["voltage_v"])
        host_v = _commands(host)
        assert len(vm_v) == len(host_v)
        worst_v = float(np.max(np.abs(vm_v - host_v)))
        print(f"{path.name}: {run_log.metadata['run']['bus']}, verified; resynthesis "
              f"{difference:.3g}; commands against the host's udp run: max |Δ| {worst_v:.3g} V")
        assert worst_v <= 1e-8, path


# -- auto, claims and `bus setup`, anywhere -----------------------------------------------------


def _fake_net(root: Path, name: str, mtu: int, up: bool, kind: int = 280) -> None:
    node = root / name
    node.mkdir()
    (node / "type").write_text(f"{kind}\n")
    (node / "mtu").write_text(f"{mtu}\n")
    (node / "flags").write_text("0x41\n" if up else "0x0\n")


def test_can_interfaces_reads_sysfs(tmp_path: Path) -> None:
    _fake_net(tmp_path, "lo", 65536, True, kind=772)
    _fake_net(tmp_path, "vcan0", 72, True)
    _fake_net(tmp_path, "vcanc0", 16, False)
    assert can_interfaces(tmp_path) == [
        CanInterface("vcan0", 72, True, True), CanInterface("vcanc0", 16, False, True)
    ]


def _auto_with(monkeypatch: pytest.MonkeyPatch, interfaces: list[CanInterface]) -> None:
    monkeypatch.setattr(bus_module, "socketcan_available", lambda: True)
    monkeypatch.setattr(bus_module, "can_interfaces", lambda: interfaces)
    monkeypatch.setattr(bus_module, "CLAIM_PREFIX", f"ballbeam-test-{os.getpid()}-")


def test_auto_gives_each_run_a_vcan_of_its_own_then_the_group(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    _auto_with(monkeypatch, [
        CanInterface("can0", 72, True, False),  # a real adapter: never chosen by auto
        CanInterface("vcan0", 72, True, True),
        CanInterface("vcan1", 72, True, True),
        CanInterface("vcanc0", 16, True, True),  # classic: no room for authenticated frames
    ])
    bus = BusSection()
    first, second = resolve_auto(bus, claim=True), resolve_auto(bus, claim=True)
    third = resolve_auto(bus, claim=True)
    try:
        assert (first.interface, first.channel) == ("socketcan", "vcan0")
        assert (second.interface, second.channel) == ("socketcan", "vcan1")
        assert (third.interface, third.channel) == ("udp_multicast", DEFAULT_BUS_GROUP)
        assert "in use by another run" in third.reason
        assert third.overrides_for(bus)[-1] == "bus.authenticate=true"
        # A node started alone takes the first free one without holding it.
        assert resolve_auto(bus, claim=False).interface == "udp_multicast"
        first.release()
        assert resolve_auto(bus, claim=False).channel == "vcan0"
        again = resolve_auto(bus, claim=True)
        assert again.channel == "vcan0"  # free again, and held
        again.release()
    finally:
        for choice in (first, second, third):
            choice.release()


def test_auto_without_socketcan_or_usable_vcan_says_why(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(bus_module, "socketcan_available", lambda: False)
    assert resolve_auto(BusSection(), claim=True).reason == "no SocketCAN in this kernel"
    _auto_with(monkeypatch, [CanInterface("vcan0", 16, True, True)])
    choice = resolve_auto(BusSection(), claim=True)
    assert choice.interface == "udp_multicast"
    assert "vcan0 classic (MTU 16)" in choice.reason


def test_a_claim_is_held_until_released_whoever_asks() -> None:
    name = f"test-{os.getpid()}"
    held = claim_interface(name)
    assert held is not None
    assert claim_interface(name) is None
    # Another process is refused as well (one name per network namespace).
    probe = subprocess.run(
        [sys.executable, "-c", "import socket,sys; s=socket.socket(socket.AF_UNIX,"
         f"socket.SOCK_DGRAM); s.bind('\\0ballbeam-bus-{name}')"],
        capture_output=True, check=False,
    )
    assert probe.returncode != 0 and b"Address already in use" in probe.stderr
    held.close()
    again = claim_interface(name)
    assert again is not None
    again.close()


def test_setup_commands_make_what_is_missing_only() -> None:
    assert setup_commands(1, True, []) == [
        ["modprobe", "vcan"], ["modprobe", "can-raw"],
        ["ip", "link", "add", "dev", "vcan0", "type", "vcan"],
        ["ip", "link", "set", "vcan0", "mtu", "72"],
        ["ip", "link", "set", "up", "vcan0"],
    ]
    ready = [CanInterface("vcan0", 72, True, True), CanInterface("vcan1", 16, True, True)]
    assert setup_commands(1, True, ready) == []
    assert setup_commands(2, True, ready)[2:] == [
        ["ip", "link", "set", "vcan1", "down"],
        ["ip", "link", "set", "vcan1", "mtu", "72"],
        ["ip", "link", "set", "up", "vcan1"],
    ]


def test_bus_setup_prints_the_commands_to_a_user_who_is_not_root(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setattr(bus_module, "can_interfaces", lambda: [])
    monkeypatch.setattr(os, "geteuid", lambda: 1000)
    assert cli_main(["bus", "setup", "--count", "1"]) == 0
    out, err = capsys.readouterr()
    assert "not root" in err
    assert out.splitlines() == [
        "modprobe vcan", "modprobe can-raw", "ip link add dev vcan0 type vcan",
        "ip link set vcan0 mtu 72", "ip link set up vcan0",
    ]


@pytest.mark.bus
def test_a_run_says_which_bus_auto_took(tmp_path: Path) -> None:
    expected = resolve_auto(BusSection(), claim=False)
    summary = _summary(_run(tmp_path, "run.duration_s=0.2", wait=False))
    assert str(summary["bus"]).split(":", 1)[0] == expected.interface
    assert str(summary["bus_choice"]).startswith("auto: ")
    run_log = read_log(Path(str(summary["log_path"])))
    assert run_log.metadata["run"]["bus_choice"] == summary["bus_choice"]
    assert run_log.metadata["run"]["bus"] == summary["bus"]


def test_socket_family_probe_matches_the_kernel() -> None:
    try:
        socket.socket(socket.PF_CAN, socket.SOCK_RAW, socket.CAN_RAW).close()
        expected = True
    except OSError:
        expected = False
    assert socketcan_available() == expected
