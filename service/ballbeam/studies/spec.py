"""A sweep spec (TOML) and the points it expands to.

::

    [sweep]
    base = "../paper.toml"         # a config file (relative to the spec) or a shipped name
    set = ["run.duration_s=4.0"]   # fixed overrides on every point
    run = "offline"                # offline | lockstep | realtime (the last two: over the bus)
    seeds = 5                      # plant.seed = 1..5 on every point (or a list of seeds)
    samples = 40                   # Monte-Carlo draws of the [random] keys
    sample_seed = 2026             # the draws' generator

    [grid]                         # every combination of these
    "plan.theta_margin_deg" = [0.25, 0.5]
    "plant.deadzone_v" = { start = 0.0, stop = 0.4, num = 3 }   # or { start, stop, step }

    [random]                       # drawn `samples` times (the same draws for every grid cell)
    "plant.ball_gain_scale" = { uniform = [0.8, 1.2] }
    "plant.motor_gain_scale" = { normal = [1.0, 0.05] }         # mean, standard deviation
    "plant.nonlinear_ball" = { choice = [false, true] }

Points: grid cells × draws × seeds. A drawn value outside a key's range is not a spec error:
that point fails validation and is recorded as failed, like a run that fails.
"""

from __future__ import annotations

import itertools
import json
import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel

from ballbeam.config import Config, read_toml_file, resolve_config_path
from ballbeam.errors import ConfigError

Runner = Literal["offline", "lockstep", "realtime"]
RUNNERS: tuple[Runner, ...] = ("offline", "lockstep", "realtime")
SEED_KEY = "plant.seed"
DISTRIBUTIONS = ("uniform", "normal", "choice")
MAX_POINTS = 1_000_000  # a typo (num = 1e9) is refused before anything is allocated
SPEC_SECTIONS = {"sweep", "grid", "random"}
SWEEP_KEYS = {"base", "set", "run", "seeds", "samples", "sample_seed", "output"}


@dataclass(frozen=True)
class Distribution:
    kind: str  # one of DISTRIBUTIONS
    parameters: tuple[Any, ...]

    def draw(self, rng: np.random.Generator) -> Any:
        if self.kind == "uniform":
            return float(rng.uniform(*self.parameters))
        if self.kind == "normal":
            return float(rng.normal(*self.parameters))
        return self.parameters[int(rng.integers(len(self.parameters)))]


@dataclass(frozen=True)
class Point:
    """One run of a sweep: the swept keys' values (spec order, the seed last) and the
    overrides that make its config (the spec's fixed ``set`` first)."""

    values: tuple[tuple[str, Any], ...]
    overrides: tuple[str, ...]

    def as_dict(self) -> dict[str, Any]:
        return dict(self.values)


@dataclass(frozen=True)
class SweepSpec:
    path: Path
    base: Path | None  # None: the paper's defaults
    fixed: tuple[str, ...]
    runner: Runner
    grid: dict[str, tuple[Any, ...]]
    random: dict[str, Distribution]
    samples: int
    sample_seed: int
    seeds: tuple[int, ...]
    output: Path | None

    @property
    def keys(self) -> list[str]:
        """The swept keys, the columns of the results table before the metrics."""
        keys = [*self.grid, *self.random]
        return [*keys, SEED_KEY] if self.seeds else keys

    def points(self) -> list[Point]:
        rng = np.random.default_rng(self.sample_seed)
        # Common random numbers: every grid cell sees the same draws, so differences between
        # cells are the grid's, not the sampling's.
        draws = [
            [(key, distribution.draw(rng)) for key, distribution in self.random.items()]
            for _ in range(self.samples if self.random else 1)
        ]
        seeds: list[list[tuple[str, Any]]] = (
            [[(SEED_KEY, seed)] for seed in self.seeds] if self.seeds else [[]]
        )
        points = []
        for cell in itertools.product(*self.grid.values()):
            grid_values = list(zip(self.grid, cell, strict=True))
            for draw in draws:
                for seed in seeds:
                    values = tuple(grid_values + draw + seed)
                    overrides = self.fixed + tuple(
                        f"{key}={toml_value(value)}" for key, value in values
                    )
                    points.append(Point(values, overrides))
        return points


