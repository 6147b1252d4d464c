"""Where a controller's time goes against Hungarian's, on the same seeded episodes (issue 16).

    python benchmarks/time_diagnosis.py --scenario 3v3 --seed 12345 --episodes 300 \
        [--policy PATH ...] [--hungarian]

For every controller (a policy ``.safetensors`` file, or ``hungarian``) it plays the
evaluation episodes of :func:`sim.evaluate` (same scenes for the same seed) with their
trajectories recorded and prints one row of:

- ``resp``, ``time``: the paper's task response rate and average time (unfinished episodes
  count the step limit), as :func:`sim.evaluate` reports them;
- ``claim k``: the mean step at which the k-th task of an episode is claimed (sorted claim
  steps; an unclaimed task counts the step limit), so the tail of the episode shows;
- ``speed``: the mean speed of idle (unparked) AGVs over the steps before their claim, as a
  fraction of the top speed along one axis (the physics' terminal speed,
  ``sim.world.Physics.terminal_speed``; a diagonal action can reach sqrt(2) of it);
- ``path/straight``: an AGV's path length to the task it claimed over the straight-line
  distance from its start to that task (mean over claiming AGVs);
- ``sum/opt``: the episode's sum of straight-line start-to-task distances of the AGVs' final
  assignment over the minimum over all assignments (finished episodes; 1.0 = the assignment
  that Hungarian on straight-line distances makes);
- ``makespan/opt``: the same for the largest start-to-task distance of the assignment
  (the bottleneck assignment: the one that would end earliest at equal speeds);
- ``opt-assigned``: the fraction of episodes that finish with the minimum-sum assignment
  (within 1e-6), and ``time if opt`` / ``time if not``: the average time over those episodes
  and over the others (NaN if none), which splits the time lost to the assignment from the
  time lost to the driving;
- ``contested``: the fraction of moving idle AGV-steps whose heading (the open task best
  aligned with its velocity) is also the heading of another moving idle AGV.

The test seed of the paper's tables is 0; validation (choices) uses 12345.
"""

from __future__ import annotations

import argparse
import itertools
import math
from pathlib import Path

import numpy as np
import torch

import sim
from sim.evaluate import evaluation_scenes, metrics_from_episodes

COLUMNS = ("resp", "time", "claim 1", "claim mid", "claim last", "speed", "path/straight",
           "sum/opt", "makespan/opt", "opt-assigned", "time if opt", "time if not", "contested")
FRACTIONS = ("resp", "speed", "path/straight", "sum/opt", "makespan/opt", "opt-assigned",
             "contested")


def _controller(name: str):  # noqa: ANN202 - a controller of any kind
    if name == "hungarian":
        import allocator

        return allocator.make("hungarian")
    from learners.policy import load_policy

    return load_policy(name)


