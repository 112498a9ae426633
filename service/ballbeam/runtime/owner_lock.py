"""The fast half of the dead-man link: a robust, process-shared mutex the daemon holds for its
whole life, and that the emulator waits on.

Why not the pipe alone (runtime/peer_link.py): the kernel closes a dying process's files only
after it has torn down its memory, 7–16 ms for a daemon with NumPy and SciPy loaded. A robust
mutex is released far earlier in the same exit: the kernel walks the dying thread's robust list
(marking each held mutex "owner died" and waking one waiter) before it frees any memory, so the
lock is free 0.1–0.5 ms after SIGKILL, whatever the daemon's size. The pipe stays: it carries
the "run over" byte, and it is the fallback where this lock cannot be had.

The emulator needs no thread for it: once a sensor period it tries the lock without blocking,
which fails while the daemon lives and succeeds ("owner died") once it is dead. The mutex lives
in a memfd the launcher creates and initialises, then hands to both processes (``pass_fds``;
``BALLBEAM_PEER_LOCK_FD``). A word next to it says the daemon has taken the lock, so that the
emulator, which starts first, never takes a lock nobody holds yet for a death.
The emulator holds a second mutex the same way, which the daemon tries when sensor samples stop
coming: a live emulator that missed a few periods (starved of CPU on a loaded machine) is
coasted over for longer before the drive is zeroed, a dead one is not waited for at all.
glibc on Linux only; elsewhere :func:`create_owner_lock` returns None and the pipe does it all.
"""

from __future__ import annotations

import ctypes
import logging
import mmap
import os
from collections.abc import Mapping

log = logging.getLogger("ballbeam")

PEER_LOCK_ENV = "BALLBEAM_PEER_LOCK_FD"
_REGION_BYTES = mmap.PAGESIZE
# One slot per holder, each a mutex (pthread_mutex_t: 40 bytes on x86-64, 48 on aarch64) and
# at +128 a uint32 that is 1 once its holder has taken it.
DAEMON_SLOT = 0
EMULATOR_SLOT = 1
_SLOT_BYTES = 256
_HELD_OFFSET = 128
_ATTR_BYTES = 64  # pthread_mutexattr_t: 4 or 8 bytes
_PTHREAD_PROCESS_SHARED = 1
_PTHREAD_MUTEX_ROBUST = 1
_EOWNERDEAD = 130
_PROT_READ_WRITE = mmap.PROT_READ | mmap.PROT_WRITE
_MAP_FAILED = ctypes.c_void_p(-1).value


def _libc() -> ctypes.CDLL | None:
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        for name in ("pthread_mutex_init", "pthread_mutex_trylock", "pthread_mutexattr_setrobust"):
            getattr(libc, name)
        libc.mmap.restype = ctypes.c_void_p
        libc.mmap.argtypes = (ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int, ctypes.c_int,
                              ctypes.c_int, ctypes.c_long)
    except (OSError, AttributeError):
        return None
    return libc


class OwnerLock:
    """One process's view of one holder's mutex (``slot``: whose, DAEMON_SLOT or
    EMULATOR_SLOT)."""

    def __init__(self, fd: int, slot: int = DAEMON_SLOT) -> None:
        libc = _libc()
        if libc is None:
            raise OSError("no process-shared robust mutexes here (glibc on Linux needed)")
        self._libc = libc
        # Mapped by libc, never unmapped: the kernel reads a dead holder's robust list from this
        # memory at its exit, after the interpreter has finalised (and would have unmapped an
        # mmap object); the waiter's mapping is as long-lived, and one page.
        address = libc.mmap(None, _REGION_BYTES, _PROT_READ_WRITE, mmap.MAP_SHARED, fd, 0)
        if address is None or address == _MAP_FAILED:
            raise OSError(ctypes.get_errno(), "cannot map the peer lock")
        self._mutex = ctypes.c_void_p(address + slot * _SLOT_BYTES)
        self._held = ctypes.c_uint32.from_address(address + slot * _SLOT_BYTES + _HELD_OFFSET)
        self._gone = False

    @classmethod
    def from_environment(
        cls, environ: Mapping[str, str] = os.environ, slot: int = DAEMON_SLOT
    ) -> OwnerLock | None:
        """The lock ``ballbeam run`` handed this process, if any (a bad one: a warning, and
        the pipe alone does the work)."""
        value = environ.get(PEER_LOCK_ENV)
        if value is None:
            return None
        try:
            return cls(int(value), slot)
        except (ValueError, OSError) as error:
            log.warning("%s=%r unusable (%s): a dead peer is noticed more slowly (the pipe, "
                        "or the silence)", PEER_LOCK_ENV, value, error)
            return None

    def hold(self) -> bool:
        """Its holder, from its main thread, once: take the lock and never give it back. Its
        death, however it dies, releases it as "owner died". False (and a warning) if refused."""
        error = self._libc.pthread_mutex_lock(self._mutex)
        if error not in (0, _EOWNERDEAD):
            log.warning("cannot take the peer lock (%s): the peer notices this process's death "
                        "more slowly (the pipe, or the silence)", os.strerror(error))
            return False
        self._held.value = 1
        return True

    @property
    def taken(self) -> bool:
        """Has the holder taken its lock (it may have died since: :meth:`holder_gone`)?"""
        return self._held.value == 1

    def holder_gone(self) -> bool:
        """The peer, once a period: has the holder that took the lock died? One
        non-blocking try (about a microsecond): it fails while the holder lives, and succeeds,
        "owner died", from the moment the kernel has walked the dead holder's robust list."""
        if self._gone:
            return True
        if not self.taken:  # the holder is still starting
            return False
        error = self._libc.pthread_mutex_trylock(self._mutex)
        self._gone = error in (0, _EOWNERDEAD)  # 0: released, which a holder never does
        return self._gone


def create_owner_lock() -> int | None:
    """The launcher: a memfd holding an initialised robust, process-shared mutex (not
    inheritable: it is passed explicitly), or None where there is none to be had."""
    libc = _libc()
    if libc is None or not hasattr(os, "memfd_create"):
        return None
    fd = os.memfd_create("ballbeam-peer-lock", os.MFD_CLOEXEC)
    try:
        os.ftruncate(fd, _REGION_BYTES)
        with mmap.mmap(fd, _REGION_BYTES, flags=mmap.MAP_SHARED) as region:
            attr = ctypes.create_string_buffer(_ATTR_BYTES)
            failed = (
                libc.pthread_mutexattr_init(attr)
                or libc.pthread_mutexattr_setpshared(attr, _PTHREAD_PROCESS_SHARED)
                or libc.pthread_mutexattr_setrobust(attr, _PTHREAD_MUTEX_ROBUST)
            )
            for slot in (DAEMON_SLOT, EMULATOR_SLOT):
                mutex = ctypes.c_char.from_buffer(region, slot * _SLOT_BYTES)
                failed = failed or libc.pthread_mutex_init(ctypes.byref(mutex), attr)
                del mutex  # the buffer's export must end before the mapping closes
    except OSError:
        os.close(fd)
        return None
    if failed:
        os.close(fd)
        return None
    return fd
