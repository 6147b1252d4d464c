"""Training and evaluation sweeps on Ray Tune, from one machine to a cluster.

A sweep is a TOML spec (see ``docs/sweeps.md``) expanded into a fixed, ordered list of trials
before anything runs: a grid or a seeded random search over the algorithm, reward, scenario
and any :class:`~learners.train.TrainConfig` or learner-config field, crossed with a list of
seeds. Every trial's settings are checked first, so a bad spec is a ValueError before any trial
starts.

Each training trial is one call of our own :func:`learners.train.train` writing into its own
folder ``RESULTS/trials/<trial id>/`` (its checkpoints, ``progress.csv``); it reports its
evaluation metrics to Tune after every checkpoint and ends by writing ``result.json``. An
evaluation trial scores one controller on one scenario and seed with :func:`sim.evaluate`.

The results folder is the sweep's state, not Tune's experiment folder: a trial with a
``result.json`` is finished and never submitted again; an unfinished trial resumes from its
own ``checkpoint.safetensors`` (bit for bit, as ``train(resume=True)`` does); a trial that
raises is retried by Tune (``retries`` in the spec) and continues from its checkpoint too.
So a driver killed at any point is continued with ``resume=True`` and the tables equal those
of an uninterrupted sweep, apart from the timing columns.

The tables, rewritten atomically (:mod:`sim.io`) whenever a trial finishes:

- ``trials.csv``: one row per finished trial, in the spec's trial order;
- ``summary.csv``: one row per configuration (the trial settings except the seed), with the
  number of seeds and, for every metric, the mean and the half-width of its 95% Student-t
  interval over the seeds (empty with a single seed).

Ray is an optional dependency (``pip install -e ".[sweep]"``); everything but
:func:`run_sweep` works without it.
"""

from __future__ import annotations

import csv
import dataclasses
import hashlib
import io
import itertools
import json
import math
import os
import random
import re
import shutil
import socket
import tempfile
import time
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import sim
from learners.algorithms import ALGORITHMS, REWARD_NAMES, make_config
from learners.common import check_int
from sim.io import atomic_write_text

__all__ = [
    "METRICS",
    "RAY_INSTALL_HINT",
    "SweepResult",
    "SweepSpec",
    "Trial",
    "aggregate",
    "load_spec",
    "parse_spec",
    "ray_available",
    "run_evaluation_trial",
    "run_sweep",
    "run_training_trial",
    "write_tables",
]

METRICS = ("response_rate", "avg_reward", "avg_time", "avg_time_finished", "collisions",
           "finished_rate")
"""The paper's metrics (:meth:`sim.Metrics.as_dict`) that every trial reports and the summary
aggregates."""

RAY_INSTALL_HINT = ('agv sweep needs Ray Tune, an optional dependency: pip install -e ".[sweep]"'
                    ' (or pip install "ray[tune]>=2.9")')
"""The one-line message printed when Ray is not installed."""

TIMING_COLUMNS = ("train_seconds", "wall_seconds", "attempts")
"""Columns of ``trials.csv`` that differ between an interrupted and an uninterrupted sweep."""

_TRAIN_AXES = ("algo", "reward", "scenario")  # listed first in the tables, in this order
_NOT_SWEPT = ("run_dir", "progress", "seed")  # TrainConfig fields a spec may not set
_SWEEP_KEYS = {"name", "search", "seeds", "samples", "search_seed", "retries", "cpus_per_trial"}
_DISTRIBUTIONS = ("choice", "uniform", "loguniform", "randint")


def ray_available() -> bool:
    """Whether Ray Tune can be imported (without importing it)."""
    import importlib.util

    try:
        return (importlib.util.find_spec("ray") is not None
                and importlib.util.find_spec("ray.tune") is not None)
    except (ImportError, ValueError):  # a broken or blocked installation
        return False


# --------------------------------------------------------------------------- the spec


@dataclass(frozen=True)
class Trial:
    """One run of a sweep: a training run or one evaluation."""

    index: int
    """Position in the sweep's canonical order (the order of the tables)."""
    trial_id: str
    """Folder name under ``RESULTS/trials/``: the index and the settings, file-name safe."""
    settings: dict[str, Any]
    """The configuration: every swept and fixed setting except the seed (the summary groups
    the trials by it)."""
    seed: int
    """The trial's seed (training: ``TrainConfig.seed``; evaluation: the test scenes' seed)."""

    def train_fields(self) -> dict[str, Any]:
        """The :class:`~learners.train.TrainConfig` fields of a training trial."""
        names = _train_field_names()
        return {k: v for k, v in self.settings.items() if k in names} | {"seed": self.seed}

    def learner_fields(self) -> dict[str, Any]:
        """The learner-config fields of a training trial."""
        names = _train_field_names()
        return {k: v for k, v in self.settings.items() if k not in names}


