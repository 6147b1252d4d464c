"""Speed of allocator.assign against scipy's linear_sum_assignment on the same cost matrix.

    python benchmarks/assign_speed.py [--repeats 5] [--seed 0]

Open world at N = M = 10, 100, 1000 (target: assign within 1.5x of linear_sum_assignment at
1000), and the warehouse layout (obstacle-aware grid costs). Writes
benchmarks/results/assign_speed.md.
"""

from __future__ import annotations

import argparse
import datetime
import time
from pathlib import Path

import numpy as np
from provenance import recorded_command
from scipy.optimize import linear_sum_assignment
from scipy.spatial.distance import cdist

import allocator
from allocator.paths import travel_costs
from sim.io import atomic_write_text
from sim.scenarios import get_scenario


def median_time(fn, repeats: int) -> float:
    fn()  # warm up (caches, imports)
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return float(np.median(times))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    rng = np.random.default_rng(args.seed)
    rows = []
    for n in (10, 100, 1000):
        half = max(1.0, np.sqrt(n / 6.0))
        agents = rng.uniform(-half, half, (n, 2))
        tasks = rng.uniform(-half, half, (n, 2))
        cost = cdist(agents, tasks)
        t_lsa = median_time(lambda c=cost: linear_sum_assignment(c), args.repeats)
        t_all = median_time(lambda a=agents, t=tasks: allocator.assign(a, t), args.repeats)
        t_greedy = median_time(
            lambda a=agents, t=tasks: allocator.assign(a, t, method="greedy"), args.repeats
        )
        rows.append(("open", n, n, t_lsa, t_all, t_greedy))
    scn = get_scenario("warehouse")
    world = scn.world
    import torch

    for n in (6, 12):
        s = scn.with_options(num_agents=n, num_tasks=n)
        a, t = s.spawn(1, torch.Generator().manual_seed(args.seed), torch.device("cpu"))
        agents, tasks = a[0].double().numpy(), t[0].double().numpy()
        cost = travel_costs(agents, tasks, world)
        t_lsa = median_time(lambda c=cost: linear_sum_assignment(c), args.repeats)
        t_all = median_time(
            lambda a=agents, t=tasks: allocator.assign(a, t, world=world), args.repeats
        )
        t_greedy = median_time(
            lambda a=agents, t=tasks: allocator.assign(a, t, method="greedy", world=world),
            args.repeats,
        )
        rows.append(("warehouse", n, n, t_lsa, t_all, t_greedy))

    lines = [
        "# allocator.assign speed",
        "",
        f"Command: `{recorded_command(__file__)}`  ",
        f"Seed: {args.seed}, median of {args.repeats} runs, date: "
        f"{datetime.datetime.now().isoformat(timespec='minutes')}  ",
        "Hungarian = `allocator.assign(agents, tasks)` (input checks, cost matrix, solve, result);"
        " scipy = `linear_sum_assignment` alone on the same cost matrix. The warehouse rows",
        "use obstacle-aware grid costs (cached grid; Dijkstra from every task each call).",
        "",
        "| world | N | M | scipy lsa (ms) | hungarian assign (ms) | ratio | greedy assign (ms) |",
        "|---|---|---|---|---|---|---|",
    ]
    for world_name, n, m, t_lsa, t_all, t_greedy in rows:
        lines.append(
            f"| {world_name} | {n} | {m} | {t_lsa * 1e3:.3f} | {t_all * 1e3:.3f} | "
            f"{t_all / t_lsa:.2f} | {t_greedy * 1e3:.3f} |"
        )
    text = "\n".join(lines) + "\n"
    out = Path(__file__).parent / "results" / "assign_speed.md"
    atomic_write_text(out, text)
    print(text)


if __name__ == "__main__":
    main()
