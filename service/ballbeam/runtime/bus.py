"""Opening the CAN bus as configured, and refusing one whose traffic would leave the host.

``bus.interface = "auto"`` (the default) is SocketCAN on a CAN FD vcan interface where the
kernel has one (``ballbeam bus setup`` creates them), and ``udp_multicast`` on an
interface-local IPv6 group (``ff11::/16``, scope 1) otherwise: the kernel loops such packets
back to local listeners and never transmits them. Wider scopes and IPv4 groups go out on the
network and are refused unless ``bus.allow_off_host`` is set.
"""

from __future__ import annotations

import contextlib
import ipaddress
import os
import secrets
import socket
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can

from ballbeam.config import BusSection
from ballbeam.errors import BusError

INTERFACE_LOCAL_SCOPE = 1
VCAN_HINT = (
    "create it with: sudo modprobe vcan && sudo ip link add dev {channel} type vcan "
    "&& sudo ip link set {channel} mtu 72 && sudo ip link set up {channel} "
    "(or: sudo ballbeam bus setup)"
)
ARPHRD_CAN = 280  # /sys/class/net/<name>/type of a CAN interface (linux/if_arp.h)
CANFD_MTU = 72  # a CAN FD interface's MTU (struct canfd_frame); classic CAN: 16
CLASSIC_CAN_MTU = 16
SYS_NET = Path("/sys/class/net")
# The launcher tells its daemon why "auto" chose the bus it did (recorded in the log).
BUS_CHOICE_ENV = "BALLBEAM_BUS_CHOICE"


def multicast_scope(group: str) -> int | None:
    """IPv6 multicast scope nibble, or None for an IPv4 group."""
    try:
        address = ipaddress.ip_address(group)
    except ValueError as error:
        raise BusError(f"bus.channel {group!r} is not an IP multicast group address") from error
    if not address.is_multicast:
        raise BusError(f"bus.channel {group!r} is not a multicast address")
    if isinstance(address, ipaddress.IPv4Address):
        return None
    return address.packed[1] & 0x0F


def check_stays_on_host(bus: BusSection) -> None:
    """Raise BusError when the configured bus would send frames off this host (``auto``: when
    its ``udp_multicast`` fallback would)."""
    if bus.interface not in ("udp_multicast", "auto") or bus.allow_off_host:
        return
    scope = multicast_scope(bus.channel)
    if scope != INTERFACE_LOCAL_SCOPE:
        where = "an IPv4 group" if scope is None else f"scope {scope:x}"
        raise BusError(
            f"bus.channel {bus.channel} is {where}: its traffic leaves this host. Use an "
            "interface-local ff11:: group, or set bus.allow_off_host = true deliberately"
        )


def check_before_start(bus: BusSection) -> None:
    """Raise BusError for a bus that ``ballbeam run``, ``daemon`` or ``emulator`` cannot use,
    before any process starts or log is made: one whose traffic leaves the host; python-can's
    ``virtual`` bus, which lives inside one interpreter (tests run both nodes in one process on
    it), while the daemon and the emulator are processes of their own; a SocketCAN interface
    this host does not have (looked up, not opened: nothing is sent)."""
    check_stays_on_host(bus)
    if bus.interface == "virtual":
        raise BusError(
            "bus.interface = 'virtual' is python-can's in-process bus: the daemon and the "
            "emulator are separate processes and would never hear each other; use "
            "udp_multicast (the default) or socketcan"
        )
    if bus.interface == "socketcan":
        if not socketcan_available():
            raise BusError(
                f"cannot use bus socketcan:{bus.channel}: this kernel has no SocketCAN "
                "(AF_CAN sockets); use udp_multicast (the default)"
            )
        try:
            socket.if_nametoindex(bus.channel)
        except OSError:
            raise BusError(
                f"cannot use bus socketcan:{bus.channel}: no such interface; "
                + VCAN_HINT.format(channel=bus.channel)
            ) from None


def isolated_group(group: str) -> str:
    """The same group prefix with random low 64 bits: a private bus for one run, as long as
    its sockets hear only their own group (open_bus sees to that; python-can alone binds the
    wildcard address and, on Linux, hears every group joined on its port). The launcher also
    gives each run its own port (free_udp_port), for listeners that do not opt out."""
    try:
        address = ipaddress.IPv6Address(group)
    except ipaddress.AddressValueError as error:
        raise BusError(
            f"bus.channel {group}: a private group per run (bus.isolate_runs) is drawn from an "
            "IPv6 group's low 64 bits; use an ff11:: group, or set bus.isolate_runs = false"
        ) from error
    prefix = int(address) >> 64 << 64
    return str(ipaddress.IPv6Address(prefix | secrets.randbits(64)))


