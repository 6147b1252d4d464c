"""``agv demo``: every available method on the paper's scenarios, the table beside the paper's
numbers, and the figures (tasks completed per episode, preference matrices, animations); the
scale headline (20 AGVs, the any-N learned weights beside Hungarian and the auction); then the
dispatchers and the shipped lifelong policy in lifelong operation on a warehouse floor
(throughput over time)."""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

import sim
from allocator.paper import PAPER_TABLES
from sim.controllers import NearestTaskController
from sim.io import atomic_save, atomic_write_text
from sim.render import _plt

__all__ = ["run_demo", "available_methods", "format_table", "run_lifelong",
           "format_lifelong_table", "lifelong_methods", "run_scale", "scale_methods",
           "format_scale_table"]


def available_methods(scenario: str) -> Iterator[tuple[str, Callable[[], Any]]]:
    """Yield ``(name, factory)`` for every method that can run on ``scenario`` here: the
    scripted nearest-task baseline, the classical allocators, and each learned allocator whose
    weights ship for the scenario (the others are reported as missing; the lifelong-only
    families, ``allocator.learned.LIFELONG_ONLY``, are left to the lifelong rows)."""
    import allocator
    from allocator.learned import LIFELONG_ONLY

    yield "nearest-task", NearestTaskController
    registry = allocator.ALLOCATORS
    for name in ("hungarian", "greedy"):
        if name in registry:
            yield name, (lambda n=name: allocator.make(n))
    for name in sorted(n for n in registry if n.split("-")[0] in ("maddpg", "bicnet")
                       and n not in LIFELONG_ONLY):
        try:
            solver = allocator.make(name, scenario=scenario)
        except (ValueError, FileNotFoundError) as err:
            print(f"  [{scenario}] {name}: skipped ({err})")
            continue
        yield name, (lambda s=solver: s)


def _markdown(columns: list[str], cells: list[list[str]]) -> str:
    """A Markdown table: a header of ``columns`` and one line per row of ``cells``."""
    lines = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    lines += ["| " + " | ".join(row) + " |" for row in cells]
    return "\n".join(lines)


def format_table(rows: list[dict[str, Any]]) -> str:
    """A Markdown table of evaluation rows, the paper's numbers beside ours."""
    cells = []
    for r in rows:
        paper = PAPER_TABLES.get(r["scenario"], {}).get(r["method"])
        pr, pw, pt = ("-", "-", "-")
        if paper:
            pr, pw, pt = f"{paper[0]:.2%}", f"{paper[1]:.1f}", f"{paper[2]:.1f}"
        cells.append([r["scenario"], r["method"], f"{r['response_rate']:.2%}", pr,
                      f"{r['avg_reward']:.1f}", pw, f"{r['avg_time']:.1f}", pt,
                      f"{r['collisions']:.2f}", f"{r['seconds']:.1f}"])
    return _markdown(["scenario", "method", "response rate", "paper", "avg reward", "paper",
                      "avg time", "paper", "collisions/ep", "eval s"], cells)


def _claims_figure(results: dict[tuple[str, str], sim.Metrics], scenario: str, path: Path) -> None:
    plt = _plt()
    items = [(m, res) for (s, m), res in results.items() if s == scenario]
    m_tasks = items[0][1].num_tasks
    fig, ax = plt.subplots(figsize=(7, 3.6))
    width = 0.8 / len(items)
    for k, (name, res) in enumerate(items):
        frac = np.bincount(res.claims_per_episode, minlength=m_tasks + 1) / res.episodes
        ax.bar(np.arange(m_tasks + 1) + k * width - 0.4 + width / 2, frac, width, label=name)
    ax.set_xlabel("tasks completed in the episode")
    ax.set_ylabel("fraction of episodes")
    ax.set_title(f"Tasks completed per episode ({scenario})")
    ax.legend(fontsize=7)
    fig.tight_layout()
    atomic_save(lambda p: fig.savefig(p, dpi=110, format="png"), path)
    plt.close(fig)


LIFELONG_FLOOR = "warehouse-20"
LIFELONG_DISPATCHERS = ("hungarian", "fifo", "auction")


def lifelong_methods() -> list[tuple[str, Callable[[], Any]]]:
    """(name, factory) of the demo's lifelong rows: the scripted nearest-task controller, each
    dispatcher of :data:`LIFELONG_DISPATCHERS` with its default driver, Hungarian with
    :class:`allocator.SafeDriver` (no overlaps), and every learned policy whose lifelong
    weights ship (``allocator/weights/lifelong``), shielded."""
    import allocator

    makers: list[tuple[str, Callable[[], Any]]] = [("nearest-task", NearestTaskController)]
    makers += [(name, lambda n=name: allocator.make(n)) for name in LIFELONG_DISPATCHERS]
    makers.append(("hungarian + SafeDriver",
                   lambda: allocator.HungarianDispatcher(driver=allocator.SafeDriver())))
    for name in _shipped_families(lifelong=True):
        makers.append((f"{name} (shielded)", lambda n=name: allocator.make(
            n, scenario=LIFELONG_FLOOR, weights="auto", shield=True)))
    return makers


