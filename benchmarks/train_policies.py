"""Train, select and ship policies: the one command that (re)creates any shipped weights.

    python benchmarks/train_policies.py --scenario 3v3 --algo bicnet --reward ipf \
        --seeds 0 1 2 --episodes 3000 [--jobs 2] [--set KEY=VALUE ...] \
        [--settings benchmarks/results/training/reward_search.json] [--tag paper-budget]

For every seed it runs ``agv train`` into ``runs/<scenario>/<algo>-<reward>-s<seed>/`` (resuming
a run that was interrupted), then

With ``--tag TAG`` every path below gains a ``TAG/`` folder after ``<scenario>/`` (runs, shipped
weights, logs), so that runs at another budget (``paper-budget``: the paper's episodes) ship
beside the default weights instead of over them. ``--settings FILE`` passes the learner
settings chosen for this ``<algo>-<reward>`` by ``benchmarks/reward_search.py`` to
``agv train`` (before any ``--set``, which wins).

- copies each seed's best-on-validation policy to
  ``allocator/weights/<scenario>/seeds/<algo>-<reward>-s<seed>.safetensors`` (+ ``.json``);
- ships the seed whose validation task response is highest (ties: lower validation time) as
  ``allocator/weights/<scenario>/<algo>-<reward>.safetensors`` (+ ``.json``), the weights that
  ``allocator.make("<algo>-<reward>", scenario=...)`` loads;
- copies each seed's ``progress.csv`` to
  ``benchmarks/results/training/<scenario>/<algo>-<reward>-s<seed>.csv`` (Fig. 9);
- records the command, seeds, episodes, validation scores and wall-clock training time in
  ``benchmarks/results/training/<scenario>/<algo>-<reward>.json``.

Validation uses the training's evaluation episodes (seed 12345), never the test episodes of
``benchmarks/paper_tables.py`` (seed 0).
"""

from __future__ import annotations

import argparse
import csv
import json
import re
import shutil
import subprocess
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from provenance import recorded_command

from sim.io import atomic_save, atomic_write_text

ROOT = Path(__file__).resolve().parents[1]
WEIGHTS = ROOT / "allocator" / "weights"
TRAINING = ROOT / "benchmarks" / "results" / "training"


def run_dir(scenario: str, name: str, seed: int, tag: str = "") -> Path:
    return ROOT / "runs" / scenario / tag / f"{name}-s{seed}"


def chosen_settings(path: Path | None, name: str) -> list[str]:
    """``KEY=VALUE`` items of the settings chosen for ``name`` in a reward-search record.

    Raises
    ------
    ValueError
        If the file is not a reward-search record or holds nothing for ``name``.
    """
    if path is None:
        return []
    try:
        methods = json.loads(path.read_text())["methods"]
        settings = methods[name]["settings"]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise ValueError(f"--settings {path}: no settings for {name!r} in a "
                         f"reward_search.json ({type(exc).__name__}: {exc})") from None
    return [f"{key}={value}" for key, value in settings.items()]


def train_seed(args: argparse.Namespace, seed: int) -> tuple[int, float]:
    """Run (or resume) one seed's training; returns (exit status, wall-clock seconds)."""
    name = f"{args.algo}-{args.reward}"
    folder = run_dir(args.scenario, name, seed, args.tag)
    log = folder.with_suffix(".log")
    log.parent.mkdir(parents=True, exist_ok=True)
    cmd = [sys.executable, "-m", "allocator.cli", "train", "--no-progress",
           "--episodes", str(args.episodes)]
    if (folder / "checkpoint.safetensors").exists():
        cmd += ["--resume", str(folder)]
    else:
        cmd += ["--algo", args.algo, "--reward", args.reward, "--scenario", args.scenario,
                "--seed", str(seed), "--run-dir", str(folder)]
        for item in chosen_settings(args.settings, name) + args.set:
            cmd += ["--set", item]
    for flag, value in (("--eval-every", args.eval_every), ("--eval-episodes", args.eval_episodes)):
        if value is not None:
            cmd += [flag, str(value)]
    start = time.perf_counter()
    with log.open("a") as fh:
        fh.write(" ".join(cmd) + "\n")
        fh.flush()
        status = subprocess.call(cmd, stdout=fh, stderr=subprocess.STDOUT, cwd=ROOT)
    return status, time.perf_counter() - start


