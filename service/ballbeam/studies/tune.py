"""``ballbeam tune SPEC.toml``: choose design keys (tracker weights, observer noise levels, plan
margins) that minimise a robust objective over a scenario set, under bounds on other metrics.

Optuna proposes (ask/tell, TPE with its constraint handling); each trial is the whole tuning
set of offline runs, its points spread over the Dask cluster's workers, several trials in
flight at once. The base config's own values are the first trial, so the result is never worse
than the default on the tuning set. The verdict is measured on a held-out set: other draws of
the same scenario distributions, other noise seeds. ::

    [tune]
    base = "../paper.toml"            # the config tuned (relative to the spec, or shipped)
    set = ["run.duration_s=4.75"]     # fixed overrides of every run (not part of the result)
    trials = 48
    parallel = 4                      # trials in flight (default: 2 per worker)
    sampler_seed = 1
    metric = "rest_ratio"
    objective = "max"                 # max | p90 | median | mean over the set
    train_seed = 1                    # the tuning set's draws and noise seeds
    seeds = [1, 2]
    holdout_seed = 2                  # the held-out set's
    holdout_seeds = [3, 4]
    holdout_samples = 16

    [tune.constraints]                # every run of a trial within these, or it is infeasible
    max_abs_theta_deg = { max = 52.0 }

    [space]                           # uniform or log_uniform; [i] names a vector's entry
    "tracker.q[3]" = { log_uniform = [1e3, 1e5] }

    [scenarios]                       # what a set draws: a [random] table and its size
    samples = 12
    [scenarios.random]
    "plant.ball_gain_scale" = { uniform = [0.85, 1.15] }
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import re
import sys
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ballbeam.config import (
    load_config,
    read_config_data,
    read_toml_file,
    resolve_config_path,
    shipped_configs,
)
from ballbeam.errors import BallbeamError, ConfigError
from ballbeam.files import replace_file
from ballbeam.runtime.stop import INTERRUPT
from ballbeam.studies.points import PointOutcome, PointTask, evaluate_batch, warm_up
from ballbeam.studies.spec import SweepSpec, check_config_key, spec_from_mapping, toml_value
from ballbeam.studies.store import point_id

OBJECTIVES = ("max", "p90", "median", "mean")
TUNE_KEYS = {
    "base", "set", "trials", "parallel", "sampler_seed", "metric", "objective", "train_seed",
    "seeds", "holdout_seed", "holdout_seeds", "holdout_samples", "constraints", "output",
}
# A run that never comes to rest (or fails) counts as this bad: worse than any real run, and
# finite (a sampler cannot rank infinities).
PENALTY = 100.0
CONSTRAINT_TOLERANCE = 1e-9  # a start on the 52° limit reads 52.000000000000007°
STUDY_FILE = "study.db"  # the Optuna study in the output directory: what a stopped tuning kept
STUDY_NAME = "ballbeam-tune"
_SCORE_ATTRS = frozenset({"violations", "failed", "default"})  # a trial's attrs, not its summary
_INDEXED = re.compile(r"^(?P<key>[a-z_.]+)\[(?P<index>\d+)\]$")


@dataclass(frozen=True)
class Parameter:
    name: str  # as in the spec: "tracker.r", "tracker.q[3]"
    key: str  # the config key: "tracker.q"
    index: int | None
    low: float
    high: float
    log: bool


@dataclass(frozen=True)
class TuneSpec:
    path: Path
    base: Path | None
    fixed: tuple[str, ...]
    trials: int
    parallel: int | None
    sampler_seed: int
    metric: str
    objective: str
    constraints: dict[str, dict[str, float]]
    space: tuple[Parameter, ...]
    train: SweepSpec
    holdout: SweepSpec
    output: Path | None


def _number(value: Any, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise ConfigError(f"{where} must be a finite number, got {value!r}")
    return float(value)


def _parameter(name: str, value: Any, where: str) -> Parameter:
    match = _INDEXED.match(name)
    key, index = (match["key"], int(match["index"])) if match else (name, None)
    check_config_key(key, where)
    if not isinstance(value, Mapping) or len(value) != 1 or next(iter(value)) not in (
        "uniform", "log_uniform"
    ):
        raise ConfigError(
            f"{where}: space.{name} needs {{ uniform = [low, high] }} or "
            "{ log_uniform = [low, high] }"
        )
    kind, bounds = next(iter(value.items()))
    if not isinstance(bounds, list) or len(bounds) != 2:
        raise ConfigError(f"{where}: space.{name}: {kind} needs [low, high]")
    low, high = (_number(bound, f"{where}: space.{name}") for bound in bounds)
    if not low < high or (kind == "log_uniform" and low <= 0):
        raise ConfigError(f"{where}: space.{name}: needs low < high (and low > 0 on a log scale)")
    return Parameter(name, key, index, low, high, kind == "log_uniform")


def _seeds(value: Any, name: str, where: str) -> list[int]:
    if not isinstance(value, list) or not value or not all(
        isinstance(seed, int) and not isinstance(seed, bool) and seed >= 0 for seed in value
    ):
        raise ConfigError(f"{where}: tune.{name} must be a list of seeds (whole numbers >= 0)")
    return value


def tune_spec_from_mapping(data: Mapping[str, Any], path: Path) -> TuneSpec:
    where = str(path)
    unknown = set(data) - {"tune", "space", "scenarios"}
    if unknown:
        raise ConfigError(f"{where}: unknown table(s) {', '.join(sorted(unknown))}; a tuning "
                          "spec has [tune], [space] and [scenarios]")
    tune, space, scenarios = (data.get(name, {}) for name in ("tune", "space", "scenarios"))
    if not all(isinstance(table, Mapping) for table in (tune, space, scenarios)):
        raise ConfigError(f"{where}: [tune], [space] and [scenarios] must be tables")
    unknown = set(tune) - TUNE_KEYS
    if unknown:
        raise ConfigError(f"{where}: unknown key(s) tune.{', tune.'.join(sorted(unknown))}")
    if not space:
        raise ConfigError(f"{where}: [space] names no parameter to tune")
    parameters = tuple(_parameter(name, value, where) for name, value in space.items())
    objective = tune.get("objective", "max")
    if objective not in OBJECTIVES:
        raise ConfigError(f"{where}: tune.objective must be one of {', '.join(OBJECTIVES)}")
    metric = tune.get("metric", "rest_ratio")
    constraints = tune.get("constraints", {})
    from ballbeam.core.metrics import RunMetrics

    for name, bound in [(metric, {"max": 0.0}), *constraints.items()]:
        if name not in RunMetrics.__dataclass_fields__:
            raise ConfigError(f"{where}: {name!r} is not a metric of an offline run")
        if not isinstance(bound, Mapping) or not bound or set(bound) - {"min", "max"}:
            raise ConfigError(f"{where}: tune.constraints.{name} needs {{ max = .. }} / min")
    trials = tune.get("trials", 40)
    if not isinstance(trials, int) or isinstance(trials, bool) or not 1 <= trials <= 100_000:
        raise ConfigError(f"{where}: tune.trials must be a whole number from 1")
    parallel = tune.get("parallel")
    if parallel is not None and (not isinstance(parallel, int) or parallel < 1):
        raise ConfigError(f"{where}: tune.parallel must be a whole number from 1")
    unknown = set(scenarios) - {"samples", "random", "grid"}
    if unknown:
        raise ConfigError(f"{where}: unknown key(s) scenarios.{', scenarios.'.join(unknown)}")
    sweep_base = {key: tune[key] for key in ("base", "set") if key in tune}

    def scenario_set(seed_key: str, seeds_key: str, samples: Any, default_seeds: list[int]) -> Any:
        sweep = {
            **sweep_base,
            "seeds": _seeds(tune.get(seeds_key, default_seeds), seeds_key, where),
            "sample_seed": tune.get(seed_key, 1),
        }
        if scenarios.get("random"):
            sweep["samples"] = samples
        return spec_from_mapping(
            {"sweep": sweep, "grid": scenarios.get("grid", {}),
             "random": scenarios.get("random", {})},
            path,
        )

    train = scenario_set("train_seed", "seeds", scenarios.get("samples", 8), [1])
    holdout = scenario_set(
        "holdout_seed", "holdout_seeds",
        tune.get("holdout_samples", scenarios.get("samples", 8)), [2],
    )
    if train.random and train.sample_seed == holdout.sample_seed:
        raise ConfigError(f"{where}: tune.holdout_seed must differ from tune.train_seed "
                          "(the held-out set must be other draws)")
    if set(train.seeds) & set(holdout.seeds):
        raise ConfigError(f"{where}: tune.seeds and tune.holdout_seeds must not share a seed")
    tuned_keys = {parameter.key for parameter in parameters}
    clash = tuned_keys & set(train.keys)
    if clash:
        raise ConfigError(f"{where}: {sorted(clash)} both tuned and varied by the scenarios")
    output = tune.get("output")
    return TuneSpec(
        path=path,
        base=train.base,
        fixed=train.fixed,
        trials=trials,
        parallel=parallel,
        sampler_seed=int(tune.get("sampler_seed", 0)),
        metric=metric,
        objective=objective,
        constraints={name: dict(bound) for name, bound in constraints.items()},
        space=parameters,
        train=train,
        holdout=holdout,
        output=(path.parent / output) if isinstance(output, str) else None,
    )


def load_tune_spec(name: str | Path) -> TuneSpec:
    path = resolve_config_path(name)
    data = read_toml_file(path, "tuning spec")
    spec = tune_spec_from_mapping(data, path.resolve())
    defaults(spec)  # every key and index exists in the base
    return spec


def defaults(spec: TuneSpec) -> dict[str, float]:
    """The base config's own values of the tuned parameters (the first trial)."""
    config = load_config(spec.base).model_dump()
    values = {}
    for parameter in spec.space:
        section, _, key = parameter.key.partition(".")
        value = config[section]
        for part in key.split("."):
            value = value[part]
        if parameter.index is not None:
            if not isinstance(value, list | tuple) or parameter.index >= len(value):
                raise ConfigError(f"{spec.path}: space.{parameter.name}: {parameter.key} has no "
                                  f"entry {parameter.index}")
            value = value[parameter.index]
        if not isinstance(value, int | float) or isinstance(value, bool):
            raise ConfigError(f"{spec.path}: space.{parameter.name} is not a number in the base")
        values[parameter.name] = float(value)
    return values


