"""Opening the CAN bus as configured, and refusing one whose traffic would leave the host.

``udp_multicast`` on an interface-local IPv6 group (``ff11::/16``, scope 1) is the default: the
kernel loops such packets back to local listeners and never transmits them. Wider scopes and
IPv4 groups go out on the network and are refused unless ``bus.allow_off_host`` is set.
"""

from __future__ import annotations

import ipaddress
import os
import secrets
import socket
import sys
import time
from collections.abc import Callable
from typing import Any

import can

from ballbeam.config import BusSection
from ballbeam.errors import BusError

INTERFACE_LOCAL_SCOPE = 1
VCAN_HINT = (
    "create it with: sudo modprobe vcan && sudo ip link add dev {channel} type vcan "
    "&& sudo ip link set up {channel}"
)


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
    """Raise BusError when the configured bus would send frames off this host."""
    if bus.interface != "udp_multicast" or bus.allow_off_host:
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


def open_bus(bus: BusSection) -> can.BusABC:
    """A python-can bus for ``bus``; BusError with a remedy when it cannot be opened.

    A ``udp_multicast`` bus hears its own group only, not other groups on the same port.
    """
    check_stays_on_host(bus)
    options: dict[str, Any] = dict(bus.options)
    if bus.interface == "udp_multicast":
        options.setdefault("port", bus.port)
        options.setdefault("hop_limit", 1)
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
