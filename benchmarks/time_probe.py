"""One probe run of issue 16's search: BiCNet with the IPF reward's time options.

    python benchmarks/time_probe.py NAME --time-cost 3 --goal-weight 3 --gamma 0.9 \
        [--assign-weight 0] [--drop-parked-sources] [--episodes 30000] [--seed 0] \
        [--scenario 3v3] [--eval-every 1000]

Trains ``bicnet`` with the fast preset's settings chosen for ``bicnet-ipf`` in
``benchmarks/results/training/reward_search.json`` (``--gamma`` replaces its 0.95) and the
reward ``IPFReward(time_cost=..., goal_weight=..., assign_weight=..., parked_sources=...)``
(the plain ``ipf`` reward when all four are at their defaults 0, 1, 0 and True) into
``runs/probes/NAME`` (continuing a run that is there, up to ``--episodes``), evaluating on
the validation seed 12345 every ``--eval-every`` episodes (``progress.csv``). The chosen
values are the defaults of the ``ipf-time`` variant, which ``agv train --reward ipf-time``
and ``benchmarks/train_policies.py`` use.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import sim.rewards
from learners.train import TrainConfig, train
from sim.rewards import IPFReward

ROOT = Path(__file__).resolve().parents[1]


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("name")
    parser.add_argument("--time-cost", type=float, default=0.0)
    parser.add_argument("--goal-weight", type=float, default=1.0)
    parser.add_argument("--assign-weight", type=float, default=0.0,
                        help="factor of the 'assign' term (distance to the optimal task)")
    parser.add_argument("--drop-parked-sources", action="store_true",
                        help="leave parked AGVs out of the IPF field (parked_sources=False)")
    parser.add_argument("--gamma", type=float, default=0.95)
    parser.add_argument("--episodes", type=int, default=30000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--scenario", default="3v3", help="an episodic NvM scenario")
    parser.add_argument("--eval-every", type=int, default=1000)
    args = parser.parse_args(argv)
    record = json.loads((ROOT / "benchmarks/results/training/reward_search.json").read_text())
    settings = dict(record["methods"]["bicnet-ipf"]["settings"], gamma=args.gamma)

    def probe_reward() -> IPFReward:
        return IPFReward(time_cost=args.time_cost, goal_weight=args.goal_weight,
                         assign_weight=args.assign_weight,
                         parked_sources=not args.drop_parked_sources)

    probe_reward()  # a bad value is refused before any run
    reward = "ipf"
    if (args.time_cost, args.goal_weight, args.assign_weight, args.drop_parked_sources) != (
            0.0, 1.0, 0.0, False):
        # the variant's name, made with this probe's values (TrainConfig takes reward names)
        sim.rewards.REWARD_VARIANTS["ipf-time"] = probe_reward
        reward = "ipf-time"
    run_dir = ROOT / "runs" / "probes" / args.name
    config = TrainConfig(algo="bicnet", reward=reward, scenario=args.scenario,
                         episodes=args.episodes, seed=args.seed, run_dir=str(run_dir),
                         eval_every=args.eval_every,
                         progress=False, tensorboard=False)
    result = train(config, settings, resume=(run_dir / "checkpoint.safetensors").is_file())
    print(args.name, result.last_eval)


if __name__ == "__main__":
    main()
