"""The classical allocators on the paper's metrics: Hungarian (+ OMPL paths + ORCA QP) and greedy.

    python benchmarks/classical_paper_metrics.py [--episodes 300] [--seed 0]
        [--scenarios 3v3 6v6] [--warehouse-episodes 50] [--other-seeds 1 2 3 4 5]

Every method runs through ``sim.evaluate`` on the same seeded episodes. Targets for Hungarian
+ avoidance on 3v3 and 6v6: task response rate >= 99.5 % with zero collisions; its average
time is the yardstick for the learned methods. Hungarian + avoidance is also run on the same
number of episodes at the other seeds (a second table), since one seed's zero is no proof.
Writes benchmarks/results/classical_paper_metrics.md.
"""

from __future__ import annotations

import argparse
import datetime
import time
from pathlib import Path

from provenance import recorded_command

import allocator
import sim
from sim.io import atomic_write_text

METHODS = {
    "hungarian + ORCA QP": ("hungarian", {}),
    "greedy + ORCA QP": ("greedy", {}),
    "hungarian, no avoidance": ("hungarian", {"avoidance": False}),
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=300)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--scenarios", nargs="+", default=["3v3", "6v6"])
    parser.add_argument("--warehouse-episodes", type=int, default=50,
                        help="episodes of the warehouse layout (0 to skip)")
    parser.add_argument("--other-seeds", type=int, nargs="*", default=[1, 2, 3, 4, 5],
                        help="seeds at which Hungarian + avoidance is checked as well")
    args = parser.parse_args()
    runs = [(s, args.episodes) for s in args.scenarios]
    if args.warehouse_episodes:
        runs.append(("warehouse", args.warehouse_episodes))
    rows = []
    for scenario, episodes in runs:
        for label, (name, options) in METHODS.items():
            solver = allocator.make(name, **options)
            t = time.perf_counter()
            m = sim.evaluate(solver, scenario, episodes=episodes, seed=args.seed)
            seconds = time.perf_counter() - t
            ctl = solver.controller
            rows.append((scenario, label, episodes, m, seconds, ctl.fallbacks, ctl.replans))
            print(scenario, label, m.as_dict(), f"{seconds:.1f} s", flush=True)
    seed_rows = []
    for scenario in args.scenarios:
        for seed in args.other_seeds:
            solver = allocator.make("hungarian")
            m = sim.evaluate(solver, scenario, episodes=args.episodes, seed=seed)
            seed_rows.append((scenario, seed, m, solver.controller.fallbacks))
            print(scenario, "seed", seed, m.as_dict(), flush=True)
    stamp = datetime.datetime.now().isoformat(timespec="minutes")
    lines = [
        "# Classical allocators on the paper's metrics",
        "",
        f"Command: `{recorded_command(__file__)}`  ",
        f"Seed: {args.seed} (the same episodes for every method), date: {stamp}  ",
        "Response = claimed / generated tasks; time = steps until every task is claimed "
        "(unfinished episodes count the step limit: 25 for 3v3 / 6v6, 80 for the warehouse); "
        "collisions = overlapping AGV pairs summed over an episode's steps, averaged; "
        "fallbacks = AGV-steps where the ORCA QP was infeasible; re-routes = stuck AGVs "
        "given a path around parked AGVs. Warehouse paths: OMPL PRM roadmap shared by all "
        "queries.",
        "",
        "| scenario | method | episodes | response rate | avg time (steps) | "
        "avg time, finished | finished | collisions | avg reward | fallbacks | re-routes | "
        "wall time (s) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for scenario, label, episodes, m, seconds, falls, replans in rows:
        lines.append(
            f"| {scenario} | {label} | {episodes} | {m.response_rate:.2%} | {m.avg_time:.2f} | "
            f"{m.avg_time_finished:.2f} | {m.finished_rate:.1%} | {m.collisions:.3f} | "
            f"{m.avg_reward:.2f} | {falls} | {replans} | {seconds:.1f} |"
        )
    if seed_rows:
        lines += [
            "",
            f"Hungarian + ORCA QP at other seeds ({args.episodes} episodes each):",
            "",
            "| scenario | seed | response rate | avg time (steps) | finished | collisions | "
            "fallbacks |",
            "|---|---|---|---|---|---|---|",
        ]
        for scenario, seed, m, falls in seed_rows:
            lines.append(
                f"| {scenario} | {seed} | {m.response_rate:.2%} | {m.avg_time:.2f} | "
                f"{m.finished_rate:.1%} | {m.collisions:.3f} | {falls} |"
            )
    text = "\n".join(lines) + "\n"
    out = Path(__file__).parent / "results" / "classical_paper_metrics.md"
    atomic_write_text(out, text)
    print(text)


if __name__ == "__main__":
    main()
