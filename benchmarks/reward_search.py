"""Each reward's own hyperparameters, chosen from the recorded search (issue 16).

    python benchmarks/reward_search.py runs/sweeps/reward-search-maddpg \
        runs/sweeps/reward-search-maddpg-base runs/sweeps/reward-search-bicnet \
        runs/sweeps/reward-search-bicnet-base

reads the sweeps' ``summary.csv`` (one row per configuration, metrics averaged over the seeds;
``benchmarks/sweeps/reward-search-*.toml``) and, for every algorithm and reward, picks the
configuration with the highest mean validation response (ties: the lower mean time). It writes

- ``benchmarks/results/training/reward_search.json``: the chosen learner settings per
  ``<algo>-<reward>`` (what ``benchmarks/train_policies.py --settings`` passes to
  ``agv train --set``), with the validation figures and the sweeps they came from;
- ``benchmarks/results/training/reward_search.md``: every configuration tried, per method;
- ``benchmarks/results/training/reward_search/<sweep>.csv``: each sweep's ``trials.csv``.

Validation is the training's evaluation scenes (seed 12345); the test scenes of
``benchmarks/paper_tables.py`` (seed 0) are never looked at.
"""

from __future__ import annotations

import argparse
import csv
import json
import shutil
import sys
import time
from pathlib import Path

from sim.io import atomic_save, atomic_write_text

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "benchmarks" / "results" / "training"

RUN_FIELDS = ("algo", "reward", "scenario", "episodes", "eval_every", "eval_episodes",
              "checkpoint_every", "tensorboard", "seeds")
"""Columns of ``summary.csv`` that describe the run, not the learner."""


def _number(text: str) -> int | float | str:
    for cast in (int, float):
        try:
            return cast(text)
        except ValueError:
            pass
    return text


def read_summary(folder: Path) -> list[dict[str, str]]:
    """The rows of one sweep's ``summary.csv``, each tagged with the sweep's folder name.

    Raises
    ------
    ValueError
        If the folder holds no ``summary.csv`` (the sweep has finished no trial).
    """
    path = folder / "summary.csv"
    if not path.is_file():
        raise ValueError(f"{folder} holds no summary.csv: run the sweep first "
                         "(agv sweep benchmarks/sweeps/reward-search-*.toml)")
    with path.open() as fh:
        rows = list(csv.DictReader(fh))
    for row in rows:
        row["sweep"] = folder.name
    return rows


def settings_of(row: dict[str, str]) -> dict[str, int | float | str]:
    """The learner settings of a summary row (every column before the metrics)."""
    out: dict[str, int | float | str] = {}
    for key, value in row.items():
        if key == "seeds":
            break
        if key not in RUN_FIELDS:
            out[key] = _number(value)
    return out


def choose(rows: list[dict[str, str]]) -> dict[str, dict]:
    """Per ``<algo>-<reward>``, the row with the best mean validation response."""
    by_method: dict[str, list[dict[str, str]]] = {}
    for row in rows:
        by_method.setdefault(f"{row['algo']}-{row['reward']}", []).append(row)
    chosen = {}
    for method, candidates in sorted(by_method.items()):
        best = max(candidates, key=lambda r: (float(r["response_rate_mean"]),
                                              -float(r["avg_time_mean"])))
        chosen[method] = {
            "settings": settings_of(best),
            "validation_response": float(best["response_rate_mean"]),
            "validation_time": float(best["avg_time_mean"]),
            "seeds": int(best["seeds"]),
            "scenario": best["scenario"],
            "episodes": int(best["episodes"]),
            "sweep": best["sweep"],
            "candidates": len(candidates),
        }
    return chosen


def table(rows: list[dict[str, str]], chosen: dict[str, dict], command: str) -> str:
    """Every configuration tried, per method, the chosen one marked (Markdown)."""
    keys = list(settings_of(rows[0]))
    lines = ["# Each reward's own hyperparameters (issue 16)", "",
             f"`{command}`, "
             + time.strftime("%Y-%m-%d") + ". Every configuration of the searches "
             "(`benchmarks/sweeps/reward-search-*.toml`: 3v3, 3000 episodes on the fast "
             "preset's learner, seeds 0 and 1), scored by the mean validation response "
             "(300 scenes of seed 12345, the last evaluation); the chosen one per method "
             "is marked. The test scenes (seed 0) were not used.", ""]
    for method in chosen:
        algo, reward = method.split("-")
        lines += [f"## {method}", "",
                  "| chosen | sweep | " + " | ".join(keys) + " | response (mean ± 95%) | time |",
                  "|---|---|" + "---|" * len(keys) + "---|---|"]
        mine = [r for r in rows if r["algo"] == algo and r["reward"] == reward]
        mine.sort(key=lambda r: -float(r["response_rate_mean"]))
        for r in mine:
            mark = "**yes**" if settings_of(r) == chosen[method]["settings"] else ""
            ci = r["response_rate_ci95"]
            ci = f" ± {float(ci):.3f}" if ci else ""
            lines.append(f"| {mark} | {r['sweep']} | "
                         + " | ".join(str(settings_of(r)[k]) for k in keys)
                         + f" | {float(r['response_rate_mean']):.3f}{ci}"
                         + f" | {float(r['avg_time_mean']):.2f} |")
        lines.append("")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("sweeps", nargs="+", type=Path, help="results folders of the sweeps")
    parser.add_argument("--out", type=Path, default=OUT, help="where the tables go")
    args = parser.parse_args(argv)
    try:
        rows = [row for folder in args.sweeps for row in read_summary(folder)]
    except ValueError as exc:
        print(f"reward_search: {exc}", file=sys.stderr)
        return 2
    chosen = choose(rows)
    command = "python benchmarks/reward_search.py " + " ".join(str(s) for s in args.sweeps)
    record = {"command": command,
              "date": time.strftime("%Y-%m-%d"), "validation_seed": 12345,
              "methods": chosen}
    atomic_write_text(args.out / "reward_search.json", json.dumps(record, indent=2) + "\n")
    atomic_write_text(args.out / "reward_search.md", table(rows, chosen, command) + "\n")
    for folder in args.sweeps:
        trials = folder / "trials.csv"
        if trials.is_file():
            atomic_save(lambda p, s=trials: shutil.copyfile(s, p),
                        args.out / "reward_search" / f"{folder.name}.csv")
    for method, c in chosen.items():
        print(f"{method}: {c['validation_response']:.3f} ({c['sweep']}) {c['settings']}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
