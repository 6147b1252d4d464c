"""Load curves of the lifelong dispatchers: throughput and p95 wait from light load to saturation.

Writes ``benchmarks/results/dispatch/load_curve.{json,md}`` and
``docs/figures/load_curve_<floor>.png``::

    OMP_NUM_THREADS=1 python benchmarks/load_curve.py                  # every floor, then report
    OMP_NUM_THREADS=1 python benchmarks/load_curve.py --floor kiva-small --no-report
    python benchmarks/load_curve.py --report-only                        # merge the parts
    OMP_NUM_THREADS=1 python benchmarks/load_curve.py --floor kiva-small --redo hungarian
    OMP_NUM_THREADS=1 python benchmarks/load_curve.py --floor kiva-small --steps 1500 \
        --probe hungarian fifo 'hungarian:{"ahead_steps": 30}'   # time shares and speeds

For each floor (``warehouse-50``, and ``benchmarks/floors/kiva-small.map`` loaded with
``sim.load_floor(..., cell_size=0.4)`` with 24 AGVs) and each dispatcher (``"hungarian"``,
``"fifo"``, ``"greedy"``, ``"auction"`` with a finite radio range, and
``sim.controllers.NearestTaskController``), :func:`sim.evaluate_lifelong` runs at Poisson
arrival rates set as fractions of the floor's ``throughput_bound`` and at saturation (the
scenario's backlog: ceil(1.5 N) open orders at all times, as the League of Robot Runners
reveals them); at saturation once more with breakdowns, for the faulted / fault-free ratio.
Every run of one floor sees the same seed, so the same orders and breakdowns. Each floor's
part is written after every run (``load_curve.<floor>.json``), so a run cut short keeps what
it measured, and a new run of the same configuration resumes it (saturation first).
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")

import argparse  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import platform  # noqa: E402
import subprocess  # noqa: E402
import time  # noqa: E402
from datetime import datetime, timezone  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402

import allocator  # noqa: E402
import sim  # noqa: E402
from sim.controllers import NearestTaskController  # noqa: E402
from sim.orders import ASSIGNED, OPEN  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "benchmarks" / "results" / "dispatch"
FIGURES = ROOT / "docs" / "figures"
KIVA = ROOT / "benchmarks" / "floors" / "kiva-small.map"
FLOORS = ("warehouse-50", "kiva-small")
DISPATCHERS = ("hungarian", "fifo", "greedy", "auction", "nearest")
COMM_RANGE = 3.0
"""The auction's radio range (world units): a few aisles, so the graph does split."""
FAULTS = dict(rate=0.0005, repair_steps=50)
"""Breakdowns per AGV-step and repair time of the faulted runs."""


def floor_scenario(name: str) -> tuple[object, dict]:
    """The ``scenario`` argument of :func:`sim.evaluate_lifelong` and its options."""
    if name == "kiva-small":
        return sim.load_floor(KIVA, cell_size=0.4), {"num_agents": 24}
    return name, {}


def controller(name: str) -> object:
    if name == "nearest":
        return NearestTaskController()
    if name == "auction":
        return allocator.make("auction", comm_range=COMM_RANGE)
    return allocator.make(name)


