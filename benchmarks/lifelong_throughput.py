"""Lifelong environment steps per second: warehouse-N against VMAS and the episodic step.

    python benchmarks/lifelong_throughput.py [--quick] [--threads 1] [--seed 0]
        [--rows warehouse-20:64 warehouse-50:64 warehouse-100:16] [--no-vmas] [--out DIR]
        [--clock wall|cpu]

For every row (a ``warehouse-N`` lifelong scenario at B parallel floors), with the ``minidist``
reward and with random breakdowns on (``sim.Breakdowns(1e-3, 50)``), in the same run:

- *lifelong*: ``LifelongEnv.step`` (physics with shelves, the order rules, arrivals, events,
  the lifelong observations and reward) with fixed random actions drawn beforehand, so the
  controller costs nothing;
- *episodic, same floor*: the episodic :class:`sim.env.AGVEnv` on the same floor with the same
  N, M = ceil(1.5 N) tasks (the lifelong backlog), the same observation slots (4 tasks, 4 AGVs)
  and AGVs starting in the same depot: the fused kernels (default) and the torch path;
- *NvN*: the episodic ``"NvN"`` scenario (open box, no shelves; e.g. ``50v50``);
- *VMAS*: ``simple_spread`` with ``n_agents=N`` at the same B on the CPU.

Every figure is environment steps per second, B x batched steps / seconds, the best of
repeated timings after a warm-up; ours (peers included) are timed in turns (``passes``
rounds over all the configurations, short turns) so that a slow spell of a shared machine
decides no row; ``--clock cpu`` times with the thread's CPU seconds instead of elapsed ones.
Writes ``lifelong_throughput.md`` and ``lifelong_throughput.csv`` to ``benchmarks/results``
(or ``--out``), with the seed, the configuration, the machine and the date.
"""

from __future__ import annotations

import argparse
import csv
import datetime
import io
import math
import os
import platform
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path

import torch
from provenance import recorded_command

import sim
from sim import native
from sim.io import atomic_write_text
from sim.lifelong import LifelongEnv, depot_sampler
from sim.scenarios import Scenario

RESULTS = Path(__file__).parent / "results"
ROWS = ("warehouse-20:64", "warehouse-50:64", "warehouse-100:16")
FAULTS = sim.Breakdowns(1e-3, 50)
"""Breakdowns of the "breakdowns on" rows: about 5% of the fleet broken at a time, so that the
breakdown branch of the step runs in most steps of a batch."""
TARGETS = {50: 50.0, 100: 100.0}
"""Issue targets: lifelong / VMAS at least this at N (warehouse-50 at B = 64, warehouse-100
at B = 16)."""
CLOCK_NOTE = {"wall": "elapsed seconds", "cpu": "the timing thread's CPU seconds"}
MAX_OVERHEAD = 0.5
"""Issue target: the lifelong rules add at most 50% to the episodic step of the same N."""


def parse_row(text: str) -> tuple[str, int]:
    """``"warehouse-50:64"`` -> ``("warehouse-50", 64)``.

    Raises
    ------
    ValueError
        For anything but ``warehouse-<N>:<B>`` with N, B >= 1.
    """
    name, sep, b = text.partition(":")
    n = name.removeprefix("warehouse-")
    if not sep or n == name or not n.isdigit() or not b.isdigit() or int(n) < 1 or int(b) < 1:
        raise ValueError(f"row {text!r}: expected warehouse-<N>:<B>, e.g. warehouse-50:64")
    return name, int(b)


@dataclass
class Row:
    """The figures of one (scenario, B, faults) row: seconds per batched step (best)."""

    scenario: str
    num_agents: int
    num_envs: int
    faults: bool
    lifelong: float = math.inf
    floor: float = math.inf
    floor_torch: float = math.inf
    nvn: float = math.inf
    vmas_sps: float = math.nan

    def sps(self, seconds: float) -> float:
        """Environment steps per second of a batched step of ``seconds``."""
        return self.num_envs / seconds if math.isfinite(seconds) else math.nan

    @property
    def ratio_vmas(self) -> float:
        return self.sps(self.lifelong) / self.vmas_sps

    @property
    def overhead_floor(self) -> float:
        """What the lifelong rules add to the episodic step on the same floor."""
        return self.lifelong / self.floor - 1.0

    @property
    def overhead_nvn(self) -> float:
        return self.lifelong / self.nvn - 1.0


CLOCKS = {"wall": time.perf_counter, "cpu": time.thread_time}
"""``wall``: elapsed seconds (the default); ``cpu``: this thread's CPU seconds, which a busy
shared machine inflates less (every figure of a run, VMAS's included, uses the same clock)."""