def diagnose(controller: object, scenario: str, episodes: int, seed: int) -> dict[str, float]:
    """Play ``episodes`` seeded evaluation episodes with trajectories and measure them.

    Returns
    -------
    dict of str to float
        The :data:`COLUMNS`, described in the module docstring.
    """
    scn = sim.get_scenario(scenario)
    agents, tasks = evaluation_scenes(scn, episodes, seed)
    env = sim.AGVEnv(scn, num_envs=episodes, reward="minidist", seed=seed)
    env.set_state(agents, tasks)
    out = run_episodes_from(env, controller)
    pos = out["agent_pos"]            # (T + 1, E, N, 2)
    claimed = out["claimed"]          # (T + 1, E, M)
    holder = out["agent_task"]        # (T + 1, E, N)
    steps = out["steps"]              # (E,)
    limit = scn.max_steps
    T1, E, N, _ = pos.shape
    task_pos = tasks.numpy()          # (E, M, 2)
    M = task_pos.shape[1]
    dt = env.world.physics.dt
    top = env.world.physics.terminal_speed

    claim_step = np.where(claimed.any(axis=0), claimed.argmax(axis=0), limit).astype(float)
    order = np.sort(claim_step, axis=1)  # (E, M)

    vel = np.diff(pos, axis=0) / dt                     # (T, E, N, 2)
    speed = np.linalg.norm(vel, axis=-1)                # (T, E, N)
    idle = holder[:-1] < 0                              # idle before the step
    t_index = np.arange(T1 - 1)[:, None, None]
    running = t_index < steps[None, :, None]
    moving_idle = idle & running
    mean_speed = float(speed[moving_idle].mean() / top)

    final = holder[-1]                                  # (E, N)
    path = (speed * dt * moving_idle).sum(axis=0)       # (E, N)
    start = pos[0]
    ratios = []
    for e, n in zip(*np.nonzero(final >= 0), strict=True):
        straight = np.linalg.norm(task_pos[e, final[e, n]] - start[e, n])
        if straight > 1e-6:
            ratios.append(path[e, n] / straight)

    dist = np.linalg.norm(start[:, :, None, :] - task_pos[:, None, :, :], axis=-1)  # (E, N, M)
    perms = np.array(list(itertools.permutations(range(N), M)))  # agent of each task
    per = dist[:, perms, np.arange(M)]                  # (E, P, M)
    best_sum, best_max = per.sum(-1).min(1), per.max(-1).min(1)
    finished = claimed[-1].all(axis=1)
    sums, maxes = [], []
    optimal = np.zeros(E, dtype=bool)
    for e in np.nonzero(finished)[0]:
        agent_of = np.full(M, -1)
        agent_of[final[e][final[e] >= 0]] = np.nonzero(final[e] >= 0)[0]
        d = dist[e, agent_of, np.arange(M)]
        sums.append(d.sum() / best_sum[e])
        optimal[e] = d.sum() <= best_sum[e] + 1e-6
        maxes.append(d.max() / best_max[e])

    shared = 0
    open_before = ~claimed[:-1]                         # (T, E, M)
    rel = task_pos[None, :, None, :, :] - pos[:-1, :, :, None, :]  # (T, E, N, M, 2)
    cos = (rel * vel[:, :, :, None, :]).sum(-1) / (
        np.linalg.norm(rel, axis=-1) * speed[..., None] + 1e-9)
    cos = np.where(open_before[:, :, None, :], cos, -np.inf)
    heading = cos.argmax(-1)                            # (T, E, N)
    movers = moving_idle & (speed > 0.2 * top)
    for a, b in itertools.combinations(range(N), 2):
        both = movers[..., a] & movers[..., b]
        same = both & (heading[..., a] == heading[..., b])
        shared += int(same.sum())
    contested = shared * 2
    metrics = metrics_from_episodes(
        out["claims"], M, steps, out["finished"], out["rewards"], out["collisions"],
        out["task_of_agent"])
    return {
        "resp": metrics.response_rate, "time": metrics.avg_time,
        "claim 1": float(order[:, 0].mean()), "claim mid": float(order[:, M // 2].mean()),
        "claim last": float(order[:, -1].mean()), "speed": mean_speed,
        "path/straight": float(np.mean(ratios)), "sum/opt": float(np.mean(sums)),
        "makespan/opt": float(np.mean(maxes)), "opt-assigned": float(optimal.mean()),
        "time if opt": float(np.mean(order[optimal, -1])) if optimal.any() else math.nan,
        "time if not": float(np.mean(order[~optimal, -1])) if (~optimal).any() else math.nan,
        "contested": contested / max(int(movers.sum()), 1),
    }


def run_episodes_from(env: sim.AGVEnv, controller: object) -> dict[str, np.ndarray]:
    """Run the episodes whose scenes ``env`` already holds, recording trajectories."""
    from sim.evaluate import _play

    return _play(env, env.observe(), controller, record=True)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", default="3v3")
    parser.add_argument("--seed", type=int, default=12345)
    parser.add_argument("--episodes", type=int, default=300)
    parser.add_argument("--policy", nargs="*", default=[], type=Path)
    parser.add_argument("--hungarian", action="store_true")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    names = (["hungarian"] if args.hungarian else []) + [str(p) for p in args.policy]
    print(f"{args.scenario}, seed {args.seed}, {args.episodes} episodes")
    print("| controller | " + " | ".join(COLUMNS) + " |")
    print("|---" * (len(COLUMNS) + 1) + "|")
    for name in names:
        row = diagnose(_controller(name), args.scenario, args.episodes, args.seed)
        cells = [f"{row[c]:.3f}" if c in FRACTIONS else f"{row[c]:.2f}" for c in COLUMNS]
        print(f"| {name} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