def overrides_for(spec: TuneSpec, params: Mapping[str, float]) -> dict[str, Any]:
    """The config keys a trial's parameters set (vector entries merged into their vector)."""
    config = load_config(spec.base).model_dump()
    values: dict[str, Any] = {}
    for parameter in spec.space:
        section, _, key = parameter.key.partition(".")
        if parameter.index is None:
            values[parameter.key] = float(params[parameter.name])
            continue
        if parameter.key not in values:
            current = config[section]
            for part in key.split("."):
                current = current[part]
            values[parameter.key] = [float(item) for item in current]
        values[parameter.key][parameter.index] = float(params[parameter.name])
    return values


def _set_tasks(spec: TuneSpec, scenario: SweepSpec, keys: Mapping[str, Any]) -> list[PointTask]:
    base = str(spec.base) if spec.base is not None else None
    base_data = read_config_data(spec.base) if spec.base is not None else {}
    tuned = tuple(f"{key}={toml_value(value)}" for key, value in keys.items())
    tasks = []
    for point in scenario.points():
        overrides = (*point.overrides, *tuned)
        tasks.append(PointTask(point_id(base_data, overrides, "offline"), base, base_data,
                               overrides, "offline", None))
    return tasks


@dataclass(frozen=True)
class SetScore:
    objective: float  # the robust objective over the set (PENALTY where runs failed)
    violations: tuple[float, ...]  # per constraint: how far past its bound (<= 0: kept)
    summary: dict[str, float]  # worst / p90 / median of the metric and the worst of the bounds
    failed: int

    @property
    def feasible(self) -> bool:
        return self.failed == 0 and all(v <= CONSTRAINT_TOLERANCE for v in self.violations)