@dataclass(frozen=True)
class SweepSpec:
    """A parsed, checked sweep: its trials in canonical order and how to run them."""

    name: str
    """The sweep's name (the default results folder ``runs/sweeps/<name>``)."""
    mode: str
    """``"train"`` or ``"evaluate"``."""
    trials: tuple[Trial, ...]
    """Every trial, in the order of the tables."""
    retries: int = 2
    """How many times a failed trial is started again before it counts as failed."""
    cpus_per_trial: float = 1.0
    """CPUs Ray reserves for each trial (trials run in parallel on the free CPUs)."""

    def as_dict(self) -> dict[str, Any]:
        """The JSON form stored in ``RESULTS/sweep.json`` (compared on resume)."""
        return {"name": self.name, "mode": self.mode,
                "trials": [{"trial_id": t.trial_id, "settings": t.settings, "seed": t.seed}
                           for t in self.trials]}


def _train_field_names() -> set[str]:
    from learners.train import TrainConfig

    return {f.name for f in dataclasses.fields(TrainConfig)}


def _learner_field_names() -> dict[str, set[str]]:
    return {algo: {f.name for f in dataclasses.fields(cfg)}
            for algo, (_, cfg) in ALGORITHMS.items()}


def load_spec(path: str | os.PathLike[str], *, mode: str = "train") -> SweepSpec:
    """Read and check a sweep spec file (TOML).

    Parameters
    ----------
    path : path-like
        The ``.toml`` file.
    mode : {"train", "evaluate"}
        What the caller runs; the spec must be of that kind (an ``[evaluate]`` table makes an
        evaluation spec).

    Returns
    -------
    SweepSpec

    Raises
    ------
    ValueError
        For a file that is not valid TOML or any error :func:`parse_spec` finds.
    FileNotFoundError
        If the file does not exist.
    """
    try:
        import tomllib
    except ModuleNotFoundError:  # Python 3.10: the [sweep] extra installs tomli
        try:
            import tomli as tomllib
        except ModuleNotFoundError:
            raise ImportError(RAY_INSTALL_HINT) from None
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no sweep spec at {path}")
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except tomllib.TOMLDecodeError as err:
        raise ValueError(f"{path} is not valid TOML: {err}") from None
    return parse_spec(data, mode=mode, default_name=path.stem)


def _check_table(data: Mapping[str, Any], name: str) -> dict[str, Any]:
    value = data.get(name, {})
    if not isinstance(value, dict):
        raise ValueError(f"[{name}] must be a table of settings, got {value!r}")
    return dict(value)


def _seeds(values: Any, where: str) -> list[int]:
    if not isinstance(values, list) or not values:
        raise ValueError(f"{where} must be a non-empty list of seeds, got {values!r}")
    seeds = [check_int(f"{where}[{i}]", v, 0, 2**63 - 3) for i, v in enumerate(values)]
    if len(set(seeds)) != len(seeds):
        raise ValueError(f"{where} lists a seed twice: {seeds}")
    return seeds


def parse_spec(data: Mapping[str, Any], *, mode: str = "train",
               default_name: str = "sweep") -> SweepSpec:
    """Check a sweep spec (the parsed TOML) and expand it into its trials.

    Parameters
    ----------
    data : mapping
        Tables ``[sweep]`` (name, search, seeds, samples, search_seed, retries,
        cpus_per_trial) and, for training, ``[fixed]``, ``[grid]``, ``[random]``; for
        evaluation, ``[evaluate]`` (allocators, scenarios, episodes).
    mode : {"train", "evaluate"}
        The kind of sweep expected.
    default_name : str
        The name when ``[sweep]`` gives none.

    Returns
    -------
    SweepSpec

    Raises
    ------
    ValueError
        Naming the table and field: an unknown table or field, an empty grid axis or seed
        list, a value outside its field's range, an unknown algorithm, reward or scenario.
    """
    if mode not in ("train", "evaluate"):
        raise ValueError(f"mode must be 'train' or 'evaluate', got {mode!r}")
    if not isinstance(data, Mapping):
        raise ValueError(f"a sweep spec is a table, got {type(data).__name__}")
    is_evaluation = "evaluate" in data
    if is_evaluation and mode == "train":
        raise ValueError("this spec has an [evaluate] table: run it with `agv sweep --evaluate`")
    if not is_evaluation and mode == "evaluate":
        raise ValueError("`agv sweep --evaluate` needs a spec with an [evaluate] table "
                         "(allocators, scenarios, episodes)")
    allowed = {"sweep", "evaluate"} if is_evaluation else {"sweep", "fixed", "grid", "random"}
    unknown = sorted(set(data) - allowed)
    if unknown:
        raise ValueError(f"unknown table(s) {unknown} in the spec; expected some of "
                         f"{sorted(allowed)}")
    head = _check_table(data, "sweep")
    bad = sorted(set(head) - _SWEEP_KEYS)
    if bad:
        raise ValueError(f"unknown field(s) {bad} in [sweep]; expected some of "
                         f"{sorted(_SWEEP_KEYS)}")
    name = head.get("name", default_name)
    if not isinstance(name, str) or not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9._-]*", name):
        raise ValueError(f"[sweep] name must be a file-name-safe word (letters, digits, "
                         f"'.', '_', '-'), got {name!r}")
    retries = check_int("[sweep] retries", head.get("retries", 2), 0, 100)
    cpus = head.get("cpus_per_trial", 1)
    if isinstance(cpus, bool) or not isinstance(cpus, (int, float)) or not 0 < cpus <= 1024:
        raise ValueError(f"[sweep] cpus_per_trial must be a number in (0, 1024], got {cpus!r}")
    if is_evaluation:
        trials = _evaluation_trials(head, _check_table(data, "evaluate"))
    else:
        trials = _training_trials(head, _check_table(data, "fixed"),
                                  _check_table(data, "grid"), _check_table(data, "random"))
    return SweepSpec(name, "evaluate" if is_evaluation else "train", tuple(trials), retries,
                     float(cpus))