def toml_value(value: Any) -> str:
    """``value`` as TOML (what ``--set key=...`` parses back to the same value)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int | float):
        return repr(value) if math.isfinite(value) else ("nan" if value != value else
                                                         ("inf" if value > 0 else "-inf"))
    if isinstance(value, str):
        return json.dumps(value)  # a TOML basic string
    if isinstance(value, list | tuple):
        return "[" + ", ".join(toml_value(item) for item in value) + "]"
    raise ConfigError(f"cannot sweep a value of type {type(value).__name__}: {value!r}")


def toml_document(data: Mapping[str, Any], prefix: str = "") -> str:
    """A TOML mapping (as ``tomllib`` reads it) written back as TOML text."""
    lines = [
        f"{json.dumps(key)} = {toml_value(value)}"
        for key, value in data.items()
        if not isinstance(value, Mapping)
    ]
    for key, value in data.items():
        if isinstance(value, Mapping):
            name = f"{prefix}{json.dumps(key)}"
            lines += ["", f"[{name}]", toml_document(value, f"{name}.")]
    return "\n".join(lines)


def check_config_key(key: str, where: str) -> None:
    """ConfigError unless ``key`` (dotted) names a config key (``plant.seed``, ``tracker.q``;
    inside ``bus.options`` or ``expect`` any name)."""
    parts = key.split(".")
    model: type[BaseModel] = Config
    for depth, part in enumerate(parts):
        field = model.model_fields.get(part)
        if field is None:
            raise ConfigError(f"{where}: {key!r} is not a config key ({part!r} unknown)")
        annotation = field.annotation
        if isinstance(annotation, type) and issubclass(annotation, BaseModel):
            model = annotation
            continue
        if depth != len(parts) - 1 and not (
            getattr(annotation, "__origin__", None) is dict or part in {"options", "expect"}
        ):
            raise ConfigError(f"{where}: {key!r} is not a config key ({part!r} has no keys)")
        return
    raise ConfigError(f"{where}: {key!r} names a config section, not a key")


def _grid_values(key: str, value: Any, where: str) -> tuple[Any, ...]:
    if isinstance(value, list):
        if not value:
            raise ConfigError(f"{where}: grid key {key!r} has no values")
        return tuple(value)
    if not isinstance(value, Mapping):
        raise ConfigError(f"{where}: grid key {key!r} needs a list or {{ start, stop, num }}")
    fields = set(value)
    try:
        if fields == {"start", "stop", "num"}:
            start, stop, num = float(value["start"]), float(value["stop"]), int(value["num"])
            if not 1 <= num <= MAX_POINTS:
                raise ConfigError(f"{where}: grid key {key!r}: num must be 1..{MAX_POINTS}")
            return tuple(float(item) for item in np.linspace(start, stop, num))
        if fields == {"start", "stop", "step"}:
            start, stop, step = float(value["start"]), float(value["stop"]), float(value["step"])
            count = math.floor((stop - start) / step + 1e-9) + 1 if step > 0 else 0
            if not 1 <= count <= MAX_POINTS:
                raise ConfigError(
                    f"{where}: grid key {key!r}: step must be > 0 and give 1..{MAX_POINTS} values"
                )
            return tuple(start + index * step for index in range(count))
    except (TypeError, ValueError) as error:
        if isinstance(error, ConfigError):
            raise
        raise ConfigError(f"{where}: grid key {key!r}: {error}") from error
    raise ConfigError(
        f"{where}: grid key {key!r}: a range is {{ start, stop, num }} or {{ start, stop, step }}"
    )


def _distribution(key: str, value: Any, where: str) -> Distribution:
    if not isinstance(value, Mapping) or len(value) != 1 or next(iter(value)) not in DISTRIBUTIONS:
        raise ConfigError(
            f"{where}: random key {key!r} needs one of {{ uniform = [low, high] }}, "
            "{ normal = [mean, std] }, { choice = [...] }"
        )
    kind, parameters = next(iter(value.items()))
    if not isinstance(parameters, list) or not parameters:
        raise ConfigError(f"{where}: random key {key!r}: {kind} needs a list")
    if kind == "choice":
        return Distribution(kind, tuple(parameters))
    if len(parameters) != 2 or not all(
        isinstance(item, int | float) and not isinstance(item, bool) and math.isfinite(item)
        for item in parameters
    ):
        raise ConfigError(f"{where}: random key {key!r}: {kind} needs two finite numbers")
    low, high = float(parameters[0]), float(parameters[1])
    if kind == "uniform" and not low < high:
        raise ConfigError(f"{where}: random key {key!r}: uniform needs low < high")
    if kind == "normal" and not high > 0:
        raise ConfigError(f"{where}: random key {key!r}: normal needs a std > 0")
    return Distribution(kind, (low, high))


def _whole(value: Any, name: str, where: str, minimum: int) -> int:
    if not isinstance(value, int) or isinstance(value, bool) or value < minimum:
        raise ConfigError(f"{where}: sweep.{name} must be a whole number >= {minimum}")
    return value


def spec_from_mapping(data: Mapping[str, Any], path: Path) -> SweepSpec:
    where = str(path)
    unknown = set(data) - SPEC_SECTIONS
    if unknown:
        raise ConfigError(
            f"{where}: unknown table(s) {', '.join(sorted(unknown))}; a spec has "
            "[sweep], [grid] and [random]"
        )
    sweep = data.get("sweep", {})
    grid_table = data.get("grid", {})
    random_table = data.get("random", {})
    if not all(isinstance(table, Mapping) for table in (sweep, grid_table, random_table)):
        raise ConfigError(f"{where}: [sweep], [grid] and [random] must be tables")
    unknown = set(sweep) - SWEEP_KEYS
    if unknown:
        raise ConfigError(
            f"{where}: unknown key(s) sweep.{', sweep.'.join(sorted(unknown))}; known: "
            f"{', '.join(sorted(SWEEP_KEYS))}"
        )
    base = None
    if "base" in sweep:
        if not isinstance(sweep["base"], str):
            raise ConfigError(f"{where}: sweep.base must be a config path or shipped name")
        beside = path.parent / sweep["base"]
        base = beside.resolve() if beside.is_file() else resolve_config_path(sweep["base"])
    fixed = sweep.get("set", [])
    if not isinstance(fixed, list) or not all(isinstance(item, str) for item in fixed):
        raise ConfigError(f'{where}: sweep.set must be a list of "dotted.key=value" strings')
    runner = sweep.get("run", "offline")
    if runner not in RUNNERS:
        raise ConfigError(f"{where}: sweep.run must be one of {', '.join(RUNNERS)}, got {runner!r}")
    seeds_value = sweep.get("seeds", [])
    if isinstance(seeds_value, list):
        seeds = tuple(_whole(seed, "seeds", where, 0) for seed in seeds_value)
    else:
        seeds = tuple(range(1, _whole(seeds_value, "seeds", where, 1) + 1))
    grid = {key: _grid_values(key, value, where) for key, value in grid_table.items()}
    random = {key: _distribution(key, value, where) for key, value in random_table.items()}
    for key in [*grid, *random]:
        check_config_key(key, where)
    if set(grid) & set(random):
        raise ConfigError(f"{where}: {sorted(set(grid) & set(random))} both in [grid] and [random]")
    if seeds and SEED_KEY in [*grid, *random]:
        raise ConfigError(f"{where}: {SEED_KEY} is swept: leave sweep.seeds out")
    samples = _whole(sweep.get("samples", 1 if not random else 0), "samples", where, 1)
    if "samples" in sweep and not random:
        raise ConfigError(f"{where}: sweep.samples needs a [random] table to draw from")
    sample_seed = _whole(sweep.get("sample_seed", 0), "sample_seed", where, 0)
    count = math.prod(len(values) for values in grid.values()) * samples * max(len(seeds), 1)
    if count > MAX_POINTS:
        raise ConfigError(f"{where}: {count} points, more than {MAX_POINTS}")
    if not grid and not random and not seeds:
        raise ConfigError(f"{where}: nothing to sweep: give [grid], [random] or sweep.seeds")
    output = sweep.get("output")
    if output is not None and not isinstance(output, str):
        raise ConfigError(f"{where}: sweep.output must be a directory path")
    return SweepSpec(
        path=path,
        base=base,
        fixed=tuple(fixed),
        runner=runner,
        grid=grid,
        random=random,
        samples=samples,
        sample_seed=sample_seed,
        seeds=seeds,
        output=(path.parent / output) if output is not None else None,
    )


def load_spec(name: str | Path) -> SweepSpec:
    """A spec file, or a shipped one (``sweeps/mismatch_monte_carlo``)."""
    path = resolve_config_path(name)
    data = read_toml_file(path, "sweep spec")
    return spec_from_mapping(data, path.resolve())
