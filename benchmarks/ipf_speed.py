"""Accuracy and speed of the IPF solvers; writes ``benchmarks/results/ipf_speed.md``.

Measures, in one run and on a fixed number of threads:

1. accuracy: max abs difference between the fast exact solver and the paper's Jacobi iteration
   (run to a guaranteed 1e-9) on random scenes with and without shelves, N up to 20, both for
   whole fields (``IPFGrid.fields``) and for the reward path (``IPFGrid.agent_potentials``);
2. speed-up of the fast solver over Jacobi, per field and per reward value;
3. a full ``env.step`` with ``reward="ipf"`` against ``reward="minidist"`` at B = 1024, N = 6
   (target: ratio <= 1.5), interleaved, median of repeats, with the fused kernels of
   :mod:`sim.native` (the default) and on the torch reference path.

With ``--large`` (writes ``benchmarks/results/ipf_speed_large.md`` instead): the separator-tree
method on large floors: the warehouse-50 lifelong step with ``reward="ipf"`` against
``reward="minidist"`` at B = 64 (the issue's target: ratio <= 3),
``IPFGrid.lifelong_potentials`` alone against a 50v50 MiniDist step, the episodic 50v50
and 100v100 IPF steps against MiniDist, and the peak memory of fresh processes
(warehouse-100 within 2 GB).

Run: ``python benchmarks/ipf_speed.py [--threads 1 [2]] [--quick]`` or
``python benchmarks/ipf_speed.py --large [--runs 3] [--quick]``.
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import statistics
import time
from pathlib import Path

import numpy as np
import torch

import sim
from sim import native
from sim.io import atomic_write_text
from sim.ipf import AGENT_VALUE, TASK_VALUE, IPFGrid, ipf_grid, jacobi_field
from sim.scenarios import warehouse_world

RESULTS = Path(__file__).parent / "results" / "ipf_speed.md"


def box_with_shelves() -> sim.World:
    """The MPE box with two shelves in the middle."""
    shelves = np.array([[-0.7, -0.15, -0.1, 0.15], [0.1, -0.55, 0.4, 0.55]])
    return sim.World(obstacles=shelves)


def random_scene(
    world: sim.World, n: int, m: int, rng: np.random.Generator, gap: float = 0.12
) -> tuple[np.ndarray, np.ndarray]:
    """``n + m`` points on the free floor (clearance 0.1), pairwise at least ``gap`` apart."""
    xmin, ymin, xmax, ymax = world.bounds
    points: list[np.ndarray] = []
    while len(points) < n + m:
        p = rng.uniform((xmin, ymin), (xmax, ymax))
        if not world.is_free(p[None], clearance=0.1)[0]:
            continue
        if all(np.linalg.norm(p - q) >= gap for q in points):
            points.append(p)
    arr = np.array(points)
    return arr[:n], arr[n:]


def sources_of(grid: IPFGrid, agents: np.ndarray, tasks: np.ndarray, agent: int):
    others = np.delete(agents, agent, axis=0)
    cells = grid.cell_of(np.concatenate([others, tasks])).numpy()
    values = np.r_[np.full(len(others), AGENT_VALUE), np.full(len(tasks), TASK_VALUE)]
    return cells, values


def accuracy(quick: bool) -> list[dict]:
    worlds = {
        "box 2x2, no shelves": sim.World(),
        "box 2x2, 2 shelves": box_with_shelves(),
        "warehouse 4.5x3.3, 4 shelves": warehouse_world(),
    }
    sizes = [1, 3, 6, 12, 20]
    rows = []
    rng = np.random.default_rng(0)
    for name, world in worlds.items():
        grid = ipf_grid(world)
        seeds = 1 if (quick or "warehouse" in name) else 2
        for n in sizes:
            if quick and n not in (6, 20):
                continue
            field_err = reward_err = kernel_err = 0.0
            jacobi_s: list[float] = []
            checked = 0
            for _ in range(seeds):
                # float32-representable points, so that the kernel (float32 positions) and the
                # torch path (float64) see the same cells
                agents, tasks = (x.astype(np.float32).astype(np.float64)
                                 for x in random_scene(world, n, n, rng))
                pot = grid.agent_potentials(
                    torch.from_numpy(agents)[None], torch.from_numpy(tasks)[None], native=False
                )[0].numpy()
                pot_kernel = None
                if native.available():
                    pot_kernel = grid.reward_potentials(
                        torch.from_numpy(agents).float()[None],
                        torch.from_numpy(tasks).float()[None], kernels=native.library(),
                    )[0].numpy()
                check = range(n) if n <= 3 else rng.choice(n, size=2 if "warehouse" in name
                                                           else 3, replace=False)
                for i in check:
                    cells, values = sources_of(grid, agents, tasks, int(i))
                    t0 = time.perf_counter()
                    ref = jacobi_field(grid, cells, values, tol=1e-9)
                    jacobi_s.append(time.perf_counter() - t0)
                    fast = grid.fields(torch.from_numpy(cells)[None],
                                       torch.from_numpy(values)[None])[0].numpy()
                    field_err = max(field_err, float(np.abs(fast - ref).max()))
                    own = int(grid.cell_of(agents[i]))
                    reward_err = max(reward_err, abs(float(pot[i]) - ref.ravel()[own]))
                    if pot_kernel is not None:
                        kernel_err = max(kernel_err,
                                         abs(float(pot_kernel[i]) - ref.ravel()[own]))
                    checked += 1
            rows.append(dict(world=name, grid=f"{grid.shape[0]}x{grid.shape[1]}",
                             free=grid.num_free, n=n, fields=checked, field_err=field_err,
                             reward_err=reward_err,
                             kernel_err=kernel_err if native.available() else float("nan"),
                             jacobi_ms=1e3 * statistics.median(jacobi_s)))
            print(rows[-1], flush=True)
    return rows


def median_time(fn, repeats: int) -> float:
    fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def solver_speed(quick: bool) -> dict:
    """Per-field and per-reward-value times of the fast solver against Jacobi (6v6 scenes)."""
    world = sim.World()
    t0 = time.perf_counter()
    grid = IPFGrid(world)
    _ = grid.green
    green_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    wgrid = IPFGrid(warehouse_world())
    _ = wgrid.green
    green_warehouse_s = time.perf_counter() - t0
    rng = np.random.default_rng(1)
    scenes = [random_scene(world, 6, 6, rng) for _ in range(64)]
    srcs = [sources_of(grid, a, t, 0) for a, t in scenes]
    jac = median_time(lambda: jacobi_field(grid, *srcs[0], tol=1e-9), 3 if quick else 7)
    cells = torch.from_numpy(np.stack([c for c, _ in srcs]))
    values = torch.from_numpy(np.stack([v for _, v in srcs]))
    fields = median_time(lambda: grid.fields(cells, values), 5 if quick else 15) / len(srcs)
    env = sim.make_env("6v6", num_envs=1024, seed=0)
    pos, tasks = env.agent_pos, env.task_pos
    open_ = ~env.task_claimed
    reward = median_time(lambda: grid.agent_potentials(pos, tasks, open_, native=False),
                         10 if quick else 30)
    kernel = (median_time(lambda: grid.agent_potentials(pos, tasks, open_, native=True),
                          10 if quick else 30) if native.available() else float("nan"))
    per_value = min(reward, kernel) / (1024 * 6)
    return dict(green_s=green_s, green_warehouse_s=green_warehouse_s,
                warehouse=f"{wgrid.shape[0]}x{wgrid.shape[1]}, F={wgrid.num_free}, "
                          f"{wgrid.num_free**2 * 8 / 2**20:.0f} MiB",
                jacobi_ms=1e3 * jac, fields_ms=1e3 * fields, reward_batch_ms=1e3 * reward,
                kernel_batch_ms=1e3 * kernel,
                reward_us=1e6 * per_value, speedup_field=jac / fields,
                speedup_reward=jac / per_value)


def step_ratio(scenario: str, num_envs: int, repeats: int, use_native: bool = True,
               reset_every: int | None = 10, warmup: int = 3) -> dict:
    """Median env.step time with ipf and with minidist, steps interleaved (both with the fused
    kernels, or both on the torch path); resets every ``reset_every`` steps (None: never, as
    a lifelong run), after ``warmup`` steps that are not timed.

    Both wall-clock and process CPU time are recorded: on a machine shared with other jobs the
    CPU time is the steadier of the two (it does not count time the process waited).
    """
    envs = {r: sim.make_env(scenario, num_envs=num_envs, reward=r, seed=0, native=use_native)
            for r in ("minidist", "ipf")}
    gen = torch.Generator().manual_seed(0)
    n = envs["ipf"].num_agents
    wall: dict[str, list[float]] = {r: [] for r in envs}
    cpu: dict[str, list[float]] = {r: [] for r in envs}
    for env in envs.values():
        env.reset(seed=0)
    for k in range(repeats + warmup):
        actions = torch.rand(num_envs, n, 2, generator=gen) * 2 - 1
        for r, env in envs.items():
            if reset_every and k and k % reset_every == 0:
                env.reset(seed=k)
            w0, c0 = time.perf_counter(), time.process_time()
            env.step(actions)
            w1, c1 = time.perf_counter(), time.process_time()
            if k >= warmup:
                wall[r].append(w1 - w0)
                cpu[r].append(c1 - c0)
    out = dict(scenario=scenario, B=num_envs, N=n,
               path="fused kernels" if use_native else "torch path")
    for kind, times in (("wall", wall), ("cpu", cpu)):
        mini, ipf = statistics.median(times["minidist"]), statistics.median(times["ipf"])
        out.update({f"minidist_{kind}_ms": 1e3 * mini, f"ipf_{kind}_ms": 1e3 * ipf,
                    f"ratio_{kind}": ipf / mini})
    return out


# ---------------------------------------------------------------------- large floors
LARGE_RESULTS = Path(__file__).parent / "results" / "ipf_speed_large.md"

_MEMORY_PROBE = """
import resource, sys, time, numpy as np, torch
torch.set_num_threads(1)
import sim
from sim.floors import warehouse_floor
from sim.ipf import ipf_grid
kind = sys.argv[1]
t0 = time.perf_counter()
if kind == "warehouse-100":
    world = warehouse_floor(100)
    grid = ipf_grid(world)
    grid.tree.build()
    build = time.perf_counter() - t0
    rng = np.random.default_rng(0)
    B, N, Q = 16, 100, 150
    xmin, ymin, xmax, ymax = world.bounds
    pts = rng.uniform((xmin, ymin), (xmax, ymax), size=(40 * B * N, 2))
    pts = pts[world.is_free(pts, clearance=world.agent_radius)][: B * N]
    agents = torch.from_numpy(pts.astype(np.float32)).view(B, N, 2)
    pk, st = np.asarray(world.pickups), np.asarray(world.stations)
    pick = torch.from_numpy(pk[np.stack([rng.permutation(len(pk))[:Q] for _ in range(B)])]
                            .astype(np.float32))
    drop = torch.from_numpy(st[rng.integers(0, len(st), (B, N))].astype(np.float32))
    loaded = torch.from_numpy(rng.random((B, N)) < 0.5)
    for _ in range(5):
        out = grid.lifelong_potentials(agents, pick, torch.ones(B, Q, dtype=torch.bool), drop,
                                       loaded)
    assert bool(torch.isfinite(out).all())
    info = f"{grid.shape[0]}x{grid.shape[1]}, F={grid.num_free}, tree {grid.tree.describe()}"
