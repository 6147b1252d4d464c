"""``agv train`` and ``agv evaluate``: the argument parsers and their entry points.

``allocator/cli.py`` wires these into the ``agv`` console script; they can also be used alone::

    parser = argparse.ArgumentParser(); add_train_arguments(parser)
    raise SystemExit(run_train(parser.parse_args()))
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from typing import Any

__all__ = ["add_train_arguments", "run_train", "add_evaluate_arguments", "run_evaluate"]

_ALGOS = ("maddpg", "bicnet")
_REWARDS = ("minidist", "greedy", "ipf")


def add_train_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the ``agv train`` options to ``parser``."""
    parser.add_argument("--algo", choices=_ALGOS, default=None,
                        help="learning algorithm (default maddpg)")
    parser.add_argument("--reward", choices=_REWARDS, default=None,
                        help="reward: minidist, greedy or ipf (default ipf)")
    parser.add_argument("--scenario", default=None, help="scenario, e.g. 3v3, 6v6 (default 3v3)")
    parser.add_argument("--episodes", type=int, default=None,
                        help="training episodes (default 5000; with --resume: the new total)")
    parser.add_argument("--seed", type=int, default=None, help="random seed (default 0)")
    parser.add_argument("--run-dir", default=None,
                        help="folder for progress.csv and checkpoints "
                             "(default runs/<algo>-<reward>-<scenario>-s<seed>)")
    parser.add_argument("--resume", metavar="RUN_DIR", default=None,
                        help="continue the run in RUN_DIR from its last checkpoint")
    parser.add_argument("--eval-every", type=int, default=None,
                        help="evaluate every this many episodes (default 500)")
    parser.add_argument("--eval-episodes", type=int, default=None,
                        help="test episodes per evaluation (default 300)")
    parser.add_argument("--checkpoint-every", type=int, default=None,
                        help="write a resumable checkpoint every this many episodes "
                             "(default 1000)")
    parser.add_argument("--stop-response", type=float, default=None,
                        help="stop once an evaluation reaches this task response rate")
    parser.add_argument("--threads", type=int, default=None, help="torch threads (default 1)")
    parser.add_argument("--set", dest="overrides", action="append", default=[],
                        metavar="KEY=VALUE",
                        help="override a learner hyperparameter, e.g. --set batch_size=512 "
                             "(see MADDPGConfig / BiCNetConfig); repeatable")
    parser.add_argument("--export", metavar="PATH", default=None,
                        help="after training, copy the best evaluated policy to PATH (e.g. "
                             "allocator/weights/3v3/bicnet-ipf.safetensors)")
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


def run_train(args: argparse.Namespace) -> int:
    """Run ``agv train``; returns the exit status (0 done, 130 interrupted, 2 bad input)."""
    from learners.train import TrainConfig, load_run_config, train

    try:
        if args.resume:
            config, saved = load_run_config(args.resume)
            for key in ("algo", "reward", "scenario", "seed"):
                given = getattr(args, key)
                if given is not None and given != getattr(config, key):
                    raise ValueError(f"cannot resume {args.resume}: it was trained with {key}="
                                     f"{getattr(config, key)!r}, --{key} asks for {given!r}")
            learner_config: Any = None
            if args.overrides:
                learner_config = {**saved, **_parse_overrides(config.algo, args.overrides)}
        else:
            config = TrainConfig()
            for key in ("algo", "reward", "scenario", "seed"):
                if getattr(args, key) is not None:
                    setattr(config, key, getattr(args, key))
            config.run_dir = args.run_dir
            learner_config = _parse_overrides(config.algo, args.overrides)
        for key in ("episodes", "eval_every", "eval_episodes", "checkpoint_every",
                    "stop_response", "threads"):
            if getattr(args, key) is not None:
                setattr(config, key, getattr(args, key))
        config.progress = not args.no_progress
        result = train(config, learner_config, resume=bool(args.resume))
        if args.export and not result.interrupted:
            from learners.checkpoint import export_policy

            best = result.run_dir / "best.safetensors"
            exported = export_policy(best if best.is_file() else
                                     result.run_dir / "policy.safetensors", args.export)
            print(f"exported the best policy to {exported}")
    except (ValueError, FileNotFoundError) as err:
        print(f"agv train: error: {err}", file=sys.stderr)
        return 2
    ev = result.last_eval
    print(f"{config.algo}-{config.reward} on {config.scenario}: {result.episodes} episodes, "
          f"{result.updates} updates, {result.seconds:.0f} s; task response "
          f"{ev.get('response_rate', float('nan')):.3f} (best "
          f"{result.best_response_rate:.3f}); checkpoints in {result.run_dir}")
    return 130 if result.interrupted else 0


def add_evaluate_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the ``agv evaluate`` options to ``parser``."""
    parser.add_argument("checkpoint",
                        help="a policy/training .safetensors file, its .json, or a run folder")
    parser.add_argument("--scenario", default=None,
                        help="scenario to test on (default: the one it was trained for)")
    parser.add_argument("--episodes", type=int, default=300,
                        help="test episodes (default 300, as in the paper)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the test scenes")
    parser.add_argument("--json", action="store_true", help="print the metrics as JSON")


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
    if args.json:
        print(json.dumps({"algo": policy.algo, "reward": policy.reward, "scenario": scenario,
                          **metrics.as_dict()}, indent=2))
        return 0
    print(f"{policy.algo}-{policy.reward} (trained on {policy.scenario}, "
          f"{policy.metadata.get('episodes')} episodes) on {scenario}, {metrics.episodes} "
          f"episodes, seed {args.seed}:")
    print(f"  task response rate  {100 * metrics.response_rate:6.2f} %")
    print(f"  average reward      {metrics.avg_reward:8.2f}")
    print(f"  average time        {metrics.avg_time:8.2f} steps "
          f"({metrics.avg_time_finished:.2f} over finished episodes)")
    print(f"  collisions          {metrics.collisions:8.2f} per episode")
    print(f"  all tasks served    {100 * metrics.finished_rate:6.2f} % of episodes")
    return 0
