"""Speed of the ORCA avoidance step for all AGVs: exact 2-D solver, batched OSQP, OSQP loop.

    python benchmarks/avoidance_speed.py [--agents 10 100 1000] [--steps 30] [--seed 0]

For each N, an ``NvN`` episode (N AGVs, N tasks, world sized as ``sim.scenarios``) is driven by
the Hungarian controller and the arguments of every avoidance call are recorded. Then, step by
step in the same run, the same scene is

- turned into constraint rows (``VelocityAvoidance.constraints``, numpy),
- solved by the exact vectorised 2-D solver (``solver="exact"``, the default, fallback
  included),
- solved as one block-diagonal OSQP problem with warm start (``solver="osqp"``),
- solved as a loop of N separate OSQP problems, each set up once and updated with warm start.

Target (issue 4): rows + solve at most 3 ms per step at N = 100. Timings are medians and 90th
percentiles over the steps (the first step, which includes OSQP setup, is dropped). Writes
benchmarks/results/avoidance_speed.md.

The braking shield (issue 14, ``allocator/avoidance/braking.py``) is timed on the same recorded
steps (its calls are recorded as well). ``--lifelong 1000`` also times a whole lifelong step on
``warehouse-N`` (re-planning by ``HungarianDispatcher``, then the driver) with
:class:`allocator.traffic.SafeDriver` against the path-following ``WaypointDriver`` in the
same run (target, issue 14: dispatch + avoidance at most 100 ms per step at N = 1000).
"""

from __future__ import annotations

import argparse
import contextlib
import datetime
import os
import time
from dataclasses import replace
from pathlib import Path

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402
import osqp  # noqa: E402
import scipy.sparse as sp  # noqa: E402
from provenance import recorded_command  # noqa: E402

import allocator  # noqa: E402
import allocator.avoidance as avoidance  # noqa: E402
import sim  # noqa: E402
from sim.io import atomic_write_text  # noqa: E402


class LoopOfSolvers:
    """One OSQP problem per AGV (set up once, then updated and warm started)."""

    def __init__(self) -> None:
        self.solvers: list = []

    def solve(self, rows: avoidance.ConstraintRows) -> tuple[np.ndarray, np.ndarray]:
        """Velocities (n, 2) and a mask (n,) of the AGVs OSQP solved."""
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
        solved = np.zeros(n, dtype=bool)
        for i, s in enumerate(self.solvers):
            s.update(q=-rows.preferred[i], l=rows.lower[i], u=rows.upper[i],
                     Ax=rows.A[i].T.reshape(-1))
            res = s.solve(raise_error=False)
            if res.info.status.startswith("solved"):
                out[i] = res.x
                solved[i] = True
        return out, solved


REPLAN_MAX = 500
"""Above this many AGVs the controller's re-planning of stuck AGVs is switched off: its grid
map of the whole 1000v1000 world takes about 8 GB and 40 s (measured), which says nothing about
the avoidance step."""


def record(n: int, steps: int, seed: int) -> tuple[avoidance.VelocityAvoidance, list]:
    """Run a Hungarian-controlled ``NvN`` episode; the avoidance object and its calls."""
    env = sim.make_env(f"{n}v{n}", num_envs=1, seed=seed)
    obs = env.reset()
    solver = allocator.make("hungarian", **({"stuck_steps": 10**9} if n > REPLAN_MAX else {}))
    solver.reset(env)
    qp = solver.controller._avoidance()
    shield = solver.controller._shield_filter()
    calls: list[tuple[tuple, dict]] = []
    shield_calls: list[tuple[tuple, dict]] = []
    original = qp.constraints
    original_filter = shield.filter

    def capture(*a, **k):
        calls.append((a, k))
        return original(*a, **k)

    def capture_filter(*a, **k):
        shield_calls.append((a, k))
        return original_filter(*a, **k)

    qp.constraints = capture
    shield.filter = capture_filter
    for _ in range(steps):
        obs, _, done, _ = env.step(solver.act(obs))
        if bool(done.all()):
            break
    qp.constraints = original
    shield.filter = original_filter
    qp.shield_calls = shield_calls
    qp.shield = shield
    return qp, calls