def _slug(value: Any) -> str:
    text = f"{value:g}" if isinstance(value, float) else str(value)
    return re.sub(r"[^A-Za-z0-9.=+-]", "_", text)


def _trial_id(index: int, settings: Mapping[str, Any], varied: Sequence[str], seed: int) -> str:
    parts = [_slug(settings[k]) if k in _TRAIN_AXES or k in ("allocator",)
             else f"{k}={_slug(settings[k])}" for k in varied]
    return "-".join([f"{index:04d}", *parts, f"s{seed}"])[:120]


def _evaluation_trials(head: dict[str, Any], table: dict[str, Any]) -> list[Trial]:
    keys = {"allocators", "scenarios", "episodes"}
    bad = sorted(set(table) - keys)
    if bad:
        raise ValueError(f"unknown field(s) {bad} in [evaluate]; expected some of "
                         f"{sorted(keys)}")
    if head.get("search", "grid") != "grid" or "samples" in head:
        raise ValueError("an evaluation sweep is the full matrix: [sweep] search must be "
                         "'grid', without samples")
    lists = {}
    for key in ("allocators", "scenarios"):
        values = table.get(key)
        if not isinstance(values, list) or not values:
            raise ValueError(f"[evaluate] {key} must be a non-empty list of names, "
                             f"got {values!r}")
        if not all(isinstance(v, str) for v in values) or len(set(values)) != len(values):
            raise ValueError(f"[evaluate] {key} must list distinct names, got {values!r}")
        lists[key] = values
    for scenario in lists["scenarios"]:
        sim.get_scenario(scenario)  # ValueError naming the known scenarios
    episodes = check_int("[evaluate] episodes", table.get("episodes", 300), 1)
    seeds = _seeds(head.get("seeds", [0]), "[sweep] seeds")
    trials = []
    for allocator, scenario in itertools.product(lists["allocators"], lists["scenarios"]):
        settings = {"allocator": allocator, "scenario": scenario, "episodes": episodes}
        for seed in seeds:
            index = len(trials)
            trials.append(Trial(index, _trial_id(index, settings, ["allocator", "scenario"],
                                                  seed), settings, seed))
    return trials


def _check_field(name: str, where: str, algos: Iterable[str]) -> None:
    train_names = _train_field_names()
    learner_names = _learner_field_names()
    if name in _NOT_SWEPT:
        hint = ("list the seeds in [sweep] seeds" if name == "seed" else
                "the sweep chooses it")
        raise ValueError(f"{where} cannot set {name!r}: {hint}")
    if name in train_names:
        return
    every = set().union(*learner_names.values())
    if name not in every:
        raise ValueError(f"unknown field {name!r} in {where}; expected a TrainConfig field "
                         f"({sorted(train_names - set(_NOT_SWEPT))}) or a learner field "
                         f"({sorted(every)})")
    missing = [a for a in algos if a in learner_names and name not in learner_names[a]]
    if missing:
        raise ValueError(f"{where} sets {name!r}, which {missing} do(es) not have; sweep "
                         "such a field in a spec of its own algorithm")


def _sample(dist: Any, rng: random.Random) -> Any:
    """One draw of a ``[random]`` entry (checked by :func:`_check_distribution`): a list is
    a uniform choice; a table names a distribution."""
    if isinstance(dist, list):
        return rng.choice(dist)
    (kind, args), = dist.items()
    if kind == "choice":
        return rng.choice(args)
    low, high = args
    if kind == "uniform":
        return low + (high - low) * rng.random()
    if kind == "loguniform":
        return math.exp(math.log(low) + (math.log(high) - math.log(low)) * rng.random())
    return rng.randint(low, high)  # randint: both ends included