def validation(folder: Path) -> dict[str, float]:
    """Best validation response, its time, and the run's total training seconds."""
    with (folder / "progress.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    evals = [r for r in rows if r.get("eval_response_rate")]
    if not evals:
        raise ValueError(f"{folder}/progress.csv holds no evaluation; train longer")
    best = max(evals, key=lambda r: (float(r["eval_response_rate"]), -float(r["eval_avg_time"])))
    return {
        "response_rate": float(best["eval_response_rate"]),
        "avg_time": float(best["eval_avg_time"]),
        "at_episode": int(float(best["episode"])),
        "episodes": int(float(rows[-1]["episode"])),
        "train_seconds": float(rows[-1]["seconds"]),
    }


def _copy_policy(src: Path, dst: Path) -> None:
    """Copy a ``.safetensors`` file and its ``.json`` sidecar, each atomically."""
    for suffix in (".safetensors", ".json"):
        source = src.with_suffix(suffix)
        atomic_save(lambda p, s=source: shutil.copyfile(s, p), dst.with_suffix(suffix))


def ship(args: argparse.Namespace, seconds: dict[int, float]) -> dict:
    """Copy every seed's best policy and log into the package and results; ship the best."""
    name = f"{args.algo}-{args.reward}"
    weights, training = WEIGHTS / args.scenario / args.tag, TRAINING / args.scenario / args.tag
    scores = {}
    for seed in args.seeds:
        folder = run_dir(args.scenario, name, seed, args.tag)
        scores[seed] = validation(folder)
        _copy_policy(folder / "best.safetensors", weights / "seeds" / f"{name}-s{seed}.safetensors")
        log = training / f"{name}-s{seed}.csv"
        atomic_save(lambda p, f=folder: shutil.copyfile(f / "progress.csv", p), log)
        config = folder / "config.json"
        if config.is_file():
            atomic_save(lambda p, c=config: shutil.copyfile(c, p),
                        training / f"{name}-s{seed}.config.json")
    best = max(args.seeds, key=lambda s: (scores[s]["response_rate"], -scores[s]["avg_time"]))
    _copy_policy(run_dir(args.scenario, name, best, args.tag) / "best.safetensors",
                 weights / f"{name}.safetensors")
    record = {
        "method": name,
        "scenario": args.scenario,
        "command": recorded_command(__file__),
        "shipped_seed": best,
        "validation_seed": 12345,
        "seeds": {str(s): {**scores[s], "wall_seconds_this_call": round(seconds.get(s, 0.0), 1)}
                  for s in args.seeds},
        "date": time.strftime("%Y-%m-%d"),
    }
    atomic_write_text(training / f"{name}.json", json.dumps(record, indent=2))
    return record


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", required=True)
    parser.add_argument("--algo", required=True, choices=["maddpg", "bicnet"])
    parser.add_argument("--reward", required=True,
                        choices=["minidist", "greedy", "ipf", "ipf-time"])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0])
    parser.add_argument("--episodes", type=int, required=True)
    parser.add_argument("--jobs", type=int, default=1, help="seeds trained at the same time")
    parser.add_argument("--eval-every", type=int, default=None)
    parser.add_argument("--eval-episodes", type=int, default=None)
    parser.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                        help="learner hyperparameter override passed to agv train")
    parser.add_argument("--settings", type=Path, default=None, metavar="FILE",
                        help="reward_search.json: this method's chosen learner settings")
    parser.add_argument("--tag", default="", metavar="TAG",
                        help="a folder for these runs under runs/, the weights and the logs")
    parser.add_argument("--ship-only", action="store_true",
                        help="skip training; select and copy from existing runs")
    args = parser.parse_args(argv)
    if args.tag and not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9_.-]*", args.tag):
        parser.error(f"--tag {args.tag!r}: letters, digits, '.', '_' and '-' only")
    try:
        chosen_settings(args.settings, f"{args.algo}-{args.reward}")
    except ValueError as exc:
        parser.error(str(exc))
    seconds: dict[int, float] = {}
    if not args.ship_only:
        with ThreadPoolExecutor(max_workers=args.jobs) as pool:
            results = dict(zip(args.seeds, pool.map(lambda s: train_seed(args, s), args.seeds),
                               strict=True))
        failed = {s: code for s, (code, _) in results.items() if code != 0}
        if failed:
            logs = run_dir(args.scenario, "*", 0, args.tag).parent.relative_to(ROOT)
            print(f"training failed for seeds {failed}; see {logs}/*.log", file=sys.stderr)
            return 1
        seconds = {s: t for s, (_, t) in results.items()}
    record = ship(args, seconds)
    print(json.dumps(record, indent=2))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
