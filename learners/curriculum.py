"""Training over a curriculum of fleet sizes with one set of weights (issue 17).

A curriculum is a list of stages ``(scenario, episodes)``, e.g. ``3v3:2000,6v6:2000,
10v10:1000,20v20:500``, or on lifelong floors ``warehouse-20:600,warehouse-50:300`` (an
episode of a lifelong stage is a window of ``TrainConfig.window`` steps). The stages are all
episodic or all lifelong: the two modes' networks differ.

Stage k is an ordinary :func:`learners.train.train` run in ``RUN_DIR/stage-k-<scenario>`` on
its own scenario, started from stage k - 1's final training
checkpoint (``init_from``: networks, targets, Adam moments and update count carry over; the
replay buffer, whose rows have the stage's N, the environments, the exploration schedule and
the counters start afresh). Only the entity learners (``maddpg-e``, ``bicnet-e``) can do this:
their weights do not depend on N.

``RUN_DIR/curriculum.json`` records the stages, the train settings and the learner config; a
finished stage leaves ``done.json`` in its folder. Resuming (:func:`train_curriculum` with
``resume=True``, or ``agv train --resume RUN_DIR``) skips the finished stages, resumes the
interrupted one from its checkpoint (bit for bit, as :func:`train` does) and starts the next
ones from the previous stage's checkpoint file, so a resumed curriculum computes exactly what
the uninterrupted one computes. ``RUN_DIR/policy.safetensors`` and ``best.safetensors`` are
the last stage's latest and best evaluated actor.
"""

from __future__ import annotations

import dataclasses
import json
import os
import re
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from learners.algorithms import ENTITY_ALGORITHMS, make_config
from learners.common import check_int
from learners.train import TrainConfig, TrainResult, train
from sim.io import atomic_write_bytes, atomic_write_text

__all__ = ["Stage", "parse_curriculum", "train_curriculum", "is_curriculum_run",
           "load_curriculum", "CURRICULUM_FILE"]

CURRICULUM_FILE = "curriculum.json"
_STAGE = re.compile(r"^\s*([^:\s]+)\s*:\s*(\S+)\s*$")


@dataclass(frozen=True)
class Stage:
    """One stage of a curriculum: train on ``scenario`` for ``episodes`` episodes."""

    scenario: str
    episodes: int

    def __post_init__(self) -> None:
        import sim

        if not isinstance(self.scenario, str):
            raise ValueError(f"a curriculum stage's scenario must be a name, got "
                             f"{self.scenario!r}")
        sim.get_scenario(self.scenario)  # a clear error for an unknown name
        object.__setattr__(self, "episodes",
                           check_int(f"episodes of stage {self.scenario!r}", self.episodes, 1))

    @property
    def lifelong(self) -> bool:
        """Whether the stage runs on a lifelong floor (``warehouse-N``)."""
        import sim

        return bool(getattr(sim.get_scenario(self.scenario), "lifelong", False))


def parse_curriculum(spec: str | list[Stage] | list[tuple[str, int]]) -> list[Stage]:
    """Stages from ``"3v3:2000,6v6:2000,20v20:500"`` (or a list of stages / pairs).

    Raises
    ------
    ValueError
        For an empty curriculum, an item that is not ``SCENARIO:EPISODES``, an unknown or
        lifelong scenario, or episodes that are not a positive integer.
    """
    if isinstance(spec, str):
        items = [s for s in spec.split(",") if s.strip()]
        stages = []
        for item in items:
            m = _STAGE.match(item)
            if not m:
                raise ValueError(f"curriculum item {item!r} must be SCENARIO:EPISODES, e.g. "
                                 "'6v6:2000'")
            try:
                episodes = int(m.group(2))
            except ValueError:
                raise ValueError(f"curriculum item {item!r}: episodes must be a positive "
                                 f"integer, got {m.group(2)!r}") from None
            stages.append(Stage(m.group(1), episodes))
    elif isinstance(spec, (list, tuple)):
        stages = [s if isinstance(s, Stage) else Stage(*s) for s in spec]
    else:
        raise ValueError(f"a curriculum is 'SCENARIO:EPISODES,...' or a list of stages, got "
                         f"{type(spec).__name__}")
    if not stages:
        raise ValueError("a curriculum needs at least one stage, e.g. '6v6:2000,20v20:500'")
    modes = {s.lifelong for s in stages}
    if len(modes) > 1:
        lifelong = [s.scenario for s in stages if s.lifelong]
        episodic = [s.scenario for s in stages if not s.lifelong]
        raise ValueError(f"a curriculum's stages are all episodic or all lifelong (their "
                         f"networks differ); got lifelong {lifelong} and episodic {episodic}")
    return stages