def score(spec: TuneSpec, outcomes: Sequence[PointOutcome]) -> SetScore:
    failed = sum(outcome.error is not None for outcome in outcomes)
    good = [outcome.metrics for outcome in outcomes if outcome.error is None]

    def values(metric: str) -> np.ndarray:
        raw = [m.get(metric) for m in good] + [None] * failed
        return np.array([PENALTY if v is None else min(float(v), PENALTY) for v in raw])

    metric = values(spec.metric)
    objective = {
        "max": float(metric.max()),
        "p90": float(np.quantile(metric, 0.9)),
        "median": float(np.median(metric)),
        "mean": float(metric.mean()),
    }[spec.objective]
    violations = []
    summary = {
        f"{spec.metric} worst": float(metric.max()),
        f"{spec.metric} p90": float(np.quantile(metric, 0.9)),
        f"{spec.metric} median": float(np.median(metric)),
    }
    for name, bound in spec.constraints.items():
        observed = values(name) if good else np.array([PENALTY])
        if "max" in bound:
            violations.append(float(observed.max()) - bound["max"])
            summary[f"{name} max"] = float(observed.max())
        if "min" in bound:
            violations.append(bound["min"] - float(observed.min()))
            summary[f"{name} min"] = float(observed.min())
    return SetScore(objective, tuple(violations), summary, failed)


