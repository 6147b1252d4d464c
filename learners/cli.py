"""``agv train`` and ``agv evaluate``: the argument parsers, their entry points, and the
argument types that check a user's values before any work starts.

``allocator/cli.py`` wires these into the ``agv`` console script; they can also be used alone::

    parser = argparse.ArgumentParser(); add_train_arguments(parser)
    raise SystemExit(run_train(parser.parse_args()))
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import sys
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

__all__ = [
    "add_train_arguments",
    "run_train",
    "add_evaluate_arguments",
    "run_evaluate",
    "print_metrics",
    "positive_int",
    "non_negative_int",
    "seed",
    "rate",
    "scenario_name",
    "output_dir",
    "output_file",
    "SEED_LIMIT",
]

SEED_LIMIT = 2**63
"""Seeds lie in [0, 2**63), as in :func:`sim.evaluate`."""


def positive_int(value: str) -> int:
    """An argparse type: an integer >= 1."""
    try:
        number = int(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {value!r}") from None
    if number < 1:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {value!r}")
    return number


def non_negative_int(value: str) -> int:
    """An argparse type: an integer >= 0."""
    try:
        number = int(value)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected an integer >= 0, got {value!r}") from None
    if number < 0:
        raise argparse.ArgumentTypeError(f"expected an integer >= 0, got {value!r}")
    return number


def seed(value: str) -> int:
    """An argparse type: a seed, an integer in [0, 2**63)."""
    try:
        number = int(value)
    except ValueError:
        number = -1
    if not 0 <= number < SEED_LIMIT:
        raise argparse.ArgumentTypeError(f"expected a seed, an integer in [0, 2**63), "
                                         f"got {value!r}")
    return number


def rate(value: str) -> float:
    """An argparse type: a finite number in [0, 1] (a task response rate)."""
    try:
        number = float(value)
    except ValueError:
        number = math.nan
    if not 0.0 <= number <= 1.0:  # also rejects NaN
        raise argparse.ArgumentTypeError(f"expected a task response rate, a number in [0, 1], "
                                         f"got {value!r}")
    return number


def scenario_name(value: str) -> str:
    """An argparse type: a scenario name that :func:`sim.get_scenario` accepts (a registered
    name or ``NvM``)."""
    import sim

    try:
        sim.get_scenario(value)
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err)) from None
    return value


def _writable_below(path: Path, value: str) -> None:
    """Raise unless a folder ``path`` exists or can be created (its nearest existing ancestor
    is a writable folder)."""
    ancestor = path
    while not ancestor.exists() and ancestor != ancestor.parent:
        ancestor = ancestor.parent
    if not ancestor.is_dir():
        raise argparse.ArgumentTypeError(f"cannot use {value!r}: {str(ancestor)!r} is a file, "
                                         "not a folder")
    if not os.access(ancestor, os.W_OK | os.X_OK):
        raise argparse.ArgumentTypeError(f"cannot use {value!r}: no permission to write in "
                                         f"{str(ancestor)!r}")


def output_dir(value: str) -> str:
    """An argparse type: a folder that exists or can be created (missing parents are made)."""
    if not value:
        raise argparse.ArgumentTypeError("expected a folder, got an empty path")
    _writable_below(Path(value).absolute(), value)
    return value


def output_file(value: str) -> str:
    """An argparse type: a file that can be written (missing parent folders are made)."""
    path = Path(value).absolute()
    if not value or value.endswith(("/", os.sep)) or path.is_dir():
        raise argparse.ArgumentTypeError(f"expected a file name, got the folder {value!r}")
    _writable_below(path.parent, value)
    return value


def _names(items: Sequence[str]) -> str:
    return ", ".join(items)


def add_train_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the ``agv train`` options to ``parser``."""
    import sim
    from learners.algorithms import ALGORITHMS, PRESETS, REWARD_NAMES

    algos = sorted(ALGORITHMS)
    parser.add_argument("--algo", choices=algos, default=None,
                        help=f"learning algorithm: {_names(algos)} (default maddpg)")
    parser.add_argument("--reward", choices=list(REWARD_NAMES), default=None,
                        help=f"reward: {_names(REWARD_NAMES)} (default ipf)")
    parser.add_argument("--scenario", type=scenario_name, default=None,
                        help=f"scenario: {_names(sim.scenario_names())} or NvM (N AGVs, M tasks)"
                             " (default 3v3)")
    parser.add_argument("--episodes", type=positive_int, default=None,
                        help="training episodes (default 5000; with --resume: the new total)")
    parser.add_argument("--seed", type=seed, default=None,
                        help="random seed of the networks, environments and noise, in "
                             "[0, 2**63) (default 0)")
    where = parser.add_mutually_exclusive_group()
    where.add_argument("--run-dir", type=output_dir, default=None,
                       help="folder for progress.csv and checkpoints "
                            "(default runs/<algo>-<reward>-<scenario>-s<seed>)")
    where.add_argument("--resume", metavar="RUN_DIR", default=None,
                       help="continue the run in RUN_DIR from its last checkpoint")
    parser.add_argument("--eval-every", type=non_negative_int, default=None,
                        help="evaluate every this many episodes (0: only at the end; "
                             "default 500)")
    parser.add_argument("--eval-episodes", type=positive_int, default=None,
                        help="test episodes per evaluation (default 300)")
    parser.add_argument("--eval-seed", type=seed, default=None,
                        help="seed of the evaluation scenes, the same at every evaluation "
                             "(default 12345)")
    parser.add_argument("--window", type=positive_int, default=None,
                        help="lifelong floors (warehouse-N): steps per training episode, a "
                             "window of the continuing run (default 100)")
    parser.add_argument("--eval-steps", type=positive_int, default=None,
                        help="lifelong floors: steps of each evaluation run (default 500)")
    parser.add_argument("--eval-runs", type=positive_int, default=None,
                        help="lifelong floors: independent runs per evaluation, their "
                             "throughput averaged (default 1)")
    parser.add_argument("--checkpoint-every", type=positive_int, default=None,
                        help="write a resumable checkpoint every this many episodes "
                             "(default 1000)")
    parser.add_argument("--stop-response", type=rate, default=None,
                        help="stop once an evaluation reaches this task response rate, in "
                             "[0, 1] (default: never)")
    parser.add_argument("--fastest-min-response", type=rate, default=None,
                        help="fastest.safetensors keeps the policy of the least validation "
                             "time among evaluations with at least this response, in [0, 1] "
                             "(default 0.97)")
    parser.add_argument("--threads", type=positive_int, default=None,
                        help="torch threads (default 1)")
    parser.add_argument("--preset", choices=sorted(PRESETS), default=None,
                        help="named learner settings applied before --set: 'default' (the "
                             "config defaults) or 'fast' (more environments per update, larger "
                             "steps; about 5x the env steps/s, see docs/learners.md)")
    parser.add_argument("--set", dest="overrides", action="append", default=[],
                        metavar="KEY=VALUE",
                        help="override a learner hyperparameter, e.g. --set batch_size=512 "
                             "(see MADDPGConfig / BiCNetConfig); repeatable")
    parser.add_argument("--export", metavar="PATH", type=output_file, default=None,
                        help="after training, copy the best evaluated policy to PATH (e.g. "
                             "allocator/weights/3v3/bicnet-ipf.safetensors)")
    parser.add_argument("--curriculum", metavar="SCENARIO:EPISODES,...", default=None,
                        help="train one entity learner (maddpg-e, bicnet-e) through stages of "
                             "growing N with the same weights, e.g. "
                             "'3v3:2000,6v6:2000,10v10:1000,20v20:500' (replaces --scenario "
                             "and --episodes; see docs/learners.md)")
    parser.add_argument("--init-from", metavar="CHECKPOINT", default=None,
                        help="start a new run from another run's training checkpoint (its "
                             "folder, a curriculum run's folder for its last stage, "
                             "checkpoint.safetensors, or a --portable-copy): networks, "
                             "targets and Adam moments carry over; the network width (hidden) "
                             "must match, the other settings may change; the scenario too for "
                             "the entity learners (maddpg-e, bicnet-e), e.g. to go on from "
                             "warehouse-20 to warehouse-50. Or a deployed "
                             "policy (best.safetensors, a shipped weight file) of any "
                             "algorithm and reward: only its actor carries over (see "
                             "--critic-warmup)")
    parser.add_argument("--critic-warmup", type=non_negative_int, default=None,
                        metavar="UPDATES",
                        help="the first UPDATES gradient updates train only the critic (the "
                             "actor's learning rate is 0): for a run started --init-from a "
                             "deployed policy, whose critic starts fresh (default 0)")
    parser.add_argument("--init-other-reward", action="store_true",
                        help="with --init-from: the checkpoint may have been trained on another "
                             "reward (e.g. an ipf run fine-tuned with ipf-time); the critic "
                             "starts from the old reward's values")
    parser.add_argument("--portable-copy", nargs=2, metavar=("RUN_DIR", "TARGET"), default=None,
                        help="train nothing: copy RUN_DIR to TARGET without its replay buffer "
                             "(a few MB: networks, optimizers, counters, progress.csv, the "
                             "policies), to commit or move a long run; `--resume TARGET` "
                             "continues it with an empty buffer")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")


