"""How fast can AGVs that see only their K nearest tasks and AGVs finish an episode? (issue 17)

    python benchmarks/local_information.py [--sizes 20 50] [--episodes 100 20]
        [--views 6:5 10:10 16:15 full] [--seed 0] [--detour [{squares,discs}]]
        [--out benchmarks/results/scale/local]

The learned policies read the paper's observation: the K_t = 6 nearest open tasks and the
K_a = 5 nearest AGVs. This script measures what that view allows a *coordinating* rule, with
no learning in the way: :class:`LocalAssignment` lets every idle AGV solve the optimal
assignment (scipy's ``linear_sum_assignment``, least total distance) of itself and the moving
AGVs it sees to the tasks it sees, from its own observation alone, every step, and drive at
its share. With the whole scene in view (``full``: K_t = M, K_a = N - 1) every AGV solves the
same problem, so this is a Hungarian dispatcher that re-plans every step; with less in view
the AGVs' problems differ and their choices clash. Beside it: ``hungarian`` (the classical
row of the scale table, planned once, OMPL paths and ORCA), on the same seeded episodes.

Columns: response, average time (steps until every task is claimed, the step limit where
not), that time over ``hungarian``'s, overlapping pairs per episode (no avoidance here: the
rule drives straight), plain and with :class:`allocator.shield.SafetyShield` (``--detour``:
also with the shield's detours round parked AGVs, :mod:`allocator.detour`; ``--detour discs``:
the planner that sees parked AGVs as discs with the shield's own gaps).

Writes ``local.md`` and ``local.json`` to ``--out`` with the command, seed and machine.
The assignment loop runs once per idle AGV and step in Python: a measuring tool, not a
controller for a hot path.
"""

from __future__ import annotations

import argparse
import datetime
import json
import platform
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from provenance import recorded_command
from scipy.optimize import linear_sum_assignment

import allocator
import sim
from allocator.shield import SafetyShield
from sim.io import atomic_write_text
from sim.observations import AGENT_FEATURES, TASK_FEATURES, ObsLayout
from sim.world import Physics

OUT = Path(__file__).parent / "results" / "scale" / "local"


def velocity_action(rel: np.ndarray, vel: np.ndarray, physics: Physics,
                    max_speed: float) -> np.ndarray:
    """The action that drives at ``rel`` and stops on it: velocity command ``rel / dt``
    (arrive in one step) capped at ``max_speed``, turned into the MPE acceleration and scaled
    (not clipped: the direction is kept) into [-1, 1]^2. (..., 2) arrays -> (..., 2)."""
    v = rel / physics.dt
    speed = np.linalg.norm(v, axis=-1, keepdims=True)
    v = v * np.minimum(1.0, max_speed / np.maximum(speed, 1e-12))
    a = (v - (1.0 - physics.damping) * vel) / (physics.sensitivity * physics.dt / physics.mass)
    return a / np.maximum(1.0, np.abs(a).max(axis=-1, keepdims=True))


def own_share(task_rel: np.ndarray, agent_rel: np.ndarray) -> int:
    """The task of the first AGV (at the origin) in the least-total-distance assignment of it
    and the AGVs at ``agent_rel`` (A, 2) to the tasks at ``task_rel`` (T >= 1, 2), all
    relative to it; its nearest task when it is left out (more AGVs than tasks)."""
    starts = np.concatenate([np.zeros((1, 2)), agent_rel])
    cost = np.linalg.norm(starts[:, None] - task_rel[None], axis=-1)
    rows, cols = linear_sum_assignment(cost)
    mine = cols[rows == 0]
    return int(mine[0]) if len(mine) else int(np.argmin(cost[0]))


