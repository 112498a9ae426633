"""The layout's dependency rules, read from the source with ``ast`` (nothing is imported).

* The core (``service/ballbeam/core/``) is pure: it imports nothing from the edges (runtime,
  logs, protocol, evaluation, CLI, assembly, config), nothing from the emulator, and no I/O
  or OS module; what it may import is listed in ``CORE_ALLOWED``.
* The emulator is a process of its own: within ``service/ballbeam/`` only the CLI, which sits
  on top of both processes, imports it.
* The core, the frame contract and the recordings do not depend on the runtime or on the
  evaluation built on them.

Every import counts, wherever it stands (module level, inside a function, under
``TYPE_CHECKING``); relative imports are resolved against their package.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SERVICE = REPO / "service"
PACKAGE = SERVICE / "ballbeam"
CORE = PACKAGE / "core"

CORE_FORBIDDEN = (
    # the edges and the other process
    "ballbeam.runtime",
    "ballbeam.logs",
    "ballbeam.protocol",
    "ballbeam.evaluation",
    "ballbeam.cli",
    "ballbeam.assembly",
    "ballbeam.config",
    "ballbeam_emulator",
    # I/O and the operating system
    "os",
    "sys",
    "socket",
    "time",
    "threading",
    "subprocess",
    "pathlib",
    "io",
    "logging",
    "can",
    "mcap",
    "signal",
    "tomllib",
    "json",
)
# Everything the core may import: numerics and pure language support. A new pure module
# (no I/O, no clock, no OS) may be added here; one that touches the world belongs to an edge.
CORE_ALLOWED = (
    "__future__",
    "numpy",
    "scipy",
    "highspy",
    "math",
    "copy",
    "dataclasses",
    "typing",
    "functools",
    "warnings",
    "collections",
    "itertools",
    "operator",
    "enum",
    "bisect",
    "ballbeam.errors",
    "ballbeam.core",
)


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(SERVICE).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def imports_in(source: str, module: str, *, is_package: bool = False) -> set[str]:
    """Every module the source of ``module`` imports, as absolute dotted names (``from a import
    b`` gives ``a`` and ``a.b``: b may be a submodule)."""
    tree = ast.parse(source, filename=module)
    package = module.split(".") if is_package else module.split(".")[:-1]
    found: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[: len(package) - (node.level - 1)]
                name = ".".join([*base, node.module] if node.module else base)
            else:
                name = node.module or ""
            found.add(name)
            found.update(f"{name}.{alias.name}" for alias in node.names if alias.name != "*")
    return found


def imports_of(path: Path) -> set[str]:
    return imports_in(
        path.read_text(encoding="utf-8"), _module_name(path), is_package=path.name == "__init__.py"
    )


def _within(name: str, prefixes: tuple[str, ...]) -> bool:
    return any(name == prefix or name.startswith(prefix + ".") for prefix in prefixes)


def _sources(root: Path) -> list[Path]:
    return sorted(root.rglob("*.py"))


def _ids(paths: list[Path]) -> list[str]:
    return [str(path.relative_to(REPO)) for path in paths]


CORE_SOURCES = _sources(CORE)


def test_the_core_is_where_the_rules_look() -> None:
    assert CORE.is_dir()
    names = {path.relative_to(CORE).as_posix() for path in CORE_SOURCES}
    assert {"model.py", "tracker.py", "planning/time_optimal.py"} <= names


@pytest.mark.parametrize("path", CORE_SOURCES, ids=_ids(CORE_SOURCES))
def test_core_imports_no_edge_and_no_io(path: Path) -> None:
    bad = sorted(name for name in imports_of(path) if _within(name, CORE_FORBIDDEN))
    assert not bad, f"{path.relative_to(REPO)} imports {bad}: the core must stay pure"


@pytest.mark.parametrize("path", CORE_SOURCES, ids=_ids(CORE_SOURCES))
def test_core_imports_only_the_allowed(path: Path) -> None:
    # ("from numpy import typing" also yields "numpy.typing": the prefixes cover both)
    other = sorted(name for name in imports_of(path) if not _within(name, CORE_ALLOWED))
    assert not other, (
        f"{path.relative_to(REPO)} imports {other}, not on the core's list (CORE_ALLOWED "
        "in tests/test_architecture.py: add a module there only if it does no I/O)"
    )


def test_only_the_cli_imports_the_emulator() -> None:
    importers = {
        str(path.relative_to(REPO))
        for path in _sources(PACKAGE)
        if any(_within(name, ("ballbeam_emulator",)) for name in imports_of(path))
    }
    assert importers <= {"service/ballbeam/cli.py"}, importers


@pytest.mark.parametrize("layer", ["core", "protocol", "logs"])
def test_lower_layers_do_not_import_runtime_or_evaluation(layer: str) -> None:
    root = PACKAGE / layer
    assert root.is_dir()
    upward = {
        str(path.relative_to(REPO)): sorted(
            name
            for name in imports_of(path)
            if _within(name, ("ballbeam.runtime", "ballbeam.evaluation"))
        )
        for path in _sources(root)
    }
    assert not {path: names for path, names in upward.items() if names}


def test_the_import_reader_sees_every_form() -> None:
    """The rules above are only as good as ``imports_in``: it must see every import form."""
    source = (
        "import os.path as p\n"
        "from .. import model\n"
        "from .lp import _solve_lp\n"
        "from ballbeam import runtime\n"
        "def f() -> None:\n"
        "    import socket\n"
        "if False:\n"
        "    from ballbeam.logs.reader import read\n"
    )
    found = imports_in(source, "ballbeam.core.planning.probe")
    assert {
        "os.path",
        "ballbeam.core",
        "ballbeam.core.model",
        "ballbeam.core.planning.lp",
        "ballbeam.runtime",
        "socket",
        "ballbeam.logs.reader",
    } <= found
    assert imports_in("from . import x", "ballbeam.core", is_package=True) == {
        "ballbeam.core",
        "ballbeam.core.x",
    }
    assert _within("os.path", CORE_FORBIDDEN)
    assert _within("ballbeam.runtime", CORE_FORBIDDEN)
    assert not _within("iosys", CORE_FORBIDDEN)