def _parse_overrides(algo: str, items: list[str]) -> dict[str, Any]:
    from learners.algorithms import ALGORITHMS

    fields = {f.name: f for f in dataclasses.fields(ALGORITHMS[algo][1])}
    out: dict[str, Any] = {}
    for item in items:
        key, sep, value = item.partition("=")
        key = key.strip().replace("-", "_")
        if not sep or key not in fields:
            raise ValueError(f"--set expects KEY=VALUE with KEY one of {sorted(fields)}, "
                             f"got {item!r}")
        default = fields[key].default
        try:
            if isinstance(default, bool):
                if value.lower() not in ("true", "false", "1", "0"):
                    raise ValueError(value)
                out[key] = value.lower() in ("true", "1")
            elif isinstance(default, int):
                out[key] = int(float(value)) if float(value).is_integer() else int(value)
            else:
                out[key] = type(default)(value)
        except ValueError:
            raise ValueError(f"--set {key}: cannot read {value!r} as "
                             f"{type(default).__name__}") from None
    return out


def _preset(algo: str, args: argparse.Namespace) -> dict[str, Any]:
    """The overrides of ``--preset`` (none without it)."""
    from learners.algorithms import preset_overrides

    preset = getattr(args, "preset", None)
    return preset_overrides(algo, preset) if preset else {}


