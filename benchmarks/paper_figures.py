"""The paper's figures from the shipped policies and their training logs.

    python benchmarks/paper_figures.py [--episodes 300] [--seed 0]

Writes PNGs (and GIFs) to ``benchmarks/results/figures/``:

- ``fig8_claims_per_episode_<scenario>.png``: tasks completed per test episode for each reward
  and learner, beside the classical solvers (the paper's Fig. 8);
- ``fig9_training_<scenario>.png``: task response during training for the three rewards, mean
  and range over the training seeds (Fig. 9), from ``benchmarks/results/training/``, each
  reward's final response in the paper's table drawn as a dashed line of its colour;
  ``--tag paper-budget`` draws the runs at the paper's budgets
  (``training/<scenario>/paper-budget/``) as ``fig9_training_<scenario>_paper-budget.png``;
- ``fig10_preferences_<scenario>.png``: for MADDPG-IPF and BiCNet-IPF, how often AGV i claims
  task j, and how often it claims its k-th nearest task (Figs. 10-12);
- ``fig3_ipf_field.png``: one AGV's information potential field in a ``3v3`` scene and in the
  warehouse (Figs. 3-4);
- ``episode_<scenario>_<method>.gif``: an animated test episode of each kind of method.
"""

from __future__ import annotations

import argparse
import csv
import re
from collections import defaultdict
from pathlib import Path

import numpy as np
import torch

import allocator
import sim
from allocator.paper import PAPER_TABLES
from sim.evaluate import run_episodes
from sim.io import atomic_save
from sim.render import _plt

RESULTS = Path(__file__).parent / "results"
REWARDS = ("minidist", "greedy", "ipf")
ALGOS = ("maddpg", "bicnet")


def _save(fig, path: Path) -> None:
    atomic_save(lambda p: fig.savefig(p, dpi=120, format="png"), path)
    _plt().close(fig)
    print(f"wrote {path}")


def claims_figure(scenario: str, episodes: int, seed: int, out: Path) -> None:
    """Fig. 8: the distribution of tasks completed per episode."""
    plt = _plt()
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.6), sharey=True)
    groups = [("MADDPG", [f"maddpg-{r}" for r in REWARDS]),
              ("BiCNet", [f"bicnet-{r}" for r in REWARDS]),
              ("classical", ["hungarian", "greedy"])]
    m_tasks = sim.get_scenario(scenario).num_tasks
    for ax, (title, methods) in zip(axes, groups, strict=True):
        width = 0.8 / len(methods)
        for k, method in enumerate(methods):
            solver = (allocator.make(method) if method in ("hungarian", "greedy")
                      else allocator.make(method, scenario=scenario))
            m = sim.evaluate(solver, scenario, episodes=episodes, seed=seed)
            frac = np.bincount(m.claims_per_episode, minlength=m_tasks + 1) / m.episodes
            x = np.arange(m_tasks + 1) + (k - (len(methods) - 1) / 2) * width
            ax.bar(x, frac, width, label=f"{method} ({m.response_rate:.1%})")
        ax.set_title(f"{title}, {scenario}")
        ax.set_xlabel("tasks completed in the episode")
        ax.set_xticks(range(m_tasks + 1))
        ax.legend(fontsize=7, loc="upper left")
    axes[0].set_ylabel(f"fraction of {episodes} test episodes")
    fig.tight_layout()
    _save(fig, out / f"fig8_claims_per_episode_{scenario}.png")


def read_curves(scenario: str, training: Path,
                tag: str = "") -> dict[str, list[tuple[np.ndarray, np.ndarray]]]:
    """``method -> [(episodes, eval response rate) per seed]`` from the training logs."""
    curves: dict[str, list[tuple[np.ndarray, np.ndarray]]] = defaultdict(list)
    pattern = re.compile(r"^(\w+-\w+)-s(\d+)\.csv$")
    for path in sorted((training / scenario / tag).glob("*.csv")):
        match = pattern.match(path.name)
        if not match:
            continue
        with path.open() as fh:
            rows = [r for r in csv.DictReader(fh) if r.get("eval_response_rate")]
        if rows:
            x = np.array([float(r["episode"]) for r in rows])
            y = np.array([float(r["eval_response_rate"]) for r in rows])
            curves[match.group(1)].append((x, y))
    return curves


def training_figure(scenario: str, training: Path, out: Path, tag: str = "") -> None:
    """Fig. 9: evaluation task response during training, per reward, mean and seed range,
    beside each reward's final response in the paper's table (dashed)."""
    curves = read_curves(scenario, training, tag)
    if not curves:
        print(f"no training logs under {training / scenario / tag}; skipping Fig. 9 for "
              f"{scenario}")
        return
    plt = _plt()
    fig, axes = plt.subplots(1, 2, figsize=(11, 3.8), sharey=True)
    for ax, algo in zip(axes, ALGOS, strict=True):
        for reward in REWARDS:
            runs = curves.get(f"{algo}-{reward}")
            if not runs:
                continue
            length = min(len(x) for x, _ in runs)
            x = runs[0][0][:length]
            ys = np.stack([y[:length] for _, y in runs])
            line = ax.plot(x, ys.mean(0), label=f"{reward} ({len(runs)} seed(s))")[0]
            if len(runs) > 1:
                ax.fill_between(x, ys.min(0), ys.max(0), color=line.get_color(), alpha=0.2)
            paper = PAPER_TABLES.get(scenario, {}).get(f"{algo}-{reward}")
            if paper:
                ax.axhline(paper[0], color=line.get_color(), linestyle="--", linewidth=1)
        ax.set_title(f"{'MADDPG' if algo == 'maddpg' else 'BiCNet'}, {scenario}"
                     + (f" ({tag})" if tag else "") + "; dashed: the paper's table")
        ax.set_xlabel("training episodes")
        ax.grid(alpha=0.3)
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=8)
    axes[0].set_ylabel("task response rate (validation)")
    fig.tight_layout()
    _save(fig, out / f"fig9_training_{scenario}{'_' + tag if tag else ''}.png")


