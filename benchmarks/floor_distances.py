"""Floor distance tables and the decentralized auction: build cost, query speed, accuracy.

Writes ``benchmarks/results/floor_distances.md``::

    OMP_NUM_THREADS=1 python benchmarks/floor_distances.py

Measured: the build time and memory of :class:`allocator.distances.FloorDistances` on
warehouse-20/50/100 and on a generated 512 x 512-cell ``.map`` floor (at the map's own cells
and at half the AGV radius); the K agents x 300 pickups gather; path and next-waypoint times;
path lengths against the grid planner and OMPL of :mod:`allocator.paths`; and the rounds and
messages of :func:`allocator.auction.auction` for N = 10, 50, 100 on warehouse-50.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy.optimize import linear_sum_assignment

import sim
from allocator.auction import auction
from allocator.distances import FloorDistances, floor_grid_cache_clear
from allocator.paths import OMPLPlanner, grid_for, path_length

OUT = Path(__file__).parent / "results" / "floor_distances.md"


def free_points(world: sim.World, n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    pts = rng.uniform(world.bounds[:2], world.bounds[2:], (50 * n + 100, 2))
    return pts[world.is_free(pts)][:n]


def best_of(fn, *args, repeat: int = 20) -> float:  # noqa: ANN001
    times = []
    for _ in range(repeat):
        start = time.perf_counter()
        fn(*args)
        times.append(time.perf_counter() - start)
    return min(times)


def kiva_map(size: int = 512) -> str:
    """A size x size Kiva-style grid: shelf blocks 2 x 10 with 1-cell aisles and 2-cell cross
    aisles, an endpoint ``e`` at both ends of every fourth block, stations ``r`` on the left."""
    grid = np.full((size, size), ".", dtype="<U1")
    block = 0
    for top in range(4, size - 4, 3):
        for left in range(6, size - 14, 12):
            grid[top:top + 2, left:left + 10] = "@"
            if block % 4 == 0:
                grid[top, left - 1] = "e"
                grid[top, left + 10] = "e"
            block += 1
    grid[8:size - 8:32, 1] = "r"
    rows = ["".join(r) for r in grid]
    return f"type octile\nheight {size}\nwidth {size}\nmap\n" + "\n".join(rows) + "\n"


def build_rows(lines: list[str]) -> None:
    lines += ["## Build: grid, graph and the fixed points' table (one per floor)", "",
              "| floor | resolution | cells (H x W) | free | fixed points | table | build s |"
              " memory MiB | gather K=100 x 300 ms | one on-demand field ms |",
              "|---|---|---|---|---|---|---|---|---|---|"]
    floors = [(f"warehouse-{n}", sim.warehouse_floor(n), None) for n in (20, 50, 100)]
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "kiva512.map"
        path.write_text(kiva_map())
        big = sim.load_floor(path, cell_size=0.3)
    floors += [("kiva 512 x 512 map (cell 0.3)", big, 0.3),
               ("kiva 512 x 512 map (cell 0.3)", big, big.agent_radius / 2)]
    for name, world, res in floors:
        floor_grid_cache_clear()
        start = time.perf_counter()
        fd = FloorDistances(world, resolution=res)
        build = time.perf_counter() - start
        h, w = fd.shape
        agents = free_points(world, 100, 0)
        reps = int(np.ceil(300 / len(world.pickups)))
        targets = np.concatenate([world.pickups] * reps)[:300]
        if fd.fixed_in_table:
            fd.distance(agents, targets)
            gather = f"{best_of(fd.distance, agents, targets) * 1e3:.2f}"
        else:
            gather = "(on demand)"
        free = int(fd._grid.free.sum())
        cell, _ = fd._grid.snap(agents[:1])  # an AGV's cell: not a fixed point, not cached
        start = time.perf_counter()
        fd._grid.fields(cell)
        field_ms = (time.perf_counter() - start) * 1e3
        fixed = len(fd._grid.fixed_cells)
        lines.append(f"| {name} | {fd.resolution:.3g} | {h * w:,} ({h} x {w}) | {free:,} | "
                     f"{fixed} | {'yes' if fd.fixed_in_table else 'no (over 512 MiB)'} | "
                     f"{build:.2f} | {fd.nbytes / 2**20:.0f} | {gather} | {field_ms:.0f} |")
    lines.append("")


def query_rows(lines: list[str]) -> None:
    world = sim.warehouse_floor(50)
    fd = FloorDistances(world)
    agents = free_points(world, 100, 1)
    goals = world.pickups[np.random.default_rng(2).integers(len(world.pickups), size=100)]
    fd.next_waypoint(agents, goals)
    wp = best_of(fd.next_waypoint, agents, goals, repeat=3)
    path = best_of(fd.path, agents[0], goals[0], repeat=5)
    lines += ["## Queries on warehouse-50", "",
              f"- `next_waypoint`, 100 AGVs to 100 pickups (table fields): {wp * 1e3:.0f} ms",
              f"- `path`, one query: {path * 1e3:.1f} ms", ""]
    lines += ["## Path lengths against `allocator.paths` (warehouse-50, 10 queries)", "",
              "`distance` is the table value (16 neighbours; 8 in brackets), `path` the smoothed "
              "path's length, `GridMap` the string-pulled path of `allocator.paths.grid_for` "
              "(clearance radius + 0.01), OMPL RRTConnect with 0.2 s of simplification and PRM "
              "(one roadmap, 0.5 s).", "",
              "| query | distance (8) | path | GridMap | OMPL RRTConnect | OMPL PRM |"
              " path / GridMap |",
              "|---|---|---|---|---|---|---|"]
    fd8 = FloorDistances(world, connectivity=8)
    rrt = OMPLPlanner(world, time_limit=1.0, simplify_time=0.2)
    prm = OMPLPlanner(world, planner="prm", time_limit=1.0, simplify_time=0.2, roadmap_time=0.5)
    grid = grid_for(world)
    starts = free_points(world, 10, 3)
    ratios = []
    for k, (a, b) in enumerate(zip(starts, goals[:10], strict=True)):
        d = fd.distance(a[None], b[None])[0, 0]
        d8 = fd8.distance(a[None], b[None])[0, 0]
        p = path_length(fd.path(a, b))
        g = path_length(grid.path(a, b))
        o = path_length(rrt.plan(a, b))
        q = path_length(prm.plan(a, b))
        ratios.append(p / g)
        lines.append(f"| {k} | {d:.3f} ({d8:.3f}) | {p:.3f} | {g:.3f} | {o:.3f} | {q:.3f} | "
                     f"{p / g:.3f} |")
    lines += ["", f"path / GridMap: mean {np.mean(ratios):.3f}, range {min(ratios):.3f} to "
              f"{max(ratios):.3f}.", ""]


def auction_rows(lines: list[str]) -> None:
    world = sim.warehouse_floor(50)
    fd = FloorDistances(world)
    lines += ["## Decentralized auction on warehouse-50", "",
              "N AGVs at random free points, N random pickups, benefit = minus the table "
              "distance; default eps (spread / (50 (N + 1))) and epsilon scaling (factor 5); "
              "gap = optimum (scipy "
              "`linear_sum_assignment`) minus the auction's total benefit, against the bound "
              "N eps.", "",
              "| N | comm_range | components | rounds | messages | converged | gap | N eps |"
              " wall s |", "|---|---|---|---|---|---|---|---|---|"]
    for n in (10, 50, 100):
        rng = np.random.default_rng(n)
        agents = free_points(world, n, 10 + n)
        tasks = world.pickups[rng.choice(len(world.pickups), size=n, replace=False)]
        benefit = -fd.distance(agents, tasks)
        opt = benefit[linear_sum_assignment(benefit, maximize=True)].sum()
        for comm in (2.0, 4.0, np.inf):
            start = time.perf_counter()
            res = auction(benefit, agents, comm_range=comm)
            wall = time.perf_counter() - start
            rows = np.flatnonzero(res.task_of_agent >= 0)
            total = benefit[rows, res.task_of_agent[rows]].sum()
            comps = len(np.unique(res.component))
            spread = benefit.max() - benefit.min()
            eps = spread / (50 * (n + 1))
            gap = f"{opt - total:.3f}" if comps == 1 else \
                f"({len(rows)} of {n} assigned across components)"
            lines.append(f"| {n} | {comm:g} | {comps} | {res.rounds} | {res.messages:,} | "
                         f"{res.converged} | {gap} | {n * eps:.3f} | {wall:.2f} |")
    lines.append("")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args()
    lines = ["# Floor distances and the decentralized auction", "",
             "Made by `OMP_NUM_THREADS=1 python benchmarks/floor_distances.py` on the shared "
             "2-core machine (best of several runs for the short timings).", ""]
    build_rows(lines)
    query_rows(lines)
    auction_rows(lines)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