# Linux hands a multicast datagram to every socket bound to its port as soon as any socket on
# the host has joined its group, unless the socket opts out (on by default). Two runs on
# different private groups but the same port would hear each other's frames, which are valid
# frames. python-can does not opt out; open_bus does. (BSD-derived systems deliver only the
# groups a socket joined.) Values from linux/in6.h and linux/in.h.
IPV6_MULTICAST_ALL = 29
IP_MULTICAST_ALL = 49


def _hear_own_group_only(opened: can.BusABC) -> None:
    """Make a udp_multicast bus's socket receive only the group it joined (Linux)."""
    if not sys.platform.startswith("linux"):
        return
    sock = getattr(getattr(opened, "_multicast", None), "_socket", None)
    if not isinstance(sock, socket.socket):
        raise BusError(
            "cannot reach python-can's udp_multicast socket to make it hear only its own "
            "group; without that, runs on other groups of the same port would be heard"
        )
    if sock.family == socket.AF_INET6:
        level, option = socket.IPPROTO_IPV6, IPV6_MULTICAST_ALL
    else:
        level, option = socket.IPPROTO_IP, IP_MULTICAST_ALL
    try:
        sock.setsockopt(level, option, 0)
    except OSError as error:
        raise BusError(
            f"cannot make the udp_multicast socket hear only its own group: {error}"
        ) from error


def free_udp_port() -> int:
    """A UDP port no socket on this host holds right now (the kernel's pick)."""
    import socket

    with socket.socket(socket.AF_INET6, socket.SOCK_DGRAM) as probe:
        probe.bind(("::1", 0))
        port: int = probe.getsockname()[1]
    return port


# -- SocketCAN vcan interfaces, and what "auto" picks --------------------------------------


@dataclass(frozen=True)
class CanInterface:
    """A SocketCAN network interface of this host."""

    name: str
    mtu: int
    up: bool
    virtual: bool  # a vcan (its driver is vcan), not an adapter

    @property
    def fd(self) -> bool:
        return self.mtu >= CANFD_MTU


def can_interfaces(sys_net: Path = SYS_NET) -> list[CanInterface]:
    """This host's CAN interfaces by name ([] without SocketCAN)."""
    found = []
    try:
        names = sorted(os.listdir(sys_net))
    except OSError:
        return []
    for name in names:
        node = sys_net / name
        try:
            if int((node / "type").read_text()) != ARPHRD_CAN:
                continue
            mtu = int((node / "mtu").read_text())
            flags = int((node / "flags").read_text(), 16)
        except (OSError, ValueError):
            continue
        driver = ""
        with contextlib.suppress(OSError):
            driver = os.path.basename(os.readlink(node / "device" / "driver"))
        # A vcan has no device behind it; an adapter's driver is named there.
        virtual = not (node / "device").exists() or driver == "vcan"
        found.append(CanInterface(name, mtu, bool(flags & 0x1), virtual))  # IFF_UP
    return found


def _interface(name: str) -> CanInterface | None:
    return next((found for found in can_interfaces() if found.name == name), None)


# A run holds its vcan interface by binding an abstract Unix socket named after it: one name
# per network namespace, whoever the user, and released by the kernel when the holder dies.
CLAIM_PREFIX = "ballbeam-bus-"


def claim_interface(name: str) -> socket.socket | None:
    """Hold ``name`` for this process's run (close the socket to let go); None if another
    run holds it."""
    claim = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    try:
        claim.bind(f"\0{CLAIM_PREFIX}{name}")
    except OSError:
        claim.close()
        return None
    return claim


@dataclass(frozen=True)
class AutoChoice:
    """What ``bus.interface = "auto"`` resolved to, and why (the run says so)."""

    interface: str  # "socketcan" or "udp_multicast"
    channel: str
    reason: str
    claim: socket.socket | None = None  # held for the run (launcher): vcan interfaces only

    def overrides_for(self, bus: BusSection) -> list[str]:
        """``--set`` overrides that make a child's config of ``bus`` name this choice (and
        keep auto's framing: authenticated unless ``bus.authenticate`` says otherwise)."""
        return [
            f"bus.interface='{self.interface}'",
            f"bus.channel='{self.channel}'",
            f"bus.authenticate={str(bus.authenticated).lower()}",
        ]

    def release(self) -> None:
        if self.claim is not None:
            self.claim.close()


