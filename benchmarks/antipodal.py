"""The antipodal circle (the ORCA paper's test) driven by the library's episodic controller.

N AGVs evenly on a circle of radius R, each sent to the task diametrically opposite it, with
the assignment given by a user's own allocator (:class:`AntipodalAllocator`, a trivial class
with ``assign``) and driven by :class:`allocator.controller.AllocatorController` through
:func:`sim.evaluate` (or, for the large circles, the env directly, recording positions).

Variants (``--variants``): R in {1.0, 1.2, 1.4, 1.6} and the tasks either exactly opposite,
just behind the opposite AGV (radius R + 0.35: every AGV crosses the centre and passes the AGV
leaving its goal), or on the paths (every other task at radius R - 0.2 instead: it lies on the
straight path of the AGV that starts behind it, which must not claim it in passing; the others
stay behind, so that tasks are at least 0.5 apart, the spawner's rule that makes every scene
servable without overlaps).

Writes ``benchmarks/results/antipodal/<label>.json`` and ``.md``. Run from the repository root::

    python benchmarks/antipodal.py --label after            # the 8 variants, 16 AGVs, and 24
    python benchmarks/antipodal.py --label large --large 1000
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
from provenance import recorded_command

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

OUT = ROOT / "benchmarks" / "results" / "antipodal"


class AntipodalAllocator:
    """A user's own allocator: each AGV takes the task nearest its antipode."""

    def __init__(self, centre: np.ndarray | None = None) -> None:
        self.centre = np.zeros(2) if centre is None else np.asarray(centre, dtype=float)

    def assign(self, agents: np.ndarray, tasks: np.ndarray, world: Any = None) -> Any:
        from scipy.optimize import linear_sum_assignment

        from allocator.base import Assignment

        a = np.asarray(agents, dtype=float) - self.centre
        t = np.asarray(tasks, dtype=float) - self.centre
        # cost: angle between the task's direction and the AGV's antipode
        ang_a = np.arctan2(-a[:, 1], -a[:, 0])
        ang_t = np.arctan2(t[:, 1], t[:, 0])
        diff = np.abs((ang_a[:, None] - ang_t[None, :] + np.pi) % (2 * np.pi) - np.pi)
        rows, cols = linear_sum_assignment(diff)
        task_of_agent = np.full(len(a), -1, dtype=np.int64)
        task_of_agent[rows] = cols
        agent_of_task = np.full(len(t), -1, dtype=np.int64)
        agent_of_task[cols] = rows
        cost = float(np.linalg.norm(a[rows] - t[cols], axis=1).sum())
        return Assignment(task_of_agent, agent_of_task, cost, method="antipodal")


def circle_scene(n: int, radius: float, kind: str) -> tuple[np.ndarray, np.ndarray]:
    """``(agents (n, 2), tasks (n, 2))``: agent i at angle 2 pi i / n, its task opposite."""
    ang = 2 * np.pi * np.arange(n) / n
    unit = np.stack([np.cos(ang), np.sin(ang)], axis=1)
    agents = radius * unit
    task_radius = np.full(n, radius + 0.35)
    if kind == "on-path":  # every other task inside the circle, on two AGVs' paths
        task_radius[::2] = radius - 0.2
    tasks = -task_radius[:, None] * unit
    return agents, tasks


def circle_scenario(n: int, radius: float, kind: str, max_steps: int) -> Any:
    import sim
    from sim.scenarios import Scenario, paper_scenario
    from sim.world import World

    agents, tasks = circle_scene(n, radius, kind)
    half = radius + 1.5  # open space around the circle, as in RVO2's example
    world = World(bounds=(-half, -half, half, half))
    base = paper_scenario(min(n, 6))
    del sim
    return Scenario.given_scene(base, agents, tasks, world=world, max_steps=max_steps,
                                name=f"antipodal-{n}-{radius}-{kind}")


def make_controller(mode: str) -> Any:
    from allocator.controller import AllocatorController

    if mode == "orca":  # the ORCA QP alone (no braking shield, no deadlock resolution)
        return AllocatorController(AntipodalAllocator(),
                                   avoidance_options={"shield": False, "liveness": False})
    return AllocatorController(AntipodalAllocator())


