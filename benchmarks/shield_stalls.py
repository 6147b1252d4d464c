"""Where a shielded learned policy loses response: the AGVs still idle when episodes end.

    python benchmarks/shield_stalls.py --scenario 20v20 --episodes 50 --seed 0 \
        [--policy bicnet-ipf] [--weights any | --checkpoint FILE] [--liveness]

Plays the test episodes of :func:`sim.evaluate` (the same scenes for the same seed) with a
learned allocator behind its safety shield (``shield=True``), then describes every AGV that
is still idle (unparked) when its episode ends:

- ``speed`` and ``intended |a|``: its speed, and the size of the action the policy wants for
  the final state (before the shield);
- ``pressed``: its nearest neighbour is within ``2 r + 0.03`` (touching, for the shield);
  ``against parked``: that neighbour is parked on a task (a static obstacle for the shield);
  ``parked around``: how many parked AGVs lie within ``2 r + 0.1``;
- ``cos to task``: the cosine between the intended action and the direction to the nearest
  open task.

The same episodes unshielded give the reference response. ``--liveness`` turns on the
shield's deadlock rules (``SafetyShield(liveness=True)``, off by default on episodic
scenarios). Issue 17: the shield costs the any-N BiCNet 2.2 points of response on 20v20.
"""

from __future__ import annotations

import argparse
from typing import Any

import numpy as np
import torch
from torch import Tensor

import allocator
import sim
from sim.evaluate import evaluation_scenes
from sim.scenarios import Scenario, get_scenario

MAX_EPISODES = 10_000
"""The most episodes one diagnosis plays: they run as one batch of environments."""


def play(alloc: Any, scenario: str, episodes: int, seed: int) -> tuple[sim.AGVEnv, Tensor]:
    """Run ``alloc`` on the test scenes to the end; the env and the final intended actions."""
    agents, tasks = evaluation_scenes(scenario, episodes, seed)
    env = sim.make_env(scenario, num_envs=episodes, seed=seed)
    env.set_state(agents, tasks)
    alloc.reset(env)
    obs = env.observe()
    while not bool(env.done.all()):
        obs, *_ = env.step(alloc.act(obs))
    base = alloc.safety.controller if alloc.safety is not None else alloc
    return env, base.act(obs)


def _quantiles(x: np.ndarray) -> list[float]:
    """The 10th, 50th and 90th percentiles, rounded ([] for no values)."""
    return np.round(np.quantile(x, [0.1, 0.5, 0.9]), 3).tolist() if x.size else []


def describe(env: sim.AGVEnv, intended: Tensor) -> dict[str, Any]:
    """Figures on the AGVs idle at the end of each episode (see the module docstring)."""
    r = env.world.agent_radius
    idle = (env.agent_task < 0).numpy()
    parked = (env.agent_task >= 0).numpy()
    pos = env.agent_pos.double().numpy()
    pair = np.linalg.norm(pos[:, :, None] - pos[:, None], axis=-1)
    pair[:, np.arange(pair.shape[1]), np.arange(pair.shape[1])] = np.inf
    nearest = pair.argmin(axis=2)
    near_d = pair.min(axis=2)
    near_parked = np.take_along_axis(parked, nearest, axis=1)
    around = ((pair < 2 * r + 0.1) & parked[:, None, :]).sum(axis=2)
    task_d = torch.cdist(env.agent_pos, env.task_pos).double().numpy()
    task_d = np.where(env.task_claimed.numpy()[:, None, :], np.inf, task_d)
    target = np.take_along_axis(env.task_pos.double().numpy(),
                                task_d.argmin(axis=2)[..., None], axis=1)
    a = intended.double().numpy()
    to_task = target - pos
    cos = (a * to_task).sum(-1) / np.maximum(np.linalg.norm(a, axis=-1)
                                             * np.linalg.norm(to_task, axis=-1), 1e-12)
    pressed = near_d < 2 * r + 0.03
    speed = np.linalg.norm(env.agent_vel.double().numpy(), axis=-1)
    return {
        "response": float(env.task_claimed.float().mean()),
        "idle at the end": int(idle.sum()),
        "speed q10/50/90": _quantiles(speed[idle]),
        "intended |a| q10/50/90": _quantiles(np.linalg.norm(a, axis=-1)[idle]),
        "pressed": float(pressed[idle].mean()) if idle.any() else float("nan"),
        "against parked": float((pressed & near_parked)[idle].mean()) if idle.any()
        else float("nan"),
        "parked around (count: AGVs)": np.bincount(around[idle]).tolist() if idle.any() else [],
        "cos to task q10/50/90": _quantiles(cos[idle & np.isfinite(task_d.min(axis=2))]),
    }


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", default="20v20", help="an episodic NvM scenario")
    parser.add_argument("--episodes", type=int, default=50)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--policy", default="bicnet-ipf", help="a learned allocator's name")
    parser.add_argument("--weights", default="any", choices=["scenario", "auto", "any"])
    parser.add_argument("--checkpoint", default=None, metavar="FILE",
                        help="a policy file of the --policy's algorithm (e.g. an entity run's "
                             "best.safetensors) instead of the shipped weights")
    parser.add_argument("--liveness", action="store_true",
                        help="the shield's deadlock rules on (off by default when episodic)")
    args = parser.parse_args(argv)
    if not 1 <= args.episodes <= MAX_EPISODES:
        raise ValueError(f"--episodes must be in [1, {MAX_EPISODES}] (all of them run as one "
                         f"batch), got {args.episodes}")
    if not isinstance(get_scenario(args.scenario), Scenario):
        raise ValueError(f"scenario {args.scenario!r} is lifelong; this diagnosis is episodic")
    source = args.checkpoint or f"{args.weights} weights"
    print(f"{args.policy} ({source}) on {args.scenario}, seed {args.seed}, "
          f"{args.episodes} episodes")
    chosen = {"checkpoint": args.checkpoint} if args.checkpoint else {"weights": args.weights}
    for shield in (False, True):
        alloc = allocator.make(args.policy, scenario=args.scenario, shield=shield, **chosen)
        if shield and args.liveness:
            alloc.safety.liveness = True
        env, intended = play(alloc, args.scenario, args.episodes, args.seed)
        print(f"shield={shield}:", describe(env, intended))


if __name__ == "__main__":
    main()