class Timer:
    """An env (lifelong or episodic) stepped with 8 pre-drawn random action tensors; the
    environments that finish are reset outside the timed region (the step alone is timed)."""

    def __init__(self, env: LifelongEnv | sim.AGVEnv, seed: int, clock: str) -> None:
        self.env = env
        self.clock = CLOCKS[clock]
        gen = torch.Generator().manual_seed(seed)
        shape = (env.num_envs, env.num_agents, 2)
        self.actions = [torch.rand(shape, generator=gen) * 2 - 1 for _ in range(8)]
        self.k = 0
        self.best = math.inf

    @classmethod
    def lifelong(cls, name: str, num_envs: int, faults: bool, seed: int, clock: str) -> Timer:
        options = {"faults": FAULTS} if faults else {}
        env = sim.make_env(name, num_envs=num_envs, reward="minidist", seed=seed, **options)
        assert isinstance(env, LifelongEnv)
        return cls(env, seed, clock)

    @torch.no_grad()
    def turn(self, steps: int) -> float:
        """Time ``steps`` batched steps; returns and keeps the best seconds per step."""
        env, clock, total = self.env, self.clock, 0.0
        for _ in range(steps):
            t0 = clock()
            _, _, done, _ = env.step(self.actions[self.k % 8])
            total += clock() - t0
            self.k += 1
            if bool(done.any()):
                env.reset(done)
        self.best = min(self.best, total / steps)
        return total / steps


def episodic_peer(env: LifelongEnv) -> Scenario:
    """The episodic scenario closest to a lifelong one: the same floor, N, M = the backlog
    (ceil(1.5 N) by default), the same observation slots and depot, a long horizon."""
    sc = env.scenario
    arrivals = sc.arrivals
    m = getattr(arrivals, "open", math.ceil(1.5 * sc.num_agents))
    return Scenario(name=f"{sc.name}-episodic", world=sc.world, num_agents=sc.num_agents,
                    num_tasks=int(m), max_steps=sc.max_steps, k_tasks=sc.k_pickups,
                    k_agents=sc.k_agents, sensing_range=sc.sensing_range,
                    agent_sampler=depot_sampler(sc.world))


def vmas_steps_per_second(n: int, b: int, budget: float, repeats: int, seed: int,
                          clock: str = "wall") -> float:
    """VMAS ``simple_spread`` (``n_agents=n``) env steps per second at B = b, random actions,
    25-step episodes with resets; about ``budget`` seconds per timed run (at least 1 step)."""
    from vmas import make_env

    env = make_env("simple_spread", num_envs=b, device="cpu", continuous_actions=True,
                   n_agents=n, max_steps=25, seed=seed)
    env.reset()
    gen = torch.Generator().manual_seed(seed)
    acts = [[torch.rand(b, 2, generator=gen) * 2 - 1 for _ in range(n)] for _ in range(8)]
    k = [0]

    def step() -> None:
        k[0] += 1
        _, _, done, _ = env.step(acts[k[0] % 8])
        if bool(done.all()):
            env.reset()
        elif bool(done.any()):
            for i in torch.nonzero(done).flatten().tolist():
                env.reset_at(i)

    now = CLOCKS[clock]
    t0 = now()
    step()  # warm-up, and the size of a timed run
    steps = max(1, int(budget / max(now() - t0, 1e-6)))
    best = math.inf
    for _ in range(repeats):
        t0 = now()
        for _ in range(steps):
            step()
        best = min(best, now() - t0)
    return b * steps / best


def git_revision(path: str) -> str:
    """Short hash of the last commit of ``path`` and whether the checkout changes it."""
    root = Path(__file__).resolve().parents[1]
    try:
        rev = subprocess.run(["git", "log", "-1", "--format=%h", "--", path], cwd=root,
                             capture_output=True, text=True, timeout=10).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--", path], cwd=root,
                               capture_output=True, text=True, timeout=10).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return (rev or "uncommitted") + (" (modified)" if dirty else "")