def run_circle(n: int, radius: float, kind: str, max_steps: int, mode: str) -> dict[str, Any]:
    """One episode, positions recorded; overlaps, steps and per-AGV arrival steps."""
    import torch

    import sim
    from sim.env import AGVEnv

    scn = circle_scenario(n, radius, kind, max_steps)
    env = AGVEnv(scn, num_envs=1, reward="minidist", seed=0)
    agents, tasks = circle_scene(n, radius, kind)
    env.set_state(torch.as_tensor(agents[None], dtype=torch.float32),
                  torch.as_tensor(tasks[None], dtype=torch.float32))
    ctl = make_controller(mode)
    ctl.reset(env)
    r2 = 2 * env.world.agent_radius
    overlaps = 0
    deepest = 0.0
    min_gap = np.inf
    arrival = np.full(n, -1)
    frames = [env.agent_pos[0].numpy().copy()]
    act_ms = []
    while not bool(env.done.all()):
        t0 = time.perf_counter()
        a = ctl.act(None)
        act_ms.append(1e3 * (time.perf_counter() - t0))
        _, _, _, info = env.step(a)
        p = env.agent_pos[0].double().numpy()
        frames.append(p.astype(np.float32))
        overlaps += int(info["collision_pairs"].sum())
        from scipy.spatial import cKDTree

        pairs = cKDTree(p).query_pairs(r2 + 0.5, output_type="ndarray")
        if len(pairs):
            d = np.linalg.norm(p[pairs[:, 0]] - p[pairs[:, 1]], axis=1)
            min_gap = min(min_gap, float(d.min()) - r2)
            deepest = max(deepest, float((r2 - d).max()))
        held = env.agent_task[0].numpy()
        arrival = np.where((arrival < 0) & (held >= 0), int(env.steps[0]), arrival)
    del sim
    ph = env.world.physics
    straight = np.linalg.norm(agents - tasks, axis=1) - env.world.capture_radius
    # straight-line time at the simulator's terminal speed
    t_line = straight / (ph.terminal_speed * ph.dt)
    served = arrival >= 0
    within = served & (arrival <= 1.6 * t_line)
    return dict(
        n=n, radius=radius, kind=kind, mode=mode, steps=int(env.steps[0]),
        served=int(served.sum()), overlapping_pair_steps=overlaps,
        deepest_penetration=max(deepest, 0.0), min_gap=float(min_gap),
        within_1_6x_straight_line=int(within.sum()),
        mean_act_ms=float(np.mean(act_ms)), median_act_ms=float(np.median(act_ms)),
        worst_act_ms=float(np.max(act_ms)), frames=np.stack(frames),
    )


SCENES = (("3v3", "hungarian", 600), ("6v6", "hungarian", 600), ("20v20", "greedy", 100),
          ("50v50", "hungarian", 40), ("warehouse", "hungarian", 200))


def plan_fits(scenario: Any, method: str, episodes: int, seed: int) -> np.ndarray:
    """Per test episode of :func:`sim.evaluate` (``episodes``, ``seed``): whether every leg of
    the allocator's first plan fits the step limit (E,).

    A leg of length L (straight, or the obstacle-aware grid path length of
    :func:`allocator.paths.travel_costs` where shelves are in the way) fits when an AGV that
    starts at rest reaches the task's capture disc within ``max_steps``: two steps to reach
    cruise speed (the terminal speed) and ``(L - capture radius) / (cruise dt)`` more.
    """
    import allocator
    from allocator.paths import travel_costs
    from sim.evaluate import evaluation_scenes

    agents, tasks = evaluation_scenes(scenario, episodes, seed)
    world = scenario.world
    step = world.physics.terminal_speed * world.physics.dt
    solver = allocator.make(method)
    fits = np.ones(episodes, dtype=bool)
    for e in range(episodes):
        a, t = agents[e].double().numpy(), tasks[e].double().numpy()
        plan = np.asarray(solver.assign(a, t, world=world).task_of_agent)
        cost = travel_costs(a, t, world)
        k = np.flatnonzero(plan >= 0)
        need = 2 + np.maximum(cost[k, plan[k]] - world.capture_radius, 0) / step
        fits[e] = bool((need <= scenario.max_steps).all())
    return fits


