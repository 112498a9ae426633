"""Checks on a path a user names before it is opened (a FIFO blocks the open, a device never
ends): only regular files are read as configs and logs. And the one way files are created:
every file a command writes (log, recovered log, report, plot, layout, JUnit XML) is new, made
exclusively and never through a symbolic link, so that no command can write over a recording,
or through a link someone planted, into a file it was never meant to touch."""

from __future__ import annotations

import contextlib
import errno
import os
import secrets
import shutil
import stat
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import BinaryIO

from ballbeam.errors import ConfigError, OutputExistsError

# O_EXCL: fail if anything (a link included: O_CREAT|O_EXCL never follows one) is there.
# O_NOFOLLOW says the same of the last component for kernels that would not.
NEW_FILE_FLAGS = os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC
# link() refused by a filesystem without hard links (FAT, some network and FUSE ones).
_NO_HARD_LINKS = frozenset({errno.EPERM, errno.EOPNOTSUPP, errno.ENOTSUP, errno.ENOSYS,
                            errno.EMLINK})
_TEMPORARY_ATTEMPTS = 16

StrPath = str | os.PathLike[str]


def not_a_regular_file(path: str | os.PathLike[str]) -> str | None:
    """Why ``path`` cannot be read as a file (None if it is a regular file or does not exist:
    opening it then gives the usual not-found error)."""
    try:
        mode = os.stat(path).st_mode
    except FileNotFoundError:
        return None
    except OSError as error:
        return f"cannot inspect it: {error.strerror or error}"
    if stat.S_ISREG(mode):
        return None
    if stat.S_ISDIR(mode):
        return "it is a directory, not a file"
    if stat.S_ISFIFO(mode):
        return "it is a pipe (FIFO), not a file"
    if stat.S_ISCHR(mode) or stat.S_ISBLK(mode):
        return "it is a device, not a file"
    if stat.S_ISSOCK(mode):
        return "it is a socket, not a file"
    return "it is not a regular file"


def exists_message(path: StrPath) -> str:
    """The one line that refuses to write ``path`` because something is there."""
    if os.path.islink(path):
        return f"{os.fspath(path)} is a symbolic link: refused (nothing is written through one)"
    return f"{os.fspath(path)} exists: refused (nothing is written over; name a new file)"


def create_new(path: StrPath) -> BinaryIO:
    """``path`` opened for writing as a file this call creates. OutputExistsError naming it if
    anything is there (a file, a link, dangling or not); OSError for the rest."""
    try:
        fd = os.open(path, NEW_FILE_FLAGS, 0o666)
    except FileExistsError as error:
        raise OutputExistsError(exists_message(path)) from error
    except OSError as error:
        if error.errno == errno.ELOOP:  # O_NOFOLLOW met a link where O_EXCL did not
            raise OutputExistsError(exists_message(path)) from error
        raise
    return os.fdopen(fd, "wb")


def temporary_beside(path: StrPath) -> tuple[Path, BinaryIO]:
    """A new hidden file in ``path``'s directory, under a random name (so nothing can be
    planted there beforehand), to be written whole and then put in place by
    :func:`link_new`."""
    target = Path(path)
    for _ in range(_TEMPORARY_ATTEMPTS):
        temporary = target.with_name(f".{target.name}.{secrets.token_hex(4)}.part")
        try:
            return temporary, create_new(temporary)
        except OutputExistsError:
            continue
    raise OutputExistsError(f"cannot make a temporary file beside {target}: every name is taken")


def link_new(temporary: StrPath, path: StrPath) -> None:
    """Give the whole file ``temporary`` the name ``path`` only if nothing is there: link()
    never replaces and never follows a link at its destination (rename() would replace).
    ``temporary`` keeps its name too: the caller removes it. Where the filesystem has no hard
    links, the bytes are copied into a file created exclusively instead."""
    try:
        os.link(temporary, path, follow_symlinks=False)
    except FileExistsError as error:
        raise OutputExistsError(exists_message(path)) from error
    except OSError as error:
        if error.errno not in _NO_HARD_LINKS:
            raise
        with open(temporary, "rb") as source, create_new(path) as copy:
            shutil.copyfileobj(source, copy)
            copy.flush()
            os.fsync(copy.fileno())


def write_new(path: StrPath, content: bytes | Callable[[BinaryIO], None]) -> None:
    """Write a new file whole: into a temporary file beside it, then put in place by
    :func:`link_new`, so that it is never half written, never replaces anything and never
    goes through a link. ``content``: the bytes, or a function that writes them to a stream.
    OutputExistsError naming ``path`` if anything is there; OSError for the rest."""
    if os.path.lexists(path):
        raise OutputExistsError(exists_message(path))
    _write_whole_beside(path, content, lambda temporary: link_new(temporary, path))


def replace_file(path: StrPath, content: bytes | Callable[[BinaryIO], None]) -> None:
    """Write a file whole that takes the place of a command's own earlier output (a resumed
    study's table and plots): into a temporary file beside it, then renamed over it. rename()
    replaces a link standing at ``path`` itself, never the file it points to."""
    _write_whole_beside(path, content, lambda temporary: os.replace(temporary, path))


def _write_whole_beside(
    path: StrPath,
    content: bytes | Callable[[BinaryIO], None],
    put_in_place: Callable[[Path], None],
) -> None:
    """``content`` into a new temporary file beside ``path``, on disk, then ``put_in_place``;
    the temporary is gone afterwards whatever happened."""
    temporary, stream = temporary_beside(path)
    try:
        with stream:
            if isinstance(content, bytes):
                stream.write(content)
            else:
                content(stream)
            stream.flush()
            os.fsync(stream.fileno())
        put_in_place(temporary)
    finally:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(temporary)


def _same_file(a: StrPath, b: StrPath) -> bool:
    try:
        return os.path.samefile(a, b)
    except OSError:
        return Path(a).resolve() == Path(b).resolve()


def check_new_outputs(outputs: Iterable[StrPath | None], inputs: Iterable[StrPath] = ()) -> None:
    """Refuse, before any work, outputs that are there already (above all the input a command
    reads, or a link to it) or that are named twice. None entries are outputs not asked for."""
    named = [Path(output) for output in outputs if output is not None]
    sources = list(inputs)
    seen: dict[Path, Path] = {}
    for output in named:
        for source in sources:
            if os.path.lexists(output) and _same_file(output, source):
                same = "" if output == Path(source) else f" ({os.fspath(source)})"
                raise OutputExistsError(
                    f"{output} is the file this command reads{same}: refused (name a new "
                    "file for the output)"
                )
        if os.path.lexists(output):
            raise OutputExistsError(exists_message(output))
        key = Path(os.path.abspath(output))
        if key in seen:
            raise ConfigError(f"{output} is named for two outputs; name one file for each")
        seen[key] = output


def remove_if_empty(path: StrPath) -> bool:
    """Remove ``path`` if it is an empty regular file (a log made for a run that never wrote
    to it); True if it did. Anything else is left alone."""
    try:
        status = os.lstat(path)
    except FileNotFoundError:
        return False
    if not stat.S_ISREG(status.st_mode) or status.st_size != 0:
        return False
    with contextlib.suppress(FileNotFoundError):
        os.unlink(path)
    return True