def resolve_auto(bus: BusSection, claim: bool) -> AutoChoice:
    """Where an ``auto`` bus goes: the first CAN FD vcan interface that is up and that no
    run holds, else ``udp_multicast`` on ``bus.channel``. With ``claim`` (a run launcher)
    the interface is held for the run: parallel runs each get a vcan of their own while
    there are enough, and the interface-local group after."""
    fallback = "udp_multicast"
    if not socketcan_available():
        return AutoChoice(fallback, bus.channel, "no SocketCAN in this kernel")
    vcans = [found for found in can_interfaces() if found.virtual]
    usable = [found for found in vcans if found.up and found.fd]
    for found in usable:
        held = claim_interface(found.name)
        if held is None:
            continue  # another run's
        if not claim:
            held.close()
            held = None
        return AutoChoice("socketcan", found.name, "a CAN FD vcan interface", held)
    if usable:
        why = f"every CAN FD vcan interface is in use by another run ({len(usable)})"
    elif vcans:
        listed = ", ".join(
            f"{found.name} {'classic (MTU 16)' if not found.fd else 'down'}" for found in vcans
        )
        why = f"no CAN FD vcan interface that is up ({listed}); see `ballbeam bus setup`"
    else:
        why = "no vcan interface (`ballbeam bus setup` creates them)"
    return AutoChoice(fallback, bus.channel, why)


def resolved_bus(bus: BusSection, choice: AutoChoice) -> BusSection:
    """``bus`` on the interface and channel ``choice`` names, its framing kept."""
    return bus.model_copy(update={
        "interface": choice.interface, "channel": choice.channel,
        "authenticate": bus.authenticated,
    })


def open_bus(bus: BusSection) -> can.BusABC:
    """A python-can bus for ``bus``; BusError with a remedy when it cannot be opened.

    A ``udp_multicast`` bus hears its own group only, not other groups on the same port. An
    ``auto`` bus (a node started alone) takes the first CAN FD vcan that is up, else the
    group: both nodes of a run started by hand find the same one. An authenticated
    ``socketcan`` bus is opened for CAN FD, and refused on a classic interface.
    """
    check_stays_on_host(bus)
    if bus.interface == "auto":
        bus = resolved_bus(bus, resolve_auto(bus, claim=False))
    options: dict[str, Any] = dict(bus.options)
    if bus.interface == "udp_multicast":
        options.setdefault("port", bus.port)
        options.setdefault("hop_limit", 1)
    if bus.interface == "socketcan" and bus.authenticated:
        found = _interface(bus.channel)
        if found is not None and not found.fd:
            raise BusError(
                f"bus {bus.channel} is classic CAN (MTU {found.mtu}): authenticated frames are "
                f"CAN FD. Make it one (sudo ip link set {bus.channel} down && sudo ip link set "
                f"{bus.channel} mtu {CANFD_MTU} && sudo ip link set up {bus.channel}), or "
                "set bus.authenticate = false for the classic 8-byte contract"
            )
        options.setdefault("fd", True)
    try:
        opened = can.Bus(interface=bus.interface, channel=bus.channel, **options)
    except ImportError as error:
        raise BusError(
            f"bus interface {bus.interface!r} needs a package that is not installed: {error}"
        ) from error
    except (OSError, can.CanError, ValueError, TypeError) as error:
        hint = ""
        if bus.interface == "socketcan":
            hint = "; " + VCAN_HINT.format(channel=bus.channel)
        raise BusError(
            f"cannot open bus {bus.interface}:{bus.channel}: {error}{hint}"
        ) from error
    if bus.interface == "udp_multicast":
        try:
            _hear_own_group_only(opened)
        except BusError:
            opened.shutdown()
            raise
    return opened


MAX_MALFORMED_PER_CALL = 64


class ReceiveQueue:
    """A socket's receive queue, the kernel's own size or a short one (SO_RCVBUF).

    A queue absorbs a burst: a process off its CPU for tens of ms reads the backlog after,
    nothing lost. But a queue that stays full only delays every frame: under a flood the
    daemon, reading at its limit, read every sample tens of ms late out of the kernel's
    default (docs/decisions.md).
    Short, the kernel drops what the reader could not have read in time anyway (the counters
    show it). The loop asks for short while it stays behind the stream, long again once it
    has kept up for a while (a standing queue, not a burst, is what to cut)."""

    SHORT_BYTES = 16 * 1024  # the kernel doubles it: ~25 datagrams on loopback, a few periods

    def __init__(self, bus: can.BusABC) -> None:
        try:
            fd = bus.fileno()
        except NotImplementedError:  # python-can's virtual bus, in-process: no socket
            fd = -1
        self._socket = socket.socket(fileno=fd) if fd >= 0 else None
        self.short = False
        self.shortened = 0  # how many times it was made short
        self._long_bytes = self._size()

    def _size(self) -> int:
        if self._socket is None:
            return 0
        return self._socket.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)

    def set_short(self, short: bool) -> None:
        if short == self.short or self._socket is None:
            return
        # The kernel doubles what it is given; the long size was read back, so halve it.
        size = self.SHORT_BYTES if short else self._long_bytes // 2
        with contextlib.suppress(OSError):  # refused: the queue stays as it is
            self._socket.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, size)
            self.short = short
            self.shortened += short

    def sizes(self) -> str:
        """The two sizes [bytes, as the kernel counts them], for the log."""
        return f"{self._long_bytes} / {2 * self.SHORT_BYTES}"

    def close(self) -> None:
        """Forget the socket (the descriptor stays the bus's)."""
        if self._socket is not None:
            self._socket.detach()
            self._socket = None