def run_scenes(mode: str, scale: float = 1.0, seeds: tuple[int, ...] = (0,),
               only: tuple[str, ...] | None = None, untangle: bool = True,
               ) -> list[dict[str, Any]]:
    """The paper's scenes through :func:`sim.evaluate`: overlaps, response, ms per step
    (each seed's episodes are a separate :func:`sim.evaluate` call; the rows sum them), and
    the response on the episodes whose first plan fits the step limit (:func:`plan_fits`)."""
    import allocator
    import sim

    off = {"shield": False, "liveness": False} if mode == "orca" else {}
    if not untangle:
        off["untangle"] = False
    rows = []
    for name, method, episodes in SCENES:
        if only is not None and name not in only:
            continue
        episodes = max(4, int(episodes * scale))
        scn = sim.scenarios.get_scenario(name)
        missed = collisions = fit_missed = fit_episodes = 0
        avg_time = wall = act_s = 0.0
        calls = [0]
        brakes = yields = replans = detours = 0
        for seed in seeds:
            solver = allocator.make(method, avoidance_options=dict(off))
            act = solver.act

            def counted(obs: Any, _act: Any = act, _calls: list = calls) -> Any:
                _calls[0] += 1
                return _act(obs)

            solver.act = counted
            t0 = time.perf_counter()
            m = sim.evaluate(solver, name, episodes=episodes, seed=seed)
            wall += time.perf_counter() - t0
            ctl = solver.controller
            missed += int(round((1 - m.response_rate) * episodes * scn.num_tasks))
            fits = plan_fits(scn, method, episodes, seed)
            fit_episodes += int(fits.sum())
            fit_missed += int((scn.num_tasks - m.claims_per_episode)[fits].sum())
            collisions += m.collisions * episodes
            avg_time += m.avg_time * episodes
            act_s += ctl.timing["act"]
            brakes += getattr(ctl, "shield_brakes", 0)
            yields += getattr(ctl, "yields", 0)
            replans += getattr(ctl, "replans", 0)
            detours += getattr(ctl, "detours", 0)
        total = episodes * len(seeds)
        row = dict(scene=name, method=method, mode=mode, episodes=total, seeds=list(seeds),
                   response_rate=1 - missed / (total * scn.num_tasks), missed_tasks=missed,
                   plan_fits_episodes=fit_episodes, plan_fits_missed=fit_missed,
                   response_rate_plan_fits=1 - fit_missed / max(1, fit_episodes * scn.num_tasks),
                   collisions_per_episode=collisions / total, avg_time=avg_time / total,
                   wall_s=wall, act_ms_per_step=1e3 * act_s / max(1, calls[0]),
                   shield_brakes=brakes, yields=yields, replans=replans, detours=detours)
        rows.append(row)
        print(json.dumps(row), flush=True)
    return rows


def untangle_cost(scenes: int, seed: int = 0) -> list[dict[str, Any]]:
    """What :func:`allocator.avoidance.ordering.untangle` costs per plan, beside the allocator's
    own ``assign`` timed in the same loop: 6v6 with Hungarian plans, 20v20 with greedy plans
    (the first ``scenes`` test scenes of ``seed``, the controller's parameters)."""
    import allocator
    from allocator.avoidance.ordering import untangle
    from sim.evaluate import evaluation_scenes
    from sim.scenarios import get_scenario

    rows = []
    for name, method in (("6v6", "hungarian"), ("20v20", "greedy")):
        scn = get_scenario(name)
        world = scn.world
        agents, tasks = evaluation_scenes(scn, scenes, seed)
        solver = allocator.make(method)
        t_assign, t_untangle, changed = [], [], 0
        for e in range(scenes):
            a, t = agents[e].double().numpy(), tasks[e].double().numpy()
            t0 = time.perf_counter()
            plan = np.asarray(solver.assign(a, t, world=world).task_of_agent)
            t_assign.append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            new = untangle(a, t, plan, clearance=2 * world.agent_radius + 0.03,
                           capture=world.capture_radius,
                           step=world.physics.terminal_speed * world.physics.dt,
                           radius=world.agent_radius, bounds=world.bounds, gate_weight=3.0)
            t_untangle.append(time.perf_counter() - t0)
            changed += int((new != plan).any())
        row = dict(scene=name, method=method, scenes=scenes, seed=seed,
                   assign_ms_median=1e3 * float(np.median(t_assign)),
                   untangle_ms_median=1e3 * float(np.median(t_untangle)),
                   untangle_ms_mean=1e3 * float(np.mean(t_untangle)),
                   ratio_of_medians=float(np.median(t_untangle) / np.median(t_assign)),
                   plans_changed=changed)
        rows.append(row)
        print(json.dumps(row), flush=True)
    return rows


