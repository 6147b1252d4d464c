"""Ship the policies a training sweep trained: the step that followed ``benchmarks/sweep.sh``.

    agv sweep benchmarks/sweeps/policies.toml --results runs/sweeps/policies
    python benchmarks/sweeps/ship.py runs/sweeps/policies [runs/sweeps/policies-greedy ...]

For every method (scenario, algorithm, reward) among the finished trials of the given sweeps,
as ``benchmarks/train_policies.py`` does for its own runs:

- copies each seed's best-on-validation policy to
  ``allocator/weights/<scenario>/seeds/<algo>-<reward>-s<seed>.safetensors`` (+ ``.json``);
- ships the seed whose validation task response is highest (ties: lower validation time) as
  ``allocator/weights/<scenario>/<algo>-<reward>.safetensors`` (+ ``.json``);
- copies each seed's ``progress.csv`` to
  ``benchmarks/results/training/<scenario>/<algo>-<reward>-s<seed>.csv``;
- records the sweep, seeds, validation scores and training time in
  ``benchmarks/results/training/<scenario>/<algo>-<reward>.json``.

Every file is written atomically. ``--weights`` and ``--training`` write elsewhere (a dry run).
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "benchmarks"))

from train_policies import validation  # noqa: E402  (a script beside this folder)

from sim.io import atomic_save, atomic_write_text  # noqa: E402


def _copy_policy(src: Path, dst: Path) -> None:
    for suffix in (".safetensors", ".json"):
        source = src.with_suffix(suffix)
        atomic_save(lambda p, s=source: shutil.copyfile(s, p), dst.with_suffix(suffix))


def finished_runs(results: Path) -> dict[tuple[str, str, str], dict[int, Path]]:
    """The finished training trials of a sweep: (scenario, algo, reward) -> seed -> folder.

    Raises
    ------
    ValueError
        If ``results`` holds no training sweep, or one method has a seed twice (two trials
        that differ in another setting: ship from a sweep of one configuration per method).
    """
    state = results / "sweep.json"
    if not state.is_file():
        raise ValueError(f"{results} holds no sweep (no sweep.json)")
    sweep = json.loads(state.read_text())
    if sweep["mode"] != "train":
        raise ValueError(f"{results} is an evaluation sweep; nothing to ship")
    methods: dict[tuple[str, str, str], dict[int, Path]] = {}
    for trial in sweep["trials"]:
        folder = results / "trials" / trial["trial_id"]
        if not (folder / "result.json").is_file():
            continue
        s = trial["settings"]
        seeds = methods.setdefault((s["scenario"], s["algo"], s["reward"]), {})
        if trial["seed"] in seeds:
            raise ValueError(f"{results}: {s['algo']}-{s['reward']} on {s['scenario']} has seed "
                             f"{trial['seed']} twice (trials differing in another setting)")
        seeds[trial["seed"]] = folder
    return methods


def ship(results: list[Path], weights: Path, training: Path) -> list[dict]:
    """Copy every seed's best policy and log, and ship each method's best seed."""
    records = []
    for folder in results:
        for (scenario, algo, reward), seeds in finished_runs(folder).items():
            name = f"{algo}-{reward}"
            scores = {seed: validation(run) for seed, run in sorted(seeds.items())}
            for seed, run in sorted(seeds.items()):
                _copy_policy(run / "best.safetensors",
                             weights / scenario / "seeds" / f"{name}-s{seed}.safetensors")
                atomic_save(lambda p, r=run: shutil.copyfile(r / "progress.csv", p),
                            training / scenario / f"{name}-s{seed}.csv")
            best = max(scores, key=lambda s: (scores[s]["response_rate"],
                                              -scores[s]["avg_time"]))
            _copy_policy(seeds[best] / "best.safetensors",
                         weights / scenario / f"{name}.safetensors")
            record = {"method": name, "scenario": scenario, "sweep": str(folder),
                      "command": "python benchmarks/sweeps/ship.py " + " ".join(sys.argv[1:]),
                      "shipped_seed": best, "validation_seed": 12345,
                      "seeds": {str(s): v for s, v in scores.items()},
                      "date": time.strftime("%Y-%m-%d")}
            atomic_write_text(training / scenario / f"{name}.json",
                              json.dumps(record, indent=2))
            records.append(record)
    return records


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("results", nargs="+", type=Path, help="results folders of sweeps")
    parser.add_argument("--weights", type=Path, default=ROOT / "allocator" / "weights")
    parser.add_argument("--training", type=Path,
                        default=ROOT / "benchmarks" / "results" / "training")
    args = parser.parse_args(argv)
    try:
        records = ship(args.results, args.weights, args.training)
    except (ValueError, FileNotFoundError) as err:
        print(f"ship.py: error: {err}", file=sys.stderr)
        return 2
    for r in records:
        print(f"shipped {r['method']} on {r['scenario']}: seed {r['shipped_seed']} of "
              f"{sorted(int(s) for s in r['seeds'])}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
