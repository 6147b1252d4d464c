"""How much throughput can the choice of orders give at saturation, on a floor's order model?

At saturation an AGV's cycle is an *empty trip* (from where it became free, a drop-off station,
to its next pickup) and a *loaded trip* (that order's pickup to its station). With orders drawn
uniformly (pickups among the floor's pickup points, drop-offs among its stations, as
``sim.Poisson`` and ``sim.Backlog`` draw them) and a dispatcher that leaves no order behind for
good, the orders served over a long run are the orders released: their loaded trips average the
order model's own, whoever dispatches, and only the empty trip is the dispatcher's. Its mean
over a long run cannot be below the **transport bound**: the cheapest way to move the
drop-offs' distribution (uniform over stations) onto the pickups' (uniform over pickup points),
an optimal-transport linear program on the floor's grid distances, because the (drop-off,
next pickup) pairs of any dispatcher have those two marginals. A min-cost cycle cover of
``--samples`` sampled orders (the drop-off of each to the pickup of the next, every order
served, :func:`scipy.optimize.linear_sum_assignment`) is the same bound from a finite sample.

For each floor this script prints and writes, in steps at the driver's top speed
(``WaypointDriver.max_speed * dt``, 0.12 world units a step):

- the free-flow loaded trip, the random empty trip (a uniform station to a uniform pickup), the
  nearest-station empty trip (each pickup from its nearest station: below any dispatcher) and
  the transport / cycle-cover empty trip;
- the cycle of ``"fifo"`` and ``"hungarian"`` measured by a probe run at saturation
  (``benchmarks/load_curve.py``'s :class:`Probe`: orders delivered by AGVs free after step 100;
  empty / loaded steps and their path lengths, the extra steps over the path at top speed),
  and the transport bound and mean nearest-station distance of the pickups those orders were
  served at (a finite run can leave the far orders open at its end);
- the highest hungarian / fifo throughput ratio a matching can give (:func:`ratios`): FIFO's
  measured cycle over a cycle whose empty trip is at the transport bound of the orders
  Hungarian served (with and without the extra steps of traffic), and over a long run, where
  the orders served are those of the order model.

Writes ``benchmarks/results/dispatch/dispatch_bound.{md,json}`` (``--name``: another stem)::

    OMP_NUM_THREADS=1 python benchmarks/dispatch_bound.py                 # both floors
    OMP_NUM_THREADS=1 python benchmarks/dispatch_bound.py --floor kiva-small --steps 800
    python benchmarks/dispatch_bound.py --report-only     # the table again from the JSON
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse  # noqa: E402
import json  # noqa: E402
import sys  # noqa: E402
from datetime import datetime, timezone  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
from scipy.optimize import linear_sum_assignment, linprog  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
import load_curve  # noqa: E402
from provenance import recorded_command

import sim  # noqa: E402
from allocator.dispatch import FifoDispatcher, HungarianDispatcher, WaypointDriver  # noqa: E402
from allocator.distances import FloorDistances  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "benchmarks" / "results" / "dispatch"
TARGET = 1.2
"""The issue's target: hungarian delivers 1.2x fifo at saturation."""


def transport_bound(cost: np.ndarray, weights: np.ndarray | None = None,
                    row_weights: np.ndarray | None = None) -> float:
    """Least mean cost of moving a uniform distribution over the rows onto a uniform one over
    the columns (or ones with the given weights): optimal transport, solved as a linear
    program by HiGHS.

    Parameters
    ----------
    cost : np.ndarray, shape (S, P)
        Finite costs, e.g. the grid distance from station s to pickup p.
    weights : np.ndarray, shape (P,), optional
        Non-negative column masses (normalized here; default uniform), e.g. how often each
        pickup was served in a run.
    row_weights : np.ndarray, shape (S,), optional
        The same for the rows (default uniform).

    Returns
    -------
    float
        ``min sum_sp x[s, p] cost[s, p]`` over ``x >= 0`` with row sums ``1/S`` (or
        ``row_weights / row_weights.sum()``) and column sums ``1/P`` (or ``weights /
        weights.sum()``).

    Raises
    ------
    ValueError
        For a cost that is not a non-empty 2-D array of finite numbers, weights of the wrong
        shape, negative, NaN or all zero, or an unsolved program.
    """
    cost = np.asarray(cost, dtype=np.float64)
    if cost.ndim != 2 or not cost.size or not np.isfinite(cost).all():
        raise ValueError(f"cost must be a non-empty (S, P) array of finite numbers, got shape "
                         f"{cost.shape}")
    s, p = cost.shape
    mass = _masses("weights", weights, p)
    row_mass = _masses("row_weights", row_weights, s)
    rows = np.kron(np.eye(s), np.ones((1, p)))  # (S, S * P): sum over p of x[s, p]
    cols = np.kron(np.ones((1, s)), np.eye(p))  # (P, S * P): sum over s of x[s, p]
    res = linprog(cost.ravel(), A_eq=np.vstack([rows, cols]),
                  b_eq=np.concatenate([row_mass, mass]),
                  bounds=(0, None), method="highs")
    if not res.success:
        raise ValueError(f"the transport program was not solved: {res.message}")
    return float(res.fun)


