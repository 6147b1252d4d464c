"""Imitation probe for issue 17: an entity policy taught by a re-planning Hungarian (DAgger).

    python benchmarks/dagger_probe.py --start POLICY.safetensors [--iterations 12]
        [--steps 300] [--lr 1e-3] [--sizes 10v10 20v20 50v50] [--view 6:5|full] [--shield]
        [--seed 0]
        [--out benchmarks/results/scale/entity/dagger]

The teacher (:func:`teacher_actions`) sees the whole scene: every step it assigns the idle AGVs
to the open tasks (least total distance) and drives each at its task
(``local_information.py``'s rule with the full view). The student is the actor of an entity
policy file (``--start``, e.g. a curriculum run's ``best.safetensors``), which reads only its
observation (``--view``: the paper's 6 nearest tasks and 5 nearest AGVs, or the whole scene).
DAgger (Ross et al., 2011): iteration 0 rolls the teacher out, later ones a mix (each
environment driven by the teacher with probability 0.3, else by the student); every state
visited is labelled with the teacher's action; the last 8 rollouts per size are kept and the
actor takes ``--steps`` Adam steps on the mean squared error between its action and the
teacher's over the AGVs that move (a batch of 64 joint states per size and step);
``--shield`` executes the rollouts' actions through the safety shield. No reward
and no critic: the file written is a policy (``kind="policy"``) that ``allocator.make(...,
checkpoint=FILE)``, ``scale_table.py --entity FILE`` and ``agv train --init-from FILE``
take.

Writes ``--out``/``dagger.safetensors`` (+ sidecar), ``progress.csv`` (loss and the 20v20
validation, seed 12345, 100 episodes, plain and shielded, every second iteration) and
``dagger.probe.json`` (the command, seed, settings and the start file).
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from local_information import velocity_action, view
from scipy.optimize import linear_sum_assignment

import sim
from allocator.shield import SafetyShield
from learners.algorithms import ENTITY_ALGORITHMS, make_learner
from learners.checkpoint import load_checkpoint, save_checkpoint
from sim.io import atomic_write_text
from sim.observations import ObsLayout

OUT = Path(__file__).parent / "results" / "scale" / "entity" / "dagger"
BATCH = {"10v10": 64, "20v20": 32, "50v50": 12}
"""Environments per rollout (other sizes: 16)."""
KEEP = 8
"""Rollouts kept per size (the oldest are dropped)."""
TEACHER_SHARE = 0.3
"""Share of the environments the teacher drives after the first iteration."""
VALIDATION_SEED = 12345


def teacher_actions(env: Any, max_speed: float = 2.0) -> torch.Tensor:
    """The re-planning Hungarian's actions (B, N, 2) from the env's state: the idle AGVs of
    each running scene assigned to its open tasks (least total distance), each driven at its
    task (:func:`local_information.velocity_action`); AGVs without a task brake."""
    pos = env.agent_pos.detach().cpu().double().numpy()
    vel = env.agent_vel.detach().cpu().double().numpy()
    tasks = env.task_pos.detach().cpu().double().numpy()
    idle = (env.agent_task < 0).cpu().numpy() & ~env.done.cpu().numpy()[:, None]
    open_ = ~env.task_claimed.cpu().numpy()
    goal = pos.copy()
    for b in np.nonzero(idle.any(1) & open_.any(1))[0]:
        agents, free = np.nonzero(idle[b])[0], np.nonzero(open_[b])[0]
        cost = np.linalg.norm(pos[b][agents][:, None] - tasks[b][free][None], axis=-1)
        rows, cols = linear_sum_assignment(cost)
        goal[b, agents[rows]] = tasks[b, free[cols]]
    act = velocity_action(goal - pos, vel, env.world.physics, max_speed)
    return torch.as_tensor(act, dtype=env.dtype)


def scenario(name: str, spec: str) -> sim.Scenario:
    n = int(name.split("v")[0])
    kt, ka = view(n, spec)
    return sim.get_scenario(name, k_tasks=kt, k_agents=ka)


def rollout(learner: Any, scen: sim.Scenario, envs: int, seed: int, teacher_share: float,
            gen: torch.Generator, shield: bool = False
            ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """One batch of episodes; returns the running states' observations (S, N, O), the
    teacher's actions (S, N, 2) and which AGVs move (S, N). ``shield``: the actions are
    executed through :class:`allocator.shield.SafetyShield` (the labels stay the teacher's
    own actions)."""
    env = sim.make_env(scen, num_envs=envs, seed=seed)
    obs = env.observe()
    learner.reset(env)
    safety = None
    if shield:
        safety = SafetyShield(learner)
        safety.reset(env)
    drive = torch.rand(envs, 1, 1, generator=gen) < teacher_share
    out: list[tuple[torch.Tensor, ...]] = []
    while not bool(env.done.all()):
        target = teacher_actions(env)
        with torch.no_grad():
            student = learner.policy(obs)
        run = ~env.done
        out.append((obs[run], target[run], ((env.agent_task < 0) & run[:, None])[run]))
        act = torch.where(drive, target, student)
        obs, *_ = env.step(act if safety is None else safety.filter(act))
    o, a, m = (torch.cat(x) for x in zip(*out, strict=True))
    return o, a, m


def validate(learner: Any, scen: sim.Scenario, episodes: int = 100) -> list[dict]:
    rows = []
    for shield in (False, True):
        ctl = SafetyShield(learner) if shield else learner
        m = sim.evaluate(ctl, scen, episodes=episodes, seed=VALIDATION_SEED)
        rows.append(dict(shield=shield, response=m.response_rate, avg_time=m.avg_time,
                         finished=m.finished_rate, overlaps=m.collisions))
    return rows


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--start", required=True, type=Path,
                        help="an entity learner's policy file (bicnet-e or maddpg-e)")
    parser.add_argument("--iterations", type=int, default=12)
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--lr", type=float, default=1e-3)
    parser.add_argument("--sizes", nargs="+", default=["10v10", "20v20", "50v50"])
    parser.add_argument("--view", default="6:5", help="'KT:KA' slots or 'full'")
    parser.add_argument("--shield", action="store_true",
                        help="roll out through the safety shield (the states a shielded "
                             "policy visits)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args(argv)
    if args.iterations < 1 or args.steps < 1 or args.seed < 0:
        parser.error("--iterations and --steps must be >= 1, --seed >= 0")
    if not (np.isfinite(args.lr) and args.lr > 0):
        parser.error(f"--lr must be a finite number > 0, got {args.lr}")
    try:
        scens = {s: scenario(s, args.view) for s in args.sizes}
        val = scenario("20v20", args.view)
        tensors, meta = load_checkpoint(args.start, kind="policy")
    except (ValueError, KeyError, FileNotFoundError) as err:
        parser.error(str(err))
    if meta["algo"] not in ENTITY_ALGORITHMS or "actor.steer.gain" in tensors:
        parser.error(f"--start must be an episodic entity policy (bicnet-e or maddpg-e), got "
                     f"{meta['algo']} on {meta['scenario']}")
    torch.set_num_threads(1)
    torch.manual_seed(args.seed)
    gen = torch.Generator().manual_seed(args.seed)
    learner = make_learner(meta["algo"], meta["obs_dim"], meta["state_dim"],
                           meta["num_agents"], meta["config"])
    learner.load_policy_tensors(tensors)
    opt = torch.optim.Adam(learner.actor.parameters(), lr=args.lr)
    args.out.mkdir(parents=True, exist_ok=True)
    data: dict[str, list[tuple[torch.Tensor, ...]]] = {s: [] for s in scens}
    log = []
    t0 = time.perf_counter()
    for it in range(args.iterations):
        share = 1.0 if it == 0 else TEACHER_SHARE
        for k, (name, scen) in enumerate(scens.items()):
            seed = args.seed * 100_000 + it * 100 + k
            data[name] = (data[name] + [rollout(learner, scen, BATCH.get(name, 16), seed,
                                                share, gen, args.shield)])[-KEEP:]
        pooled = {s: [torch.cat(x) for x in zip(*d, strict=True)] for s, d in data.items()}
        total = 0.0
        for _ in range(args.steps):
            loss = torch.zeros(())
            for name, (o, a, m) in pooled.items():
                learner.set_layout(ObsLayout(scens[name].k_tasks, scens[name].k_agents))
                idx = torch.randint(len(o), (64,), generator=gen)
                err = ((learner.policy(o[idx]) - a[idx]) ** 2).sum(-1) * m[idx]
                loss = loss + err.sum() / m[idx].sum().clamp_min(1)
            opt.zero_grad()
            loss.backward()
            torch.nn.utils.clip_grad_norm_(learner.actor.parameters(), 1.0)
            opt.step()
            total += float(loss.detach()) / len(pooled)
        row: dict[str, Any] = dict(iteration=it + 1, loss=total / args.steps,
                                   seconds=round(time.perf_counter() - t0, 1))
        if it % 2 == 1 or it == args.iterations - 1:
            plain, shielded = validate(learner, val)
            row.update({f"{k}": v for k, v in plain.items() if k != "shield"})
            row.update({f"shielded_{k}": v for k, v in shielded.items() if k != "shield"})
        log.append(row)
        print(json.dumps(row), flush=True)
    learner.target_actor.load_state_dict(learner.actor.state_dict())
    keep = ("algo", "reward", "scenario", "num_agents", "num_tasks", "obs_dim", "state_dim",
            "config")
    save_checkpoint(args.out / "dagger.safetensors", learner.policy_tensors(),
                    {"kind": "policy", "seed": args.seed, **{k: meta[k] for k in keep}})
    fields = list(log[-1])  # the last iteration always validates: every column
    with open(args.out / "progress.csv.tmp", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=fields)
        w.writeheader()
        w.writerows(log)
    (args.out / "progress.csv.tmp").replace(args.out / "progress.csv")
    command = "python benchmarks/dagger_probe.py " + " ".join(
        sys.argv[1:] if argv is None else argv)
    atomic_write_text(args.out / "dagger.probe.json", json.dumps(
        {"command": command.strip(), "seed": args.seed, "start": str(args.start),
         "iterations": args.iterations, "steps": args.steps, "lr": args.lr,
         "sizes": args.sizes, "view": args.view, "shield": args.shield,
         "teacher_share": TEACHER_SHARE,
         "keep": KEEP, "batch": BATCH, "final": log[-1]}, indent=2) + "\n")
    print(f"wrote {args.out / 'dagger.safetensors'}")


if __name__ == "__main__":
    main()