def run(rows: list[tuple[str, int]], quick: bool, threads: int, seed: int, vmas: bool,
        clock: str = "wall") -> tuple[list[Row], dict[str, object]]:
    """Measure every row; returns the rows and the configuration."""
    torch.set_num_threads(threads)
    passes, turns = (1, 2) if quick else (3, 5)
    results: list[Row] = []
    timers: dict[tuple[str, int, str], Timer] = {}
    for name, b in rows:
        for faults in (False, True):
            t = Timer.lifelong(name, b, faults, seed, clock)
            timers[(name, b, "on" if faults else "off")] = t
            results.append(Row(name, t.env.num_agents, b, faults))
        env = timers[(name, b, "off")].env
        n = env.num_agents
        floor = episodic_peer(env)
        for label, scenario, nat in (("floor", floor, None), ("floor_torch", floor, False),
                                     ("nvn", f"{n}v{n}", None)):
            # The episodic peers: the same reward, seed and actions as the lifelong rows.
            peer = sim.AGVEnv(scenario, num_envs=b, reward="minidist", seed=seed, native=nat)
            timers[(name, b, label)] = Timer(peer, seed, clock)

    # Short turns: about 20 ms at the measured speed (3 to 50 steps).
    def steps_for(seconds: float) -> int:
        return max(3, min(50, int(0.02 / max(seconds, 1e-6))))

    for t in timers.values():
        t.turn(3)  # warm-up (and the first estimate of a step)
    for _ in range(passes):  # rounds over every configuration, peers included
        for t in timers.values():
            for _ in range(turns):
                t.turn(steps_for(t.best))
    for row in results:
        key = (row.scenario, row.num_envs)
        row.lifelong = timers[(*key, "on" if row.faults else "off")].best
        row.floor = timers[(*key, "floor")].best
        row.floor_torch = timers[(*key, "floor_torch")].best
        row.nvn = timers[(*key, "nvn")].best
    if vmas:
        try:
            import vmas as _  # noqa: F401
        except ImportError:
            vmas = False
    if vmas:
        by_nb: dict[tuple[int, int], float] = {}
        for row in results:
            key = (row.num_agents, row.num_envs)
            if key not in by_nb:
                by_nb[key] = vmas_steps_per_second(*key, budget=0.5 if quick else 3.0,
                                                   repeats=1 if quick else 2, seed=seed,
                                                   clock=clock)
                print(f"VMAS simple_spread N={key[0]} B={key[1]}: {by_nb[key]:,.1f} env "
                      "steps/s", flush=True)
            row.vmas_sps = by_nb[key]
    config = {
        "seed": seed, "threads": threads, "quick": quick, "passes": passes, "turns": turns,
        "clock": clock,
        "faults": f"Breakdowns(rate={FAULTS.rate}, repair_steps={FAULTS.repair_steps})",
        "machine": f"{platform.processor() or platform.machine()}, {os.cpu_count()} CPUs, "
                   f"{platform.system()} {platform.release()}",
        "python": platform.python_version(), "torch": torch.__version__,
        "date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
        "kernels": ("fused C kernels of `sim.native` (episodic)" if native.available()
                    else f"torch path only ({native.disabled_reason()})"),
        "sim/lifelong.py": git_revision("sim/lifelong.py"),
        "vmas": vmas,
    }
    return results, config


CSV_FIELDS = ("scenario", "N", "B", "reward", "faults", "lifelong_sps", "lifelong_step_us",
              "episodic_floor_sps", "episodic_floor_step_us", "episodic_floor_torch_sps",
              "nvn", "nvn_sps", "nvn_step_us", "vmas_sps", "lifelong_over_vmas",
              "overhead_vs_floor", "overhead_vs_nvn", "seed", "threads", "clock", "machine",
              "torch", "date", "lifelong_rev")