def _check_distribution(name: str, dist: Any) -> None:
    where = f"[random] {name}"
    if isinstance(dist, list):
        if not dist:
            raise ValueError(f"{where} is an empty list: nothing to choose from")
        return
    if not isinstance(dist, dict) or len(dist) != 1:
        raise ValueError(f"{where} must be a list of values or a table with one of "
                         f"{list(_DISTRIBUTIONS)}, e.g. {{loguniform = [1e-4, 1e-2]}}; got "
                         f"{dist!r}")
    (kind, args), = dist.items()
    if kind not in _DISTRIBUTIONS:
        raise ValueError(f"{where}: unknown distribution {kind!r}; expected one of "
                         f"{list(_DISTRIBUTIONS)}")
    if kind == "choice":
        if not isinstance(args, list) or not args:
            raise ValueError(f"{where}: choice needs a non-empty list, got {args!r}")
        return
    if (not isinstance(args, list) or len(args) != 2
            or not all(isinstance(a, (int, float)) and not isinstance(a, bool) for a in args)
            or not all(math.isfinite(a) for a in args) or not args[0] <= args[1]):
        raise ValueError(f"{where}: {kind} needs [low, high] with low <= high, got {args!r}")
    if kind == "loguniform" and args[0] <= 0:
        raise ValueError(f"{where}: loguniform needs low > 0, got {args!r}")
    if kind == "randint" and not all(isinstance(a, int) for a in args):
        raise ValueError(f"{where}: randint needs integer bounds, got {args!r}")


def _training_trials(head: dict[str, Any], fixed: dict[str, Any], grid: dict[str, Any],
                     rand: dict[str, Any]) -> list[Trial]:
    search = head.get("search", "grid")
    if search not in ("grid", "random"):
        raise ValueError(f"[sweep] search must be 'grid' or 'random', got {search!r}")
    if search == "grid" and (rand or "samples" in head):
        raise ValueError("[random] and samples need [sweep] search = 'random'")
    for name, values in grid.items():
        if not isinstance(values, list):
            raise ValueError(f"[grid] {name} must be a list of values, got {values!r}")
        if not values:
            raise ValueError(f"[grid] {name} is empty: the grid has no trial")
    twice = sorted((set(fixed) & set(grid)) | (set(fixed) & set(rand)) | (set(grid) & set(rand)))
    if twice:
        raise ValueError(f"field(s) {twice} set in more than one of [fixed], [grid], [random]")
    algos = grid.get("algo", [fixed.get("algo", "maddpg")])
    for algo in algos:
        if algo not in ALGORITHMS:
            raise ValueError(f"unknown algorithm {algo!r}; expected one of {sorted(ALGORITHMS)}")
    for where, table in (("[fixed]", fixed), ("[grid]", grid), ("[random]", rand)):
        for name in table:
            _check_field(name, where, algos)
    for name, dist in rand.items():
        _check_distribution(name, dist)
    seeds = _seeds(head.get("seeds", [0]), "[sweep] seeds")

    combos = [dict(zip(grid, values, strict=True)) for values in itertools.product(*grid.values())]
    if search == "random":
        samples = check_int("[sweep] samples", head.get("samples", 1), 1)
        rng = random.Random(check_int("[sweep] search_seed", head.get("search_seed", 0), 0))
        combos = [{**combo, **{k: _sample(d, rng) for k, d in rand.items()}}
                  for _ in range(samples) for combo in combos]
    varied = [k for k in _TRAIN_AXES if k in grid] + [k for k in (*grid, *rand)
                                                     if k not in _TRAIN_AXES]
    trials: list[Trial] = []
    from learners.train import TrainConfig

    train_names = _train_field_names()
    for combo in combos:
        defaults = {k: getattr(TrainConfig, k) for k in _TRAIN_AXES}
        settings = {**defaults, **fixed, **combo}
        settings["tensorboard"] = settings.get("tensorboard", False)
        ordered = {k: settings[k] for k in _TRAIN_AXES}
        ordered.update({k: settings[k] for k in settings if k not in ordered})
        train_fields = {k: v for k, v in ordered.items() if k in train_names}
        learner_fields = {k: v for k, v in ordered.items() if k not in train_names}
        label = ", ".join(f"{k}={ordered[k]!r}" for k in varied) or "the fixed settings"
        try:  # every trial is checked before any starts
            config = TrainConfig(**train_fields, seed=seeds[0], progress=False)
            learner = make_config(config.algo, learner_fields)
            learner.validate()
        except (ValueError, TypeError) as err:
            raise ValueError(f"trial with {label}: {err}") from None
        normal = {**dataclasses.asdict(config), **dataclasses.asdict(learner)}
        ordered = {k: normal[k] for k in ordered}  # numbers normalised by validate()
        for seed in seeds:
            index = len(trials)
            trials.append(Trial(index, _trial_id(index, ordered, varied, seed), ordered, seed))
    return trials


# --------------------------------------------------------------------------- the tables


def _t_quantile(dof: int) -> float:
    from scipy.stats import t

    return float(t.ppf(0.975, dof))


