"""What the shield's detours cost in time, squares against discs (issue 17).

    python benchmarks/detour_speed.py [--size 50v50] [--episodes 20] [--repeats 3] [--seed 0]
        [--out benchmarks/results/scale/detour_speed]

Runs the whole-scene assignment rule (``local_information.LocalAssignment``, a Hungarian
dispatcher that re-plans every step) behind :class:`allocator.shield.SafetyShield` on the same
``--episodes`` episodes of ``--size``, without detours, with the squares model
(``detour="squares"``) and with the discs model (``detour="discs"``), alternating, ``--repeats``
times, on one torch thread. Reports the median seconds of each, their ratio to the shield
without detours, the seconds per batch step (the batch steps until its last scene ends, so a
setting that finishes scenes sooner also runs fewer steps) and its ratio, and what each does
to response and time. The discs model's planner is built
on a grid of ``r / 6`` cells per scene each time the set of parked AGVs changes, against
``r / 2`` for squares: this measures what that costs a whole rollout. Writes
``detour_speed.md`` and ``detour_speed.json`` (command, machine, every timing).
"""

from __future__ import annotations

import argparse
import datetime
import json
import platform
import statistics
import sys
import time
from pathlib import Path

import torch
from local_information import LocalAssignment, detour_label
from provenance import recorded_command

import sim
from allocator.shield import SafetyShield
from sim.io import atomic_write_text

OUT = Path(__file__).parent / "results" / "scale" / "detour_speed"
DETOURS = (False, "squares", "discs")
"""The shield's settings compared: none, squares, discs."""


def run(scenario: sim.Scenario, detour: bool | str, episodes: int, seed: int
        ) -> tuple[float, sim.Metrics]:
    """Seconds and metrics of the shielded rule over the episodes."""
    ctl = SafetyShield(LocalAssignment(), detour=detour)
    t0 = time.perf_counter()
    m = sim.evaluate(ctl, scenario, episodes=episodes, seed=seed, batch_size=episodes)
    return time.perf_counter() - t0, m


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", default="50v50", help="an 'NvN' scenario")
    parser.add_argument("--episodes", type=int, default=20)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args(argv)
    if args.episodes < 1 or args.repeats < 1 or args.seed < 0:
        parser.error("--episodes and --repeats must be >= 1 and --seed >= 0")
    try:
        n = int(args.size.split("v")[0])
        scenario = sim.get_scenario(args.size, k_tasks=n, k_agents=n - 1)
    except (ValueError, KeyError) as err:
        parser.error(f"--size must be an 'NvN' scenario, got {args.size!r} ({err})")
    torch.set_num_threads(1)
    times: dict[str, list[float]] = {str(d): [] for d in DETOURS}
    metrics: dict[str, sim.Metrics] = {}
    for _ in range(args.repeats):
        for detour in DETOURS:
            seconds, metrics[str(detour)] = run(scenario, detour, args.episodes, args.seed)
            times[str(detour)].append(seconds)
    med = {k: statistics.median(v) for k, v in times.items()}
    base = med[str(False)]
    command = recorded_command(__file__, sys.argv[1:] if argv is None else argv)
    stamp = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    lines = [f"# What the shield's detours cost: {args.size}, {args.episodes} episodes", "",
             f"`{command}` on {platform.machine()}, Python {platform.python_version()}, "
             f"torch {torch.__version__}, one thread, {stamp}; seed {args.seed}, median of "
             f"{args.repeats}. The whole-scene assignment rule behind the shield.", "",
             "| shield | s | ratio to no detour | batch steps | s per batch step | ratio | "
             "response | avg time |", "|---|---|---|---|---|---|---|---|"]
    steps = {k: int(m.episode_time.max()) for k, m in metrics.items()}
    per_step = {k: med[k] / steps[k] for k in med}
    for detour in DETOURS:
        k, m = str(detour), metrics[str(detour)]
        lines.append(f"| yes{detour_label(detour)} | {med[k]:.2f} | {med[k] / base:.2f} | "
                     f"{steps[k]} | {per_step[k]:.4f} | {per_step[k] / per_step['False']:.2f} "
                     f"| {m.response_rate:.4f} | {m.avg_time:.2f} |")
    args.out.mkdir(parents=True, exist_ok=True)
    atomic_write_text(args.out / "detour_speed.md", "\n".join(lines) + "\n")
    atomic_write_text(args.out / "detour_speed.json", json.dumps(
        dict(command=command, date=stamp, size=args.size, episodes=args.episodes,
             seed=args.seed, seconds=times, median=med,
             ratio={k: v / base for k, v in med.items()}, batch_steps=steps,
             seconds_per_step=per_step,
             ratio_per_step={k: v / per_step["False"] for k, v in per_step.items()},
             response={k: m.response_rate for k, m in metrics.items()},
             avg_time={k: m.avg_time for k, m in metrics.items()}), indent=1) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