def run_one(floor: str, name: str, rate: float | None, faults: bool, steps: int,
            seed: int) -> dict:
    scenario, options = floor_scenario(floor)
    ctrl = controller(name)
    seen = Probe(ctrl, record=False)
    start = time.perf_counter()
    m = sim.evaluate_lifelong(seen, scenario, steps=steps, seed=seed, arrival_rate=rate,
                              faults=sim.Breakdowns(**FAULTS) if faults else None, **options)
    row = dict(floor=floor, dispatcher=name, load="saturation" if rate is None else "poisson",
               rate=rate, faults=faults, throughput=m.throughput,
               throughput_bound=m.throughput_bound, wait_mean=m.wait_mean,
               wait_p95=m.wait_p95, lead_p95=m.lead_p95, utilization=m.utilization,
               reassignments=m.reassignments, lost=m.lost, released=m.released,
               delivered=m.delivered, open_at_end=m.open_at_end,
               collisions_per_1000=m.collisions_per_1000,
               oldest_open_at_end=oldest_open(seen.env),
               seconds=time.perf_counter() - start, commit=_commit(),
               date=datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC"))
    dispatcher = getattr(ctrl, "_dispatcher", None)
    if name == "auction" and dispatcher is not None:
        per = dispatcher.replan_messages
        row.update(messages=dispatcher.messages, replans=len(per),
                   messages_per_replan=dispatcher.messages / max(len(per), 1),
                   comm_range=COMM_RANGE)
    return row


def oldest_open(env: object) -> int:
    """Age in steps of the oldest order not yet picked up (open or assigned) in any floor of
    ``env`` (0 when none). The waits of :func:`sim.evaluate_lifelong` count picked-up orders
    only: an order a dispatcher leaves behind for good is in none of them, so this is kept."""
    o = env.orders
    waiting = (o.status == OPEN) | (o.status == ASSIGNED)
    ages = (env.steps.unsqueeze(1) - o.release)[waiting]
    return int(ages.max()) if ages.numel() else 0


class Probe:
    """Wraps a controller (keeping its env in :attr:`env`) and records, at every step, the
    fleet's time shares and speeds (unless ``record`` is False)."""

    def __init__(self, inner: object, record: bool = True) -> None:
        self.inner = inner
        self.record = record
        self.counts: list = []
        self.speed: list = []
        self.slow: list = []
        # Per delivery: free step, free x and y, picked, finished, pickup x, y, drop-off x, y.
        self.trips: list = []

    def reset(self, env: object) -> None:
        self.env = env
        self.inner.reset(env)
        pos = env.agent_pos[0].double().cpu().numpy()
        self.free = {a: (0, pos[a].copy()) for a in range(env.num_agents)}

    def act(self, obs: object) -> object:
        if not self.record:
            return self.inner.act(obs)
        st = self.env.agent_status[0].cpu().numpy()
        sp = self.env.agent_vel[0].norm(dim=-1).cpu().numpy()
        self.counts.append(np.bincount(st, minlength=4))
        self.speed.append([sp[st == k].mean() if (st == k).any() else np.nan for k in range(3)])
        self.slow.append([(sp[st == k] < 0.2).mean() if (st == k).any() else np.nan
                          for k in range(3)])
        o = self.env.orders
        for q in np.flatnonzero(self.env.events.delivered[0].cpu().numpy()):
            a = int(o.agent[0, q])
            t0, p0 = self.free[a]
            drop = o.dropoff[0, q].double().cpu().numpy()
            self.trips.append((t0, *p0, int(o.picked[0, q]), int(o.finished[0, q]),
                               *o.pickup[0, q].double().cpu().numpy(), *drop))
            self.free[a] = (int(o.finished[0, q]), drop.copy())
        return self.inner.act(obs)

    def cycle(self, distances: object, per_step: float, after: int = 100) -> dict:
        """Mean empty and loaded trip of the orders delivered (by AGVs free after step
        ``after``, past the start from the depot): path length on the floor's distance table,
        steps, and the steps beyond path / ``per_step`` (the top speed's distance a step)."""
        t = np.array(self.trips).reshape(-1, 9)
        t = t[t[:, 0] > after]
        if not len(t):
            return {}
        empty = distances.pairwise(t[:, 1:3], t[:, 5:7])
        loaded = distances.pairwise(t[:, 5:7], t[:, 7:9])
        e_steps, l_steps = t[:, 3] - t[:, 0], t[:, 4] - t[:, 3]
        return dict(orders=len(t), empty_path=empty.mean(), empty_steps=e_steps.mean(),
                    empty_extra_steps=(e_steps - empty / per_step).mean(),
                    loaded_path=loaded.mean(), loaded_steps=l_steps.mean(),
                    loaded_extra_steps=(l_steps - loaded / per_step).mean())


def probe(floor: str, names: list[str], steps: int, seed: int,
          num_agents: int | None = None) -> None:
    """Print, per dispatcher, the throughput and the share of the time the AGVs spend idle, to a
    pickup, loaded and broken, their mean speed in the first three, the share of them
    under 0.2 (world units per second), and the mean cycle of an order (:meth:`Probe.cycle`).
    A name is ``hungarian``, ``fifo`` or ``hungarian:{json options of HungarianDispatcher}``;
    ``num_agents`` runs the floor with another fleet (e.g. 2: AGVs that hardly meet)."""
    from allocator.dispatch import FifoDispatcher, HungarianDispatcher

    scenario, options = floor_scenario(floor)
    if num_agents is not None:
        scenario = sim.get_scenario(scenario, **options).world
        options = {"num_agents": num_agents}
    for name in names:
        base, _, opts = name.partition(":")
        kw = json.loads(opts) if opts else {}
        inner = HungarianDispatcher(**kw) if base == "hungarian" else \
            FifoDispatcher() if base == "fifo" else controller(base)
        p = Probe(inner)
        m = sim.evaluate_lifelong(p, scenario, steps=steps, seed=seed, **options)
        counts = np.array(p.counts)
        print(json.dumps(dict(
            floor=floor, dispatcher=name, steps=steps, seed=seed, throughput=m.throughput,
            wait_p95=m.wait_p95, oldest_open_at_end=oldest_open(p.env),
            reassignments=m.reassignments,
            share_idle_pickup_loaded_broken=(counts.sum(0) / counts.sum()).round(3).tolist(),
            speed_idle_pickup_loaded=np.nanmean(p.speed, 0).round(3).tolist(),
            slow_idle_pickup_loaded=np.nanmean(p.slow, 0).round(3).tolist(),
            num_agents=p.env.num_agents,
            cycle={k: round(float(v), 3) for k, v in
                   p.cycle(inner.distances, inner.speed).items()}
            if hasattr(inner, "distances") else None)), flush=True)


def _commit() -> str:
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True,
                              text=True, check=True, cwd=ROOT).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def _write_json(path: Path, data: dict) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(data, indent=2, allow_nan=True))
    tmp.replace(path)


