"""The paper's Tables I and II, beside the classical solvers, on fixed test episodes.

    python benchmarks/paper_tables.py [--episodes 300] [--seed 0] [--scenarios 3v3 6v6]

For each scenario: the six learned methods (MADDPG and BiCNet with MiniDist, Greedy and IPF)
from the weights that ship in ``allocator/weights/``, plus ``hungarian`` (with OMPL paths and
ORCA avoidance) and ``greedy``. Each learned method is scored with its shipped (best-on-
validation) seed, and, where the weights of several training seeds ship in
``allocator/weights/<scenario>/seeds/``, as the mean and 95% t-interval over those seeds. The
test episodes (``--seed``, default 0) are never the validation episodes used to pick the seed
(``learners`` evaluates on seed 12345). The runs at the paper's training budgets (30k episodes
on 3v3; 50k for MADDPG and 90k for BiCNet on 6v6; ``benchmarks/train_policies.py --tag
paper-budget``) ship their seeds in ``allocator/weights/<scenario>/paper-budget/seeds/`` and are
scored beside the 5k-episode ones, as the mean and 95% t-interval over their seeds. Writes
``paper_tables.md`` and ``paper_tables.csv`` to
``benchmarks/results/`` (atomically).
"""

from __future__ import annotations

import argparse
import csv
import datetime
import io
import math
import re
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from provenance import recorded_command
from scipy import stats

import allocator
import sim
from allocator.paper import PAPER_TABLES
from sim.io import atomic_write_text

RESULTS = Path(__file__).parent / "results"
LEARNED = [f"{a}-{r}" for a in ("maddpg", "bicnet") for r in ("minidist", "greedy", "ipf")]
CLASSICAL = ["hungarian", "greedy"]
BUDGET_TAG = "paper-budget"
"""The folder of the runs at the paper's training budgets (``train_policies.py --tag``)."""


@dataclass
class Row:
    """One method on one scenario."""

    scenario: str
    method: str
    shipped: sim.Metrics
    seeds: list[sim.Metrics] = field(default_factory=list)
    budget: list[sim.Metrics] = field(default_factory=list)
    """The seeds trained at the paper's budget (empty until they ship)."""

    def interval(self, attr: str, budget: bool = False) -> tuple[float, float]:
        """Mean and 95% t half-width of ``attr`` over the seeds (NaN half-width if < 2);
        ``budget``: over the paper-budget seeds (NaN, NaN if none)."""
        if budget:
            values = np.array([getattr(m, attr) for m in self.budget])
            if not len(values):
                return float("nan"), float("nan")
        else:
            values = np.array([getattr(m, attr) for m in self.seeds]
                              or [getattr(self.shipped, attr)])
        if len(values) < 2:
            return float(values.mean()), float("nan")
        half = stats.t.ppf(0.975, len(values) - 1) * values.std(ddof=1) / math.sqrt(len(values))
        return float(values.mean()), float(half)


def seed_checkpoints(scenario: str, method: str, tag: str = "") -> list[Path]:
    """The per-seed weights shipped for ``method`` on ``scenario`` (under ``tag``), by seed."""
    folder = Path(allocator.__file__).parent / "weights" / scenario / tag / "seeds"
    pattern = re.compile(rf"^{re.escape(method)}-s(\d+)\.safetensors$")
    found = [(int(m.group(1)), p) for p in folder.glob("*.safetensors")
             if (m := pattern.match(p.name))]
    return [p for _, p in sorted(found)]


def evaluate_method(scenario: str, method: str, episodes: int, seed: int) -> Row:
    """Score one method: its shipped solver and, for learned ones, every shipped seed."""
    if method in CLASSICAL:
        solver = allocator.make(method)
        return Row(scenario, method, sim.evaluate(solver, scenario, episodes=episodes, seed=seed))
    shipped = sim.evaluate(allocator.make(method, scenario=scenario), scenario,
                           episodes=episodes, seed=seed)
    seeds, budget = (
        [sim.evaluate(allocator.make(method, scenario=scenario, checkpoint=path), scenario,
                      episodes=episodes, seed=seed)
         for path in seed_checkpoints(scenario, method, tag)]
        for tag in ("", BUDGET_TAG)
    )
    return Row(scenario, method, shipped, seeds, budget)


def _fmt(mean: float, half: float, pct: bool = False) -> str:
    if pct:
        return f"{mean:.2%}" + ("" if math.isnan(half) else f" ± {half:.2%}")
    return f"{mean:.1f}" + ("" if math.isnan(half) else f" ± {half:.1f}")