@torch.no_grad()
def preference_counts(controller, scenario: str, episodes: int, seed: int) -> tuple[np.ndarray,
                                                                                     np.ndarray]:
    """``(by_index, by_rank)``: (N, M) fractions of episodes in which AGV i claimed task j, and
    in which it claimed its k-th nearest task at the start (k = 0 the nearest)."""
    env = sim.AGVEnv(sim.get_scenario(scenario), num_envs=episodes, seed=seed)
    rec = run_episodes(env, controller, seed=seed, record=True)
    start = rec["agent_pos"][0]  # (E, N, 2)
    tasks = env.task_pos.numpy()  # (E, M, 2)
    task_of_agent = rec["task_of_agent"]  # (E, N)
    n, m = task_of_agent.shape[1], tasks.shape[1]
    rank = np.argsort(np.argsort(np.linalg.norm(start[:, :, None] - tasks[:, None], axis=-1),
                                 axis=-1), axis=-1)  # (E, N, M): rank of task j for AGV i
    by_index = np.zeros((n, m))
    by_rank = np.zeros((n, m))
    e_idx, a_idx = np.nonzero(task_of_agent >= 0)
    t_idx = task_of_agent[e_idx, a_idx]
    np.add.at(by_index, (a_idx, t_idx), 1)
    np.add.at(by_rank, (a_idx, rank[e_idx, a_idx, t_idx]), 1)
    return by_index / episodes, by_rank / episodes


def preference_figure(scenario: str, episodes: int, seed: int, out: Path) -> None:
    """Figs. 10-12: agent-to-task preferences of MADDPG-IPF and BiCNet-IPF."""
    plt = _plt()
    fig, axes = plt.subplots(2, 2, figsize=(10, 8.5), constrained_layout=True)
    for row, method in enumerate(("maddpg-ipf", "bicnet-ipf")):
        by_index, by_rank = preference_counts(allocator.make(method, scenario=scenario),
                                              scenario, episodes, seed)
        for col, (mat, xlabel) in enumerate(((by_index, "task index j"),
                                             (by_rank, "k-th nearest task at the start"))):
            ax = axes[row, col]
            im = ax.imshow(mat, vmin=0, vmax=1, cmap="viridis")
            for (i, j), v in np.ndenumerate(mat):
                ax.text(j, i, f"{v:.0%}", ha="center", va="center", fontsize=7,
                        color="w" if v < 0.6 else "k")
            ax.set_xticks(range(mat.shape[1]))
            ax.set_yticks(range(mat.shape[0]))
            ax.set_xlabel(xlabel)
            ax.set_ylabel("AGV i")
            ax.set_title(f"{method}, {scenario}: P(AGV i claims ...)", fontsize=9)
    fig.colorbar(im, ax=axes, shrink=0.6)
    _save(fig, out / f"fig10_preferences_{scenario}.png")


def field_figure(out: Path, seed: int) -> None:
    """Figs. 3-4: an AGV's information potential field in an open and a shelved scene."""
    from sim.ipf import ipf_field
    from sim.render import plot_field

    plt = _plt()
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.6), gridspec_kw={"width_ratios": [1, 1.4]})
    for ax, scenario in zip(axes, ("3v3", "warehouse"), strict=True):
        env = sim.make_env(scenario, num_envs=1, seed=seed)
        agents, tasks = env.agent_pos[0].numpy(), env.task_pos[0].numpy()
        field = ipf_field(agents, tasks, agent=0, world=env.world)
        plot_field(field, agents, tasks, agent=0, ax=ax)
        ax.set_title(f"IPF of AGV 0, {scenario}")
    fig.tight_layout()
    _save(fig, out / "fig3_ipf_field.png")


def animations(out: Path, seed: int) -> None:
    """An animated test episode of each kind of method on both paper scenarios."""
    for scenario in ("3v3", "6v6"):
        for method in ("hungarian", "greedy", "bicnet-ipf", "maddpg-ipf"):
            solver = (allocator.make(method) if method in ("hungarian", "greedy")
                      else allocator.make(method, scenario=scenario))
            path = out / f"episode_{scenario}_{method}.gif"
            sim.render_episode(solver, scenario, seed=seed, path=path, title=method)
            print(f"wrote {path}")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=300, help="test episodes per method")
    parser.add_argument("--seed", type=int, default=0, help="seed of the test episodes")
    parser.add_argument("--out", type=Path, default=RESULTS / "figures")
    parser.add_argument("--training", type=Path, default=RESULTS / "training",
                        help="folder of the training logs (<scenario>/<algo>-<reward>-s<k>.csv)")
    parser.add_argument("--tag", default="", help="training logs of tagged runs "
                        "(training/<scenario>/<tag>/, e.g. paper-budget): Fig. 9 only")
    parser.add_argument("--only", nargs="+", default=["claims", "training", "preferences",
                                                      "field", "animations"])
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    for scenario in ("3v3", "6v6"):
        if "claims" in args.only:
            claims_figure(scenario, args.episodes, args.seed, args.out)
        if "training" in args.only:
            training_figure(scenario, args.training, args.out, args.tag)
        if "preferences" in args.only:
            preference_figure(scenario, args.episodes, args.seed, args.out)
    if "field" in args.only:
        field_figure(args.out, args.seed)
    if "animations" in args.only:
        animations(args.out, args.seed)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
