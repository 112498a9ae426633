"""What every node process does around its loop: CPU and scheduling, no core dumps, a settled
heap, the provenance a log records (package versions, git revision), the log's file name."""

from __future__ import annotations

import argparse
import contextlib
import ctypes
import datetime as dt
import gc
import logging
import os
import platform
import resource
import secrets
import signal
import stat
import subprocess
import threading
from collections.abc import Iterator
from importlib import metadata
from pathlib import Path
from typing import TYPE_CHECKING, BinaryIO

from ballbeam.errors import OutputExistsError, RecorderError
from ballbeam.files import create_new, exists_message
from ballbeam.protocol.secoc import RunKey
from ballbeam.runtime.ticker import scheduled_realtime

if TYPE_CHECKING:  # the config stack (pydantic, numpy) loads when a command reads a config
    from ballbeam.config import Config

log = logging.getLogger("ballbeam")

# A checkout's root (service/ballbeam/runtime/process.py); an installed package has none.
CHECKOUT_ROOT = Path(__file__).resolve().parents[3]
REALTIME_SWITCH_INTERVAL_S = 2e-4
PACKAGES = ("ballbeam-hil", "numpy", "scipy", "python-can", "mcap", "pydantic", "cantools")


LOG_NAME_ATTEMPTS = 8


def log_directory(log_dir: str | Path) -> Path:
    """The run's log directory, absolute. One that is missing is made, but only its last
    level (as ``mkdir`` without ``-p``): the default ``logs/`` beside where the command runs,
    or ``runs/today`` in an existing ``runs/``. A deeper missing path is far more likely a typo
    or a disk not mounted than a place to fill, and is refused, naming it."""
    directory = Path(log_dir).absolute()
    if directory.is_dir():
        return directory
    try:
        directory.mkdir()
    except FileNotFoundError as error:
        raise RecorderError(
            f"log directory {directory} does not exist, nor does {directory.parent}: create "
            "it first (only the last level of a log directory is made)"
        ) from error
    except FileExistsError as error:  # a file, or a dangling link, stands there
        raise RecorderError(
            f"cannot create log directory {directory}: something that is not a directory "
            "is there"
        ) from error
    except OSError as error:
        raise RecorderError(
            f"cannot create log directory {directory}: {error.strerror or error}"
        ) from error
    return directory


def new_log_file(log_dir: str | Path, kind: str) -> tuple[Path, BinaryIO]:
    """A new log file, created here and open for writing: its name unique and sortable (UTC
    time to the microsecond, then a random suffix; absolute, so the path a run prints opens
    from anywhere). Created exclusively, so that nothing planted at the name (a link to
    another file) is ever written through: a taken name is passed over for another."""
    directory = log_directory(log_dir)
    for _ in range(LOG_NAME_ATTEMPTS):
        stamp = dt.datetime.now(dt.UTC).strftime("%Y%m%dT%H%M%S.%fZ")
        path = directory / f"{stamp}_{kind}_{secrets.token_hex(3)}.mcap"
        try:
            return path, create_new(path)
        except OutputExistsError:
            log.warning("%s was there already (not written through); taking another name", path)
        except OSError as error:
            raise RecorderError(
                f"cannot create log {path}: {error.strerror or error}"
            ) from error
    raise RecorderError(f"cannot create a log in {directory}: every name tried was taken")


def log_from_arguments(args: argparse.Namespace, config: Config) -> tuple[Path, BinaryIO | None]:
    """Where the daemon records, and the stream if it is open already: ``--log-fd N`` (a new,
    empty file that ``ballbeam run`` created, named by ``--log``), ``--log PATH`` (None: the
    recorder creates it, a new file only), else a new file in ``run.log_dir``."""
    fd = getattr(args, "log_fd", None)
    if fd is None:
        if args.log:
            if os.path.lexists(args.log):  # said before the plan is made; the open is exclusive
                raise OutputExistsError(f"log {exists_message(args.log)}")
            return Path(args.log), None
        return new_log_file(config.run.log_dir, config.plan.kind)
    if not args.log:
        raise RecorderError("--log-fd needs --log naming the file it is open on")
    try:
        status = os.fstat(fd)
    except OSError as error:
        raise RecorderError(f"--log-fd {fd}: {error.strerror or error}") from error
    if not stat.S_ISREG(status.st_mode) or status.st_size != 0:
        raise RecorderError(
            f"--log-fd {fd}: not an empty regular file (a log is only written to a new file)"
        )
    return Path(args.log), os.fdopen(fd, "wb")