def _shipped_families(lifelong: bool) -> list[str]:
    """The ``<algo>-<reward>`` names whose any-N weights ship (``lifelong``: the lifelong ones,
    ``allocator/weights/lifelong``; else ``allocator/weights/any``)."""
    from allocator.learned import ALGOS, REWARDS, TAUGHT, any_n_weights_path

    return [f"{a}-{r}" for a in ALGOS for r in REWARDS + TAUGHT.get(a, ())
            if any_n_weights_path(a, r, lifelong=lifelong).is_file()]


def run_lifelong(out: Path, steps: int, seed: int) -> list[dict[str, Any]]:
    """The lifelong row of the demo: every :func:`lifelong_methods` entry on
    :data:`LIFELONG_FLOOR` for ``steps`` steps, the same orders for all; writes
    ``table_lifelong.md`` and ``lifelong_throughput.png`` (throughput and waits over time) to
    ``out``."""
    rows, runs = [], {}
    from allocator.learned import scenario_to_run  # a taught family: its own view

    for name, make in lifelong_methods():
        ctl = make()
        m = sim.evaluate_lifelong(ctl, scenario_to_run(ctl, LIFELONG_FLOOR), steps=steps,
                                  seed=seed)
        runs[name] = m
        rows.append({"floor": LIFELONG_FLOOR, "method": name, "steps": steps,
                     "throughput": m.throughput, "bound": m.throughput_bound,
                     "wait_p95": m.wait_p95, "lost": m.lost,
                     "overlaps": m.collisions_per_1000, "seconds": m.seconds})
        print(f"  {LIFELONG_FLOOR} {name:24s} {m.throughput:6.1f} deliveries / 1000 steps  "
              f"(bound {m.throughput_bound:.0f}; p95 wait {m.wait_p95:.0f} steps; "
              f"{m.collisions_per_1000:.0f} overlapping pairs / 1000 steps; {m.seconds:.1f} s)")
    atomic_write_text(out / "table_lifelong.md", format_lifelong_table(rows) + "\n")
    sim.plot_lifelong(runs, path=out / "lifelong_throughput.png",
                      title=f"{LIFELONG_FLOOR}, {steps} steps, seed {seed}")
    return rows


def format_lifelong_table(rows: list[dict[str, Any]]) -> str:
    """A Markdown table of the demo's lifelong rows."""
    return _markdown(
        ["floor", "method", "steps", "deliveries / 1000 steps", "bound", "p95 wait (steps)",
         "lost", "overlapping pairs / 1000 steps", "s"],
        [[r["floor"], r["method"], str(r["steps"]), f"{r['throughput']:.1f}",
          f"{r['bound']:.0f}", f"{r['wait_p95']:.0f}", str(r["lost"]), f"{r['overlaps']:.0f}",
          f"{r['seconds']:.1f}"] for r in rows])


SCALE_SCENARIO = "20v20"
SCALE_EPISODES = 50
"""The scale headline's episodes by default (one 20v20 episode's time swings by several
steps: over 20 episodes a policy's time against Hungarian's moves by about a tenth)."""


def scale_methods() -> list[tuple[str, Callable[[], Any]]]:
    """(name, factory) of the demo's scale headline on :data:`SCALE_SCENARIO`: Hungarian, the
    auction at the scenario's sensing range, and every learned family whose any-N weights ship
    (``allocator/weights/any``), plain, shielded, and shielded with the detours that see
    parked AGVs as discs (``detour="discs"``)."""
    import allocator

    rng = float(sim.get_scenario(SCALE_SCENARIO).sensing_range)
    makers: list[tuple[str, Callable[[], Any]]] = [
        ("hungarian", lambda: allocator.make("hungarian")),
        (f"auction (range {rng:g})", lambda: allocator.make("auction", comm_range=rng))]
    guards = [("", {}), (", shielded", dict(shield=True)),
              (", shielded + discs detour", dict(shield=True, detour="discs"))]
    for name in _shipped_families(lifelong=False):
        for label, guard in guards:
            makers.append((f"{name} (any-N{label})", lambda n=name, g=guard: allocator.make(
                n, scenario=SCALE_SCENARIO, weights="auto", **g)))
    return makers