def to_csv(rows: list[Row], config: dict[str, object]) -> str:
    """The rows as CSV text (one line per row, the configuration repeated on each)."""
    out = io.StringIO()
    w = csv.DictWriter(out, fieldnames=CSV_FIELDS, lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({
            "scenario": r.scenario, "N": r.num_agents, "B": r.num_envs, "reward": "minidist",
            "faults": config["faults"] if r.faults else "none",
            "lifelong_sps": f"{r.sps(r.lifelong):.1f}",
            "lifelong_step_us": f"{1e6 * r.lifelong:.0f}",
            "episodic_floor_sps": f"{r.sps(r.floor):.1f}",
            "episodic_floor_step_us": f"{1e6 * r.floor:.0f}",
            "episodic_floor_torch_sps": f"{r.sps(r.floor_torch):.1f}",
            "nvn": f"{r.num_agents}v{r.num_agents}", "nvn_sps": f"{r.sps(r.nvn):.1f}",
            "nvn_step_us": f"{1e6 * r.nvn:.0f}", "vmas_sps": f"{r.vmas_sps:.2f}",
            "lifelong_over_vmas": f"{r.ratio_vmas:.2f}",
            "overhead_vs_floor": f"{r.overhead_floor:.3f}",
            "overhead_vs_nvn": f"{r.overhead_nvn:.3f}", "seed": config["seed"],
            "threads": config["threads"], "clock": config["clock"],
            "machine": config["machine"],
            "torch": config["torch"], "date": config["date"],
            "lifelong_rev": config["sim/lifelong.py"],
        })
    return out.getvalue()


def _pct(x: float) -> str:
    return f"{x:+.0%}" if math.isfinite(x) else "n/a"


def _num(x: float, fmt: str = ",.0f") -> str:
    return format(x, fmt) if math.isfinite(x) else "n/a"


def to_markdown(rows: list[Row], config: dict[str, object], command: str) -> str:
    """The results table, the targets and whether each is met."""
    lines = [
        "# Lifelong throughput (environment steps per second, CPU)",
        "",
        f"`{command}` on {config['machine']}, Python {config['python']}, torch "
        f"{config['torch']}, {config['threads']} thread(s), {config['date']}; seed "
        f"{config['seed']}; episodic peers with the {config['kernels']}; `sim/lifelong.py` at "
        f"{config['sim/lifelong.py']}; {config['clock']} clock ({CLOCK_NOTE[config['clock']]}), "
        "the same for every figure. Fixed random actions drawn beforehand (no controller); "
        f"best of {config['passes']} x {config['turns']} short timed turns of ours, in rounds "
        "over all the configurations, after a warm-up; VMAS best of "
        f"{1 if config['quick'] else 2} timed runs; all in the same run.",
        "",
        "- *lifelong*: `LifelongEnv.step` (`sim.make_env('warehouse-N', num_envs=B)`, "
        "`minidist` reward, backlog arrivals of ceil(1.5 N) open orders), with breakdowns "
        f"`sim.{config['faults']}` or none; *step*: microseconds per batched step;",
        "- *episodic floor*: `AGVEnv` on the same floor, N AGVs from the same depot, M = "
        "ceil(1.5 N) tasks, 4 task and 4 AGV slots in the observations, fused kernels "
        "(and *torch*: `native=False`); *NvN*: the open-box episodic scenario (e.g. `50v50`), "
        "fused kernels; every *step* excludes the resets of finished environments;",
        "- *over floor*, *over NvN*: what the lifelong step adds to those steps "
        "(lifelong step / episodic step - 1); *VMAS*: `simple_spread`, `n_agents=N`, same B.",
        "",
        "| scenario | B | breakdowns | lifelong | step (us) | episodic floor | step (us) "
        "| episodic floor, torch | NvN | step (us) | over floor | over NvN | VMAS "
        "| lifelong / VMAS |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r.scenario} | {r.num_envs} | {'on' if r.faults else 'off'} "
            f"| {_num(r.sps(r.lifelong))} | {_num(1e6 * r.lifelong)} | {_num(r.sps(r.floor))} "
            f"| {_num(1e6 * r.floor)} | {_num(r.sps(r.floor_torch))} | {_num(r.sps(r.nvn))} "
            f"| {_num(1e6 * r.nvn)} | {_pct(r.overhead_floor)} | {_pct(r.overhead_nvn)} "
            f"| {_num(r.vmas_sps, ',.1f')} | {_num(r.ratio_vmas, ',.1f')} |")
    lines += ["", "Targets (issue 13):", ""]
    for r in rows:
        want = TARGETS.get(r.num_agents)
        tag = f"{r.scenario} B={r.num_envs} breakdowns {'on' if r.faults else 'off'}"
        if want is not None and math.isfinite(r.ratio_vmas):
            ok = "met" if r.ratio_vmas >= want else "NOT met"
            lines.append(f"- {tag}: lifelong / VMAS {r.ratio_vmas:,.1f} >= {want:.0f}: {ok};")
        ok = "met" if r.overhead_floor <= MAX_OVERHEAD else "NOT met"
        lines.append(f"- {tag}: lifelong over the episodic step on the same floor "
                     f"{_pct(r.overhead_floor)} <= +{MAX_OVERHEAD:.0%}: {ok} (over "
                     f"{r.num_agents}v{r.num_agents}: {_pct(r.overhead_nvn)}).")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="fewer passes, turns and repeats")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default 1)")
    parser.add_argument("--seed", type=int, default=0, help="seed of envs and actions")
    parser.add_argument("--rows", nargs="+", default=list(ROWS),
                        help="warehouse-<N>:<B> rows (default: %(default)s)")
    parser.add_argument("--no-vmas", action="store_true", help="skip the VMAS peers")
    parser.add_argument("--out", type=Path, default=RESULTS, help="where the results go")
    parser.add_argument("--clock", choices=sorted(CLOCKS), default="wall",
                        help="seconds of the figures: elapsed (wall, default) or this thread's "
                             "CPU time (cpu), for a busy shared machine")
    args = parser.parse_args(argv)
    if args.threads < 1:
        parser.error(f"--threads must be >= 1, got {args.threads}")
    if args.seed < 0:
        parser.error(f"--seed must be >= 0, got {args.seed}")
    try:
        rows = [parse_row(r) for r in args.rows]
    except ValueError as err:
        parser.error(str(err))
    results, config = run(rows, args.quick, args.threads, args.seed, not args.no_vmas,
                          args.clock)
    command = recorded_command(__file__, argv)
    args.out.mkdir(parents=True, exist_ok=True)
    text = to_markdown(results, config, command)
    atomic_write_text(args.out / "lifelong_throughput.md", text)
    atomic_write_text(args.out / "lifelong_throughput.csv", to_csv(results, config))
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
