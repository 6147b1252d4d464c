"""What the choice head's intent exchange costs a DAgger step (issue 17).

    python benchmarks/intent_speed.py [--size 50v50] [--batch 64] [--rounds 2] [--regret]
        [--sinkhorn R] [--repeats 5] [--out benchmarks/results/scale/entity/intent_speed]

Times one forward and backward pass of a BiCNet-E choice-head actor over ``--batch`` joint
states of ``--size`` at the whole view (what one Adam step of ``dagger_probe.py`` does per
size), with ``choice_rounds`` = 0 and = ``--rounds`` (``--regret``: with
``choice_regret``; ``--sinkhorn R``: with R rounds of the assignment exchange,
``choice_sinkhorn``), alternating, on one torch thread; the
untrained networks of the same seed. Reports the median seconds of each and their ratio.
Writes ``intent_speed.md`` and ``intent_speed.json`` (command, machine, every timing).
"""

from __future__ import annotations

import argparse
import datetime
import json
import platform
import statistics
import sys
import time
from pathlib import Path

import torch
from dagger_probe import scenario
from provenance import recorded_command

import sim
from learners.algorithms import make_learner
from learners.entity import SINKHORN_MAX_ROUNDS
from sim.io import atomic_write_text
from sim.observations import ObsLayout

OUT = Path(__file__).parent / "results" / "scale" / "entity" / "intent_speed"


def step_seconds(learner: object, obs: torch.Tensor) -> float:
    """Seconds of one forward and backward pass of the actor's action and pointer."""
    learner.actor.zero_grad()
    t0 = time.perf_counter()
    act, w = learner.policy_and_choice(obs)
    (act.sum() + torch.log(w.amax(-1).clamp_min(1e-9)).sum()).backward()
    return time.perf_counter() - t0


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", default="50v50", help="an 'NvN' scenario")
    parser.add_argument("--batch", type=int, default=64)
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--regret", action="store_true",
                        help="the exchange's messages carry regrets (choice_regret)")
    parser.add_argument("--sinkhorn", type=int, default=0,
                        help="rounds of the assignment exchange after the intent rounds "
                             "(choice_sinkhorn)")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args(argv)
    if args.batch < 1 or args.repeats < 1 or not 1 <= args.rounds <= 8 \
            or not 0 <= args.sinkhorn <= SINKHORN_MAX_ROUNDS:
        parser.error("--batch and --repeats must be >= 1, --rounds in [1, 8], --sinkhorn in "
                     f"[0, {SINKHORN_MAX_ROUNDS}]")
    try:
        scen = scenario(args.size, "full")
    except ValueError as err:
        parser.error(str(err))
    torch.set_num_threads(1)
    env = sim.make_env(scen, num_envs=args.batch, seed=0)
    obs = env.observe()
    nets = {}
    for rounds in (0, args.rounds):
        torch.manual_seed(0)
        learner = make_learner("bicnet-e", env.obs_dim, env.state_dim, env.num_agents,
                               {"choice_head": True, "choice_rounds": rounds,
                                "choice_regret": bool(rounds) and args.regret,
                                "choice_sinkhorn": args.sinkhorn if rounds else 0})
        learner.set_layout(ObsLayout(scen.k_tasks, scen.k_agents))
        step_seconds(learner, obs)  # warm-up
        nets[rounds] = learner
    times: dict[int, list[float]] = {r: [] for r in nets}
    for _ in range(args.repeats):
        for rounds, learner in nets.items():
            times[rounds].append(step_seconds(learner, obs))
    med = {r: statistics.median(t) for r, t in times.items()}
    ratio = med[args.rounds] / med[0]
    command = recorded_command(__file__, sys.argv[1:] if argv is None else argv)
    stamp = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    lines = [f"# The intent exchange's cost: {args.size}, {args.batch} joint states", "",
             f"`{command}` on {platform.machine()}, Python {platform.python_version()}, "
             f"torch {torch.__version__}, one thread, {stamp}; median of {args.repeats}.", "",
             "| choice_rounds | forward + backward, s | ratio |", "|---|---|---|",
             f"| 0 | {med[0]:.3f} | 1.00 |",
             f"| {args.rounds}{' (with regrets)' if args.regret else ''}"
             f"{f', {args.sinkhorn} assignment rounds' if args.sinkhorn else ''} | "
             f"{med[args.rounds]:.3f} | {ratio:.2f} |"]
    args.out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(args.out / "intent_speed.md", "\n".join(lines) + "\n")
    atomic_write_text(args.out / "intent_speed.json", json.dumps(
        dict(command=command, date=stamp, size=args.size, batch=args.batch,
             rounds=args.rounds, regret=args.regret, sinkhorn=args.sinkhorn,
             seconds={str(r): t for r, t in times.items()},
             median={str(r): m for r, m in med.items()}, ratio=ratio), indent=1) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