def git_revision() -> str:
    """The checkout's revision, or "installed" when the package is not run from a checkout."""
    if not (CHECKOUT_ROOT / "service" / "ballbeam").is_dir():
        return "installed"
    try:
        result = subprocess.run(
            ["git", "-C", str(CHECKOUT_ROOT), "describe", "--always", "--dirty", "--abbrev=12"],
            capture_output=True, text=True, timeout=5, check=False,
        )
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return result.stdout.strip() or "unknown"


def package_versions() -> dict[str, str]:
    versions = {}
    for name in PACKAGES:
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            versions[name] = "not installed"
    return versions


def apply_scheduling(
    cpu: int | None, realtime_priority: int, fair_slice_us: int = 0
) -> dict[str, str]:
    """Pin to a CPU and/or switch to SCHED_FIFO (priority 0: don't); what was refused is
    reported in one line that says how to grant it, not fatal (an unprivileged user still gets
    a working, if jittery, bench). Left at normal scheduling, ask for a short time slice
    (``fair_slice_us``; 0: the kernel's), which any user may."""
    applied: dict[str, str] = {}
    if cpu is not None and cpu >= 0:
        try:
            os.sched_setaffinity(0, {cpu})
            applied["cpu"] = str(cpu)
        except OSError as error:
            applied["cpu"] = f"refused: {error.strerror}"
            log.warning("cannot pin to CPU %d: %s", cpu, error.strerror)
    if realtime_priority:
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(realtime_priority))
            applied["realtime_priority"] = f"SCHED_FIFO {realtime_priority}"
        except OSError as error:
            applied["realtime_priority"] = f"refused: {error.strerror}"
            log.warning("%s", realtime_refused_message(
                realtime_priority, error.strerror or "not permitted"
            ))
    if fair_slice_us and not scheduled_realtime():
        applied["fair_slice"] = request_fair_slice(fair_slice_us)
    return applied


_SYS_SCHED_SETATTR = {"x86_64": 314, "aarch64": 274}
_SCHED_OTHER = 0


class _SchedAttr(ctypes.Structure):
    """``struct sched_attr`` (include/uapi/linux/sched/types.h), its first version."""

    _fields_ = (
        ("size", ctypes.c_uint32), ("policy", ctypes.c_uint32), ("flags", ctypes.c_uint64),
        ("nice", ctypes.c_int32), ("priority", ctypes.c_uint32), ("runtime_ns", ctypes.c_uint64),
        ("deadline_ns", ctypes.c_uint64), ("period_ns", ctypes.c_uint64),
        ("util_min", ctypes.c_uint32), ("util_max", ctypes.c_uint32),
    )


def request_fair_slice(slice_us: int) -> str:
    """Ask the fair scheduler (EEVDF, Linux 6.12 and later) for a time slice of ``slice_us``
    (it keeps it within 0.1–100 ms). A task with a shorter slice than the others gets an earlier
    virtual deadline, so it preempts a CPU-bound process when its timer wakes it instead of
    waiting for that process's slice to end (about 3 ms), and no permission is needed. Older
    kernels accept and ignore it. Returns what happened, for the log's metadata."""
    number = _SYS_SCHED_SETATTR.get(platform.machine())
    if number is None:
        return f"not asked: no sched_setattr number known for {platform.machine()}"
    attr = _SchedAttr(
        size=ctypes.sizeof(_SchedAttr), policy=_SCHED_OTHER,
        nice=os.getpriority(os.PRIO_PROCESS, 0), runtime_ns=slice_us * 1000,
    )
    libc = ctypes.CDLL(None, use_errno=True)
    if libc.syscall(number, 0, ctypes.byref(attr), 0) != 0:
        reason = os.strerror(ctypes.get_errno())
        log.info("a %d µs time slice was refused (%s): the kernel's default stays", slice_us,
                 reason)
        return f"refused: {reason}"
    return f"{slice_us} us"