def aggregate(rows: Sequence[Mapping[str, Any]], group_by: Sequence[str],
              metrics: Sequence[str] = METRICS) -> list[dict[str, Any]]:
    """Mean and 95% interval of each metric over the seeds of each configuration.

    Parameters
    ----------
    rows : sequence of mapping
        One per trial, holding the ``group_by`` columns, ``seed`` and the metrics.
    group_by : sequence of str
        The configuration's columns; trials equal in all of them form one group.
    metrics : sequence of str
        The columns aggregated.

    Returns
    -------
    list of dict
        One per configuration, in order of first appearance: the ``group_by`` columns,
        ``seeds`` (how many) and, per metric, ``<m>_mean`` and ``<m>_ci95`` (half-width
        t(0.975, n - 1) * s / sqrt(n) of the Student-t interval; NaN for one seed). NaN
        values (e.g. an average time with no finished episode) are left out of their
        metric's mean; an all-NaN metric is NaN.

    Raises
    ------
    ValueError
        If a row lacks a column.
    """
    groups: dict[tuple[Any, ...], list[Mapping[str, Any]]] = {}
    for i, row in enumerate(rows):
        missing = [c for c in (*group_by, *metrics) if c not in row]
        if missing:
            raise ValueError(f"row {i} lacks column(s) {missing}")
        groups.setdefault(tuple(json.dumps(row[c]) for c in group_by), []).append(row)
    out = []
    for members in groups.values():
        record: dict[str, Any] = {c: members[0][c] for c in group_by}
        record["seeds"] = len(members)
        for m in metrics:
            values = [float(r[m]) for r in members if not math.isnan(float(r[m]))]
            n = len(values)
            mean = math.fsum(values) / n if n else math.nan
            if n > 1:
                var = math.fsum((v - mean) ** 2 for v in values) / (n - 1)
                half = _t_quantile(n - 1) * math.sqrt(var / n)
            else:
                half = math.nan
            record[f"{m}_mean"], record[f"{m}_ci95"] = mean, half
        out.append(record)
    return out


def _cell(value: Any) -> Any:
    if isinstance(value, float):
        return "" if math.isnan(value) else repr(value)
    if isinstance(value, (list, dict)) or value is None:
        return json.dumps(value)
    return value


def _csv(rows: Sequence[Mapping[str, Any]], columns: Sequence[str]) -> str:
    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=list(columns), lineterminator="\n")
    writer.writeheader()
    for row in rows:
        writer.writerow({c: _cell(row.get(c)) for c in columns})
    return buf.getvalue()


def _trial_dir(results: Path, trial: Trial) -> Path:
    return results / "trials" / trial.trial_id


def write_tables(spec: SweepSpec, results: str | os.PathLike[str]) -> tuple[Path, Path, int]:
    """(Re)write ``trials.csv`` and ``summary.csv`` from the finished trials' ``result.json``.

    Parameters
    ----------
    spec : SweepSpec
    results : path-like
        The sweep's results folder.

    Returns
    -------
    (Path, Path, int)
        The two tables and how many trials are finished.
    """
    results = Path(results)
    group_by = list(spec.trials[0].settings) if spec.trials else []
    rows = []
    for trial in spec.trials:
        path = _trial_dir(results, trial) / "result.json"
        if not path.is_file():
            continue
        record = json.loads(path.read_text(encoding="utf-8"))
        metrics = {k: (math.nan if v is None else v) for k, v in record["metrics"].items()}
        rows.append({"trial": trial.trial_id, "index": trial.index, **trial.settings,
                     "seed": trial.seed, **metrics, **record.get("counters", {}),
                     "train_seconds": record.get("train_seconds", math.nan),
                     "wall_seconds": record.get("wall_seconds", math.nan),
                     "attempts": record.get("attempts", 1)})
    counter_cols = (["episodes_done", "env_steps", "updates", "best_response_rate"]
                    if spec.mode == "train" else [])
    columns = ["trial", "index", *group_by, "seed", *METRICS, *counter_cols,
               *(c for c in TIMING_COLUMNS if spec.mode == "train" or c != "train_seconds")]
    trials_csv = atomic_write_text(results / "trials.csv", _csv(rows, columns))
    summary = aggregate(rows, group_by)
    sum_cols = [*group_by, "seeds", *(f"{m}_{s}" for m in METRICS for s in ("mean", "ci95"))]
    summary_csv = atomic_write_text(results / "summary.csv", _csv(summary, sum_cols))
    return trials_csv, summary_csv, len(rows)


# --------------------------------------------------------------------------- the trials


def _finite(record: Mapping[str, Any]) -> dict[str, Any]:
    return {k: (None if isinstance(v, float) and not math.isfinite(v) else v)
            for k, v in record.items()}


def _log_attempt(folder: Path, text: str) -> int:
    """Append a line to ``attempts.log``; returns the number of attempts so far."""
    folder.mkdir(parents=True, exist_ok=True)
    log = folder / "attempts.log"
    with log.open("a", encoding="utf-8") as fh:
        fh.write(f"{time.strftime('%Y-%m-%dT%H:%M:%S')} {socket.gethostname()} pid "
                 f"{os.getpid()}: {text}\n")
    return len(log.read_text(encoding="utf-8").splitlines())


def _report(metrics: Mapping[str, Any]) -> None:
    from ray import tune

    tune.report({k: v for k, v in metrics.items() if isinstance(v, (int, float))})


