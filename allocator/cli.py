"""The ``agv`` command line: ``demo``, ``train``, ``evaluate``, ``bench``, ``render``."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

__all__ = ["main", "build_parser"]


def _add_demo(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("demo", help="evaluate every method on the paper's scenarios and draw it")
    p.add_argument("--quick", action="store_true", help="fewer episodes (a smoke run)")
    p.add_argument("--episodes", type=int, default=None,
                   help="test episodes per scenario (default 300, 30 with --quick)")
    p.add_argument("--out", default="agv-demo", help="folder for the figures and animations")
    p.add_argument("--seed", type=int, default=0, help="seed of the test episodes")
    p.set_defaults(func=_run_demo)


def _run_demo(args: argparse.Namespace) -> int:
    from allocator.demo import run_demo

    return run_demo(args)


def _add_train(sub: argparse._SubParsersAction) -> None:
    try:
        from learners.cli import add_train_arguments, run_train
    except ImportError:  # pragma: no cover - learners not built yet
        return
    p = sub.add_parser("train", help="train a MADDPG or BiCNet policy")
    add_train_arguments(p)
    p.set_defaults(func=run_train)


def _add_evaluate(sub: argparse._SubParsersAction) -> None:
    try:
        from learners.cli import add_evaluate_arguments, run_evaluate
    except ImportError:  # pragma: no cover
        return
    p = sub.add_parser("evaluate", help="print the paper's metrics of a checkpoint")
    add_evaluate_arguments(p)
    p.set_defaults(func=run_evaluate)


def _add_bench(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("bench", help="quick simulator throughput (full peers: benchmarks/)")
    p.add_argument("--scenario", default="6v6")
    p.add_argument("--envs", type=int, nargs="+", default=[1, 32, 1024])
    p.add_argument("--reward", default="minidist")
    p.add_argument("--threads", type=int, default=1,
                   help="torch threads (default 1: steadier, and what the benchmarks use)")
    p.set_defaults(func=_run_bench)


def _run_bench(args: argparse.Namespace) -> int:
    import torch

    from sim import native
    from sim.throughput import measure

    torch.set_num_threads(args.threads)
    kernels = "fused kernels" if native.available() else "torch path"
    print(f"{args.scenario}, reward {args.reward}, {kernels}")
    print(f"{'B':>6} {'env steps/s':>14} {'step us':>10} {'reset us':>10} {'physics us':>11}"
          f" {'overhead':>9}")
    for b in args.envs:
        m = measure(args.scenario, b, reward=args.reward, physics=True)
        print(f"{b:>6} {m.steps_per_second:>14,.0f} {1e6 * m.step_seconds:>10,.0f} "
              f"{1e6 * m.reset_seconds:>10,.0f} {1e6 * m.physics_seconds:>11,.0f} "
              f"{m.overhead:>+9.0%}")
    return 0


def _add_render(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("render", help="draw a scene, an episode (GIF) or an IPF field")
    p.add_argument("--scenario", default="3v3")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--field", action="store_true", help="draw AGV --agent's IPF heatmap")
    p.add_argument("--agent", type=int, default=0, help="whose field (with --field)")
    p.add_argument("--gif", action="store_true",
                   help="animate an episode of the scripted nearest-task controller")
    p.add_argument("--out", default=None, help="output file (PNG or GIF)")
    p.set_defaults(func=_run_render)


def _run_render(args: argparse.Namespace) -> int:
    import sim
    from sim.controllers import NearestTaskController

    env = sim.make_env(args.scenario, num_envs=1, seed=args.seed)
    if args.field:
        from sim.ipf import ipf_field, plot_field

        agents = env.agent_pos[0].numpy()
        tasks = env.task_pos[0].numpy()
        field = ipf_field(agents, tasks, agent=args.agent, world=env.world)
        out = args.out or f"ipf_{args.scenario}_agent{args.agent}.png"
        plot_field(field, agents, tasks, agent=args.agent, path=out)
    elif args.gif:
        out = args.out or f"episode_{args.scenario}.gif"
        sim.render_episode(NearestTaskController(env.world.physics), args.scenario,
                           seed=args.seed, path=out)
    else:
        out = args.out or f"scene_{args.scenario}.png"
        sim.render_scene(env, path=out)
    print(f"wrote {out}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    """The ``agv`` argument parser with every available subcommand."""
    parser = argparse.ArgumentParser(
        prog="agv", description="Multi-AGV task allocation: simulator, learners and solvers."
    )
    sub = parser.add_subparsers(dest="command", required=True)
    for add in (_add_demo, _add_train, _add_evaluate, _add_bench, _add_render):
        add(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``agv`` console script."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except ValueError as err:
        print(f"agv {args.command}: error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
