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
  aligned with its velocity) is also the heading of another moving idle AGV;
- ``claim 90%``: the mean step of the claim that leaves the last tenth of the tasks (rounded
  up) open: the 18th of 20, the 5th of 6;
- the episode's end after that claim (issue 17's look at the tail, measured on idle AGV-steps
  while some task is open): ``late idle``, their number per episode; ``late far``, the share
  whose nearest open task is more than 1.0 away; ``late by parked``, the share touching a
  parked AGV (centres within ``2 r + 0.03``); ``late uphill``, the share for which a step of 0.1
  toward the nearest open task raises the AGV's own IPF field (the paper's reward term, parked
  AGVs staying sources at -3), i.e. where that term leads toward the task.

``--plot PNG`` also draws each controller's mean fraction of tasks claimed against the step.

The test seed of the paper's tables is 0; validation (choices) uses 12345.
"""

from __future__ import annotations

import argparse
import itertools
import math
from pathlib import Path

import numpy as np
import torch
from scipy.optimize import linear_sum_assignment
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import maximum_bipartite_matching
from torch import Tensor

import sim
from sim.evaluate import evaluation_scenes, metrics_from_episodes
from sim.ipf import ipf_grid

COLUMNS = ("resp", "time", "claim 1", "claim mid", "claim last", "speed", "path/straight",
           "sum/opt", "makespan/opt", "opt-assigned", "time if opt", "time if not", "contested",
           "claim 90%", "late idle", "late far", "late by parked", "late uphill")
FRACTIONS = ("resp", "speed", "path/straight", "sum/opt", "makespan/opt", "opt-assigned",
             "contested", "late far", "late by parked", "late uphill")


MAX_EPISODES = 2000
"""At most this many episodes in one recorded batch: the trajectories and the end-game arrays
grow with it (about 1.2 GB at 20v20 and 2000 episodes)."""


def check_episodes(episodes: int) -> int:
    """``--episodes`` in [1, :data:`MAX_EPISODES`], or a ValueError naming the range."""
    if not 1 <= episodes <= MAX_EPISODES:
        raise ValueError(f"--episodes must be in [1, {MAX_EPISODES}] (one recorded batch), "
                         f"got {episodes}")
    return episodes


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
    env, tasks, out = recorded_episodes(controller, scn, episodes, seed)
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
    best_sum = np.array([_min_sum(d) for d in dist])
    best_max = np.array([_bottleneck(d) for d in dist])
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
    late = _endgame(env, pos, claimed, holder, task_pos, rel, steps, claim_step)
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
        "claim 90%": float(order[:, _ninety(M) - 1].mean()),
        **late,
        "claimed by step": _claim_curve(claimed, limit),
    }


def _claim_curve(claimed: np.ndarray, limit: int) -> np.ndarray:
    """The mean fraction of the tasks claimed after each step 0 .. limit, (limit + 1,), from the
    recorded claims (T + 1, E, M); a finished episode keeps its last state."""
    frames = claimed[np.minimum(np.arange(limit + 1), claimed.shape[0] - 1)]
    return frames.mean(axis=(1, 2))


def _ninety(m: int) -> int:
    """The claim that leaves the last tenth of ``m`` tasks (rounded up) open: 18 of 20, 5 of 6."""
    return max(m - math.ceil(0.1 * m), 1)


def _endgame(env: sim.AGVEnv, pos: np.ndarray, claimed: np.ndarray, holder: np.ndarray,
             task_pos: np.ndarray, rel: np.ndarray, steps: np.ndarray,
             claim_step: np.ndarray) -> dict[str, float]:
    """The ``late ...`` columns: idle AGV-steps after an episode's 90% claim, while it runs.

    Parameters
    ----------
    pos : (T + 1, E, N, 2) positions; claimed : (T + 1, E, M); holder : (T + 1, E, N);
    task_pos : (E, M, 2); rel : (T, E, N, M, 2) each task's position relative to each AGV
    before each step; steps : (E,); claim_step : (E, M) step of each task's claim.
    """
    T = pos.shape[0] - 1
    M = task_pos.shape[1]
    r = env.world.agent_radius
    after = np.sort(claim_step, axis=1)[:, _ninety(M) - 1]              # (E,)
    t = np.arange(T)[:, None]
    window = (t >= after[None]) & (t < steps[None])                    # (T, E)
    idle = (holder[:-1] < 0) & window[..., None] & (~claimed[:-1]).any(-1, keepdims=True)
    dist = np.where((~claimed[:-1])[:, :, None], np.linalg.norm(rel, axis=-1), np.inf)
    near = dist.argmin(-1)                                              # (T, E, N)
    d_near = np.take_along_axis(dist, near[..., None], -1)[..., 0]
    pair = np.linalg.norm(pos[:-1, :, :, None] - pos[:-1, :, None], axis=-1)
    pair = np.where((holder[:-1] >= 0)[:, :, None, :], pair, np.inf)   # to parked AGVs only
    by_parked = pair.min(-1) < 2 * r + 0.03
    # The paper's IPF field (parked AGVs stay sources at -3) at the AGV and 0.1 nearer its
    # nearest open task: "uphill" when the step toward the task raises the AGV's own field.
    grid = ipf_grid(env.world)
    step = np.take_along_axis(rel, near[..., None, None], 3)[..., 0, :]
    step = 0.1 * step / np.maximum(np.linalg.norm(step, axis=-1, keepdims=True), 1e-9)
    uphill = np.zeros_like(idle)
    for k in np.nonzero(idle.any(axis=(1, 2)))[0]:
        args = (torch.from_numpy(task_pos).double(), torch.from_numpy(claimed[k]),
                torch.from_numpy(holder[k]))
        here = grid.reward_potentials(torch.from_numpy(pos[k]).double(), *args)
        ahead = grid.reward_potentials(torch.from_numpy(pos[k] + step[k]).double(), *args)
        uphill[k] = (ahead > here + 1e-9).numpy()
    n = max(int(idle.sum()), 1)
    return {"late idle": float(idle.sum() / pos.shape[1]),
            "late far": float((idle & (d_near > 1.0)).sum() / n),
            "late by parked": float((idle & by_parked).sum() / n),
            "late uphill": float((idle & uphill).sum() / n)}


def _min_sum(dist: np.ndarray) -> float:
    """The least summed distance over the largest matchings, (N, M) -> float."""
    rows, cols = linear_sum_assignment(dist.T)
    return float(dist.T[rows, cols].sum())


def _bottleneck(dist: np.ndarray) -> float:
    """The least largest distance over the largest matchings, (N, M) -> float.

    The smallest distance ``d`` such that the AGV-task pairs within ``d`` still match
    ``min(N, M)`` pairs, found by bisection over the sorted distances (one bipartite matching
    per probe).
    """
    need = min(dist.shape)
    values = np.unique(dist)
    lo, hi = 0, len(values) - 1
    while lo < hi:
        mid = (lo + hi) // 2
        graph = csr_matrix(dist.T <= values[mid])
        matched = maximum_bipartite_matching(graph, perm_type="column")
        if int((matched >= 0).sum()) == need:
            hi = mid
        else:
            lo = mid + 1
    return float(values[lo])


def recorded_episodes(controller: object, scn: sim.Scenario, episodes: int,
                      seed: int) -> tuple[sim.AGVEnv, Tensor, dict[str, np.ndarray]]:
    """Play the evaluation scenes of :func:`sim.evaluate` (same scenes for the same seed) with
    trajectories recorded: the environment, the tasks (E, M, 2) and ``_play``'s record."""
    from sim.evaluate import _play

    agents, tasks = evaluation_scenes(scn, episodes, seed)
    env = sim.AGVEnv(scn, num_envs=episodes, reward="minidist", seed=seed)
    env.set_state(agents, tasks)
    return env, tasks, _play(env, env.observe(), controller, record=True)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", default="3v3")
    parser.add_argument("--seed", type=int, default=12345)
    parser.add_argument("--episodes", type=int, default=300)
    parser.add_argument("--policy", nargs="*", default=[], type=Path)
    parser.add_argument("--hungarian", action="store_true")
    parser.add_argument("--plot", type=Path, default=None, metavar="PNG",
                        help="also draw the fraction of tasks claimed against the step, one "
                             "line per controller, into this file")
    args = parser.parse_args(argv)
    check_episodes(args.episodes)
    if args.plot is not None and args.plot.suffix.lower() != ".png":
        raise ValueError(f"--plot must name a .png file, got {str(args.plot)!r}")
    torch.set_num_threads(1)
    names = (["hungarian"] if args.hungarian else []) + [str(p) for p in args.policy]
    print(f"{args.scenario}, seed {args.seed}, {args.episodes} episodes")
    print("| controller | " + " | ".join(COLUMNS) + " |")
    print("|---" * (len(COLUMNS) + 1) + "|")
    curves = {}
    for name in names:
        row = diagnose(_controller(name), args.scenario, args.episodes, args.seed)
        cells = [f"{row[c]:.3f}" if c in FRACTIONS else f"{row[c]:.2f}" for c in COLUMNS]
        print(f"| {name} | " + " | ".join(cells) + " |")
        curves[name] = row["claimed by step"]
    if args.plot is not None:
        plot_claims(curves, f"{args.scenario}, seed {args.seed}, {args.episodes} episodes",
                    args.plot)
        print(f"wrote {args.plot}")


def plot_claims(curves: dict[str, np.ndarray], title: str, path: Path) -> None:
    """Draw each controller's mean fraction of tasks claimed against the step into ``path``.

    Parameters
    ----------
    curves : dict of str to ndarray
        (limit + 1,) fractions by controller name (a policy file's name is shortened to its
        parent folder and stem).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    for name, curve in curves.items():
        label = name if name == "hungarian" else "/".join(Path(name).parts[-2:])
        ax.plot(np.arange(len(curve)), curve, label=label)
    ax.axhline(0.9, color="grey", lw=0.8, ls=":")
    ax.set_xlabel("step")
    ax.set_ylabel("tasks claimed (mean fraction)")
    ax.set_ylim(0, 1.02)
    ax.set_title(title)
    ax.legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)


if __name__ == "__main__":
    main()