def markdown(rows: list[Row], header: str) -> str:
    """The tables as Markdown, one per scenario."""
    out = [header, ""]
    for scenario in dict.fromkeys(r.scenario for r in rows):
        part = [r for r in rows if r.scenario == scenario]
        ref = next((r.shipped.avg_time for r in part if r.method == "hungarian"), float("nan"))
        out += [
            f"## {scenario}",
            "",
            "| method | response rate (shipped) | over seeds | paper | avg reward (shipped) "
            "| paper | avg time (shipped) | over seeds | paper | time / Hungarian "
            "| collisions / episode | seeds | paper budget: response over seeds "
            "| paper budget: time over seeds | paper-budget seeds |",
            "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
        ]
        for r in part:
            paper = PAPER_TABLES.get(scenario, {}).get(r.method)
            p_rate, p_rew, p_time = (
                (f"{paper[0]:.2%}", f"{paper[1]:.1f}", f"{paper[2]:.1f}") if paper else ("-",) * 3
            )
            m = r.shipped
            out.append(
                f"| {r.method} | {m.response_rate:.2%} "
                f"| {_fmt(*r.interval('response_rate'), pct=True) if r.seeds else '-'} "
                f"| {p_rate} | {m.avg_reward:.1f} | {p_rew} | {m.avg_time:.2f} "
                f"| {_fmt(*r.interval('avg_time')) if r.seeds else '-'} | {p_time} "
                f"| {m.avg_time / ref:.2f} | {m.collisions:.2f} | {len(r.seeds) or '-'} "
                f"| {_fmt(*r.interval('response_rate', True), pct=True) if r.budget else '-'} "
                f"| {_fmt(*r.interval('avg_time', True)) if r.budget else '-'} "
                f"| {len(r.budget) or '-'} |"
            )
        out.append("")
    return "\n".join(out)


def csv_text(rows: list[Row]) -> str:
    """One CSV line per method and scenario, with the seed intervals and the paper's numbers."""
    buf = io.StringIO()
    writer = csv.writer(buf)
    writer.writerow([
        "scenario", "method", "response_rate", "avg_reward", "avg_time", "avg_time_finished",
        "collisions", "response_rate_seed_mean", "response_rate_seed_ci95", "avg_time_seed_mean",
        "avg_time_seed_ci95", "seeds", "paper_response_rate", "paper_avg_reward",
        "paper_avg_time", "time_ratio_to_hungarian", "budget_response_rate_mean",
        "budget_response_rate_ci95", "budget_avg_time_mean", "budget_avg_time_ci95",
        "budget_seeds",
    ])
    for r in rows:
        ref = next((x.shipped.avg_time for x in rows
                    if x.scenario == r.scenario and x.method == "hungarian"), float("nan"))
        paper = PAPER_TABLES.get(r.scenario, {}).get(r.method, (float("nan"),) * 3)
        m = r.shipped
        writer.writerow([
            r.scenario, r.method, m.response_rate, m.avg_reward, m.avg_time, m.avg_time_finished,
            m.collisions, *r.interval("response_rate"), *r.interval("avg_time"), len(r.seeds),
            *paper, m.avg_time / ref, *r.interval("response_rate", True),
            *r.interval("avg_time", True), len(r.budget),
        ])
    return buf.getvalue()


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=300, help="test episodes (paper: 300)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the test episodes")
    parser.add_argument("--scenarios", nargs="+", default=["3v3", "6v6"])
    parser.add_argument("--methods", nargs="+", default=LEARNED + CLASSICAL)
    parser.add_argument("--out", type=Path, default=RESULTS, help="output folder")
    args = parser.parse_args(argv)
    rows: list[Row] = []
    start = time.perf_counter()
    try:
        for scenario in args.scenarios:
            for method in args.methods:
                row = evaluate_method(scenario, method, args.episodes, args.seed)
                rows.append(row)
                print(f"{scenario} {method:16s} response {row.shipped.response_rate:7.2%} "
                      f"time {row.shipped.avg_time:5.2f} seeds {len(row.seeds)}", flush=True)
    except (FileNotFoundError, ValueError) as err:
        print(f"paper_tables: {err}", file=sys.stderr)
        return 2
    command = recorded_command(__file__, argv)
    header = (
        "# The paper's Tables I and II, reproduced beside the classical solvers\n\n"
        f"`{command.strip()}`, {datetime.date.today()}: {args.episodes} test episodes per "
        f"method, test seed {args.seed} (validation, used to pick the shipped seed, is seed "
        f"12345), {time.perf_counter() - start:.0f} s. Response rate = claimed / generated "
        "tasks; average reward = mean episode sum of R_t = -(sum of task-to-nearest-AGV "
        "distances) - overlapping pairs; average time = steps until every task is claimed, an "
        "unfinished episode counting the step limit. 'over seeds' is the mean ± 95% t-interval "
        "over the training seeds that ship (5000 episodes each); 'paper budget' the same over "
        "the seeds "
        f"trained at the paper's budgets (`allocator/weights/<scenario>/{BUDGET_TAG}/seeds/`, "
        "each reward with its own settings from `benchmarks/results/training/reward_search.md`;"
        " '-': not trained yet); 'time / Hungarian' divides by the Hungarian plan's "
        "average time on the same episodes."
    )
    args.out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(args.out / "paper_tables.md", markdown(rows, header))
    atomic_write_text(args.out / "paper_tables.csv", csv_text(rows))
    print(markdown(rows, header))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