def run_scale(out: Path, episodes: int, seed: int) -> list[dict[str, Any]]:
    """The scale headline: every :func:`scale_methods` entry on ``episodes`` episodes of
    :data:`SCALE_SCENARIO` (the same scenes for all); writes ``table_scale.md`` to ``out``.
    The whole table, N = 3 to 100 and the lifelong floors: ``benchmarks/scale_table.py``."""
    from allocator.learned import scenario_to_run  # a taught family: the whole scene

    rows: list[dict[str, Any]] = []
    hungarian_time = float("nan")
    for name, make in scale_methods():
        solver = make()
        scenario = sim.get_scenario(scenario_to_run(solver, SCALE_SCENARIO))
        m = sim.evaluate(solver, scenario, episodes=episodes, seed=seed)
        if name == "hungarian":
            hungarian_time = m.avg_time
        rows.append({"scenario": SCALE_SCENARIO, "method": name,
                     "view": f"{scenario.k_tasks}:{scenario.k_agents}", "response_rate":
                     m.response_rate, "avg_time": m.avg_time,
                     "time_vs_hungarian": m.avg_time / hungarian_time, "overlaps": m.collisions,
                     "seconds": m.seconds})
        print(f"  {SCALE_SCENARIO} {name:30s} response {m.response_rate:7.2%}  time "
              f"{m.avg_time:5.1f} ({m.avg_time / hungarian_time:.2f}x Hungarian)  "
              f"{m.collisions:.1f} overlapping pairs / episode  ({m.seconds:.1f} s)")
    atomic_write_text(out / "table_scale.md", format_scale_table(rows) + "\n")
    return rows


def format_scale_table(rows: list[dict[str, Any]]) -> str:
    """A Markdown table of the demo's scale headline."""
    return _markdown(
        ["scenario", "method", "view (tasks:AGVs)", "response rate", "avg time",
         "time / Hungarian", "overlapping pairs / episode", "s"],
        [[r["scenario"], r["method"], r.get("view", ""), f"{r['response_rate']:.2%}",
          f"{r['avg_time']:.1f}",
          f"{r['time_vs_hungarian']:.2f}", f"{r['overlaps']:.1f}", f"{r['seconds']:.1f}"]
         for r in rows])


def run_demo(args: argparse.Namespace) -> int:
    """Evaluate, print the table, write figures under ``args.out``.

    Parameters
    ----------
    args : argparse.Namespace
        ``episodes`` (a positive int, or None: 30 with ``quick``, else 300), ``quick``,
        ``out`` (the folder), ``seed``, ``scale_episodes`` (the scale headline's 20v20
        episodes; None: :data:`SCALE_EPISODES`, 4 with ``quick``; 0 skips it) and
        ``lifelong_steps`` (None: 500, 200 with ``quick``; 0 skips the lifelong row).

    Returns
    -------
    int
        The exit status, 0.

    Raises
    ------
    ValueError
        If ``args.episodes`` is not None and not a positive integer.
    """
    episodes = args.episodes
    if episodes is None:
        episodes = 30 if args.quick else 300
    elif isinstance(episodes, bool) or not isinstance(episodes, int) or episodes < 1:
        raise ValueError(f"episodes must be a positive integer, got {episodes!r}")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rows, results = [], {}
    t0 = time.perf_counter()
    methods = {scenario: list(available_methods(scenario)) for scenario in ("3v3", "6v6")}
    for scenario, available in methods.items():
        for name, factory in available:
            metrics = sim.evaluate(factory(), scenario, episodes=episodes, seed=args.seed)
            results[(scenario, name)] = metrics
            rows.append({"scenario": scenario, "method": name, **metrics.as_dict(),
                         "seconds": metrics.seconds})
            print(f"  {scenario} {name:18s} response {metrics.response_rate:7.2%}  "
                  f"time {metrics.avg_time:5.1f}  ({metrics.seconds:.1f} s)")
    table = format_table(rows)
    print()
    print(table)
    atomic_write_text(out / "table.md", table + "\n")
    for scenario, available in methods.items():
        _claims_figure(results, scenario, out / f"claims_per_episode_{scenario}.png")
        for name, factory in available:
            if name in ("nearest-task", "hungarian", "bicnet-ipf", "maddpg-ipf"):
                sim.render_episode(factory(), scenario, seed=args.seed,
                                   path=out / f"episode_{scenario}_{name}.gif",
                                   still=out / f"episode_{scenario}_{name}.png", title=name)
    scale_episodes = getattr(args, "scale_episodes", None)
    if scale_episodes is None:
        scale_episodes = 4 if args.quick else SCALE_EPISODES
    if scale_episodes:
        print()
        scale_rows = run_scale(out, episodes=scale_episodes, seed=args.seed)
        print()
        print(format_scale_table(scale_rows))
        print(f"({scale_episodes} episodes, seed {args.seed}: one episode's time swings by "
              "several steps, so few episodes are noisy; every N with up to 200 episodes: "
              "benchmarks/results/scale/taught/, three seeds: docs/learners.md)")
    steps = getattr(args, "lifelong_steps", None)
    if steps is None:
        steps = 200 if args.quick else 500
    if steps:
        lifelong_rows = run_lifelong(out, steps=steps, seed=args.seed)
        print()
        print(format_lifelong_table(lifelong_rows))
    print(f"\nwrote the table, figures and animations to {out}/ "
          f"({time.perf_counter() - t0:.0f} s, {episodes} episodes per method and scenario)")
    return 0