def measure(n: int, steps: int, seed: int, loop_max: int) -> dict:
    """Time rows, exact solve, batched OSQP and the per-AGV loop on the same recorded steps."""
    qp, calls = record(n, steps, seed)
    exact = avoidance.VelocityAvoidance(qp.world, replace(qp.config, solver="exact"))
    exact_np = avoidance.VelocityAvoidance(qp.world, replace(qp.config, solver="exact",
                                                             native=False))
    batched = avoidance.VelocityAvoidance(qp.world, replace(qp.config, solver="osqp"))
    loop = LoopOfSolvers() if n <= loop_max else None
    t = {"rows": [], "exact": [], "exact_np": [], "osqp": [], "loop": []}
    diff_osqp, diff_loop, diff_np, fell_exact, fell_osqp, R = 0.0, 0.0, 0.0, 0, 0, 0
    for a, k in calls:  # consecutive steps, so OSQP warm starts as in the controller
        t0 = time.perf_counter()
        rows = exact.constraints(*a, **k)
        t["rows"].append(time.perf_counter() - t0)
        R = rows.A.shape[1]
        t0 = time.perf_counter()
        v_ex, f_ex, _, _ = exact.solve_rows(rows)
        t["exact"].append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        v_np, _, _, _ = exact_np.solve_rows(rows)
        t["exact_np"].append(time.perf_counter() - t0)
        diff_np = max(diff_np, float(np.abs(v_ex - v_np).max()))
        t0 = time.perf_counter()
        v_os, f_os, _, _ = batched.solve_rows(rows)
        t["osqp"].append(time.perf_counter() - t0)
        fell_exact += int(f_ex.sum())
        fell_osqp += int(f_os.sum())
        ok = rows.active & ~f_ex & ~f_os
        if ok.any():
            diff_osqp = max(diff_osqp, float(np.abs(v_ex[ok] - v_os[ok]).max()))
        if loop is not None:
            t0 = time.perf_counter()
            v_lp, solved = loop.solve(rows)
            t["loop"].append(time.perf_counter() - t0)
            ok = rows.active & ~f_ex & solved
            if ok.any():
                diff_loop = max(diff_loop, float(np.abs(v_ex[ok] - v_lp[ok]).max()))
    t["shield"] = []
    for a, k in qp.shield_calls:
        t0 = time.perf_counter()
        qp.shield.filter(*a, **k)
        t["shield"].append(time.perf_counter() - t0)
    ms = {key: np.array(val[1:]) * 1e3 for key, val in t.items() if val}
    ms["total_exact"] = ms["rows"] + ms["exact"]
    if "shield" in ms and len(ms["shield"]) == len(ms["total_exact"]):
        ms["total_shield"] = ms["total_exact"] + ms["shield"]
    ms["total_osqp"] = ms["rows"] + ms["osqp"]
    return dict(n=n, steps=len(calls) - 1, R=R, ms=ms, diff_osqp=diff_osqp, diff_loop=diff_loop,
                diff_np=diff_np,
                fell_exact=fell_exact, fell_osqp=fell_osqp, loop=loop is not None)


@contextlib.contextmanager
def dense_neighbours():
    """The neighbour search as it was before the k-d tree (the dense (N, N) matrix)."""
    from allocator.avoidance import orca

    old = orca.DENSE_MAX
    orca.DENSE_MAX = 10**9
    try:
        yield
    finally:
        orca.DENSE_MAX = old


def lifelong_step_ms(n: int, steps: int, seed: int, driver: object, dense: bool = False) -> dict:
    """Median ms of a dispatcher's ``act`` (re-plan + drive) on ``warehouse-N``; also the
    recorded arguments of every avoidance call (SafeDriver only)."""
    import torch

    from allocator.dispatch import HungarianDispatcher

    env = sim.make_env(f"warehouse-{n}", num_envs=1, seed=seed)
    env.reset()
    disp = HungarianDispatcher(driver=driver)
    t0 = time.perf_counter()
    disp.reset(env)
    setup = time.perf_counter() - t0
    calls: list = []
    qp = getattr(driver, "_avoid", None)
    if qp is not None:
        original = qp.solve

        def capture(*a, **k):
            calls.append((a, k))
            return original(*a, **k)

        qp.solve = capture
    total, collisions, parts = [], 0, []
    with dense_neighbours() if dense else contextlib.nullcontext():
        for _ in range(steps):
            before = dict(getattr(driver, "timing", {}))
            t0 = time.perf_counter()
            a = disp.act(None)
            total.append(time.perf_counter() - t0)
            after = getattr(driver, "timing", {})
            parts.append({k: after[k] - before[k] for k in before})
            _, _, _, info = env.step(a)
            collisions += int(torch.as_tensor(info["collision_pairs"]).sum())
    if qp is not None:
        qp.solve = original
    return dict(ms=np.array(total[1:]) * 1e3, setup=setup, collisions=collisions,
                parts=parts[1:], steps=steps, calls=calls[1:], qp=qp)