def run_train(args: argparse.Namespace) -> int:
    """Run ``agv train``; returns the exit status (0 done, 130 interrupted, 2 bad input)."""
    from learners.checkpoint import resolve_checkpoint_path
    from learners.train import TrainConfig, load_run_config, train

    if getattr(args, "portable_copy", None):
        return _portable_copy(*args.portable_copy)
    curriculum = getattr(args, "curriculum", None)
    if curriculum is not None or (args.resume and _is_curriculum(args.resume)):
        return _run_curriculum(args)
    try:
        if args.resume:
            config, saved = load_run_config(args.resume)
            for key in ("algo", "reward", "scenario", "seed"):
                given = getattr(args, key)
                if given is not None and given != getattr(config, key):
                    raise ValueError(f"cannot resume {args.resume}: it was trained with {key}="
                                     f"{getattr(config, key)!r}, --{key} asks for {given!r}")
            learner_config: Any = None
            if args.overrides or getattr(args, "preset", None):
                learner_config = {**saved, **_preset(config.algo, args),
                                  **_parse_overrides(config.algo, args.overrides)}
        else:
            config = TrainConfig()
            for key in ("algo", "reward", "scenario", "seed"):
                if getattr(args, key) is not None:
                    setattr(config, key, getattr(args, key))
            config.run_dir = args.run_dir
            learner_config = {**_preset(config.algo, args),
                              **_parse_overrides(config.algo, args.overrides)}
        _set_run_flags(config, args, with_episodes=True)
        init_from = getattr(args, "init_from", None)
        if getattr(args, "init_other_reward", False) and init_from is None:
            raise ValueError("--init-other-reward goes with --init-from (it lets the checkpoint "
                             "that starts the run have another reward)")
        if init_from is not None:
            if args.resume:
                raise ValueError("--init-from starts a new run; --resume continues one from its "
                                 "own checkpoint: give one of them")
            if _is_curriculum(init_from):  # its last stage's checkpoint
                from learners.curriculum import last_stage_checkpoint

                init_from = last_stage_checkpoint(init_from)
            init_from = resolve_checkpoint_path(init_from)
            if not init_from.is_file():
                raise ValueError(f"--init-from: no checkpoint at {init_from}")
        with warnings.catch_warnings():  # one plain line, not a source location
            warnings.showwarning = _show_warning
            result = train(config, learner_config, resume=bool(args.resume),
                           init_from=init_from, make_shield=getattr(args, "make_shield", None),
                           init_other_reward=getattr(args, "init_other_reward", False))
        _export_best(args, result, "the best policy")
    except (ValueError, FileNotFoundError) as err:
        print(f"agv train: error: {err}", file=sys.stderr)
        return 2
    print(f"{config.algo}-{config.reward} on {config.scenario}: {result.episodes} episodes, "
          f"{result.updates} updates, {result.seconds:.0f} s; "
          f"{_score(result, config.lifelong)}; checkpoints in {result.run_dir}")
    return 130 if result.interrupted else 0