class LocalAssignment:
    """Each idle AGV assigns itself from its own observation (see the module docstring).

    The AGVs it counts as rivals are the visible ones that move (nonzero velocity): a parked
    AGV stands exactly still and will take no other task (the rule of
    ``EntityConfig.margin_moving``). An AGV that sees no task brakes.

    Parameters
    ----------
    max_speed : float
        Cap of the velocity command (> 0; default 2.0, the terminal speed of a unit action).
    """

    name = "local-assignment"

    def __init__(self, max_speed: float = 2.0) -> None:
        if not (isinstance(max_speed, (int, float)) and np.isfinite(max_speed)
                and max_speed > 0):
            raise ValueError(f"max_speed must be a finite number > 0, got {max_speed!r}")
        self.max_speed = float(max_speed)
        self.layout: ObsLayout | None = None
        self.physics = Physics()

    def reset(self, env: Any) -> None:
        """Read the episodic observation layout and physics of ``env``."""
        if not isinstance(env.obs_layout, ObsLayout):
            raise ValueError("LocalAssignment drives episodic scenes (an ObsLayout), got "
                             f"{type(env.obs_layout).__name__}")
        self.layout, self.physics = env.obs_layout, env.world.physics

    def act(self, obs: torch.Tensor) -> torch.Tensor:
        """Actions (B, N, 2) from observations (B, N, O)."""
        lay = self.layout
        if lay is None:
            raise ValueError("LocalAssignment needs reset(env) before act")
        o = obs.detach().cpu().double().numpy()
        B, N, _ = o.shape
        tasks = o[..., lay.tasks].reshape(B, N, lay.k_tasks, len(TASK_FEATURES))
        agents = o[..., lay.agents].reshape(B, N, lay.k_agents, len(AGENT_FEATURES))
        vel = o[..., lay.vel]
        idle = o[..., lay.holding][..., 0] < 0.5
        goal = np.zeros((B, N, 2))
        has = np.zeros((B, N), dtype=bool)
        for b, i in zip(*np.nonzero(idle & (tasks[..., 2] > 0.5).any(-1)), strict=True):
            t = tasks[b, i][tasks[b, i, :, 2] > 0.5, :2]
            a = agents[b, i]
            seen = a[:, 4] > 0.5
            moving = seen & (np.abs(a[:, 2:4]) > 0).any(-1)
            # at the start every AGV stands still: then all count
            rivals = a[moving if moving.any() else seen, :2]
            goal[b, i] = t[own_share(t, rivals)]
            has[b, i] = True
        act = velocity_action(goal, vel, self.physics, self.max_speed)
        brake = velocity_action(np.zeros_like(vel), vel, self.physics, self.max_speed)
        out = np.where(has[..., None], act, brake)
        return torch.as_tensor(out, dtype=obs.dtype)


def view(n: int, spec: str) -> tuple[int, int]:
    """``"full"`` or ``"KT:KA"`` -> (k_tasks, k_agents) for an NvN scene."""
    if spec == "full":
        return n, n - 1
    try:
        kt, ka = (int(x) for x in spec.split(":"))
    except ValueError:
        raise ValueError(f"a view is 'full' or 'KT:KA' (e.g. 6:5), got {spec!r}") from None
    if kt < 1 or ka < 0:
        raise ValueError(f"a view needs K_t >= 1 and K_a >= 0, got {spec!r}")
    return min(kt, n), min(ka, n - 1)


def rows_for(n: int, episodes: int, views: list[str], seed: int,
             detour: bool | str = False) -> list[dict]:
    """The rows of one NvN scene: ``hungarian``, then the rule at every view, plain and
    shielded (``detour``: also shielded with the shield's detours round parked AGVs,
    ``"squares"`` or ``"discs"``; True: the default model, discs)."""
    name = f"{n}v{n}"
    rows: list[dict] = []
    hung = None
    runs: list[tuple[str, str, bool, bool, Any, Any]] = [
        ("hungarian", "-", False, False, allocator.make("hungarian"), sim.get_scenario(name))]
    guards = [(False, False), (True, False)] + ([(True, detour)] if detour else [])
    for spec in views:
        kt, ka = view(n, spec)
        scenario = sim.get_scenario(name, k_tasks=kt, k_agents=ka)
        for shield, det in guards:
            ctl: Any = LocalAssignment()
            if shield:
                ctl = SafetyShield(ctl, detour=det)
            runs.append((LocalAssignment.name, f"{kt}:{ka}", shield, det, ctl, scenario))
    for method, seen, shield, det, ctl, scenario in runs:
        t = time.perf_counter()
        m = sim.evaluate(ctl, scenario, episodes=episodes, seed=seed, batch_size=episodes)
        hung = m.avg_time if hung is None else hung
        row = dict(scenario=name, method=method, view=seen, shield=shield, detour=det,
                   episodes=episodes,
                   response=m.response_rate, avg_time=m.avg_time,
                   time_vs_hungarian=m.avg_time / hung, finished=m.finished_rate,
                   overlaps=m.collisions, seconds=time.perf_counter() - t)
        rows.append(row)
        print(json.dumps(row), flush=True)
    return rows