def run_set(client: Any, tasks: list[PointTask], workers: int) -> list[PointOutcome]:
    """One scenario set at once on the cluster, in the tasks' order."""
    chunks = [tasks[index::workers] for index in range(workers) if tasks[index::workers]]
    futures = [client.submit(evaluate_batch, chunk, pure=False) for chunk in chunks]
    by_id = {o.point_id: o for future in futures for o in future.result()}
    return [by_id[task.point_id] for task in tasks]


@dataclass(frozen=True)
class TuneOutcome:
    default_params: dict[str, float]
    best_params: dict[str, float]
    best_trial: int
    trials: Any  # pandas.DataFrame, Optuna's trial table
    table: list[dict[str, Any]]  # the before/after rows
    tuned_path: Path
    holdout_improvement: float  # 1 − tuned worst / default worst on the held-out set


def spec_fingerprint(spec: TuneSpec) -> str:
    """What makes two tunings one study: the space, the objective, the bounds and the tuning
    set's runs (not the trial count, the parallelism or the held-out set)."""
    base_data = read_config_data(spec.base) if spec.base is not None else {}
    content = {
        "space": [[p.name, p.low, p.high, p.log] for p in spec.space],
        "metric": spec.metric,
        "objective": spec.objective,
        "constraints": spec.constraints,
        "train": sorted(task.point_id for task in _set_tasks(spec, spec.train, {})),
        "base": base_data,
        "fixed": list(spec.fixed),
    }
    return hashlib.sha256(json.dumps(content, sort_keys=True).encode()).hexdigest()[:20]


def _open_study(spec: TuneSpec, output: Path) -> Any:
    """The study in ``output/study.db``: new, or the one a tuning of the same spec left there
    (an interrupted one resumes). SQLite, Optuna's RDB storage: each told trial is one
    committed transaction, so a kill at any moment loses at most the trials in flight, and
    no lock file outlives a killed process (Optuna's journal file storage leaves one to
    expire). A trial left running by an interrupted tuning is marked failed."""
    import optuna
    from optuna.trial import TrialState

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    try:
        output.mkdir(parents=True, exist_ok=True)
    except OSError as error:
        raise ConfigError(f"cannot create the tuning directory {output}: {error}") from error
    sampler = optuna.samplers.TPESampler(
        seed=spec.sampler_seed,
        n_startup_trials=min(10, max(spec.trials // 4, 1)),
    )
    path = (output / STUDY_FILE).resolve()
    try:
        storage = optuna.storages.RDBStorage(f"sqlite:///{path}")
        study = optuna.create_study(study_name=STUDY_NAME, storage=storage,
                                    direction="minimize", sampler=sampler, load_if_exists=True)
    except Exception as error:  # sqlalchemy's and Optuna's own errors: not a study we can use
        raise ConfigError(f"cannot open the tuning study {path}: {error}") from error
    fingerprint = spec_fingerprint(spec)
    stored = study.user_attrs.get("spec")
    if stored is None:
        study.set_user_attr("spec", fingerprint)
    elif stored != fingerprint:
        raise ConfigError(
            f"{path} holds the trials of another tuning (its space, objective, bounds or "
            "tuning set differ): name another --output, or delete it to start afresh"
        )
    for trial in study.get_trials(deepcopy=False, states=(TrialState.RUNNING,)):
        study.tell(trial.number, state=TrialState.FAIL)  # its runs were lost with its process
    return study


def completed_trials(output: Path) -> int:
    """How many trials the study in ``output`` holds whole (0 if there is none)."""
    path = output / STUDY_FILE
    if not path.is_file():
        return 0
    import optuna
    from optuna.trial import TrialState

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    study = optuna.load_study(study_name=STUDY_NAME, storage=f"sqlite:///{path.resolve()}")
    return len(study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,)))


def _stored_score(trial: Any) -> SetScore:
    attrs = trial.user_attrs
    summary = {key: value for key, value in attrs.items() if key not in _SCORE_ATTRS}
    return SetScore(float(trial.value), tuple(attrs["violations"]), summary, int(attrs["failed"]))