else:
    env = sim.make_env(kind, num_envs=16 if kind == "100v100" else 64, reward="ipf", seed=0)
    for _ in range(5):
        env.step(torch.rand(env.num_envs, env.num_agents, 2) * 2 - 1)
    build = time.perf_counter() - t0
    grid = ipf_grid(env.world)
    info = f"{grid.shape[0]}x{grid.shape[1]}, F={grid.num_free}, tree {grid.tree.describe()}"
peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
try:  # the peak of this process's own memory (ru_maxrss keeps the parent's across exec)
    with open("/proc/self/status") as fh:
        peak = next(int(x.split()[1]) for x in fh if x.startswith("VmHWM")) / 1024
except (OSError, StopIteration):
    pass
print(peak, build, info, sep="|")
"""


def memory_probe(kind: str) -> dict:
    """Peak RSS of a fresh process that builds the floor's tables and runs the IPF on it."""
    import subprocess
    import sys

    out = subprocess.run([sys.executable, "-c", _MEMORY_PROBE, kind], capture_output=True,
                         text=True, check=True, cwd=Path(__file__).resolve().parents[1])
    rss, build, info = out.stdout.strip().splitlines()[-1].split("|")
    return dict(kind=kind, rss_mib=float(rss), build_s=float(build), info=info)


