"""What the VM's Python processes read, listed on the host for .ci/vcan-guest to copy into the
guest's memory first (each file over 9p on the emulated CPU costs milliseconds a time, and
every process start reads about a thousand of them).

Run as ``sitecustomize`` (``PYTHONPATH`` holding this directory and ``VCAN_STAGE_OUT`` set):
each process then appends, at exit, the files of its loaded modules and shared libraries;
without ``VCAN_STAGE_OUT`` (in the guest) it finds what the copies lack on the host's files.
Run as ``python .ci/vcan-stage.py OUT TREE... -- LIST...``: puts the files of the lists, and
every file under each TREE (the project's import roots), in the archive OUT, and prints the
``PYTHONPATH`` that puts the copies first, in the processes' own order.
"""

from __future__ import annotations

import atexit
import importlib.abc
import importlib.machinery
import os
import sys
import tarfile
from collections.abc import Sequence
from importlib.machinery import ModuleSpec
from types import ModuleType

STAGE = "/tmp/stage"
LARGE_BYTES = 2 << 20


def _loaded_files() -> set[str]:
    modules = list(sys.modules.values())
    files = {getattr(m, "__file__", None) for m in modules}
    files |= {getattr(m, "__cached__", None) for m in modules}  # the bytecode read, if any
    found = {os.path.realpath(f) for f in files if isinstance(f, str) and os.path.isfile(f)}
    with open("/proc/self/maps") as maps:  # shared libraries loaded by extension modules
        for line in maps:
            path = line.split(maxsplit=5)[-1].strip()
            if path.startswith("/") and ".so" in path and os.path.isfile(path):
                found.add(os.path.realpath(path))
    return found


def _dump() -> None:
    out = os.environ.get("VCAN_STAGE_OUT")
    if not out:
        return
    here = os.path.dirname(os.path.abspath(__file__))  # this hook's own folder is no entry
    entries = [
        os.path.realpath(p) for p in sys.path if p and os.path.isdir(p) and p != here
    ]
    with open(f"{out}.{os.getpid()}", "w") as listing:
        for entry in entries:
            listing.write(f"path {entry}\n")
        for path in sorted(_loaded_files()):
            listing.write(f"file {path}\n")


def _merge(out: str, listings: list[str], whole: list[str]) -> str:
    entries: list[str] = []
    files: set[str] = set()
    for name in listings:
        with open(name) as listing:
            for line in listing:
                kind, path = line.rstrip("\n").split(" ", 1)
                if kind == "path" and path not in entries:
                    entries.append(path)
                elif kind == "file":
                    files.add(path)
    # Only files under a path entry are found through the copies; the rest (the interpreter,
    # system libraries) stay where they are.
    staged = {f for f in files if any(f.startswith(e + "/") for e in entries)}
    roots = [os.path.realpath(tree) for tree in whole]
    for root in roots:  # the project's own: small, and read for data files too (its configs
        # through a link: copied as the files they are)
        for folder, _, names in os.walk(root, followlinks=True):
            staged.update(os.path.join(folder, name) for name in names)
    # One archive, read in one stream by the guest: over 9p each file opened costs more than
    # its bytes do. The few large files (shared libraries: BLAS, C extensions) go in as links
    # to the host's: a process maps only the pages it touches.
    with tarfile.open(out, "w", dereference=True) as archive:
        for path in sorted(staged):
            name = path.lstrip("/")
            if os.path.getsize(path) < LARGE_BYTES:
                archive.add(path, arcname=name, recursive=False)
            else:
                link = tarfile.TarInfo(name)
                link.type, link.linkname = tarfile.SYMTYPE, os.path.realpath(path)
                archive.addfile(link)
    # The project's roots first: the editable install finds them after the path entries.
    return ":".join(STAGE + entry for entry in [*roots, *entries])


class FromHost(importlib.abc.MetaPathFinder):
    """In the guest (``sitecustomize`` there): a module of a staged package that the list
    left out (``encodings.cp1252``, say, which the host's run never loaded) is found where the
    host has it, as it would be without the copies."""

    def find_spec(
        self, fullname: str, path: Sequence[str] | None, target: ModuleType | None = None
    ) -> ModuleSpec | None:
        originals = [entry[len(STAGE):] for entry in path or () if entry.startswith(STAGE + "/")]
        if not originals:
            return None
        return importlib.machinery.PathFinder.find_spec(fullname, originals, target)


if __name__ == "__main__":
    # python .ci/vcan-stage.py OUT DIR... -- LIST...
    split = sys.argv.index("--")
    print(_merge(sys.argv[1], sys.argv[split + 1:], sys.argv[2:split]))
elif os.environ.get("VCAN_STAGE_OUT"):
    atexit.register(_dump)
else:
    sys.meta_path.append(FromHost())