def recv_frame(
    bus: can.BusABC,
    timeout_s: float,
    on_malformed: Callable[[str], None],
    poll_s: float = 0.0,
) -> can.Message | None:
    """``bus.recv``, except that noise which is not a CAN frame at all does not kill the node.

    A datagram python-can cannot turn into a message (udp_multicast: not msgpack, or not a
    valid frame) raises CanOperationError from inside ``recv``; it is reported to
    ``on_malformed`` and skipped, and the wait goes on until ``timeout_s`` from the call.
    Returns a message, or None when the time is up (with ``timeout_s`` 0: once
    MAX_MALFORMED_PER_CALL datagrams were skipped, so that a stream of them cannot hold the
    caller). Failures of the socket itself (an OSError underneath) still raise.

    ``poll_s`` > 0: first poll without blocking for up to that long, yielding the CPU between
    polls. A reply expected within tens of microseconds (lock-step) then costs no wake-up
    from sleep, which here is as long as the whole exchange; yielding keeps the poll from
    starving a process that shares the core.
    """
    now = time.monotonic()
    deadline = now + timeout_s
    poll_until = now + min(poll_s, timeout_s)
    skipped = 0
    while True:
        now = time.monotonic()
        polling = now < poll_until
        wait_s = 0.0 if polling else max(0.0, deadline - now)
        try:
            message = bus.recv(timeout=wait_s)
        except can.CanOperationError as error:
            if isinstance(error.__cause__, OSError):
                raise
            cause = f": {error.__cause__}" if error.__cause__ is not None else ""
            on_malformed(f"{error}{cause}")
            skipped += 1
            if skipped >= MAX_MALFORMED_PER_CALL and time.monotonic() >= deadline:
                return None
            continue
        if message is not None or not polling:
            return message
        os.sched_yield()


def socketcan_available() -> bool:
    """True when this kernel supports AF_CAN sockets (SocketCAN)."""
    import socket

    try:
        probe = socket.socket(socket.PF_CAN, socket.SOCK_RAW, socket.CAN_RAW)
    except (OSError, AttributeError):
        return False
    probe.close()
    return True


# -- ``ballbeam bus setup`` ----------------------------------------------------------------

VCAN_PREFIX = "vcan"


def setup_commands(
    count: int, fd: bool, existing: list[CanInterface], prefix: str = VCAN_PREFIX
) -> list[list[str]]:
    """The commands (root's) that make ``prefix0`` … ``prefix{count-1}`` vcan interfaces that
    are up, CAN FD (MTU 72) or classic (16): what is already right is left alone."""
    mtu = CANFD_MTU if fd else CLASSIC_CAN_MTU
    by_name = {found.name: found for found in existing}
    commands: list[list[str]] = []
    for index in range(count):
        name = f"{prefix}{index}"
        found = by_name.get(name)
        if found is not None and found.mtu == mtu and found.up:
            continue
        if found is None:
            commands.append(["ip", "link", "add", "dev", name, "type", "vcan"])
        elif found.up and found.mtu != mtu:
            commands.append(["ip", "link", "set", name, "down"])  # the MTU changes when down
        if found is None or found.mtu != mtu:
            commands.append(["ip", "link", "set", name, "mtu", str(mtu)])
        commands.append(["ip", "link", "set", "up", name])
    if not commands:
        return []
    return [["modprobe", "vcan"], ["modprobe", "can-raw"], *commands]


def run_setup(commands: list[list[str]]) -> None:
    """Run ``commands`` in order (as root); BusError naming the first that fails."""
    import subprocess

    for command in commands:
        try:
            done = subprocess.run(command, capture_output=True, text=True, check=False,
                                  timeout=30)
        except (OSError, subprocess.TimeoutExpired) as error:
            raise BusError(f"cannot run {' '.join(command)}: {error}") from error
        if done.returncode != 0:
            said = (done.stderr or done.stdout).strip().splitlines()
            raise BusError(
                f"{' '.join(command)} failed: {said[-1] if said else done.returncode}"
                + ("; this kernel has no vcan: runs go over udp_multicast (README: "
                   "\"SocketCAN in a VM\")" if command[0] == "modprobe" or "vcan" in command
                   else "")
            )