def lifelong_scene(world: sim.World, B: int, N: int, Q: int, rng: np.random.Generator,
                   sets: int = 8) -> dict:
    """AGV positions (``sets`` draws, (B, N, 2) each) on the free floor, Q distinct open
    pickups per environment from the floor's pickups, drop-offs at its stations, half the
    AGVs loaded."""
    xmin, ymin, xmax, ymax = world.bounds
    agents = []
    for _ in range(sets):
        pts = rng.uniform((xmin, ymin), (xmax, ymax), size=(40 * B * N, 2))
        pts = pts[world.is_free(pts, clearance=world.agent_radius)][: B * N]
        agents.append(torch.from_numpy(pts.astype(np.float32)).view(B, N, 2))
    pk, st = np.asarray(world.pickups), np.asarray(world.stations)
    pick = np.stack([rng.permutation(len(pk))[:Q] for _ in range(B)])
    return dict(agents=agents,
                pickups=torch.from_numpy(pk[pick].astype(np.float32)),
                dropoffs=torch.from_numpy(st[rng.integers(0, len(st), (B, N))]
                                          .astype(np.float32)),
                loaded=torch.from_numpy(rng.random((B, N)) < 0.5))


def lifelong_ratio(repeats: int) -> dict:
    """One ``lifelong_potentials`` call on warehouse-50 (B = 64, N = 50, Q = 75 open pickups)
    against one ``make_env("50v50", num_envs=64, reward="minidist")`` step, interleaved. Each
    call sees new AGV positions, and one environment in eight changes one pickup (an order
    picked up, another released), so the pickups' cached factors are refreshed as in a run."""
    from sim.floors import warehouse_floor
    from sim.ipf import TaskBlockCache

    world = warehouse_floor(50)
    grid = ipf_grid(world)
    t0 = time.perf_counter()
    built = grid.tree._built
    grid.tree.build()
    build_s = float("nan") if built else time.perf_counter() - t0
    B, N, Q = 64, 50, 75
    rng = np.random.default_rng(0)
    scene = lifelong_scene(world, B, N, Q, rng)
    open_ = torch.ones(B, Q, dtype=torch.bool)
    cache = TaskBlockCache()
    env = sim.make_env("50v50", num_envs=B, reward="minidist", seed=0)
    gen = torch.Generator().manual_seed(0)
    times: dict[str, list[float]] = {"minidist": [], "lifelong": []}
    first = None
    for k in range(repeats + 3):
        actions = torch.rand(B, N, 2, generator=gen) * 2 - 1
        if k % 10 == 0:
            env.reset(seed=k)
        t = time.perf_counter()
        env.step(actions)
        t1 = time.perf_counter()
        flip = torch.from_numpy(rng.random(B) < 1 / 8)
        col = torch.from_numpy(rng.integers(0, Q, B))
        open_[flip, col[flip]] = ~open_[flip, col[flip]]
        t2 = time.perf_counter()
        grid.lifelong_potentials(scene["agents"][k % len(scene["agents"])], scene["pickups"],
                                 open_, scene["dropoffs"], scene["loaded"], cache=cache)
        t3 = time.perf_counter()
        if first is None:
            first = t3 - t2
        if k >= 3:
            times["minidist"].append(t1 - t)
            times["lifelong"].append(t3 - t2)
    mini, life = statistics.median(times["minidist"]), statistics.median(times["lifelong"])
    return dict(floor=f"warehouse-50 {world.size[0]:g} x {world.size[1]:g}, "
                      f"{grid.shape[0]}x{grid.shape[1]} cells, F={grid.num_free}",
                tree=grid.tree.describe(), build_s=build_s, first_call_s=first,
                minidist_ms=1e3 * mini, lifelong_ms=1e3 * life, ratio=life / mini)


