"""Accuracy and speed of the IPF solvers; writes ``benchmarks/results/ipf_speed.md``.

Measures, in one run and on a fixed number of threads:

1. accuracy: max abs difference between the fast exact solver and the paper's Jacobi iteration
   (run to a guaranteed 1e-9) on random scenes with and without shelves, N up to 20, both for
   whole fields (``IPFGrid.fields``) and for the reward path (``IPFGrid.agent_potentials``);
2. speed-up of the fast solver over Jacobi, per field and per reward value;
3. a full ``env.step`` with ``reward="ipf"`` against ``reward="minidist"`` at B = 1024, N = 6
   (target: ratio <= 1.5), interleaved, median of repeats, with the fused kernels of
   :mod:`sim.native` (the default) and on the torch reference path.

Run: ``python benchmarks/ipf_speed.py [--threads 1 [2]] [--quick]``.
"""

from __future__ import annotations

import argparse
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


def step_ratio(scenario: str, num_envs: int, repeats: int, use_native: bool = True) -> dict:
    """Median env.step time with ipf and with minidist, steps interleaved (both with the fused
    kernels, or both on the torch path).

    Both wall-clock and process CPU time are recorded: on a machine shared with other jobs the
    CPU time is the steadier of the two (it does not count time the process waited).
    """
    envs = {r: sim.make_env(scenario, num_envs=num_envs, reward=r, seed=0, native=use_native)
            for r in ("minidist", "ipf")}
    gen = torch.Generator().manual_seed(0)
    n = envs["ipf"].num_agents
    wall: dict[str, list[float]] = {r: [] for r in envs}
    cpu: dict[str, list[float]] = {r: [] for r in envs}
    for k in range(repeats + 3):
        actions = torch.rand(num_envs, n, 2, generator=gen) * 2 - 1
        for r, env in envs.items():
            if k % 10 == 0:
                env.reset(seed=k)
            w0, c0 = time.perf_counter(), time.process_time()
            env.step(actions)
            w1, c1 = time.perf_counter(), time.process_time()
            if k >= 3:
                wall[r].append(w1 - w0)
                cpu[r].append(c1 - c0)
    out = dict(scenario=scenario, B=num_envs, N=n,
               path="fused kernels" if use_native else "torch path")
    for kind, times in (("wall", wall), ("cpu", cpu)):
        mini, ipf = statistics.median(times["minidist"]), statistics.median(times["ipf"])
        out.update({f"minidist_{kind}_ms": 1e3 * mini, f"ipf_{kind}_ms": 1e3 * ipf,
                    f"ratio_{kind}": ipf / mini})
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, nargs="+", default=[1],
                        help="torch thread counts for the step comparison (default 1)")
    parser.add_argument("--quick", action="store_true", help="fewer scenes and repeats")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
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