def _stage_dir(run_dir: Path, k: int, stage: Stage) -> Path:
    return run_dir / f"stage-{k}-{stage.scenario}"


def is_curriculum_run(run_dir: str | os.PathLike[str]) -> bool:
    """Whether ``run_dir`` holds a curriculum run (its ``curriculum.json``)."""
    return (Path(run_dir) / CURRICULUM_FILE).is_file()


def last_stage_checkpoint(run_dir: str | os.PathLike[str]) -> Path:
    """The training checkpoint of a curriculum run's last stage that has one, for
    ``--init-from RUN_DIR`` (a curriculum folder has no checkpoint of its own).

    Raises
    ------
    ValueError
        If ``run_dir`` holds no curriculum, or no stage of it has written a checkpoint.
    """
    _, stages, _ = load_curriculum(run_dir)
    for k in range(len(stages) - 1, -1, -1):
        path = _stage_dir(Path(run_dir), k, stages[k]) / "checkpoint.safetensors"
        if path.is_file():
            return path
    raise ValueError(f"{run_dir} is a curriculum run whose stages have no training checkpoint "
                     f"yet")


def load_curriculum(run_dir: str | os.PathLike[str]
                    ) -> tuple[TrainConfig, list[Stage], dict[str, Any]]:
    """The train settings, stages and learner config recorded in a curriculum run.

    Raises
    ------
    ValueError
        If ``run_dir`` holds no curriculum or its record is not valid.
    """
    path = Path(run_dir) / CURRICULUM_FILE
    if not path.is_file():
        raise ValueError(f"nothing to resume: {run_dir} holds no {CURRICULUM_FILE}")
    try:
        record = json.loads(path.read_text(encoding="utf-8"))
        config = TrainConfig(**{**record["train"], "run_dir": str(run_dir)})
        stages = parse_curriculum([tuple(s) for s in record["stages"]])
        learner = dict(record["learner"])
        make_config(config.algo, learner)
    except (KeyError, TypeError, ValueError, json.JSONDecodeError) as err:
        raise ValueError(f"{path} is not a valid curriculum record: {err}") from None
    return config, stages, learner