def large_floors(quick: bool, runs: int) -> dict:
    """The large-floor section: ``runs`` runs of the lifelong ratio and of the episodic
    50v50 / 100v100 step ratios (medians reported), and peak memory in fresh processes."""
    reps = 10 if quick else 30
    steps = [step_ratio("warehouse-50", 64, 2 * reps, reset_every=None, warmup=20)
             for _ in range(runs)]
    for r in steps:
        print(r, flush=True)
    lifelong = [lifelong_ratio(reps) for _ in range(runs)]
    for r in lifelong:
        print(r, flush=True)
    episodic = {}
    for scenario, B in (("50v50", 64), ("100v100", 16)):
        episodic[scenario] = [step_ratio(scenario, B, reps) for _ in range(runs)]
        for r in episodic[scenario]:
            print(r, flush=True)
    memory = [memory_probe(kind) for kind in ("warehouse-100", "50v50", "100v100")]
    for m in memory:
        print(m, flush=True)
    return dict(steps=steps, lifelong=lifelong, episodic=episodic, memory=memory, runs=runs,
                quick=quick)


def large_markdown(res: dict, command: str) -> str:
    med = statistics.median
    life = res["lifelong"]
    lines = [
        "# IPF on large floors: speed and memory",
        "",
        f"Measured by `{command}` on {platform.machine()}, {os.cpu_count()} cores (shared), "
        f"torch {torch.__version__}, 1 torch thread; each row is one run, times are medians "
        "of the repeats inside it, and the two things compared run interleaved in one process.",
        "",
        "## The lifelong step: IPF against MiniDist (target ratio <= 3)",
        "",
        "`sim.make_env(\"warehouse-50\", num_envs=64, reward=...)`, the lifelong env with its "
        "default arrivals (a backlog of 1.5 N orders), random actions, no resets, 20 untimed "
        "steps first (the kept columns of G fill as pickups first appear), then the two "
        "envs stepped in turns; CPU time is the steadier measure on this shared machine.",
        "",
        "| run | MiniDist step (ms) | IPF step (ms) | ratio (wall) | MiniDist CPU (ms) | "
        "IPF CPU (ms) | ratio (CPU) |",
        "|---|---|---|---|---|---|---|",
    ]
    for k, s in enumerate(res["steps"]):
        lines.append(f"| {k + 1} | {s['minidist_wall_ms']:.2f} | {s['ipf_wall_ms']:.2f} | "
                     f"**{s['ratio_wall']:.2f}** | {s['minidist_cpu_ms']:.2f} | "
                     f"{s['ipf_cpu_ms']:.2f} | **{s['ratio_cpu']:.2f}** |")
    st = res["steps"]
    lines += [f"| median | {med(s['minidist_wall_ms'] for s in st):.2f} | "
              f"{med(s['ipf_wall_ms'] for s in st):.2f} | "
              f"**{med(s['ratio_wall'] for s in st):.2f}** | "
              f"{med(s['minidist_cpu_ms'] for s in st):.2f} | "
              f"{med(s['ipf_cpu_ms'] for s in st):.2f} | "
              f"**{med(s['ratio_cpu'] for s in st):.2f}** |", ""]
    lines += [
        "## Lifelong potentials against an episodic 50v50 MiniDist step",
        "",
        f"`IPFGrid.lifelong_potentials` on {life[0]['floor']} (tree: {life[0]['tree']}), "
        "B = 64, N = 50, Q = 75 open pickups, half the AGVs loaded, new AGV positions at every "
        "call, one environment in eight changing a pickup per call; against one step of "
        "`sim.make_env(\"50v50\", num_envs=64, reward=\"minidist\")`.",
        "",
        "| run | tree build (s, once per floor) | first call (s) | MiniDist step (ms) | "
        "lifelong_potentials (ms) | ratio |",
        "|---|---|---|---|---|---|",
    ]
    for k, r in enumerate(life):
        build = "built before" if math.isnan(r["build_s"]) else f"{r['build_s']:.1f}"
        lines.append(f"| {k + 1} | {build} | {r['first_call_s']:.2f} | "
                     f"{r['minidist_ms']:.2f} | {r['lifelong_ms']:.2f} | **{r['ratio']:.2f}** |")
    lines += [f"| median | | | {med(r['minidist_ms'] for r in life):.2f} | "
              f"{med(r['lifelong_ms'] for r in life):.2f} | "
              f"**{med(r['ratio'] for r in life):.2f}** |", ""]
    lines += [
        "## Episodic IPF step against MiniDist (default resolution 0.05, fused kernels on)",
        "",
        "| scenario | B | run | MiniDist step (ms) | IPF step (ms) | ratio (wall) | "
        "ratio (CPU) |",
        "|---|---|---|---|---|---|---|",
    ]
    for scenario, rows in res["episodic"].items():
        for k, s in enumerate(rows):
            lines.append(f"| {scenario} | {s['B']} | {k + 1} | {s['minidist_wall_ms']:.2f} | "
                         f"{s['ipf_wall_ms']:.2f} | **{s['ratio_wall']:.2f}** | "
                         f"{s['ratio_cpu']:.2f} |")
        lines.append(f"| {scenario} | | median | {med(s['minidist_wall_ms'] for s in rows):.2f} "
                     f"| {med(s['ipf_wall_ms'] for s in rows):.2f} | "
                     f"**{med(s['ratio_wall'] for s in rows):.2f}** | "
                     f"{med(s['ratio_cpu'] for s in rows):.2f} |")
    lines += [
        "",
        "## Memory (peak resident memory, VmHWM, of a fresh process; target < 2 GB)",
        "",
        "warehouse-100: the grid and its tree built, then 5 calls of `lifelong_potentials` "
        "(B = 16, N = 100, Q = 150); 50v50 (B = 64) and 100v100 (B = 16): `make_env(..., "
        "reward=\"ipf\")` and 5 steps. The time column includes the tree build.",
        "",
        "| what | grid and tree | peak RSS (MiB) | time (s) |",
        "|---|---|---|---|",
    ]
    for m in res["memory"]:
        lines.append(f"| {m['kind']} | {m['info']} | **{m['rss_mib']:.0f}** | "
                     f"{m['build_s']:.1f} |")
    lines.append("")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, nargs="+", default=[1],
                        help="torch thread counts for the step comparison (default 1)")
    parser.add_argument("--quick", action="store_true", help="fewer scenes and repeats")
    parser.add_argument("--out", type=Path, default=RESULTS)
    parser.add_argument("--large", action="store_true",
                        help="only the large-floor section (writes ipf_speed_large.md)")
    parser.add_argument("--runs", type=int, default=3,
                        help="runs of the large-floor comparisons (medians reported)")
    args = parser.parse_args()
    if args.large:
        torch.set_num_threads(1)
        res = large_floors(args.quick, args.runs)
        command = (f"python benchmarks/ipf_speed.py --large --runs {args.runs}"
                   f"{' --quick' if args.quick else ''}")
        out = LARGE_RESULTS if args.out == RESULTS else args.out
        out.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(out, large_markdown(res, command))
        print(f"wrote {out}")
        return
    steps = []
    for threads in args.threads:
        torch.set_num_threads(threads)
        for use_native in ((True, False) if native.available() else (False,)):
            for scenario, repeats in (("6v6", 100), ("warehouse", 50)):
                s = step_ratio(scenario, 1024, repeats // 3 if args.quick else repeats,
                               use_native)
                steps.append(dict(s, threads=threads))
                print(steps[-1], flush=True)
    torch.set_num_threads(1)
    speed = solver_speed(args.quick)
    print(speed, flush=True)
    acc = accuracy(args.quick)

    worst = max(max(r["field_err"], r["reward_err"], np.nan_to_num(r["kernel_err"]))
                for r in acc)
    lines = [
        "# IPF solver: accuracy and speed",
        "",
        f"Measured by `python benchmarks/ipf_speed.py --threads "
        f"{' '.join(map(str, args.threads))}{' --quick' if args.quick else ''}` on "
        f"{platform.machine()}, {os.cpu_count()} cores, torch "
        f"{torch.__version__}; times are medians of repeats, the step comparison interleaves "
        "the two environments step by step. Solver timings below use 1 thread.",
        "",
        "## Environment step, ipf against minidist (target ratio <= 1.5)",
        "",
        "Wall-clock and process CPU time per `env.step` (random actions, resets every 10 "
        "steps). CPU time is the steadier measure on a shared machine.",
        "",
        "| path | scenario | B | N | threads | minidist wall (ms) | ipf wall (ms) | ratio wall | "
        "minidist CPU (ms) | ipf CPU (ms) | ratio CPU |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for s in steps:
        lines.append(
            f"| {s['path']} | {s['scenario']} | {s['B']} | {s['N']} | {s['threads']} | "
            f"{s['minidist_wall_ms']:.2f} | {s['ipf_wall_ms']:.2f} | **{s['ratio_wall']:.2f}** | "
            f"{s['minidist_cpu_ms']:.2f} | {s['ipf_cpu_ms']:.2f} | **{s['ratio_cpu']:.2f}** |")
    lines += [
        "",
        "## Fast exact solver against the paper's Jacobi iteration",
        "",
        "6v6 scenes on the default 40x40 grid of the MPE box (F = 1444 free cells).",
        "",
        "| what | time |",
        "|---|---|",
        f"| Green's function, once per world (40x40 box) | {speed['green_s']:.2f} s |",
        f"| Green's function, once per world (warehouse {speed['warehouse']}) | "
        f"{speed['green_warehouse_s']:.2f} s |",
        f"| Jacobi to a guaranteed 1e-9, one field | {speed['jacobi_ms']:.1f} ms |",
        f"| fast, whole field, batched 64 fields, per field | {speed['fields_ms']:.3f} ms |",
        f"| fast, reward path (torch), B=1024 x N=6 values in one call | "
        f"{speed['reward_batch_ms']:.2f} ms |",
        f"| fast, reward path (C kernel, no cached task factors), the same call | "
        f"{speed['kernel_batch_ms']:.2f} ms |",
        f"| per r_IPF value, the faster of the two | {speed['reward_us']:.2f} us |",
        f"| speed-up, whole field | **{speed['speedup_field']:.0f}x** |",
        f"| speed-up, one r_IPF value (reward path vs a Jacobi field) | "
        f"**{speed['speedup_reward']:.0f}x** |",
        "",
        "## Accuracy (max abs difference to Jacobi, target 1e-5)",
        "",
        "N AGVs and N tasks at random on the free floor; for each scene the fields of some "
        "AGVs (all for N <= 3) are compared over the whole grid, and the reward path's value "
        "at each checked AGV's cell against the Jacobi field there.",
        "",
        "| world | grid | N = M | fields checked | whole field | reward path (torch) | "
        "reward path (C kernel) | Jacobi per field (ms) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in acc:
        lines.append(f"| {r['world']} | {r['grid']} | {r['n']} | {r['fields']} | "
                     f"{r['field_err']:.1e} | {r['reward_err']:.1e} | {r['kernel_err']:.1e} | "
                     f"{r['jacobi_ms']:.0f} |")
    lines += ["", f"Worst difference: **{worst:.1e}** (Jacobi's own guaranteed error is "
              "below 1e-9).", ""]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(args.out, "\n".join(lines))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