def detour_label(detour: bool | str | None) -> str:
    """The shield column's suffix for a row's ``detour``: ``""`` (none), ``" + detour"``
    (True: rows written before 2026-12-07, when True meant the squares model) or
    ``" + squares detour"`` / ``" + discs detour"`` (the model named)."""
    if not detour:
        return ""
    return " + detour" if detour is True else f" + {detour} detour"


def guard(row: dict) -> str:
    """The shield column of a row: ``no``, ``yes``, ``yes + detour`` (rows written before
    2026-12-07), ``yes + squares detour`` or ``yes + discs detour``."""
    return "yes" + detour_label(row.get("detour")) if row["shield"] else "no"


def write(rows: list[dict], out: Path, command: str, seed: int) -> None:
    out.mkdir(parents=True, exist_ok=True)
    stamp = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    head = (f"`{command}` on {platform.machine()}, Python {platform.python_version()}, torch "
            f"{torch.__version__}, {stamp}; seed {seed} (the same episodes for every row). "
            "View K_t:K_a: the task and AGV slots each AGV observes (the paper's is 6:5).")
    lines = ["# What a local view allows: a coordinating rule at K nearest tasks and AGVs",
             "", head, "",
             "| scenario | method | view K_t:K_a | shield | episodes | response | avg time "
             "| time / Hungarian | all claimed | overlapping pairs per episode | s |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['scenario']} | {r['method']} | {r['view']} | "
                     f"{guard(r)} | {r['episodes']} | "
                     f"{r['response']:.3f} | {r['avg_time']:.2f} | "
                     f"{r['time_vs_hungarian']:.2f} | {r['finished']:.2f} | "
                     f"{r['overlaps']:.2f} | {r['seconds']:.0f} |")
    atomic_write_text(out / "local.md", "\n".join(lines) + "\n")
    atomic_write_text(out / "local.json", json.dumps(
        {"command": command, "seed": seed, "rows": rows}, indent=2) + "\n")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=int, nargs="+", default=[20, 50])
    parser.add_argument("--episodes", type=int, nargs="+", default=[100, 20])
    parser.add_argument("--views", nargs="+", default=["6:5", "10:10", "16:15", "full"])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=OUT)
    parser.add_argument("--detour", nargs="?", const="squares", default=False,
                        choices=("squares", "discs"),
                        help="also run the rule shielded with detours round parked AGVs: "
                             "squares (a bare --detour, as recorded before 2026-12-07) or "
                             "discs (detour=True's model now)")
    args = parser.parse_args(argv)
    if len(args.sizes) != len(args.episodes):
        parser.error("--sizes and --episodes need one value each per size")
    if any(n < 2 for n in args.sizes) or any(e < 1 for e in args.episodes):
        parser.error("sizes must be >= 2 AGVs and episodes >= 1")
    if args.seed < 0:
        parser.error("--seed must be >= 0")
    for spec in args.views:
        try:
            view(2, spec)
        except ValueError as err:
            parser.error(str(err))
    torch.set_num_threads(1)
    rows = [r for n, e in zip(args.sizes, args.episodes, strict=True)
            for r in rows_for(n, e, args.views, args.seed,
                              args.detour)]
    command = recorded_command(__file__, argv)
    write(rows, args.out, command.strip(), args.seed)
    print(f"wrote {args.out / 'local.md'}")


if __name__ == "__main__":
    main()