def _masses(name: str, weights: np.ndarray | None, n: int) -> np.ndarray:
    if weights is None:
        return np.full(n, 1.0 / n)
    w = np.asarray(weights, dtype=np.float64)
    if w.shape != (n,) or not np.isfinite(w).all() or (w < 0).any() or w.sum() <= 0:
        raise ValueError(f"{name} must be ({n},) finite numbers >= 0 with a positive sum, got "
                         f"shape {w.shape}")
    return w / w.sum()


def cycle_cover(cost: np.ndarray, samples: int, seed: int) -> float:
    """Mean empty trip of a min-cost cycle cover of ``samples`` orders drawn uniformly.

    Order k has station ``s_k`` and pickup ``p_k``; serving order b right after order a costs
    ``cost[s_a, p_b]``; every order has exactly one successor and one predecessor (an
    assignment, :func:`scipy.optimize.linear_sum_assignment`), never itself.

    Parameters
    ----------
    cost : np.ndarray, shape (S, P)
    samples : int
        Orders drawn, >= 2.
    seed : int

    Returns
    -------
    float
        The mean successor cost of the optimal cover.
    """
    if isinstance(samples, bool) or not isinstance(samples, (int, np.integer)) or samples < 2:
        raise ValueError(f"samples must be an int >= 2, got {samples!r}")
    cost = np.asarray(cost, dtype=np.float64)
    rng = np.random.default_rng(seed)
    si = rng.integers(cost.shape[0], size=samples)
    pi = rng.integers(cost.shape[1], size=samples)
    c = cost[si][:, pi]  # (K, K): drop-off of a to pickup of b
    np.fill_diagonal(c, np.inf)
    c = np.where(np.isfinite(c), c, 1e9)
    r, k = linear_sum_assignment(c)
    return float(c[r, k].mean())


def order_model(floor: str, samples: int, seed: int) -> dict:
    """The floor's order-model figures, in world units and steps at the driver's top speed."""
    scenario, options = load_curve.floor_scenario(floor)
    sc = sim.get_scenario(scenario, **options)
    world = sc.world
    per_step = WaypointDriver().max_speed * world.physics.dt
    stations, pickups = np.asarray(sc.stations), np.asarray(sc.pickups)
    d = FloorDistances(world)
    empty = d.distance(stations, pickups)  # (S, P)
    loaded = d.distance(pickups, stations)  # (P, S)
    if not (np.isfinite(empty).all() and np.isfinite(loaded).all()):
        raise ValueError(f"{floor}: a station and a pickup do not reach each other")
    out = dict(floor=floor, num_agents=sc.num_agents, pickups=len(pickups),
               stations=len(stations), service_steps=sc.service_steps, per_step=per_step,
               loaded_path=float(loaded.mean()), random_empty_path=float(empty.mean()),
               nearest_station_empty_path=float(empty.min(axis=0).mean()),
               transport_empty_path=transport_bound(empty),
               cycle_cover_empty_path=cycle_cover(empty, samples, seed),
               cycle_cover_samples=samples)
    for key in ("loaded", "random_empty", "nearest_station_empty", "transport_empty",
                "cycle_cover_empty"):
        out[f"{key}_steps"] = out[f"{key}_path"] / per_step
    return out


def _nearest(points: np.ndarray, of: np.ndarray) -> np.ndarray:
    """Index into ``of`` (M, 2) of the nearest point to each of ``points`` (K, 2)."""
    return np.linalg.norm(points[:, None, :] - of[None, :, :], axis=-1).argmin(axis=1)