def run_tune(
    spec: TuneSpec,
    output: Path,
    client: Any,
    progress: bool = True,
    on_trial: Callable[[int, SetScore], None] | None = None,
) -> TuneOutcome:
    """Tune until the study in ``output`` holds ``spec.trials`` whole trials (those a stopped
    tuning left there count), then judge the best on the held-out set."""
    import optuna
    from distributed import as_completed
    from optuna.trial import TrialState
    from tqdm import tqdm

    from ballbeam.studies.cluster import worker_count

    study = _open_study(spec, output)
    workers = max(worker_count(client), 1)
    client.run(warm_up)
    in_flight_max = spec.parallel or 2 * workers
    default_params = defaults(spec)
    complete = study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,))
    scores: dict[int, SetScore] = {trial.number: _stored_score(trial) for trial in complete}
    done = len(scores)
    default_done = any(trial.user_attrs.get("default") for trial in complete)
    waiting = study.get_trials(deepcopy=False, states=(TrialState.WAITING,))
    if not default_done and not any(trial.user_attrs.get("default") for trial in waiting):
        # The base's own values: the first trial asked (again, if a stop lost it).
        study.enqueue_trial(default_params, user_attrs={"default": True})
    to_ask = max(spec.trials - done, 0 if default_done else 1)
    distributions: dict[str, optuna.distributions.BaseDistribution] = {
        parameter.name: optuna.distributions.FloatDistribution(
            parameter.low, parameter.high, log=parameter.log
        )
        for parameter in spec.space
    }
    pending: dict[int, tuple[Any, list[PointTask], dict[str, PointOutcome], int]] = {}
    futures = as_completed()
    owner: dict[Any, int] = {}
    asked = 0

    def ask() -> None:
        nonlocal asked
        trial = study.ask(distributions)
        asked += 1
        tasks = _set_tasks(spec, spec.train, overrides_for(spec, trial.params))
        # A trial's points in a few chunks: several trials share the workers.
        chunk_count = max(1, min(workers, len(tasks)))
        chunks = [tasks[index::chunk_count] for index in range(chunk_count)]
        pending[trial.number] = (trial, tasks, {}, len(chunks))
        for chunk in chunks:
            future = client.submit(evaluate_batch, chunk, pure=False)
            owner[future] = trial.number
            futures.add(future)

    for _ in range(min(in_flight_max, to_ask)):
        ask()
    with tqdm(total=max(spec.trials, done), initial=done, unit="trial", desc=spec.path.stem,
              file=sys.stderr, disable=not progress or not to_ask) as bar:
        for future in futures if to_ask else ():
            INTERRUPT.check()
            number = owner.pop(future)
            trial, tasks, outcomes, remaining = pending[number]
            try:
                for outcome in future.result():
                    outcomes[outcome.point_id] = outcome
            except Exception as error:  # a lost worker: those points failed
                for task in tasks:
                    outcomes.setdefault(task.point_id, PointOutcome(
                        task.point_id, {}, None, f"{type(error).__name__}: {error}", 0.0, "lost"
                    ))
            future.release()
            if remaining > 1:
                pending[number] = (trial, tasks, outcomes, remaining - 1)
                continue
            del pending[number]
            result = score(spec, [outcomes[task.point_id] for task in tasks])
            scores[number] = result
            for index, violation in enumerate(result.violations):
                # Optuna counts a trial feasible when every constraint value is <= 0.
                trial.set_constraint(f"bound_{index}", violation - CONSTRAINT_TOLERANCE)
            for name, value in result.summary.items():
                trial.set_user_attr(name, value)
            # What the score is made of, so that a resumed tuning knows it without the runs.
            trial.set_user_attr("violations", list(result.violations))
            trial.set_user_attr("failed", result.failed)
            study.tell(trial, result.objective)
            if on_trial is not None:
                on_trial(number, result)
            so_far = min((s.objective for s in scores.values() if s.feasible), default=math.nan)
            bar.set_postfix_str(f"best {spec.objective} {spec.metric} {so_far:.4g}")
            bar.update()
            if asked < to_ask:
                ask()
    complete = study.get_trials(states=(TrialState.COMPLETE,))
    default_number = next(trial.number for trial in complete if trial.user_attrs.get("default"))
    feasible = [trial for trial in complete if scores[trial.number].feasible]
    if not feasible:
        raise TuningError(
            f"no trial kept every bound of tune.constraints (the default's: "
            f"{scores[default_number].summary}); widen the space or the bounds"
        )
    best = min(feasible, key=lambda trial: (scores[trial.number].objective, trial.number))
    best_params = {name: float(value) for name, value in best.params.items()}
    tuned_path = write_tuned_config(spec, output / "tuned.toml", best_params, scores[best.number],
                                    scores[default_number], best.number)
    import pandas as pd

    table = []
    holdout: dict[str, SetScore] = {}
    holdout_rows = []
    for label, params in (("default", default_params), ("tuned", best_params)):
        tasks = _set_tasks(spec, spec.holdout, overrides_for(spec, params))
        held_out = run_set(client, tasks, workers)
        holdout[label] = score(spec, held_out)
        holdout_rows += [
            {"config": label, **point.as_dict(), **outcome.metrics, "error": outcome.error}
            for point, outcome in zip(spec.holdout.points(), held_out, strict=True)
        ]
    # Every held-out run of both configs: which scenarios make the worst case.
    holdout_frame = pd.DataFrame(holdout_rows)
    replace_file(output / "holdout.parquet",
                 lambda stream: holdout_frame.to_parquet(stream, index=False))
    for label, trial_number in (("default", default_number), ("tuned", best.number)):
        for set_name, result in (("tuning", scores[trial_number]), ("held-out", holdout[label])):
            table.append({"set": set_name, "config": label, "feasible": result.feasible,
                          "failed": result.failed, **result.summary})
    worst = f"{spec.metric} worst"
    improvement = 1.0 - holdout["tuned"].summary[worst] / holdout["default"].summary[worst]
    trials_frame = study.trials_dataframe()
    # The whole trials (a stopped tuning's lost ones, failed, stay in the study only).
    trials_frame = trials_frame[trials_frame["state"] == "COMPLETE"].reset_index(drop=True)
    replace_file(output / "trials.parquet",
                 lambda stream: trials_frame.to_parquet(stream, index=False))
    replace_file(output / "before_after.md", (markdown_table(table) + "\n").encode("utf-8"))
    return TuneOutcome(default_params, best_params, best.number, trials_frame, table, tuned_path,
                       improvement)