def measure_floor(floor: str, fractions: list[float], dispatchers: list[str], steps: int,
                  seed: int, redo: tuple[str, ...] = ()) -> None:
    scenario, options = floor_scenario(floor)
    bound = sim.get_scenario(scenario, **options).throughput_bound()
    config = dict(floor=floor, steps=steps, seed=seed, runs=1, fractions=fractions,
                  rates=[f * bound / 1000.0 for f in fractions], throughput_bound=bound,
                  faults=FAULTS, comm_range=COMM_RANGE, dispatchers=dispatchers,
                  saturation="the scenario's backlog: ceil(1.5 N) open orders at all times",
                  commit=_commit(), torch_threads=torch.get_num_threads(),
                  omp_num_threads=os.environ.get("OMP_NUM_THREADS"),
                  machine=f"{platform.machine()}, {os.cpu_count()} CPUs",
                  date=datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC"))
    if floor == "kiva-small":
        config.update(map=str(KIVA.relative_to(ROOT)), cell_size=0.4, num_agents=24)
    part = OUT / f"load_curve.{floor}.json"
    rows: list[dict] = []
    if part.exists():  # resume: keep the runs of the same configuration already measured
        old = json.loads(part.read_text())
        same = all(old["config"].get(k) == config[k] for k in ("steps", "seed", "faults",
                                                                "comm_range"))
        rows = old["results"] if same else []
        rows = [r for r in rows if r["dispatcher"] not in redo]  # measured again
        for r in rows:  # runs stored before rows kept their own commit and date
            r.setdefault("commit", old["config"].get("commit", "unknown"))
            r.setdefault("date", old["config"].get("date", "unknown"))
    # Every dispatcher with a stored run stays in the figure and the table.
    config["dispatchers"] = _ordered(list(dispatchers) + [r["dispatcher"] for r in rows])
    done = {(r["dispatcher"], r["rate"], r["faults"]) for r in rows}
    # Saturation first (the targets), then the Poisson rates from the heaviest down.
    loads: list[tuple[float | None, bool]] = [(None, False), (None, True)]
    loads += [(r, False) for r in sorted(config["rates"], reverse=True)]
    for rate, faults in loads:
        for name in dispatchers:
            if (name, rate, faults) in done:
                continue
            row = run_one(floor, name, rate, faults, steps, seed)
            rows.append(row)
            print(json.dumps(row), flush=True)
            _write_json(part, dict(config=config, results=rows))


def _fmt(x: float | None, spec: str = ".1f") -> str:
    return "-" if x is None or (isinstance(x, float) and math.isnan(x)) else format(x, spec)


def _ordered(names: list[str]) -> list[str]:
    """The distinct names, those of DISPATCHERS first in its order."""
    seen = list(dict.fromkeys(names))
    return [d for d in DISPATCHERS if d in seen] + [d for d in seen if d not in DISPATCHERS]


def _provenance(rows: list[dict], cfg: dict) -> str:
    """'commit C (dispatchers, date)' for each commit the floor's runs were measured at."""
    by: dict[str, list[dict]] = {}
    for r in rows:
        by.setdefault(r.get("commit", cfg["commit"]), []).append(r)
    parts = []
    for commit, rs in by.items():
        names = _ordered([r["dispatcher"] for r in rs])
        dates = sorted(r.get("date", cfg["date"]) for r in rs)
        parts.append(f"commit {commit} ({', '.join(names)}; {dates[-1]})")
    return "; ".join(parts)


def report() -> None:
    parts = {}
    for floor in FLOORS:
        path = OUT / f"load_curve.{floor}.json"
        if path.exists():
            parts[floor] = json.loads(path.read_text())
    summary: dict[str, dict] = {}
    lines = ["# Load curves of the lifelong dispatchers", "",
             "`OMP_NUM_THREADS=1 python benchmarks/load_curve.py` (one process per floor, "
             "`--floor NAME`). Throughput in orders delivered per 1000 steps; waits release to "
             "pickup, steps, over the orders picked up; *oldest open at end* = the age in "
             "steps of the oldest order not picked up when the run ends (an order a "
             "dispatcher leaves behind for good is in no wait; '-': run before this column "
             "was kept); *bound* = `throughput_bound` (every AGV always on a shortest "
             "loaded trip at top speed). Poisson rates as fractions of the bound; *saturation* "
             "= the scenario's backlog (ceil(1.5 N) open orders at all times); *faults* = "
             f"`sim.Breakdowns(rate={FAULTS['rate']}, repair_steps={FAULTS['repair_steps']})` "
             "at saturation. One run per point (seed and steps below).", ""]
    for floor, part in parts.items():
        cfg, rows = part["config"], part["results"]
        order = _ordered([r["dispatcher"] for r in rows])
        # Saturation, then with faults, then the Poisson rates from light to heavy.
        rows = sorted(rows, key=lambda r: (r["load"] != "saturation", r["faults"],
                                           r["rate"] or 0.0, order.index(r["dispatcher"])))
        lines += [f"## {floor}", "",
                  f"{cfg['steps']} steps, seed {cfg['seed']}, {cfg['runs']} run per point, "
                  f"bound {cfg['throughput_bound']:.1f}, auction comm_range "
                  f"{cfg['comm_range']}, {_provenance(rows, cfg)}"
                  + (f", map `{cfg['map']}` at cell_size {cfg['cell_size']} with "
                     f"{cfg['num_agents']} AGVs" if "map" in cfg else "") + ".", "",
                  "| load | rate (orders/step) | dispatcher | throughput | / bound | wait mean |"
                  " wait p95 | oldest open at end | reassignments | lost |"
                  " auction messages / re-plan |",
                  "|---|---|---|---|---|---|---|---|---|---|---|"]
        for r in rows:
            # The floor's bound (cfg), not the run's: a Poisson run's throughput_bound is
            # capped by its own arrival rate, which made every rate read "1.00 x bound".
            load = ("saturation + faults" if r["faults"] else "saturation") \
                if r["load"] == "saturation" else \
                f"{r['rate'] * 1000 / cfg['throughput_bound']:.2f} x bound" \
                if cfg["throughput_bound"] else "poisson"
            lines.append(
                f"| {load} | {_fmt(r['rate'], '.4f')} | {r['dispatcher']} | "
                f"{r['throughput']:.1f} | {r['throughput'] / cfg['throughput_bound']:.2f} | "
                f"{_fmt(r['wait_mean'])} | {_fmt(r['wait_p95'])} | "
                f"{_fmt(r.get('oldest_open_at_end'), 'd')} | "
                f"{r['reassignments']:.0f} | {r['lost']} | "
                f"{_fmt(r.get('messages_per_replan'), '.0f')} |")
        sat = {r["dispatcher"]: r for r in rows if r["load"] == "saturation" and not r["faults"]}
        top = max((r["rate"] for r in rows if r["rate"] is not None), default=None)
        heavy = {r["dispatcher"]: r for r in rows if r["rate"] == top and top is not None}
        faulted = {r["dispatcher"]: r for r in rows if r["faults"]}
        s: dict = {}
        for label, table in (("saturation", sat), ("highest Poisson rate", heavy)):
            if "hungarian" in table and "fifo" in table and table["fifo"]["throughput"]:
                s[f"hungarian / fifo, {label}"] = (table["hungarian"]["throughput"]
                                                   / table["fifo"]["throughput"])
        for name, r in faulted.items():
            if name in sat and sat[name]["throughput"]:
                s[f"faulted / fault-free, {name}"] = r["throughput"] / sat[name]["throughput"]
        s["lost (all runs)"] = sum(r["lost"] for r in rows)
        summary[floor] = s
        lines += ["", "Targets (issue 14): hungarian >= 1.2x fifo at saturation; with faults "
                  ">= 85% of the fault-free throughput; 0 lost.", ""]
        for key, value in s.items():
            verdict = ""
            if key.startswith("hungarian / fifo"):
                verdict = " (met)" if value >= 1.2 else " (NOT met)"
            elif key.startswith("faulted"):
                verdict = " (met)" if value >= 0.85 else " (NOT met)"
            lines.append(f"- {key}: {value:.3f}{verdict}" if isinstance(value, float)
                         else f"- {key}: {value}")
        lines.append("")
        plot(floor, cfg, rows)
        lines += [f"![load curve {floor}](../../../docs/figures/load_curve_{floor}.png)", ""]
    _write_json(OUT / "load_curve.json", dict(parts=parts, summary=summary))
    tmp = OUT / "load_curve.md.tmp"
    tmp.write_text("\n".join(lines) + "\n")
    tmp.replace(OUT / "load_curve.md")


def plot(floor: str, cfg: dict, rows: list[dict]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax_t, ax_w) = plt.subplots(1, 2, figsize=(10, 4))
    bound = cfg["throughput_bound"]
    for name in _ordered([r["dispatcher"] for r in rows]):
        pts = sorted((r["rate"], r) for r in rows if r["dispatcher"] == name
                     and r["load"] == "poisson")
        sat = [r for r in rows if r["dispatcher"] == name and r["load"] == "saturation"
               and not r["faults"]]
        xs = [1000 * rate for rate, _ in pts]
        line, = ax_t.plot(xs, [r["throughput"] for _, r in pts], "o-", label=name)
        ax_w.plot(xs, [r["wait_p95"] for _, r in pts], "o-", color=line.get_color(),
                  label=name)
        if sat:
            x_sat = 1000 * max(rate for rate, _ in pts) * 1.25 if pts else 0.0
            ax_t.plot([x_sat], [sat[0]["throughput"]], "s", color=line.get_color())
            ax_w.plot([x_sat], [sat[0]["wait_p95"]], "s", color=line.get_color())
    top = max((1000 * r["rate"] for r in rows if r["rate"]), default=1.0) * 1.3
    ax_t.plot([0, top], [0, top], ":", color="grey", label="arrival rate")
    if bound <= top * 1.1:
        ax_t.axhline(bound, color="black", ls="--", lw=1, label="throughput_bound")
    ax_t.set_xlabel("arrival rate (orders per 1000 steps); squares: saturation (backlog)")
    ax_t.set_ylabel("throughput (orders per 1000 steps)")
    ax_t.set_ylim(0, min(bound * 1.05, top * 1.1))
    ax_w.set_xlabel("arrival rate (orders per 1000 steps); squares: saturation")
    ax_w.set_ylabel("p95 wait, release to pickup (steps)")
    ax_t.legend(fontsize=8)
    fig.suptitle(f"{floor}: {cfg['steps']} steps, seed {cfg['seed']}; throughput_bound "
                 f"{bound:.0f} orders per 1000 steps"
                 + (" (above the axis)" if bound > top * 1.1 else ""))
    fig.tight_layout()
    FIGURES.mkdir(parents=True, exist_ok=True)
    tmp = FIGURES / f"load_curve_{floor}.tmp.png"
    fig.savefig(tmp, dpi=110)
    plt.close(fig)
    tmp.replace(FIGURES / f"load_curve_{floor}.png")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--floor", choices=FLOORS, action="append")
    parser.add_argument("--dispatchers", nargs="+", default=list(DISPATCHERS))
    parser.add_argument("--fractions", nargs="+", type=float, default=[0.1, 0.2, 0.3, 0.4])
    parser.add_argument("--steps", type=int, default=1500)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--no-report", action="store_true")
    parser.add_argument("--report-only", action="store_true")
    parser.add_argument("--probe", nargs="+", metavar="NAME[:JSON]",
                        help="only print time shares and speeds of these dispatchers "
                             "(saturation, the first --floor)")
    parser.add_argument("--num-agents", type=int, default=None,
                        help="with --probe: the floor with this many AGVs instead")
    parser.add_argument("--redo", nargs="+", default=[], choices=DISPATCHERS,
                        help="measure these dispatchers again (drop their stored runs)")
    args = parser.parse_args()
    if args.probe:
        probe((args.floor or FLOORS)[0], args.probe, args.steps, args.seed, args.num_agents)
        return
    if not args.report_only:
        for floor in args.floor or FLOORS:
            measure_floor(floor, args.fractions, args.dispatchers, args.steps, args.seed,
                          tuple(args.redo))
    if not args.no_report:
        report()


if __name__ == "__main__":
    main()
