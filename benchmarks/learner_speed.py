"""Learner speed: batched vs textbook MADDPG updates, and training throughput of both learners.

Measures, in one process so the ratios are fair on a shared machine:

1. one MADDPG update over a batch of 1024, with the agents' networks stacked (one batched
   matmul per layer for all actors / all critics) and with the textbook loop of separate
   per-agent networks and optimizers (:class:`learners.reference.LoopedMADDPG`), interleaved,
   at N = 3 and N = 6;
2. one BiCNet update over the same batch;
3. end-to-end training throughput (environment steps and gradient updates per second) of
   ``learners.train.train`` with each learner's default config, IPF reward.

Run: ``python benchmarks/learner_speed.py [--threads 1] [--repeats 30]``; writes
``benchmarks/results/learner_speed.md``.
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import tempfile
import time
from pathlib import Path

import torch

import sim
from learners.bicnet import BiCNet, BiCNetConfig
from learners.buffer import Batch
from learners.maddpg import MADDPG, MADDPGConfig
from learners.reference import LoopedMADDPG
from learners.train import TrainConfig, train
from sim.io import atomic_write_text

RESULTS = Path(__file__).resolve().parent / "results" / "learner_speed.md"


def _batch(n: int, size: int = 1024) -> Batch:
    env = sim.make_env(f"{n}v{n}", num_envs=size, reward="minidist", seed=0)
    obs, state = env.reset(), env.global_state()
    action = torch.rand(size, n, 2, generator=torch.Generator().manual_seed(0)) * 2 - 1
    next_obs, reward, _, _ = env.step(action)
    return Batch(obs, state, action, reward, next_obs, env.global_state(),
                 env.task_claimed.all(1).float())


def _time(fn, repeats: int) -> list[float]:
    out = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t)
    return out


def update_costs(n: int, repeats: int, hidden: int) -> dict[str, float]:
    """Median ms per update of batched MADDPG, looped MADDPG and BiCNet, and the median of the
    per-pair ratios looped / batched (the two are timed back to back, ``repeats`` times, so
    that load from other users hits both alike)."""
    batch = _batch(n)
    torch.manual_seed(0)
    env = sim.make_env(f"{n}v{n}", num_envs=1)
    maddpg = MADDPG(env.obs_dim, env.state_dim, n, MADDPGConfig(hidden=hidden))
    looped = LoopedMADDPG(maddpg)
    bicnet = BiCNet(env.obs_dim, env.state_dim, n, BiCNetConfig())
    for _ in range(3):  # warm up
        maddpg.update(batch)
        looped.update(batch)
        bicnet.update(batch)
    times: dict[str, list[float]] = {"batched": [], "looped": [], "bicnet": []}
    for r in range(repeats):
        times["batched"] += _time(lambda: maddpg.update(batch), 1)
        times["looped"] += _time(lambda: looped.update(batch), 1)
        if r % 2 == 0:
            times["bicnet"] += _time(lambda: bicnet.update(batch), 1)
    out = {k: 1e3 * statistics.median(v) for k, v in times.items()}
    out["ratio"] = statistics.median(lo / ba for lo, ba in zip(times["looped"],
                                                               times["batched"], strict=True))
    out["batched_min"] = 1e3 * min(times["batched"])
    out["looped_min"] = 1e3 * min(times["looped"])
    return out


def training_throughput(algo: str, n: int, episodes: int) -> dict[str, float]:
    """Env steps and updates per second of the real training loop (default config, ipf)."""
    with tempfile.TemporaryDirectory() as tmp:
        cfg = TrainConfig(algo=algo, reward="ipf", scenario=f"{n}v{n}", episodes=episodes,
                          seed=0, run_dir=tmp, eval_every=0, eval_episodes=10,
                          checkpoint_every=10**9, progress=False,
                          threads=torch.get_num_threads())
        r = train(cfg)
    return {"env_steps_per_s": r.env_steps / r.seconds, "updates_per_s": r.updates / r.seconds,
            "agent_steps_per_s": n * r.env_steps / r.seconds, "seconds": r.seconds}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--repeats", type=int, default=30)
    parser.add_argument("--episodes", type=int, default=600,
                        help="training episodes per throughput measurement")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    load_before = os.getloadavg()
    lines = [
        "# Learner speed",
        "",
        f"`python benchmarks/learner_speed.py --threads {args.threads} --repeats "
        f"{args.repeats} --episodes {args.episodes}`; torch {torch.__version__}, "
        f"{args.threads} thread(s), {platform.processor() or platform.machine()}, "
        "a 2-core machine shared with other users (expect noise; ratios are measured "
        "interleaved in one process).",
        "",
        "LOAD_LINE",
        "",
        "## One update over a batch of 1024 (median ms)",
        "",
        "| N | MADDPG hidden | stacked (min) | textbook loop (min) | speed-up "
        "(median of pairs) | BiCNet, shared BiGRU |",
        "|---|---|---|---|---|---|",
    ]
    for n in (3, 6):
        for hidden in sorted({64, MADDPGConfig().hidden, 128}):
            c = update_costs(n, args.repeats, hidden)
            lines.append(f"| {n} | {hidden} | {c['batched']:.1f} ({c['batched_min']:.1f}) | "
                         f"{c['looped']:.1f} ({c['looped_min']:.1f}) | {c['ratio']:.2f}x | "
                         f"{c['bicnet']:.1f} |")
            print(lines[-1], flush=True)
    lines += [
        "",
        "Stacked: `MADDPG.update`, all agents' networks stacked, gradients written by hand",
        "into reused workspace tensors (see docs/learners.md). The textbook loop",
        "(`learners/reference.py`) computes the same update (tested equal to 1e-6) with N",
        "separate `nn.Module` networks and N Adam optimizers, agent by agent, with autograd.",
        "Speed-up: the median over the repeats of (loop time / stacked time), the two timed",
        "back to back; a BiCNet update runs after every other pair. Issue 5 asks for 1.4x.",
        "BiCNet uses its default config (hidden 64, 2 + 2 shared layers around a BiGRU).",
        "",
        "## Training throughput (default configs, IPF reward, evaluation excluded)",
        "",
        "| learner | N | env steps/s | agent steps/s | updates/s |",
        "|---|---|---|---|---|",
    ]
    for algo in ("maddpg", "bicnet"):
        for n in (3, 6):
            t = training_throughput(algo, n, args.episodes)
            lines.append(f"| {algo} | {n} | {t['env_steps_per_s']:.0f} | "
                         f"{t['agent_steps_per_s']:.0f} | {t['updates_per_s']:.1f} |")
            print(lines[-1], flush=True)
    lines += [
        "",
        "An env step here is one joint step of one environment (N agent-steps). Training runs",
        "B = num_envs environments in parallel and does updates_per_step updates per batched",
        "step, so updates/s x (B / updates_per_step) = env steps/s once learning has started;",
        "the first learning_starts transitions are collected without updates.",
        "",
    ]
    load_after = os.getloadavg()
    lines[lines.index("LOAD_LINE")] = (
        f"1-minute load average {load_before[0]:.2f} at the start, {load_after[0]:.2f} at the "
        f"end ({os.cpu_count()} cores; this benchmark itself accounts for about 1).")
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(RESULTS, "\n".join(lines))
    print(f"wrote {RESULTS}")


if __name__ == "__main__":
    main()