def recorded_avoidance(r: dict) -> list[str]:
    """Rows (k-d tree / dense) and solvers (C / numpy / block OSQP) on the recorded steps."""
    qp = r["qp"]
    fast = avoidance.VelocityAvoidance(qp.world, qp.config)
    numpy_ = avoidance.VelocityAvoidance(qp.world, replace(qp.config, native=False))
    osqp_ = avoidance.VelocityAvoidance(qp.world, replace(qp.config, solver="osqp"))
    t: dict[str, list[float]] = {k: [] for k in ("rows", "rows_dense", "c", "numpy", "osqp")}
    fell, diff, n = 0, 0.0, 0
    for a, k in r["calls"]:
        t0 = time.perf_counter()
        rows = fast.constraints(*a, **k)
        t["rows"].append(time.perf_counter() - t0)
        with dense_neighbours():
            t0 = time.perf_counter()
            dense = numpy_.constraints(*a, **k)
            t["rows_dense"].append(time.perf_counter() - t0)
        both = np.isfinite(rows.upper) & np.isfinite(dense.upper)
        same = np.array_equal(np.isfinite(rows.upper), np.isfinite(dense.upper))
        diff = max(diff, float(np.abs(rows.upper[both] - dense.upper[both]).max(initial=0.0))
                   if same else np.inf)
        for key, solver in (("c", fast), ("numpy", numpy_), ("osqp", osqp_)):
            t0 = time.perf_counter()
            v, f, _, _ = solver.solve_rows(rows)
            t[key].append(time.perf_counter() - t0)
            if key == "c":
                fell += int(f.sum())
                n = rows.A.shape[0]
    ms = {k: np.array(v) * 1e3 for k, v in t.items()}
    names = (("rows", "rows, k-d tree neighbours (default)"),
             ("rows_dense", "rows, dense (N, N) neighbours (before)"),
             ("c", "**exact solver in C (default)**"),
             ("numpy", "exact solver, vectorised numpy (before)"),
             ("osqp", "block-diagonal OSQP, warm (oracle)"))
    out = [f"The avoidance calls of the SafeDriver run above ({len(r['calls'])} steps, {n} AGVs, "
           f"{fell} AGV-steps fell back to the least-violation program; rows of the two "
           f"neighbour searches differ by at most {diff:.1e}), timed again one by one:", "",
           "| what | median (ms) | 90th percentile (ms) | max (ms) |", "|---|---|---|---|"]
    for key, name in names:
        out.append(f"| {name} | {np.median(ms[key]):.1f} | {np.percentile(ms[key], 90):.1f} | "
                   f"{ms[key].max():.1f} |")
    out.append("")
    return out


