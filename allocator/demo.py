"""``agv demo``: every available method on the paper's scenarios, the table beside the paper's
numbers, and the figures (tasks completed per episode, preference matrices, animations); then
the dispatchers in lifelong operation on a warehouse floor (throughput over time)."""

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
           "format_lifelong_table"]


def available_methods(scenario: str) -> Iterator[tuple[str, Callable[[], Any]]]:
    """Yield ``(name, factory)`` for every method that can run on ``scenario`` here: the
    scripted nearest-task baseline, the classical allocators, and each learned allocator whose
    weights ship for the scenario (the others are reported as missing)."""
    import allocator

    yield "nearest-task", NearestTaskController
    registry = allocator.ALLOCATORS
    for name in ("hungarian", "greedy"):
        if name in registry:
            yield name, (lambda n=name: allocator.make(n))
    for name in sorted(n for n in registry if n.split("-")[0] in ("maddpg", "bicnet")):
        try:
            solver = allocator.make(name, scenario=scenario)
        except (ValueError, FileNotFoundError) as err:
            print(f"  [{scenario}] {name}: skipped ({err})")
            continue
        yield name, (lambda s=solver: s)


def format_table(rows: list[dict[str, Any]]) -> str:
    """A Markdown table of evaluation rows, the paper's numbers beside ours."""
    head = ("| scenario | method | response rate | paper | avg reward | paper | avg time | paper "
            "| collisions/ep | eval s |")
    lines = [head, "|" + "---|" * 10]
    for r in rows:
        paper = PAPER_TABLES.get(r["scenario"], {}).get(r["method"])
        pr, pw, pt = ("-", "-", "-")
        if paper:
            pr, pw, pt = f"{paper[0]:.2%}", f"{paper[1]:.1f}", f"{paper[2]:.1f}"
        lines.append(
            f"| {r['scenario']} | {r['method']} | {r['response_rate']:.2%} | {pr} "
            f"| {r['avg_reward']:.1f} | {pw} | {r['avg_time']:.1f} | {pt} "
            f"| {r['collisions']:.2f} | {r['seconds']:.1f} |"
        )
    return "\n".join(lines)


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


def run_lifelong(out: Path, steps: int, seed: int) -> list[dict[str, Any]]:
    """The lifelong row of the demo: each dispatcher (and the scripted nearest-task
    controller) on :data:`LIFELONG_FLOOR` for ``steps`` steps, the same orders for all;
    writes ``table_lifelong.md`` and ``lifelong_throughput.png`` (throughput and waits over
    time) to ``out``."""
    import allocator

    rows, runs = [], {}
    makers: list[tuple[str, Callable[[], Any]]] = [("nearest-task", NearestTaskController)]
    makers += [(name, lambda n=name: allocator.make(n)) for name in LIFELONG_DISPATCHERS]
    for name, make in makers:
        m = sim.evaluate_lifelong(make(), LIFELONG_FLOOR, steps=steps, seed=seed)
        runs[name] = m
        rows.append({"floor": LIFELONG_FLOOR, "method": name, "steps": steps,
                     "throughput": m.throughput, "bound": m.throughput_bound,
                     "wait_p95": m.wait_p95, "lost": m.lost, "seconds": m.seconds})
        print(f"  {LIFELONG_FLOOR} {name:18s} {m.throughput:6.1f} deliveries / 1000 steps  "
              f"(bound {m.throughput_bound:.0f}; p95 wait {m.wait_p95:.0f} steps; "
              f"{m.seconds:.1f} s)")
    atomic_write_text(out / "table_lifelong.md", format_lifelong_table(rows) + "\n")
    sim.plot_lifelong(runs, path=out / "lifelong_throughput.png",
                      title=f"{LIFELONG_FLOOR}, {steps} steps, seed {seed}")
    return rows


def format_lifelong_table(rows: list[dict[str, Any]]) -> str:
    """A Markdown table of the demo's lifelong rows."""
    lines = ["| floor | method | steps | deliveries / 1000 steps | bound | p95 wait (steps) | "
             "lost | s |", "|" + "---|" * 8]
    for r in rows:
        lines.append(f"| {r['floor']} | {r['method']} | {r['steps']} | {r['throughput']:.1f} "
                     f"| {r['bound']:.0f} | {r['wait_p95']:.0f} | {r['lost']} | "
                     f"{r['seconds']:.1f} |")
    return "\n".join(lines)


def run_demo(args: argparse.Namespace) -> int:
    """Evaluate, print the table, write figures under ``args.out``.

    Parameters
    ----------
    args : argparse.Namespace
        ``episodes`` (a positive int, or None: 30 with ``quick``, else 300), ``quick``,
        ``out`` (the folder), ``seed`` and ``lifelong_steps`` (None: 500, 200 with
        ``quick``; 0 skips the lifelong row).

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
