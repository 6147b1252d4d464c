"""Validation time and response during training, against Hungarian's time (issue 16).

    python benchmarks/time_figure.py --scenario 3v3 \
        --runs paper-budget/bicnet-ipf time/bicnet-ipf-time \
        [--out benchmarks/results/figures/time_3v3.png]

Each ``--runs`` item ``TAG/METHOD`` reads the per-seed training logs
``benchmarks/results/training/<scenario>/TAG/METHOD-s<seed>.csv`` (what
``benchmarks/train_policies.py --tag TAG`` copies there) and draws the mean over seeds and
their range of the validation average time (left) and task response (right), evaluated on
seed 12345; Hungarian's time on the same validation scenes (``sim.evaluate``, 300 episodes)
and 1.15x of it are drawn as horizontal lines.
"""

from __future__ import annotations

import argparse
import csv
from pathlib import Path

import numpy as np

import sim

ROOT = Path(__file__).resolve().parents[1]
TRAINING = ROOT / "benchmarks" / "results" / "training"


def read_runs(scenario: str, item: str) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """``[(episodes, response, time) per seed]`` of the logs of ``TAG/METHOD``.

    Raises
    ------
    ValueError
        If no log matches.
    """
    tag, _, method = item.rpartition("/")
    paths = sorted((TRAINING / scenario / tag).glob(f"{method}-s[0-9]*.csv"))
    runs = []
    for path in paths:
        if not path.stem.removeprefix(f"{method}-s").isdigit():
            continue
        with path.open() as fh:
            rows = [r for r in csv.DictReader(fh) if r.get("eval_response_rate")]
        runs.append(tuple(np.array([float(r[k]) for r in rows]) for k in
                          ("episode", "eval_response_rate", "eval_avg_time")))
    if not runs:
        raise ValueError(f"no training logs {TRAINING / scenario / tag}/{method}-s*.csv")
    return runs


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", default="3v3")
    parser.add_argument("--runs", nargs="+", required=True, metavar="TAG/METHOD")
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)
    import matplotlib

    import allocator

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    hungarian = sim.evaluate(allocator.make("hungarian"), args.scenario, episodes=300,
                             seed=12345).avg_time
    fig, (ax_t, ax_r) = plt.subplots(1, 2, figsize=(11, 3.8))
    for item in args.runs:
        runs = read_runs(args.scenario, item)
        length = min(len(x) for x, _, _ in runs)
        x = runs[0][0][:length]
        for ax, k in ((ax_r, 1), (ax_t, 2)):
            ys = np.stack([r[k][:length] for r in runs])
            line = ax.plot(x, ys.mean(0), label=f"{item} ({len(runs)} seeds)")[0]
            ax.fill_between(x, ys.min(0), ys.max(0), color=line.get_color(), alpha=0.2)
    ax_t.axhline(hungarian, color="k", linewidth=1, label=f"Hungarian {hungarian:.2f}")
    ax_t.axhline(1.15 * hungarian, color="k", linestyle="--", linewidth=1, label="1.15x")
    ax_t.set_ylim(hungarian * 0.9, 25)
    ax_t.set_ylabel("average time, steps (validation)")
    ax_r.set_ylabel("task response rate (validation)")
    ax_r.set_ylim(0.8, 1.005)
    for ax in (ax_t, ax_r):
        ax.set_xlabel("training episodes")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    ax_t.set_title(f"BiCNet, {args.scenario}: time (seed 12345)")
    ax_r.set_title("task response")
    fig.tight_layout()
    out = args.out or ROOT / "benchmarks" / "results" / "figures" / f"time_{args.scenario}.png"
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=120)
    print(out)


if __name__ == "__main__":
    main()