def run_training_trial(trial: Trial, results: str | os.PathLike[str],
                       report: Callable[[dict[str, Any]], None] | None = None
                       ) -> dict[str, Any]:
    """Run (or resume, or skip) one training trial in ``results/trials/<trial id>/``.

    What every Tune trial of a training sweep runs; usable alone (without Ray).

    Parameters
    ----------
    trial : Trial
        From a training :class:`SweepSpec`.
    results : path-like
        The sweep's results folder.
    report : callable, optional
        Called with the metrics after every checkpoint and at the end (Tune's ``report``).

    Returns
    -------
    dict
        The trial's record, also written to ``result.json``: settings, seed, ``metrics`` (the
        last evaluation; NaN as None), ``counters``, ``train_seconds``, ``wall_seconds``,
        ``attempts``. A trial that already has a ``result.json`` is not run again: its record
        is returned.

    Raises
    ------
    RuntimeError
        If a signal stopped the training (it resumes from its checkpoint on the next try).
    """
    import torch

    from learners.train import TrainConfig, train

    folder = _trial_dir(Path(results), trial)
    if (folder / "result.json").is_file():  # finished before (a retried or resumed driver)
        record = json.loads((folder / "result.json").read_text(encoding="utf-8"))
        if report is not None:
            report(record["metrics"])
        return record
    resume = (folder / "checkpoint.safetensors").is_file()
    start = time.perf_counter()
    attempts = _log_attempt(folder, "resume from checkpoint.safetensors" if resume
                            else "start")
    torch.set_num_threads(int(trial.settings.get("threads", 1)))

    def on_checkpoint(counters: dict[str, Any]) -> None:
        if report is not None:
            report({"episodes_done": counters["episodes"], **counters.get("last_eval", {})})

    train_config = TrainConfig(**trial.train_fields(), run_dir=str(folder), progress=False)
    result = train(train_config, trial.learner_fields(), resume=resume,
                   on_checkpoint=on_checkpoint)
    if result.interrupted:
        raise RuntimeError(f"trial {trial.trial_id} was interrupted at episode "
                           f"{result.episodes}; it resumes from its checkpoint")
    metrics = {m: float(result.last_eval.get(m, math.nan)) for m in METRICS}
    record = {"trial_id": trial.trial_id, "settings": trial.settings, "seed": trial.seed,
              "metrics": _finite(metrics),
              "counters": {"episodes_done": result.episodes, "env_steps": result.env_steps,
                           "updates": result.updates,
                           "best_response_rate": result.best_response_rate},
              "train_seconds": result.seconds,
              "wall_seconds": time.perf_counter() - start, "attempts": attempts}
    atomic_write_text(folder / "result.json", json.dumps(record, indent=2) + "\n")
    if report is not None:
        report({"episodes_done": result.episodes, **metrics})
    return record


def _controller_options(name: str, scenario: str) -> dict[str, Any]:
    """Learned allocators (``<algo>-<reward>``) are built for a scenario; others are not."""
    algo, _, reward = name.partition("-")
    return {"scenario": scenario} if algo in ALGORITHMS and reward in REWARD_NAMES else {}


def run_evaluation_trial(trial: Trial, results: str | os.PathLike[str],
                         make_controller: Callable[..., Any],
                         report: Callable[[dict[str, Any]], None] | None = None
                         ) -> dict[str, Any]:
    """Run (or skip) one evaluation trial: ``sim.evaluate`` of one controller, scenario, seed.

    Parameters
    ----------
    trial : Trial
        From an evaluation :class:`SweepSpec`.
    results : path-like
        The sweep's results folder.
    make_controller : callable
        ``make_controller(name, **options)``; learned names get ``scenario=``.
    report : callable, optional
        Called with the metrics at the end.

    Returns
    -------
    dict
        The record written to ``results/trials/<trial id>/result.json``.
    """
    import torch

    folder = _trial_dir(Path(results), trial)
    if (folder / "result.json").is_file():
        record = json.loads((folder / "result.json").read_text(encoding="utf-8"))
        if report is not None:
            report(record["metrics"])
        return record
    start = time.perf_counter()
    attempts = _log_attempt(folder, "start")
    torch.set_num_threads(1)
    name, scenario = trial.settings["allocator"], trial.settings["scenario"]
    controller = make_controller(name, **_controller_options(name, scenario))
    result = sim.evaluate(controller, scenario, episodes=trial.settings["episodes"],
                          seed=trial.seed)
    metrics = {m: float(v) for m, v in result.as_dict().items() if m in METRICS}
    record = {"trial_id": trial.trial_id, "settings": trial.settings, "seed": trial.seed,
              "metrics": _finite(metrics), "wall_seconds": time.perf_counter() - start,
              "attempts": attempts}
    atomic_write_text(folder / "result.json", json.dumps(record, indent=2) + "\n")
    if report is not None:
        report(metrics)
    return record


def _train_trial(config: dict[str, Any]) -> None:
    """The Tune trainable of a training trial (runs in a Ray worker)."""
    run_training_trial(Trial(**config["trial"]), config["results"], _report)


def _evaluate_trial(config: dict[str, Any], make_controller: Callable[..., Any]) -> None:
    """The Tune trainable of an evaluation trial (runs in a Ray worker)."""
    run_evaluation_trial(Trial(**config["trial"]), config["results"], make_controller, _report)


