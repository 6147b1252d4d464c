"""One probe run of issue 17's search: a BiCNet-E fine-tune with the IPF reward's options.

    python benchmarks/entity_probe.py NAME --start CHECKPOINT [--scenario 20v20] \
        [--episodes 2000] [--assign-weight 0] [--drop-parked-sources] [--seed 0] \
        [--settings benchmarks/results/scale/entity/bicnet-e-margin-20.config.json]

Starts a new ``bicnet-e`` run in ``runs/entity-probes/NAME`` from the training checkpoint
``--start`` (e.g. the ``margin_moving`` fine-tune of the shipped any-N run, which was trained
with the plain ``ipf`` reward: ``train(..., init_other_reward=True)``), with the learner
settings recorded in ``--settings`` (its ``"bicnet-e"`` entry) and the reward
``IPFReward(assign_weight=..., parked_sources=...)``, evaluated on the validation seed 12345
every 500 episodes (100 episodes each). As in ``time_probe.py``, the reward runs under the
variant name ``ipf-time`` (``TrainConfig`` takes reward names), so the run's checkpoints say
``ipf-time``; ``NAME.probe.json`` beside the run records what it really was.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import sim.rewards
from learners.train import TrainConfig, train
from sim.rewards import IPFReward

ROOT = Path(__file__).resolve().parents[1]
SETTINGS = ROOT / "benchmarks/results/scale/entity/bicnet-e-margin-20.config.json"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("name")
    parser.add_argument("--start", required=True, type=Path,
                        help="a bicnet-e training checkpoint (or run folder) to start from")
    parser.add_argument("--scenario", default="20v20", help="an episodic NvM scenario")
    parser.add_argument("--episodes", type=int, default=2000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--assign-weight", type=float, default=0.0,
                        help="factor of the 'assign' term (distance to the optimal task)")
    parser.add_argument("--drop-parked-sources", action="store_true",
                        help="leave parked AGVs out of the IPF field (parked_sources=False)")
    parser.add_argument("--settings", type=Path, default=SETTINGS,
                        help="a run's config.json whose 'bicnet-e' entry holds the settings")
    args = parser.parse_args(argv)
    options = {"assign_weight": args.assign_weight,
               "parked_sources": not args.drop_parked_sources}
    IPFReward(**options)  # a bad value is refused before any run
    if not args.settings.is_file():
        raise ValueError(f"--settings {args.settings}: no such file")
    settings = json.loads(args.settings.read_text()).get("bicnet-e")
    if not isinstance(settings, dict):
        raise ValueError(f"--settings {args.settings} has no 'bicnet-e' entry of settings")
    sim.rewards.REWARD_VARIANTS["ipf-time"] = lambda: IPFReward(**options)
    run_dir = ROOT / "runs" / "entity-probes" / args.name
    config = TrainConfig(algo="bicnet-e", reward="ipf-time", scenario=args.scenario,
                         episodes=args.episodes, seed=args.seed, run_dir=str(run_dir),
                         eval_every=500, eval_episodes=100, progress=False, tensorboard=False)
    record = {"reward": "IPFReward", "options": options, "start": str(args.start),
              "settings": settings, "train": {"scenario": args.scenario,
                                              "episodes": args.episodes, "seed": args.seed}}
    run_dir.parent.mkdir(parents=True, exist_ok=True)
    (run_dir.parent / f"{run_dir.name}.probe.json").write_text(json.dumps(record, indent=1))
    result = train(config, settings, init_from=args.start, init_other_reward=True)
    print(args.name, result.last_eval)


if __name__ == "__main__":
    main()