def _show_warning(message: Warning | str, *args: Any, **kwargs: Any) -> None:
    """Print a warning of ``agv train`` as one line on stderr."""
    print(f"agv train: warning: {message}", file=sys.stderr)


def _portable_copy(run_dir: str, target: str) -> int:
    """``agv train --portable-copy RUN_DIR TARGET``."""
    from learners.train import portable_copy

    try:
        folder = portable_copy(run_dir, target).parent
    except (ValueError, FileNotFoundError) as err:
        print(f"agv train: error: {err}", file=sys.stderr)
        return 2
    size = sum(f.stat().st_size for f in folder.iterdir() if f.is_file())
    print(f"copied {run_dir} without its replay buffer to {folder} ({size / 1e6:.1f} MB); "
          f"continue it with `agv train --resume {folder}`")
    return 0


def _set_run_flags(config: Any, args: argparse.Namespace, with_episodes: bool) -> None:
    """Copy the run flags given on the command line into the ``TrainConfig``."""
    keys = ("episodes",) * with_episodes + ("eval_every", "eval_episodes", "eval_seed",
                                            "checkpoint_every", "stop_response", "threads",
                                            "window", "eval_steps", "eval_runs",
                                            "fastest_min_response",
                                            "critic_warmup")
    for key in keys:
        if getattr(args, key) is not None:
            setattr(config, key, getattr(args, key))
    config.progress = not args.no_progress


def _export_best(args: argparse.Namespace, result: Any, what: str) -> None:
    """``--export``: copy the run's best policy (its latest if none was evaluated)."""
    if args.export and not result.interrupted:
        from learners.checkpoint import export_policy

        best = result.run_dir / "best.safetensors"
        exported = export_policy(best if best.is_file() else
                                 result.run_dir / "policy.safetensors", args.export)
        print(f"exported {what} to {exported}")


def _is_curriculum(run_dir: str) -> bool:
    from learners.curriculum import is_curriculum_run

    return is_curriculum_run(run_dir)


def _run_curriculum(args: argparse.Namespace) -> int:
    """``agv train --curriculum ...`` or ``--resume`` of a curriculum run."""
    from learners.curriculum import load_curriculum, parse_curriculum, train_curriculum
    from learners.train import TrainConfig

    try:
        if args.scenario is not None or args.episodes is not None:
            raise ValueError("--curriculum sets the scenario and episodes of every stage; "
                             "leave out --scenario and --episodes")
        if getattr(args, "init_from", None) is not None:
            raise ValueError("--init-from is for a single run; a curriculum starts each stage "
                             "from the previous one (put the first floor in as a stage)")
        if args.resume:
            config, stages, saved = load_curriculum(args.resume)
            for key in ("algo", "reward", "seed"):
                given = getattr(args, key)
                if given is not None and given != getattr(config, key):
                    raise ValueError(f"cannot resume {args.resume}: it was trained with {key}="
                                     f"{getattr(config, key)!r}, --{key} asks for {given!r}")
            if args.curriculum is not None:
                stages = parse_curriculum(args.curriculum)
            learner_config: Any = {**saved, **_preset(config.algo, args),
                                   **_parse_overrides(config.algo, args.overrides)}
        else:
            stages = parse_curriculum(args.curriculum)
            config = TrainConfig(algo=args.algo or "maddpg-e", reward=args.reward or "ipf",
                                 scenario=stages[0].scenario, seed=args.seed or 0,
                                 run_dir=args.run_dir or os.path.join(
                                     "runs", f"{args.algo or 'maddpg-e'}-"
                                     f"{args.reward or 'ipf'}-curriculum-s{args.seed or 0}"))
            learner_config = {**_preset(config.algo, args),
                              **_parse_overrides(config.algo, args.overrides)}
        _set_run_flags(config, args, with_episodes=False)  # each stage has its own
        result = train_curriculum(config, stages, learner_config, resume=bool(args.resume),
                                  make_shield=getattr(args, "make_shield", None))
        _export_best(args, result, "the best policy of the last stage")
    except (ValueError, FileNotFoundError) as err:
        print(f"agv train: error: {err}", file=sys.stderr)
        return 2
    print(f"{config.algo}-{config.reward} curriculum "
          f"{','.join(f'{s.scenario}:{s.episodes}' for s in stages)}: last stage "
          f"{result.episodes} episodes, {result.updates} updates in all; "
          f"{_score(result, stages[-1].lifelong)}; checkpoints in {result.run_dir.parent}")
    return 130 if result.interrupted else 0