def run_lifelong(steps: int, driver_name: str, rate: float = 1e-3,
                 repair_steps: int = 50) -> dict[str, Any]:
    """``warehouse-50`` with breakdowns under ``HungarianDispatcher`` and the given driver."""
    import sim
    from allocator.dispatch import HungarianDispatcher
    from allocator.traffic import SafeDriver

    drv = SafeDriver() if driver_name == "safe" else None
    t0 = time.time()
    m = sim.evaluate_lifelong(HungarianDispatcher(driver=drv), "warehouse-50", steps=steps,
                              seed=0, faults=sim.Breakdowns(rate=rate, repair_steps=repair_steps))
    return dict(driver="SafeDriver" if drv else "WaypointDriver", steps=steps,
                breakdown_rate=rate, repair_steps=repair_steps, throughput=m.throughput,
                throughput_bound=m.throughput_bound, collisions_per_1000=m.collisions_per_1000,
                lost=m.lost, wait_p95=m.wait_p95, wall_s=time.time() - t0,
                driver_ms_per_step=(1e3 * drv.timing["total"] / max(1, drv.steps))
                if drv else None, shield_brakes=drv.braked if drv else None)


def atomic_write(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".tmp")
    with os.fdopen(fd, "w") as f:
        f.write(text)
    os.replace(tmp, path)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--label", default="after")
    p.add_argument("--mode", default="default", choices=["default", "orca"])
    p.add_argument("--sizes", default="16,24")
    p.add_argument("--radii", default="1.0,1.2,1.4,1.6")
    p.add_argument("--kinds", default="opposite,on-path")
    p.add_argument("--max-steps", type=int, default=300)
    p.add_argument("--large", type=int, default=0, help="also a circle of this many AGVs")
    p.add_argument("--scenes", action="store_true", help="the paper's scenes instead")
    p.add_argument("--lifelong", type=int, default=0,
                   help="warehouse-50 with breakdowns for this many steps instead")
    p.add_argument("--driver", default="safe", choices=["safe", "waypoint"])
    p.add_argument("--scale", type=float, default=1.0, help="episodes factor for --scenes")
    p.add_argument("--seeds", default="0", help="--scenes: evaluation seeds, comma-separated")
    p.add_argument("--only", default="", help="--scenes: only these scenes (comma-separated)")
    p.add_argument("--untangle-cost", type=int, default=0,
                   help="time the plan untangling on this many 6v6 and 20v20 scenes instead")
    p.add_argument("--no-untangle", action="store_true",
                   help="--scenes: the controller without the plan untangling (before)")
    p.add_argument("--figure", action="store_true", help="docs/figures/safety_antipodal.png")
    args = p.parse_args(argv)
    import torch

    torch.set_num_threads(1)
    if args.untangle_cost:
        rows = untangle_cost(args.untangle_cost)
        doc = dict(command=recorded_command(__file__, argv),
                   date=time.strftime("%Y-%m-%dT%H:%M", time.gmtime()), rows=rows)
        atomic_write(OUT / "untangle-cost.json", json.dumps(doc, indent=1))
        lines = ["# What the plan untangling costs per plan", "",
                 f"Command: `{doc['command']}`; date {doc['date']}; seed 0; 1 thread.", "",
                 "| scene | allocator | scenes | assign ms (median) | untangle ms (median / "
                 "mean) | untangle / assign | plans changed |", "|---|---|---|---|---|---|---|"]
        for r in rows:
            lines.append(f"| {r['scene']} | {r['method']} | {r['scenes']} | "
                         f"{r['assign_ms_median']:.2f} | {r['untangle_ms_median']:.1f} / "
                         f"{r['untangle_ms_mean']:.1f} | {r['ratio_of_medians']:.1f} | "
                         f"{r['plans_changed']} |")
        atomic_write(OUT / "untangle-cost.md", "\n".join(lines) + "\n")
        return
    if args.lifelong:
        row = run_lifelong(args.lifelong, args.driver)
        row["command"] = recorded_command(__file__, argv)
        print(json.dumps(row), flush=True)
        atomic_write(OUT / f"lifelong-{args.driver}-{args.lifelong}.json",
                     json.dumps(row, indent=1))
        return
    if args.scenes:
        seeds = tuple(int(x) for x in args.seeds.split(","))
        only = tuple(args.only.split(",")) if args.only else None
        rows = run_scenes(args.mode, args.scale, seeds, only, untangle=not args.no_untangle)
        doc = dict(command=recorded_command(__file__, argv),
                   date=time.strftime("%Y-%m-%dT%H:%M", time.gmtime()), rows=rows)
        atomic_write(OUT / f"scenes-{args.label}.json", json.dumps(doc, indent=1))
        lines = [f"# Episodic scenes ({args.label})", "", f"Command: `{doc['command']}`; "
                 f"date {doc['date']}; seeds {args.seeds}; 1 thread.", "",
                 "| scene | method | episodes | response | missed tasks | episodes whose plan "
                 "fits the step limit | response on those | overlapping pairs "
                 "per episode | avg time | act ms/step | shield brakes | yields |",
                 "|---|---|---|---|---|---|---|---|---|---|---|---|"]
        for r in rows:
            lines.append(f"| {r['scene']} | {r['method']} | {r['episodes']} | "
                         f"{r['response_rate']:.4f} | {r['missed_tasks']} | "
                         f"{r['plan_fits_episodes']} | {r['response_rate_plan_fits']:.4f} | "
                         f"{r['collisions_per_episode']:.4f} | {r['avg_time']:.2f} | "
                         f"{r['act_ms_per_step']:.2f} | {r['shield_brakes']} | {r['yields']} |")
        atomic_write(OUT / f"scenes-{args.label}.md", "\n".join(lines) + "\n")
        return
    rows = []
    figure_runs = []
    for n in [int(s) for s in args.sizes.split(",") if s]:
        for radius in [float(s) for s in args.radii.split(",")]:
            for kind in args.kinds.split(","):
                # 24 AGVs need a larger circle to stand on it one diameter apart
                rad = radius if n <= 16 else radius * n / 16
                res = run_circle(n, rad, kind, args.max_steps, args.mode)
                frames = res.pop("frames")
                if n == 16 and kind == "opposite" and len(figure_runs) < 2:
                    figure_runs.append((res, frames))
                rows.append(res)
                print(json.dumps(res), flush=True)
    if args.large:
        n = args.large
        rad = 0.4 * n / (2 * np.pi) * 1.05  # AGVs 0.42 apart on the circle
        res = run_circle(n, rad, "opposite", max(args.max_steps, int(4 * rad / 0.15) + 100),
                         args.mode)
        res.pop("frames")
        rows.append(res)
        print(json.dumps(res), flush=True)
    doc = dict(command=recorded_command(__file__, argv),
               date=time.strftime("%Y-%m-%dT%H:%M", time.gmtime()), rows=rows)
    atomic_write(OUT / f"{args.label}.json", json.dumps(doc, indent=1))
    lines = [f"# Antipodal circle ({args.label})", "",
             f"Command: `{doc['command']}`; date {doc['date']}; 1 thread; one episode each, "
             f"step limit {args.max_steps}.", "",
             "| N | R | tasks | served | steps | overlapping pair-steps | deepest | "
             "within 1.6x line | act ms (mean / worst) |", "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['n']} | {r['radius']:.2f} | {r['kind']} | {r['served']}/{r['n']} | "
                     f"{r['steps']} | {r['overlapping_pair_steps']} | "
                     f"{r['deepest_penetration']:.3f} | {r['within_1_6x_straight_line']} | "
                     f"{r['mean_act_ms']:.2f} / {r['worst_act_ms']:.1f} |")
    atomic_write(OUT / f"{args.label}.md", "\n".join(lines) + "\n")
    if args.figure and figure_runs:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, axes = plt.subplots(1, len(figure_runs), figsize=(5 * len(figure_runs), 5))
        axes = np.atleast_1d(axes)
        for ax, (res, frames) in zip(axes, figure_runs, strict=False):
            cmap = plt.get_cmap("hsv")
            for i in range(frames.shape[1]):
                ax.plot(frames[:, i, 0], frames[:, i, 1], color=cmap(i / frames.shape[1]), lw=1)
                ax.add_patch(plt.Circle(frames[-1, i], 0.15, fill=False,
                                        color=cmap(i / frames.shape[1])))
            ax.set_aspect("equal")
            ax.set_title(f"N={res['n']} R={res['radius']} {res['kind']}: served "
                         f"{res['served']}, overlaps {res['overlapping_pair_steps']}")
        fig.tight_layout()
        path = ROOT / "docs" / "figures" / "safety_antipodal.png"
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".tmp.png")
        fig.savefig(tmp, dpi=90)
        os.replace(tmp, path)


if __name__ == "__main__":
    main()