def train_curriculum(
    config: TrainConfig,
    stages: str | list[Stage] | list[tuple[str, int]],
    learner_config: Any = None,
    *,
    resume: bool = False,
    on_checkpoint: Callable[[dict[str, Any]], None] | None = None,
    make_shield: Callable[[Any], Any] | None = None,
) -> TrainResult:
    """Train one entity learner through the stages (see the module docstring).

    Parameters
    ----------
    config : TrainConfig
        Algorithm (``maddpg-e`` or ``bicnet-e``), reward, seed, run folder, evaluation and
        checkpoint settings; its ``scenario`` and ``episodes`` are replaced by each stage's.
    stages : str or list
        The curriculum (:func:`parse_curriculum`).
    learner_config : config dataclass, dict or None
        The learner's hyperparameters (the same for every stage).
    resume : bool
        Continue the curriculum in ``config.run_dir``; its stages and settings must be the
        recorded ones (a later stage may be appended).
    on_checkpoint : callable, optional
        Passed to every stage's :func:`train` (tests use it to simulate a crash).
    make_shield : callable, optional
        Passed to every stage's :func:`train`: the shield of a ``shield=True`` learner config
        (``allocator.SafetyShield``).

    Returns
    -------
    TrainResult
        The last stage's result (``interrupted`` if a signal stopped a stage; then the later
        stages were not run).

    Raises
    ------
    ValueError
        For an algorithm whose weights depend on N, a bad curriculum, a new run in a folder
        that holds one, or a resume whose settings differ from the record.
    """
    config.validate()
    if config.algo not in ENTITY_ALGORITHMS:
        raise ValueError(f"a curriculum over N needs an algorithm whose weights do not depend "
                         f"on N: one of {list(ENTITY_ALGORITHMS)}, got {config.algo!r}")
    stages = parse_curriculum(stages)
    run_dir = config.resolved_run_dir()
    if isinstance(learner_config, dict) or learner_config is None:
        cfg = make_config(config.algo, learner_config)
    else:
        cfg = learner_config
        cfg.validate()
    learner = dataclasses.asdict(cfg)
    train_record = {k: v for k, v in dataclasses.asdict(config).items()
                    if k not in ("scenario", "episodes", "run_dir")}
    record = {"train": train_record, "stages": [[s.scenario, s.episodes] for s in stages],
              "learner": learner}
    path = run_dir / CURRICULUM_FILE
    if resume:
        _, saved_stages, saved_learner = load_curriculum(run_dir)
        saved = json.loads(path.read_text(encoding="utf-8"))
        for key in ("algo", "reward", "seed"):
            if saved["train"][key] != train_record[key]:
                raise ValueError(f"cannot resume {run_dir}: it was trained with {key}="
                                 f"{saved['train'][key]!r}, this call asks for "
                                 f"{train_record[key]!r}")
        if saved_learner != json.loads(json.dumps(learner)):
            raise ValueError(f"cannot resume {run_dir} with different hyperparameters; the "
                             f"record has {saved_learner}")
        if stages[:len(saved_stages)] != saved_stages[:len(stages)] or \
                len(stages) < len(saved_stages):
            raise ValueError(f"cannot resume {run_dir}: its curriculum is "
                             f"{[(s.scenario, s.episodes) for s in saved_stages]}; a resumed "
                             "curriculum keeps those stages (later ones may be appended)")
    elif path.exists():
        raise ValueError(f"{run_dir} already holds a curriculum ({CURRICULUM_FILE}); continue "
                         "it with --resume or choose another --run-dir")
    run_dir.mkdir(parents=True, exist_ok=True)
    atomic_write_text(path, json.dumps(record, indent=2) + "\n")

    result: TrainResult | None = None
    previous: Path | None = None
    for k, stage in enumerate(stages):
        folder = _stage_dir(run_dir, k, stage)
        done = folder / "done.json"
        stage_config = dataclasses.replace(config, scenario=stage.scenario,
                                           episodes=stage.episodes, run_dir=str(folder))
        if done.is_file():
            previous = folder / "checkpoint.safetensors"
            continue
        if (folder / "checkpoint.safetensors").is_file():
            result = train(stage_config, cfg, resume=True, on_checkpoint=on_checkpoint,
                           make_shield=make_shield)
        else:
            result = train(stage_config, cfg, init_from=previous, on_checkpoint=on_checkpoint,
                           make_shield=make_shield)
        if result.interrupted:
            return result
        score = ({"best_throughput": result.best_throughput} if stage.lifelong else
                 {"best_response_rate": result.best_response_rate})
        atomic_write_text(done, json.dumps({"episodes": result.episodes,
                                            "updates": result.updates, **score},
                                           indent=2) + "\n")
        previous = folder / "checkpoint.safetensors"
    last = _stage_dir(run_dir, len(stages) - 1, stages[-1])
    for name in ("policy", "best"):
        for suffix in (".safetensors", ".json"):
            src = last / f"{name}{suffix}"
            if src.is_file():
                atomic_write_bytes(run_dir / f"{name}{suffix}", src.read_bytes())
    if result is None:  # every stage was already done: the last one, loaded (nothing runs)
        result = train(dataclasses.replace(config, scenario=stages[-1].scenario,
                                           episodes=stages[-1].episodes, run_dir=str(last)),
                       cfg, resume=True, make_shield=make_shield)
    return result