def _score(result: Any, lifelong: bool) -> str:
    """The summary line's score: throughput on a lifelong floor, else task response."""
    ev = result.last_eval
    if lifelong:
        return (f"throughput {ev.get('throughput', float('nan')):.1f} deliveries / 1000 steps "
                f"(best {result.best_throughput:.1f})")
    return (f"task response {ev.get('response_rate', float('nan')):.3f} (best "
            f"{result.best_response_rate:.3f})")


def add_evaluate_arguments(parser: argparse.ArgumentParser,
                           registry: Sequence[str] = ()) -> None:
    """Add the ``agv evaluate`` options to ``parser``.

    Parameters
    ----------
    parser : argparse.ArgumentParser
    registry : sequence of str
        Allocator names that the caller also accepts in place of a checkpoint (named in the
        help only; :func:`run_evaluate` reads checkpoints).
    """
    import sim

    what = "a policy/training .safetensors file, its .json, or a run folder"
    if registry:
        what = (f"an allocator name ({_names(registry)}) or {what} (write ./NAME for a file "
                "named like an allocator)")
    parser.add_argument("checkpoint", metavar="CHECKPOINT" if not registry else "NAME_OR_FILE",
                        help=what)
    parser.add_argument("--scenario", type=scenario_name, default=None,
                        help=f"scenario to test on: {_names(sim.scenario_names())} or NvM "
                             "(default: the one a checkpoint was trained for, 3v3 for a name)")
    parser.add_argument("--episodes", type=positive_int, default=300,
                        help="test episodes (default 300, as in the paper)")
    parser.add_argument("--seed", type=seed, default=0,
                        help="seed of the test scenes, in [0, 2**63) (default 0)")
    parser.add_argument("--json", action="store_true", help="print the metrics as JSON")


def _finite_or_none(value: Any) -> Any:
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def print_metrics(title: str, info: dict[str, Any], metrics: Any, seed: int,
                  as_json: bool) -> None:
    """Print :class:`sim.Metrics` as the paper's table rows, or as JSON.

    Parameters
    ----------
    title : str
        What was evaluated, e.g. ``"maddpg-ipf (trained on 3v3, 5000 episodes)"``.
    info : dict
        Fields put before the metrics in the JSON output (``algo``, ``scenario``, ...).
    metrics : sim.Metrics
    seed : int
        Seed of the test scenes.
    as_json : bool
        JSON (NaN, e.g. the average time when no episode finished, is written as null).
    """
    if as_json:
        record = {**info, **metrics.as_dict()}
        print(json.dumps({k: _finite_or_none(v) for k, v in record.items()}, indent=2,
                         allow_nan=False))
        return
    print(f"{title} on {info['scenario']}, {metrics.episodes} episodes, seed {seed}:")
    print(f"  task response rate  {100 * metrics.response_rate:6.2f} %")
    print(f"  average reward      {metrics.avg_reward:8.2f}")
    print(f"  average time        {metrics.avg_time:8.2f} steps "
          f"({metrics.avg_time_finished:.2f} over finished episodes)")
    print(f"  collisions          {metrics.collisions:8.2f} per episode")
    print(f"  all tasks served    {100 * metrics.finished_rate:6.2f} % of episodes")


def run_evaluate(args: argparse.Namespace) -> int:
    """Run ``agv evaluate``: print the paper's metrics of a checkpoint (exit 2 on bad input)."""
    import sim
    from learners.policy import LearnedPolicy

    try:
        policy = LearnedPolicy.load(args.checkpoint)
        scenario = args.scenario or policy.scenario
        metrics = sim.evaluate(policy, scenario, episodes=args.episodes, seed=args.seed)
    except (ValueError, FileNotFoundError) as err:
        print(f"agv evaluate: error: {err}", file=sys.stderr)
        return 2
    title = (f"{policy.algo}-{policy.reward} (trained on {policy.scenario}, "
             f"{policy.metadata.get('episodes')} episodes)")
    print_metrics(title, {"algo": policy.algo, "reward": policy.reward, "scenario": scenario},
                  metrics, args.seed, args.json)
    return 0