def measure(floor: str, steps: int, seed: int) -> dict:
    """Throughput, oldest open order and mean cycle of ``fifo`` and ``hungarian`` (defaults)
    at the scenario's saturation, from one probe run each; and, over the orders of the cycle,
    the transport bound from the stations the AGVs were free at to the pickups they were
    served at (``served_transport_empty_path``: no pairing of these empty trips' ends is
    shorter) and the pickups' mean nearest-station distance
    (``served_nearest_station_path``)."""
    scenario, options = load_curve.floor_scenario(floor)
    sc = sim.get_scenario(scenario, **options)
    stations, pickups = np.asarray(sc.stations), np.asarray(sc.pickups)
    empty = FloorDistances(sc.world).distance(stations, pickups)  # (S, P)
    out = {}
    for name, inner in (("fifo", FifoDispatcher()), ("hungarian", HungarianDispatcher())):
        p = load_curve.Probe(inner)
        m = sim.evaluate_lifelong(p, scenario, steps=steps, seed=seed, **options)
        cycle = p.cycle(inner.distances, inner.speed)
        if not cycle:
            raise ValueError(f"{floor}: no order of {name} was delivered by an AGV free after "
                             f"step 100 in {steps} steps; run more steps")
        trips = np.array(p.trips).reshape(-1, 9)
        trips = trips[trips[:, 0] > 100]  # the cycle's orders: free at a drop-off station
        which = _nearest(trips[:, 5:7], pickups)
        counts = np.bincount(which, minlength=len(pickups))
        origins = np.bincount(_nearest(trips[:, 1:3], stations), minlength=len(stations))
        out[name] = dict(throughput=m.throughput, wait_p95=m.wait_p95,
                         oldest_open_at_end=load_curve.oldest_open(p.env),
                         served_transport_empty_path=transport_bound(empty, counts, origins),
                         served_nearest_station_path=float(empty.min(axis=0)[which].mean()),
                         **{k: float(v) for k, v in cycle.items()})
        print(json.dumps({"floor": floor, "dispatcher": name, **out[name]}), flush=True)
    return out


def ratios(model: dict, runs: dict) -> dict:
    """Hungarian / FIFO throughput ratios: measured, and the highest a matching could give.

    All against FIFO's measured cycle (empty plus loaded steps). *served*: the orders
    Hungarian served in the run, from the stations it was free at, at their transport bound
    (no matching of the same orders has shorter empty trips), with Hungarian's measured extra
    steps and loaded steps (``optimal_matching``), without the extra steps of the empty trip
    (``no_empty_traffic``), and without any (``no_traffic``: both trips at their path length).
    *model*: over a long run, where the orders served are the orders released (the order
    model's transport bound for the empty trip, FIFO's loaded steps), with no extra steps on
    the empty trip (``long_run_no_empty_traffic``).
    """
    f, h = runs["fifo"], runs["hungarian"]
    per = model["per_step"]
    fifo_cycle = f["empty_steps"] + f["loaded_steps"]
    served = h["served_transport_empty_path"] / per
    return dict(measured=h["throughput"] / f["throughput"],
                cycle_measured=fifo_cycle / (h["empty_steps"] + h["loaded_steps"]),
                optimal_matching=fifo_cycle / (served + h["empty_extra_steps"]
                                               + h["loaded_steps"]),
                no_empty_traffic=fifo_cycle / (served + h["loaded_steps"]),
                no_traffic=fifo_cycle / (served + h["loaded_path"] / per),
                long_run_no_empty_traffic=fifo_cycle / (model["transport_empty_steps"]
                                                        + f["loaded_steps"]),
                fifo_cycle=fifo_cycle,
                cycle_for_target=fifo_cycle / TARGET,
                empty_for_target=fifo_cycle / TARGET - h["loaded_steps"])