_PR_SET_PDEATHSIG = 1  # linux/prctl.h
_PR_GET_DUMPABLE = 3
_PR_SET_DUMPABLE = 4


def _prctl(option: int, value: int = 0) -> int:
    """``prctl(option, value)``: its result, or -1 where there is none (not Linux)."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        return int(libc.prctl(option, value, 0, 0, 0))
    except (OSError, AttributeError):
        return -1


def dumpable() -> int:
    """This process's dumpable flag (``PR_GET_DUMPABLE``: 1 yes, 0 no; -1: not Linux)."""
    return _prctl(_PR_GET_DUMPABLE)


def forbid_core_dumps() -> None:
    """Never write this process's memory anywhere: core size limit 0 (soft and hard: nothing
    it starts can raise it again) and not dumpable (``PR_SET_DUMPABLE`` 0: no core even
    through a piped ``core_pattern``, which ignores the size limit, and no ptrace or
    /proc/PID/mem for other processes of the same user). A node holds the run's key for the
    whole run: a crash or a ``kill -ABRT`` would otherwise write it, with the rest of the
    heap, into a core file in the working directory."""
    with contextlib.suppress(ValueError, OSError):
        resource.setrlimit(resource.RLIMIT_CORE, (0, 0))
    if _prctl(_PR_SET_DUMPABLE, 0) not in (0, -1):
        log.warning("cannot make this process undumpable: %s", os.strerror(ctypes.get_errno()))


_NO_DUMP_LOCK = threading.Lock()
_no_dump_holders = 0  # launches inside no_core_dumps_while now (regress launches in threads)
_dump_state_before: tuple[int, int, int] = (1, 0, 0)  # dumpable, soft and hard core limits


@contextlib.contextmanager
def no_core_dumps_while() -> Iterator[None]:
    """:func:`forbid_core_dumps` for a while (the launcher holds the key only to hand it on),
    then the process's soft core limit and dumpable flag as they were before the first of the
    threads that overlap in here came in."""
    global _no_dump_holders, _dump_state_before
    with _NO_DUMP_LOCK:
        if _no_dump_holders == 0:
            soft, hard = resource.getrlimit(resource.RLIMIT_CORE)
            _dump_state_before = (dumpable(), soft, hard)
            with contextlib.suppress(ValueError, OSError):
                resource.setrlimit(resource.RLIMIT_CORE, (0, hard))
            _prctl(_PR_SET_DUMPABLE, 0)
        _no_dump_holders += 1
    try:
        yield
    finally:
        with _NO_DUMP_LOCK:
            _no_dump_holders -= 1
            if _no_dump_holders == 0:
                was_dumpable, soft, hard = _dump_state_before
                if was_dumpable > 0:
                    _prctl(_PR_SET_DUMPABLE, was_dumpable)
                with contextlib.suppress(ValueError, OSError):
                    resource.setrlimit(resource.RLIMIT_CORE, (soft, hard))


def stop_with_parent() -> None:
    """Have the kernel send this process SIGTERM when the process that started it dies (the
    ``ballbeam run`` launcher, even killed with SIGKILL): the node then stops as if asked,
    instead of running on alone for the rest of its run. Linux only; elsewhere nothing."""
    parent = os.getppid()
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        done = libc.prctl(_PR_SET_PDEATHSIG, signal.SIGTERM, 0, 0, 0)
    except (OSError, AttributeError):
        return
    if done != 0:
        log.info("cannot ask to stop with the launcher: %s", os.strerror(ctypes.get_errno()))
    elif os.getppid() != parent or parent == 1:
        os.kill(os.getpid(), signal.SIGTERM)  # it died before we asked