class TuningError(BallbeamError, RuntimeError):
    """The tuning found nothing to recommend."""


def write_tuned_config(
    spec: TuneSpec,
    path: Path,
    params: Mapping[str, float],
    tuned: SetScore,
    default: SetScore,
    trial_number: int,
) -> Path:
    """A config that ``extends`` the base and sets the tuned keys (loadable by every command)."""
    keys = overrides_for(spec, params)
    extends = extends_name(spec.base, path.parent)
    worst = f"{spec.metric} worst"
    lines = [
        f"# Tuned by `ballbeam tune {spec.path.name}` (trial {trial_number} of {spec.trials}): "
        f"{spec.objective} {spec.metric} on the tuning set",
        f"# {default.objective:.4g} (the base) -> {tuned.objective:.4g}; worst "
        f"{default.summary[worst]:.4g} -> {tuned.summary[worst]:.4g}.",
        f"extends = {toml_value(extends)}",
    ]
    sections: dict[str, list[str]] = {}
    for key, value in keys.items():
        section, _, name = key.partition(".")
        sections.setdefault(section, []).append(f"{name} = {toml_value(value)}")
    for section, entries in sections.items():
        lines += ["", f"[{section}]", *entries]
    replace_file(path, ("\n".join(lines) + "\n").encode("utf-8"))
    load_config(path)  # what was written is a valid config
    return path


def extends_name(base: Path | None, directory: Path) -> str:
    """How a config written in ``directory`` names its base in ``extends``: a shipped config
    by its name (``"paper"``: found in whichever install reads it, where a path into this
    install's package would break when it moves or is upgraded), any other file by its path
    relative to ``directory``."""
    if base is None:
        return "paper"  # what a config without a file is: the paper's set-up
    resolved = base.resolve()
    shipped = shipped_configs().resolve()
    if resolved.is_relative_to(shipped):
        return resolved.relative_to(shipped).with_suffix("").as_posix()
    try:
        return os.path.relpath(resolved, directory.resolve())
    except ValueError:  # another drive: an absolute path
        return str(resolved)


def markdown_table(rows: list[dict[str, Any]]) -> str:
    columns = list(dict.fromkeys(key for row in rows for key in row))

    def cell(value: Any) -> str:
        if isinstance(value, float):
            return f"{value:.4g}"
        return str(value)

    lines = ["| " + " | ".join(columns) + " |", "|" + " --- |" * len(columns)]
    lines += ["| " + " | ".join(cell(row.get(column, "")) for column in columns) + " |"
              for row in rows]
    return "\n".join(lines)
