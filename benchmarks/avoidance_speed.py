"""Speed of the ORCA avoidance QP for all AGVs in one step, against a loop of per-AGV problems.

    python benchmarks/avoidance_speed.py [--agents 100] [--steps 20] [--seed 0]

An ``NvN`` episode (default 100 AGVs, 100 tasks, world sized as ``sim.scenarios``) is driven by
the Hungarian controller; at every step the same constraint rows are solved (a) as one
block-diagonal OSQP problem with warm start (what the controller does), and (b) as a loop of
N separate OSQP problems, each set up once and updated with warm start. Target: (a) at most
3 ms per step at N = 100. Writes benchmarks/results/avoidance_speed.md.
"""

from __future__ import annotations

import argparse
import datetime
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import osqp
import scipy.sparse as sp

import allocator
import allocator.avoidance as avoidance
import sim


class LoopOfSolvers:
    """One OSQP problem per AGV (set up once, then updated and warm started)."""

    def __init__(self) -> None:
        self.solvers: list = []

    def solve(self, rows: avoidance.ConstraintRows) -> np.ndarray:
        n, R, _ = rows.A.shape
        if len(self.solvers) != n:
            self.solvers = []
            for _ in range(n):
                s = osqp.OSQP()
                A = sp.csc_matrix((np.ones(2 * R), np.tile(np.arange(R), 2), [0, R, 2 * R]),
                                  shape=(R, 2))
                s.setup(sp.identity(2, format="csc"), np.zeros(2), A, np.full(R, -np.inf),
                        np.full(R, np.inf), verbose=False, polishing=False, eps_abs=1e-6,
                        eps_rel=1e-6, max_iter=2000, eps_prim_inf=1e-3)
                self.solvers.append(s)
        out = np.zeros((n, 2))
        for i, s in enumerate(self.solvers):
            s.update(q=-rows.preferred[i], l=rows.lower[i], u=rows.upper[i],
                     Ax=rows.A[i].T.reshape(-1))
            res = s.solve(raise_error=False)
            if res.info.status.startswith("solved"):
                out[i] = res.x
        return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--agents", type=int, default=100)
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--chunk", type=int, default=None, help="AGVs per OSQP problem")
    args = parser.parse_args()
    n = args.agents
    scenario = f"{n}v{n}"
    env = sim.make_env(scenario, num_envs=1, seed=args.seed)
    obs = env.reset()
    solver = allocator.make("hungarian")
    solver.reset(env)
    qp = solver.controller._avoidance()
    captured: list[avoidance.ConstraintRows] = []
    build_times: list[float] = []
    original = qp.constraints

    def capture(*a, **k):
        t = time.perf_counter()
        rows = original(*a, **k)
        build_times.append(time.perf_counter() - t)
        captured.append(rows)
        return rows

    qp.constraints = capture
    for _ in range(args.steps):
        obs, _, done, _ = env.step(solver.act(obs))
        if bool(done.all()):
            break
    qp.constraints = original

    config = qp.config if args.chunk is None else replace(qp.config, chunk_size=args.chunk)
    batched = avoidance.VelocityAvoidance(env.world, config)
    loop = LoopOfSolvers()
    t_batch, t_loop, diffs, falls = [], [], [], 0
    for rows in captured:  # consecutive steps, so both warm start as in the controller
        t = time.perf_counter()
        v_batch, fell, _, _ = batched.solve_rows(rows)
        t_batch.append(time.perf_counter() - t)
        t = time.perf_counter()
        v_loop = loop.solve(rows)
        t_loop.append(time.perf_counter() - t)
        falls += int(fell.sum())
        ok = ~fell & rows.active
        if ok.any():
            diffs.append(np.abs(v_batch[ok] - v_loop[ok]).max())
    t_batch_ms = np.array(t_batch[1:]) * 1e3  # the first includes OSQP setup
    t_loop_ms = np.array(t_loop[1:]) * 1e3
    build_ms = np.array(build_times[1:]) * 1e3
    total = t_batch_ms + build_ms
    stamp = datetime.datetime.now().isoformat(timespec="minutes")
    lines = [
        "# Avoidance QP speed (all AGVs, one step)",
        "",
        f"Command: `python {' '.join(sys.argv)}`  ",
        f"Seed: {args.seed}, scenario {scenario}, {len(captured) - 1} timed steps of one "
        f"Hungarian-controlled episode, date: {stamp}  ",
        f"Rows per AGV: {captured[0].A.shape[1]}; AGVs per OSQP problem: {config.chunk_size}; "
        f"AGV-steps that fell back: {falls}; largest "
        f"difference between the two solvers where feasible: {max(diffs):.1e}.",
        "",
        "| what | median (ms) | 90th percentile (ms) | per AGV, median (us) |",
        "|---|---|---|---|",
    ]
    for name, arr in (
        ("build the rows (numpy)", build_ms),
        ("one block-diagonal OSQP solve, warm", t_batch_ms),
        ("**rows + batched solve (the avoidance step)**", total),
        (f"loop of {n} separate OSQP problems, warm", t_loop_ms),
    ):
        lines.append(
            f"| {name} | {np.median(arr):.2f} | {np.percentile(arr, 90):.2f} | "
            f"{np.median(arr) / n * 1e3:.1f} |"
        )
    text = "\n".join(lines) + "\n"
    out = Path(__file__).parent / "results" / "avoidance_speed.md"
    out.write_text(text)
    print(text)


if __name__ == "__main__":
    main()