CAP_SYS_NICE = 23  # capability bit (linux/capability.h)


def realtime_permitted(priority: int) -> bool:
    """Whether this process may take SCHED_FIFO ``priority``: CAP_SYS_NICE, or an rtprio
    limit that high (what the kernel checks)."""
    if priority <= 0:
        return True
    try:
        with open("/proc/self/status", encoding="ascii") as status:
            for line in status:
                if line.startswith("CapEff:") and int(line.split()[1], 16) >> CAP_SYS_NICE & 1:
                    return True
    except OSError:
        pass
    soft, _ = resource.getrlimit(resource.RLIMIT_RTPRIO)
    return soft == resource.RLIM_INFINITY or soft >= priority


def realtime_refused_message(priority: int, reason: str = "not permitted") -> str:
    """One line: what was refused, what it costs, and how to grant it."""
    return (
        f"real-time scheduling refused (SCHED_FIFO {priority}: {reason}): running at normal "
        "priority, where other jobs' load makes the loop late (the angle guard keeps the "
        "lateness it measures as margin); to grant it, run as root, or give this user an "
        f"rtprio limit of {priority} or more ('USER - rtprio {priority}' in "
        "/etc/security/limits.conf, then log in again), or 'setcap cap_sys_nice+ep' on the "
        "Python interpreter"
    )


def settle_heap() -> None:
    """Collect once, then exempt every object alive now from later collections.

    A full collection of the tens of thousands of objects numpy, scipy, pydantic and the
    controller design leave behind stalls the loop for many periods (README, benchmarks), and
    the interpreter starts one whenever enough allocations pile up. Frozen, they are never
    scanned again, so the collections the loop's own allocations trigger stay short.
    """
    gc.collect()
    gc.freeze()




def configure_logging() -> None:
    logging.basicConfig(level=logging.INFO, format="%(name)s: %(levelname)s: %(message)s")


def add_config_arguments(parser: argparse.ArgumentParser) -> None:
    """A config file (or a shipped config's name) and ``--set`` overrides, for every command."""
    parser.add_argument(
        "config",
        nargs="?",
        help="TOML config file, or a shipped config's name (`ballbeam configs` lists them; "
        "default: the paper's set-up, as in paper.toml)",
    )
    parser.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a config key, e.g. --set plan.kind=rate_limited (repeatable)",
    )


def add_secret_argument(parser: argparse.ArgumentParser) -> None:
    """``--secret-fd N``: read the run's 32-byte secret from inherited file descriptor N."""
    parser.add_argument(
        "--secret-fd",
        type=int,
        metavar="N",
        help="read the run's 32-byte frame-authentication secret from file descriptor N "
        "(ballbeam run passes a pipe; alone: --secret-fd 0 < secret.bin). Never put a "
        "secret on the command line",
    )


def secret_from_arguments(args: argparse.Namespace) -> RunKey | None:
    """The secret ``--secret-fd`` names (read once, the descriptor closed), or None. The
    caller wipes it when its run ends."""
    from ballbeam.errors import BusError
    from ballbeam.protocol.secoc import read_secret

    fd = getattr(args, "secret_fd", None)
    if fd is None:
        return None
    try:
        return read_secret(fd)
    except (OSError, ValueError) as error:
        raise BusError(f"cannot read the run secret from --secret-fd {fd}: {error}") from error


def resolve_config_argument(args: argparse.Namespace) -> None:
    """Turn ``args.config`` into the absolute path of the file it names: child processes and
    the log then get the file itself, wherever the name led."""
    from ballbeam.config import resolve_config_path

    if getattr(args, "config", None):
        args.config = str(resolve_config_path(args.config).resolve())


def config_from_arguments(args: argparse.Namespace) -> Config:
    from ballbeam.config import load_config

    return load_config(args.config, args.overrides)