# --------------------------------------------------------------------------- the driver


@dataclass
class SweepResult:
    """What :func:`run_sweep` returns."""

    results: Path
    """The results folder."""
    trials_csv: Path
    """One row per finished trial."""
    summary_csv: Path
    """Mean and 95% interval over the seeds, per configuration."""
    finished: int
    """Trials with a result."""
    ran: list[str] = field(default_factory=list)
    """The trials submitted to Ray by this call (the unfinished ones)."""
    failed: list[str] = field(default_factory=list)
    """Trials that still failed after their retries."""
    seconds: float = 0.0
    """Wall-clock time of this call."""


def _check_state(spec: SweepSpec, results: Path, resume: bool) -> None:
    state = results / "sweep.json"
    if not resume:
        if state.exists():
            raise ValueError(f"{results} already holds a sweep ({state.name}); continue it with "
                             "--resume or choose another --results folder")
        return
    if not state.is_file():
        raise ValueError(f"nothing to resume: no sweep at {results} (expected {state})")
    stored = json.loads(state.read_text(encoding="utf-8"))
    now = json.loads(json.dumps(spec.as_dict()))
    if stored != now:
        diff = next((f"trial {a.get('trial_id')}" for a, b in
                     zip(stored.get("trials", []), now["trials"], strict=False) if a != b),
                    "its name, mode or number of trials")
        raise ValueError(f"cannot resume {results}: the spec differs from the sweep stored "
                         f"there ({diff}); resume with the same spec, or start a new sweep in "
                         "another --results folder")


def _start_ray(address: str | None, cpus: int | None, temp_dir: Path | None) -> Any:
    """Connect to a cluster or start Ray on this machine, on 127.0.0.1 only."""
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    if address is None:
        # Ray otherwise replaces 127.0.0.1 by this machine's network address and listens
        # on every interface; this keeps a local Ray on the loopback interface.
        os.environ["RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"] = "0"
        # Ray starts its workers at nice 15, where a trial gets a few percent of a core beside
        # any ordinary process (measured: BiCNet trials at 2% CPU while other work ran); a
        # local sweep's trials run at the driver's priority instead.
        os.environ.setdefault("RAY_worker_niceness", "0")
    import ray
    import ray._private.ray_constants as constants

    if address is None:
        constants.ENABLE_RAY_CLUSTER = False  # read at call time; set if ray was imported
        ray.init(num_cpus=cpus or os.cpu_count() or 1, include_dashboard=False,
                 _node_ip_address="127.0.0.1", _temp_dir=str(temp_dir),
                 configure_logging=False, log_to_driver=True)
    else:
        ray.init(address=address, configure_logging=False, log_to_driver=True)
    return ray


def run_sweep(
    spec: SweepSpec,
    results: str | os.PathLike[str],
    *,
    resume: bool = False,
    address: str | None = None,
    cpus: int | None = None,
    make_controller: Callable[..., Any] | None = None,
    ray_temp_dir: str | os.PathLike[str] | None = None,
    verbose: int = 1,
) -> SweepResult:
    """Run a sweep's unfinished trials on Ray Tune and write its tables.

    Parameters
    ----------
    spec : SweepSpec
        From :func:`load_spec` or :func:`parse_spec`.
    results : path-like
        The results folder: ``sweep.json``, ``trials/<id>/``, ``trials.csv``,
        ``summary.csv``. On a cluster every machine must see it at the same path.
    resume : bool
        Continue the sweep in ``results`` (same spec): finished trials are skipped,
        unfinished ones resume from their checkpoints.
    address : str, optional
        A running Ray cluster (``ray start --head`` prints it, e.g. ``10.0.0.5:6379``).
        Default: start Ray on this machine, listening on 127.0.0.1 only.
    cpus : int, optional
        CPUs of the local Ray (default: all of this machine's); not with ``address``.
    make_controller : callable, optional
        ``make_controller(name, **options) -> controller`` for evaluation sweeps (the ``agv``
        command passes ``allocator.make``; learned names get ``scenario=``).
    ray_temp_dir : path-like, optional
        Ray's session folder for a local Ray (default ``results/ray`` when that path is short
        enough for Ray's sockets, else ``agv-ray-<digest of results>`` in the system's
        temporary folder, removed when the sweep ends).
    verbose : int
        Tune's verbosity (0 silent, 1 status, 2 trial results).

    Returns
    -------
    SweepResult

    Raises
    ------
    ValueError
        For a results folder that holds another sweep (or none, with ``resume``), a spec that
        differs from the stored one, ``cpus`` with ``address``, or an evaluation sweep without
        ``make_controller`` or whose controllers cannot be built.
    ImportError
        If Ray Tune is not installed (the message says how to install it).
    """
    begin = time.perf_counter()
    if not isinstance(spec, SweepSpec):
        raise ValueError(f"spec must be a SweepSpec (load_spec), got {type(spec).__name__}")
    if cpus is not None:
        cpus = check_int("cpus", cpus, 1)
        if address is not None:
            raise ValueError("cpus sizes a local Ray; with address, the cluster's machines "
                             "bring their own CPUs (ray start --num-cpus)")
    if spec.mode == "evaluate":
        if make_controller is None:
            raise ValueError("an evaluation sweep needs make_controller (run it as "
                             "`agv sweep --evaluate`, which passes allocator.make)")
        for name, scenario in dict.fromkeys((t.settings["allocator"], t.settings["scenario"])
                                            for t in spec.trials):
            try:  # every controller is built once before any trial starts
                make_controller(name, **_controller_options(name, scenario))
            except (ValueError, KeyError, FileNotFoundError) as err:
                raise ValueError(f"[evaluate] allocator {name!r} on {scenario!r}: "
                                 f"{err}") from None
    if not ray_available():
        raise ImportError(RAY_INSTALL_HINT)
    results = Path(results).absolute()
    _check_state(spec, results, resume)
    results.mkdir(parents=True, exist_ok=True)
    atomic_write_text(results / "sweep.json", json.dumps(spec.as_dict(), indent=2) + "\n")
    pending = [t for t in spec.trials if not (_trial_dir(results, t) / "result.json").is_file()]
    failed: list[str] = []
    if pending:
        failed = _run_on_ray(spec, pending, results, address, cpus, make_controller,
                             ray_temp_dir, verbose)
    trials_csv, summary_csv, finished = write_tables(spec, results)
    return SweepResult(results, trials_csv, summary_csv, finished, [t.trial_id for t in pending],
                       failed, time.perf_counter() - begin)