def report(rows: list[dict], command: str, out: Path, name: str = "dispatch_bound") -> str:
    when = "; ".join(dict.fromkeys(f"commit {r['commit']}, {r['date']}" for r in rows))
    lines = ["# What the empty trip can give: dispatch bounds at saturation", "",
             f"`{command}` ({when}; steps and seed in the JSON). Distances on the "
             "floor's grid table (`allocator.distances.FloorDistances`), in steps at the "
             "driver's top speed (0.12 world units a step). Order model: pickups uniform over "
             "the floor's pickup points, drop-offs uniform over its stations. See the script's "
             "docstring for each figure.", "",
             "| floor | AGVs | loaded trip | random empty | nearest-station empty | transport"
             " bound (empty) | cycle cover (empty) |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        m = r["model"]
        lines.append(f"| {m['floor']} | {m['num_agents']} | {m['loaded_steps']:.1f} | "
                     f"{m['random_empty_steps']:.1f} | {m['nearest_station_empty_steps']:.1f}"
                     f" | {m['transport_empty_steps']:.1f} | "
                     f"{m['cycle_cover_empty_steps']:.1f} ({m['cycle_cover_samples']}) |")
    lines += ["", "Measured at saturation (the scenario's backlog, ceil(1.5 N) open orders), "
              "default dispatchers, one probe run each (steps and seed in the JSON); paths in "
              "steps at top speed, *extra* = steps over it:", "",
              "| floor | dispatcher | throughput | oldest open at end | empty path | empty "
              "steps (extra) | loaded path | loaded steps (extra) | cycle | transport bound "
              "to the pickups served | nearest station of the pickups served |",
              "|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        per = r["model"]["per_step"]
        for who, x in r["runs"].items():
            lines.append(
                f"| {r['model']['floor']} | {who} | {x['throughput']:.1f} | "
                f"{x['oldest_open_at_end']} | {x['empty_path'] / per:.1f} | "
                f"{x['empty_steps']:.1f} ({x['empty_extra_steps']:.1f}) | "
                f"{x['loaded_path'] / per:.1f} | {x['loaded_steps']:.1f} "
                f"({x['loaded_extra_steps']:.1f}) | "
                f"{x['empty_steps'] + x['loaded_steps']:.1f} | "
                f"{x['served_transport_empty_path'] / per:.1f} | "
                f"{x['served_nearest_station_path'] / per:.1f} |")
    lines += ["", "The last two columns are over the orders of the cycle (the pickups they "
              "were served at): a dispatcher that serves these orders cannot have a mean empty "
              "trip below the first; a run of finite length can serve fewer far orders than "
              "the order model releases (up to the backlog, ceil(1.5 N), stay open at the "
              "end), which lowers both below the model's.", "",
              "Hungarian / FIFO throughput: measured; the ratio of the measured cycles; and "
              "the highest any matching could give (FIFO's measured cycle over a cycle whose "
              "empty trip is the transport bound of the orders Hungarian served, plus "
              "Hungarian's measured extra steps on it and loaded steps; then without the empty "
              "trip's extra steps; then without any extra steps); and over a long run (the "
              "order model's transport bound, FIFO's loaded steps, no extra steps on the empty "
              "trip). Then the cycle, and the empty trip beside Hungarian's loaded steps, that "
              "1.2x needs:", "",
              "| floor | measured | cycles | optimal matching | no traffic on the empty trip |"
              " no traffic | long run, no traffic on the empty trip | cycle for 1.2x | "
              "empty trip for 1.2x |", "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        q = r["ratios"]
        lines.append(f"| {r['model']['floor']} | {q['measured']:.3f} | "
                     f"{q['cycle_measured']:.3f} | {q['optimal_matching']:.3f} | "
                     f"{q['no_empty_traffic']:.3f} | {q['no_traffic']:.3f} | "
                     f"{q['long_run_no_empty_traffic']:.3f} | {q['cycle_for_target']:.1f} | "
                     f"{q['empty_for_target']:.1f} |")
    text = "\n".join(lines) + "\n"
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{name}.md").write_text(text)
    (out / f"{name}.json").write_text(json.dumps(dict(command=command, rows=rows), indent=2))
    return text


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--floor", action="append",
                        help="warehouse-50, kiva-small or another lifelong scenario's name "
                             "(repeatable; default warehouse-50 and kiva-small)")
    parser.add_argument("--steps", type=int, default=1500)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--samples", type=int, default=3000,
                        help="orders of the cycle cover")
    parser.add_argument("--out", type=Path, default=OUT)
    parser.add_argument("--name", default="dispatch_bound",
                        help="file stem of the table and the JSON (default dispatch_bound)")
    parser.add_argument("--report-only", action="store_true",
                        help="recompute the ratios and the table from the stored JSON")
    args = parser.parse_args(argv)
    if args.steps < 101:
        parser.error(f"--steps must be > 100 (cycles count AGVs free after step 100), got "
                     f"{args.steps}")
    if args.samples < 2:
        parser.error(f"--samples must be >= 2, got {args.samples}")
    command = recorded_command(__file__, argv, env="OMP_NUM_THREADS=1")
    if args.report_only:  # the stored runs, the ratios and the table as the code makes them
        data = json.loads((args.out / f"{args.name}.json").read_text())
        rows = data["rows"]
        for r in rows:
            r["ratios"] = ratios(r["model"], r["runs"])
        print(report(rows, data["command"], args.out, args.name))
        return
    rows = []
    for floor in args.floor or list(load_curve.FLOORS):
        model = order_model(floor, args.samples, args.seed)
        runs = measure(floor, args.steps, args.seed)
        rows.append(dict(model=model, runs=runs, ratios=ratios(model, runs), steps=args.steps,
                         seed=args.seed, commit=load_curve._commit(),
                         date=datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")))
    print(report(rows, command.strip(), args.out, args.name))


if __name__ == "__main__":
    main()
