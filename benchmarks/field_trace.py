"""The IPF field one idle AGV sees at one step of a recorded episode (issue 17's tail).

    python benchmarks/field_trace.py --policy allocator/weights/any/bicnet-ipf.safetensors \
        --scenario 20v20 --seed 0 --episodes 50 --episode 13 --agv 4 --step 22

Plays the evaluation episodes of ``sim.evaluate`` (same scenes for the same seed) with
trajectories recorded, takes the state after ``--step`` steps of episode ``--episode``, and
prints AGV ``--agv``'s own field (every other AGV a source at -3, the open tasks at +5) at its
cell, at 11 points along the straight line to each open task, and its 5 / 25 / 50 / 75 / 95%
quantiles over the floor, in three readings of the parked AGVs: sources at -3 (the paper's
field, the shipped reward), fixed at 0 like the walls, and left out (``IPFReward(
parked_sources=False)``).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))  # the scripts beside this one

import numpy as np
import torch
from time_diagnosis import _controller, check_episodes, recorded_episodes

import sim
from sim.ipf import AGENT_VALUE, TASK_VALUE, ipf_grid

READINGS = {"parked at -3 (paper)": AGENT_VALUE, "parked at 0": 0.0, "parked left out": None}
"""Each reading of the parked AGVs: the value of their sources, or None for no source."""


def trace(controller: object, scenario: str, seed: int, episodes: int, episode: int,
          agv: int, step: int) -> dict[str, dict[str, object]]:
    """The three readings' fields, as described in the module docstring.

    Returns
    -------
    dict
        By reading: ``"here"`` (float), ``"lines"`` ({task position: 11 floats}),
        ``"quantiles"`` (5 floats).

    Raises
    ------
    ValueError
        For a number of episodes outside [1, 2000], an episode, AGV or step out of range, or
        an AGV that is not idle at that step.
    """
    scn = sim.get_scenario(scenario)
    check_episodes(episodes)
    if not 0 <= episode < episodes:
        raise ValueError(f"--episode must be in [0, {episodes - 1}], got {episode}")
    if not 0 <= agv < scn.num_agents:
        raise ValueError(f"--agv must be in [0, {scn.num_agents - 1}], got {agv}")
    env, tasks, out = recorded_episodes(controller, scn, episodes, seed)
    pos, claimed, holder = out["agent_pos"], out["claimed"], out["agent_task"]
    if not 0 <= step < pos.shape[0]:
        raise ValueError(f"--step must be in [0, {pos.shape[0] - 1}], got {step}")
    if holder[step, episode, agv] >= 0:
        raise ValueError(f"AGV {agv} is parked at step {step} of episode {episode}")
    grid = ipf_grid(env.world)
    me = pos[step, episode, agv].astype(np.float64)
    others = [j for j in range(scn.num_agents) if j != agv]
    parked = holder[step, episode, others] >= 0
    open_tasks = tasks[episode].numpy()[~claimed[step, episode]].astype(np.float64)
    result = {}
    for reading, parked_value in READINGS.items():
        if parked_value is None:
            keep, agent_values = ~parked, np.full(int((~parked).sum()), AGENT_VALUE)
        else:
            keep, agent_values = np.ones_like(parked), np.where(parked, parked_value, AGENT_VALUE)
        points = np.concatenate([pos[step, episode, others][keep], open_tasks])
        values = torch.tensor(np.r_[agent_values, np.full(len(open_tasks), TASK_VALUE)],
                              dtype=torch.float64)
        cells = grid.cell_of(torch.from_numpy(points)).long()
        field = grid.fields(cells[None], values[None])[0].flatten().numpy()

        def at(p: np.ndarray, field: np.ndarray = field) -> float:
            return float(field[int(grid.cell_of(torch.from_numpy(p[None]))[0])])

        lines = {(round(float(t[0]), 2), round(float(t[1]), 2)):
                 [at(me + s * (t - me)) for s in np.linspace(0, 1, 11)] for t in open_tasks}
        result[reading] = {"here": at(me), "lines": lines,
                           "quantiles": np.quantile(field, [0.05, 0.25, 0.5, 0.75, 0.95])}
    return result


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--policy", required=True,
                        help="a policy .safetensors file, or 'hungarian'")
    parser.add_argument("--scenario", default="20v20")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--episodes", type=int, default=50)
    parser.add_argument("--episode", type=int, required=True)
    parser.add_argument("--agv", type=int, required=True)
    parser.add_argument("--step", type=int, required=True)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)

    result = trace(_controller(args.policy), args.scenario, args.seed, args.episodes,
                   args.episode, args.agv, args.step)
    for reading, r in result.items():
        print(f"{reading}: field at the AGV {r['here']:.2f}; floor quantiles "
              + " / ".join(f"{q:.2f}" for q in r["quantiles"]))
        for task, line in r["lines"].items():
            print(f"  to the task at {task}: " + ", ".join(f"{v:.2f}" for v in line))


if __name__ == "__main__":
    main()