# Ray puts its sockets at TEMP/session_<YYYY-MM-DD_HH-MM-SS_ffffff>_<pid>/sockets/plasma_store:
# 64 characters after TEMP with a 7-digit pid, and an AF_UNIX path holds at most 107 bytes.
_RAY_SOCKET_SUFFIX = len("/session_2026-12-02_17-01-07_653513_4194304/sockets/plasma_store")
_AF_UNIX_PATH_MAX = 107


def ray_temp_dir_fits(path: str | os.PathLike[str]) -> bool:
    """Whether Ray's socket files fit under ``path`` (AF_UNIX paths are at most 107 bytes)."""
    return len(os.fsencode(Path(path).absolute())) + _RAY_SOCKET_SUFFIX <= _AF_UNIX_PATH_MAX


def _run_on_ray(spec: SweepSpec, pending: list[Trial], results: Path, address: str | None,
                cpus: int | None, make_controller: Callable[..., Any] | None,
                ray_temp_dir: str | os.PathLike[str] | None, verbose: int) -> list[str]:
    own_temp = None
    temp_dir = None
    if address is None:
        if ray_temp_dir is not None:
            temp_dir = Path(ray_temp_dir).absolute()
        elif ray_temp_dir_fits(results / "ray"):
            temp_dir = results / "ray"
        else:  # one folder per results folder: a resumed sweep reuses and removes it
            digest = hashlib.sha1(str(results).encode()).hexdigest()[:12]
            temp_dir = own_temp = Path(tempfile.gettempdir()) / f"agv-ray-{digest}"
    saved_env = {k: os.environ.get(k) for k in ("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER",
                                                "RAY_USAGE_STATS_ENABLED", "RAY_worker_niceness")}
    ray = _start_ray(address, cpus, temp_dir)
    import ray._private.ray_constants as constants

    cluster_flag = constants.ENABLE_RAY_CLUSTER if address is not None else True
    try:
        from ray import tune

        class _Tables(tune.Callback):  # the tables follow the trials as they finish
            def on_trial_complete(self, iteration: int, trials: list, trial: Any,
                                  **info: Any) -> None:
                write_tables(spec, results)

        if spec.mode == "train":
            trainable: Any = _train_trial
        else:
            trainable = tune.with_parameters(_evaluate_trial, make_controller=make_controller)
        trainable = tune.with_resources(trainable, {"cpu": spec.cpus_per_trial})
        param_space = {"results": str(results), "trial": tune.grid_search(
            [{"index": t.index, "trial_id": t.trial_id, "settings": t.settings, "seed": t.seed}
             for t in pending])}
        tuner = tune.Tuner(
            trainable,
            param_space=param_space,
            tune_config=tune.TuneConfig(
                reuse_actors=True,  # a trial's worker runs the next trial: no new imports
                trial_dirname_creator=lambda t: t.config["trial"]["trial_id"]),
            run_config=tune.RunConfig(
                name=f"{spec.name}-{time.strftime('%Y%m%d-%H%M%S')}-{os.getpid()}",
                storage_path=str(results / "tune"),
                failure_config=tune.FailureConfig(max_failures=spec.retries),
                callbacks=[_Tables()], verbose=verbose),
        )
        grid = tuner.fit()
        failed = sorted(r.config["trial"]["trial_id"] for r in grid if r.error is not None)
    finally:
        ray.shutdown()
        for key, value in saved_env.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value
        constants.ENABLE_RAY_CLUSTER = cluster_flag
        if own_temp is not None:
            shutil.rmtree(own_temp, ignore_errors=True)
    return failed