def lifelong_section(n: int, steps: int, seed: int, waypoint: bool) -> list[str]:
    from allocator.dispatch import WaypointDriver
    from allocator.traffic import SafeDriver

    out = [f"## Lifelong step, warehouse-{n}", "",
           f"{steps} steps from the start of a seeded run (the first is not timed); "
           "`HungarianDispatcher(driver=...)`: re-planning on events plus the driver. "
           "Rows of one run, one after the other.", "",
           "| driver | median (ms) | 90th percentile (ms) | overlapping pair-steps | "
           "setup (s) | driver parts, median ms per step (path / ORCA / shield) |",
           "|---|---|---|---|---|---|"]
    drivers = [("**SafeDriver** (C solver, k-d tree)", SafeDriver(), False),
               ("SafeDriver, the QP path before (numpy solvers, dense neighbours)",
                SafeDriver(avoidance_options={"native": False}), True),
               ("SafeDriver(avoidance=False)", SafeDriver(avoidance=False), False)]
    if waypoint:
        drivers.insert(0, ("WaypointDriver", WaypointDriver(), False))
    recorded = None
    for name, drv, dense in drivers:
        r = lifelong_step_ms(n, steps, seed, drv, dense)
        parts = ""
        if r["parts"] and r["parts"][0]:
            parts = " / ".join(f"{1e3 * np.median([p[k] for p in r['parts']]):.1f}"
                               for k in ("path", "avoid", "shield"))
        out.append(f"| {name} | {np.median(r['ms']):.1f} | {np.percentile(r['ms'], 90):.1f} | "
                   f"{r['collisions']} | {r['setup']:.1f} | {parts} |")
        print(out[-1], flush=True)
        if recorded is None and r["calls"]:
            recorded = r
    out.append("")
    if recorded is not None:
        out += recorded_avoidance(recorded)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--agents", type=int, nargs="+", default=[10, 100, 1000])
    parser.add_argument("--steps", type=int, default=30)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--loop-max", type=int, default=1000,
                        help="skip the per-AGV OSQP loop above this many AGVs")
    parser.add_argument("--out", type=Path,
                        default=Path(__file__).parent / "results" / "avoidance_speed.md")
    parser.add_argument("--lifelong", type=int, nargs="*", default=[],
                        help="also time a lifelong step on warehouse-N for these N")
    parser.add_argument("--lifelong-steps", type=int, default=20)
    parser.add_argument("--waypoint", action="store_true",
                        help="also time the WaypointDriver (its setup takes minutes at N=1000)")
    args = parser.parse_args()
    stamp = datetime.datetime.now().isoformat(timespec="minutes")
    lines = [
        "# Avoidance step speed (all AGVs, one step)",
        "",
        f"Command: `{recorded_command(__file__)}`  ",
        f"Seed {args.seed}; up to {args.steps} steps of one Hungarian-controlled `NvN` episode "
        f"per N (the first step is not timed); 1 thread; date: {stamp}.  ",
        "Target (issue 4): rows + solve at most 3 ms per step at N = 100. Above "
        f"N = {REPLAN_MAX} the controller does not re-plan stuck AGVs while recording (its "
        "whole-world grid map would take 8 GB).",
        "",
    ]
    names = (
        ("rows", "build the rows (numpy)"),
        ("exact", "exact 2-D solver (default: its C twin, `qp2d.c`)"),
        ("exact_np", "exact 2-D solver, vectorised numpy"),
        ("total_exact", "**rows + exact solve (the avoidance step)**"),
        ("osqp", "one block-diagonal OSQP problem, warm"),
        ("total_osqp", "rows + block-diagonal OSQP"),
        ("loop", "loop of N separate OSQP problems, warm"),
        ("shield", "braking shield (issue 14)"),
        ("total_shield", "**rows + exact solve + shield**"),
    )
    for n in args.agents:
        r = measure(n, args.steps, args.seed, args.loop_max)
        lines += [
            f"## N = {n}",
            "",
            f"{r['steps']} timed steps, {r['R']} rows per AGV; AGV-steps that fell back: "
            f"{r['fell_exact']} (exact), {r['fell_osqp']} (OSQP); largest velocity difference "
            f"where both are feasible: exact vs block-diagonal OSQP {r['diff_osqp']:.1e}"
            + (f", exact vs loop {r['diff_loop']:.1e}" if r["loop"] else "")
            + f"; C vs numpy exact solver {r['diff_np']:.1e}.",
            "",
            "| what | median (ms) | 90th percentile (ms) | per AGV, median (us) |",
            "|---|---|---|---|",
        ]
        for key, name in names:
            if key not in r["ms"]:
                continue
            arr = r["ms"][key]
            lines.append(f"| {name} | {np.median(arr):.3f} | {np.percentile(arr, 90):.3f} | "
                         f"{np.median(arr) / n * 1e3:.1f} |")
        lines.append("")
        print("\n".join(lines[-12:]), flush=True)
    for n in args.lifelong:
        lines += lifelong_section(n, args.lifelong_steps, args.seed, args.waypoint)
        print("\n".join(lines[-12:]), flush=True)
    text = "\n".join(lines)
    atomic_write_text(args.out, text)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
