"""Imitation probe for issue 17: an entity policy taught by a re-planning Hungarian (DAgger).

    python benchmarks/dagger_probe.py --start POLICY.safetensors [--iterations 12 | 0]
        [--steps 300] [--lr 1e-3] [--sizes 10v10 20v20 50v50] [--view 6:5|full] [--shield]
        [--choice-head] [--choice-weight 1.0] [--choice-rounds R] [--choice-regret]
        [--choice-accumulate] [--choice-sinkhorn R] [--sinkhorn-beta 30] [--first-share 1.0]
        [--seed 0]
        [--out benchmarks/results/scale/entity/dagger]

The teacher (:func:`teacher_actions`) sees the whole scene: every step it assigns the idle AGVs
to the open tasks (least total distance) and drives each at its task
(``local_information.py``'s rule with the full view). The student is the actor of an entity
policy file (``--start``, e.g. a curriculum run's ``best.safetensors``), which reads only its
observation (``--view``: the paper's 6 nearest tasks and 5 nearest AGVs, or the whole scene).
DAgger (Ross et al., 2011): iteration 0 rolls the teacher out (``--first-share``: drives
that share of its environments with the teacher, 1.0 by default; 0.3 suits a fine-tune of a
student that already drives well, whose first iteration then sees its own states), later
ones a mix (each environment driven by the teacher with probability 0.3, else by the
student); every state visited is labelled with the teacher's action; the last 8 rollouts
per size are kept and the actor takes ``--steps`` Adam steps on the mean squared error
between its action and the teacher's over the AGVs that move (a batch of 64 joint states per
size and step);
``--shield`` executes the rollouts' actions through the safety shield. ``--choice-head``: the
student's last layers are a :class:`learners.entity.TaskChoiceHead` (a pointer over the task
tokens), fresh, on the start file's encoder (and recurrence), and the loss adds
``--choice-weight`` times the cross-entropy of the pointer against the slot of the teacher's
task (:func:`choice_slots`; AGVs whose teacher task is out of view add nothing).
``--choice-rounds R`` gives the pointer R rounds of intent exchange, ``--choice-regret``
regrets in its messages (new layers and input columns start at zero), ``--choice-accumulate``
rounds whose biases add up, ``--choice-sinkhorn R`` R rounds of the assignment exchange
(:attr:`learners.entity.EntityConfig.choice_sinkhorn`; its one parameter starts fresh) and
``--sinkhorn-beta B`` its last inverse temperature (``choice_sinkhorn_beta``). No
reward and no critic: the file written is a policy (``kind="policy"``) that
``allocator.make(..., checkpoint=FILE)``, ``scale_table.py --entity FILE`` and ``agv train
--init-from FILE`` take.

``--iterations 0`` trains nothing: it writes the start file under the flags (new layers
fresh, e.g. an exchange added at test time) and validates it once.

Writes ``--out``/``dagger.safetensors`` (+ sidecar), ``progress.csv`` (loss and the 20v20
validation, seed 12345, 100 episodes, plain and shielded, every second iteration) and
``dagger.probe.json`` (the command, seed, settings and the start file).
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from local_information import velocity_action, view
from provenance import recorded_command
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
    return teacher(env, max_speed)[0]


def teacher(env: Any, max_speed: float = 2.0) -> tuple[torch.Tensor, np.ndarray]:
    """:func:`teacher_actions` and the teacher's goals relative to each AGV (B, N, 2), NaN
    for the AGVs it assigns no task."""
    pos = env.agent_pos.detach().cpu().double().numpy()
    vel = env.agent_vel.detach().cpu().double().numpy()
    tasks = env.task_pos.detach().cpu().double().numpy()
    idle = (env.agent_task < 0).cpu().numpy() & ~env.done.cpu().numpy()[:, None]
    open_ = ~env.task_claimed.cpu().numpy()
    goal = pos.copy()
    chosen = np.full(pos.shape, np.nan)
    for b in np.nonzero(idle.any(1) & open_.any(1))[0]:
        agents, free = np.nonzero(idle[b])[0], np.nonzero(open_[b])[0]
        cost = np.linalg.norm(pos[b][agents][:, None] - tasks[b][free][None], axis=-1)
        rows, cols = linear_sum_assignment(cost)
        goal[b, agents[rows]] = tasks[b, free[cols]]
        chosen[b, agents[rows]] = tasks[b, free[cols]] - pos[b, agents[rows]]
    act = velocity_action(goal - pos, vel, env.world.physics, max_speed)
    return torch.as_tensor(act, dtype=env.dtype), chosen


def choice_slots(obs: torch.Tensor, layout: ObsLayout, chosen: np.ndarray) -> torch.Tensor:
    """The observation's task slot holding the teacher's goal, (B, N) int64: the visible slot
    within 1e-4 of ``chosen`` (the goals relative to the AGVs, (B, N, 2), NaN for none), -1
    where there is none (no goal, or the goal outside the AGV's view)."""
    B, N, _ = obs.shape
    t = obs[..., layout.tasks].reshape(B, N, layout.k_tasks, 3).double()
    gap = torch.linalg.vector_norm(t[..., :2] - torch.as_tensor(chosen).unsqueeze(-2), dim=-1)
    gap = gap.masked_fill(~(t[..., 2] > 0.5), np.inf).nan_to_num(nan=np.inf)
    best, slot = gap.min(-1)
    return torch.where(best < 1e-4, slot, torch.full_like(slot, -1))


def fitting_tensors(learner: Any, tensors: dict[str, torch.Tensor]
                    ) -> tuple[dict[str, torch.Tensor], list[str]]:
    """The learner's policy tensors with every one the file has at the same name and shape
    taken from ``tensors``, and every weight matrix the learner has wider (more input
    columns, e.g. the intent layer with ``--choice-regret``) taken with zero columns added,
    so that it computes what the file's did; returns them and the names that do not come
    whole from the file (sorted)."""
    own = learner.policy_tensors()
    out, fresh = {}, []
    for name, value in own.items():
        theirs = tensors.get(name)
        if theirs is not None and theirs.shape == value.shape:
            out[name] = theirs
            continue
        if theirs is not None and theirs.dim() == value.dim() == 2 \
                and theirs.shape[0] == value.shape[0] and theirs.shape[1] < value.shape[1]:
            out[name] = torch.cat([theirs, value.new_zeros(value.shape[0], value.shape[1]
                                                           - theirs.shape[1])], dim=1)
        else:
            out[name] = value
        fresh.append(name)
    return out, sorted(fresh)


def imitation_loss(act: torch.Tensor, target: torch.Tensor, movable: torch.Tensor,
                   w: torch.Tensor | None, labels: torch.Tensor,
                   choice_weight: float, action_weight: float = 1.0) -> torch.Tensor:
    """The student's loss on a batch: ``action_weight`` times the squared error to the
    teacher's actions (B, N, 2) summed over the two components and averaged over the AGVs
    that can move (``movable``, (B, N) bool), plus ``choice_weight`` times the cross-entropy
    of the choice weights ``w`` (B, N, K; None: no such term) against the teacher's
    ``labels`` (B, N; -1: none), averaged over the movable AGVs with a label."""
    loss = action_weight * (((act - target) ** 2).sum(-1) * movable).sum() \
        / movable.sum().clamp_min(1)
    if w is not None and choice_weight > 0:
        has = (labels >= 0) & movable
        picked = w.gather(-1, labels.clamp_min(0).unsqueeze(-1)).squeeze(-1)
        ce = -torch.log(picked.clamp_min(1e-9)) * has
        loss = loss + choice_weight * ce.sum() / has.sum().clamp_min(1)
    return loss


def write_progress(path: Path, log: list[dict[str, Any]]) -> None:
    """Write the iterations' rows as a CSV (atomic); the columns are the last row's (the
    last iteration always validates, so it has every column)."""
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(log[-1]))
        w.writeheader()
        w.writerows(log)
    tmp.replace(path)


def save_policy(learner: Any, meta: dict[str, Any], path: Path, seed: int) -> None:
    """Write the student as a policy file (atomic): the start file's scenario and sizes, the
    student's own config (with ``--choice-head``, ``choice_head=True``)."""
    learner.target_actor.load_state_dict(learner.actor.state_dict())
    keep = ("algo", "reward", "scenario", "num_agents", "num_tasks", "obs_dim", "state_dim")
    save_checkpoint(path, learner.policy_tensors(),
                    {"kind": "policy", "seed": seed, **{k: meta[k] for k in keep},
                     "config": dataclasses.asdict(learner.config)})


def scenario(name: str, spec: str) -> sim.Scenario:
    n = int(name.split("v")[0])
    kt, ka = view(n, spec)
    return sim.get_scenario(name, k_tasks=kt, k_agents=ka)


def rollout(learner: Any, scen: sim.Scenario, envs: int, seed: int, teacher_share: float,
            gen: torch.Generator, shield: bool = False
            ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """One batch of episodes; returns the running states' observations (S, N, O), the
    teacher's actions (S, N, 2), which AGVs move (S, N) and the task slot the teacher sends
    each to (S, N; -1: none, see :func:`choice_slots`). ``shield``: the actions are
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
        target, chosen = teacher(env)
        slots = choice_slots(obs, env.obs_layout, chosen)
        with torch.no_grad():
            student = learner.policy(obs)
        run = ~env.done
        out.append((obs[run], target[run], ((env.agent_task < 0) & run[:, None])[run],
                    slots[run]))
        act = torch.where(drive, target, student)
        obs, *_ = env.step(act if safety is None else safety.filter(act))
    o, a, m, c = (torch.cat(x) for x in zip(*out, strict=True))
    return o, a, m, c


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
    parser.add_argument("--choice-head", action="store_true",
                        help="the student ends in a TaskChoiceHead (EntityConfig.choice_head): "
                             "the --start file's other layers are loaded, the head starts "
                             "fresh, and the loss adds --choice-weight x the cross-entropy "
                             "of its pointer against the teacher's task")
    parser.add_argument("--choice-weight", type=float, default=1.0)
    parser.add_argument("--choice-rounds", type=int, default=None,
                        help="rounds of the choice head's intent exchange "
                             "(EntityConfig.choice_rounds, bicnet-e); the exchange's layers "
                             "start fresh (default: the --start file's)")
    parser.add_argument("--choice-regret", action="store_true",
                        help="the intent messages carry regrets (EntityConfig.choice_regret); "
                             "the intent layer's new input columns start at zero")
    parser.add_argument("--choice-accumulate", action="store_true",
                        help="the exchange's rounds add their biases up "
                             "(EntityConfig.choice_accumulate)")
    parser.add_argument("--choice-sinkhorn", type=int, default=None,
                        help="rounds of the choice head's assignment exchange "
                             "(EntityConfig.choice_sinkhorn, bicnet-e; default: the --start "
                             "file's)")
    parser.add_argument("--sinkhorn-beta", type=float, default=None,
                        help="the assignment exchange's last inverse temperature "
                             "(EntityConfig.choice_sinkhorn_beta; default: the --start file's)")
    parser.add_argument("--first-share", type=float, default=1.0,
                        help="share of the first iteration's environments the teacher drives "
                             f"(later iterations: {TEACHER_SHARE})")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args(argv)
    if args.iterations < 0 or args.steps < 1 or args.seed < 0:
        parser.error("--iterations must be >= 0, --steps >= 1, --seed >= 0")
    if not 0.0 <= args.first_share <= 1.0:
        parser.error(f"--first-share must be in [0, 1], got {args.first_share}")
    if not (np.isfinite(args.lr) and args.lr > 0):
        parser.error(f"--lr must be a finite number > 0, got {args.lr}")
    if not (np.isfinite(args.choice_weight) and args.choice_weight >= 0):
        parser.error(f"--choice-weight must be a finite number >= 0, got {args.choice_weight}")
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
    config = dict(meta["config"])
    wanted = dict(config)
    if args.choice_head:
        wanted["choice_head"] = True
    if args.choice_rounds is not None:
        wanted["choice_rounds"] = args.choice_rounds
    if args.choice_regret:
        wanted["choice_regret"] = True
    if args.choice_accumulate:
        wanted["choice_accumulate"] = True
    if args.choice_sinkhorn is not None:
        wanted["choice_sinkhorn"] = args.choice_sinkhorn
    if args.sinkhorn_beta is not None:
        wanted["choice_sinkhorn_beta"] = args.sinkhorn_beta
    fresh: list[str] = []
    try:
        learner = make_learner(meta["algo"], meta["obs_dim"], meta["state_dim"],
                               meta["num_agents"], wanted)
    except ValueError as err:
        parser.error(str(err))
    if wanted != config:
        tensors, fresh = fitting_tensors(learner, tensors)
        print(f"fresh: {', '.join(fresh)}", flush=True)
    choice = bool(learner.config.choice_head)
    learner.load_policy_tensors(tensors)
    opt = torch.optim.Adam(learner.actor.parameters(), lr=args.lr)
    args.out.mkdir(parents=True, exist_ok=True)
    data: dict[str, list[tuple[torch.Tensor, ...]]] = {s: [] for s in scens}
    log = []
    t0 = time.perf_counter()
    for it in range(args.iterations):
        share = args.first_share if it == 0 else TEACHER_SHARE
        for k, (name, scen) in enumerate(scens.items()):
            seed = args.seed * 100_000 + it * 100 + k
            data[name] = (data[name] + [rollout(learner, scen, BATCH.get(name, 16), seed,
                                                share, gen, args.shield)])[-KEEP:]
        pooled = {s: [torch.cat(x) for x in zip(*d, strict=True)] for s, d in data.items()}
        total = 0.0
        for _ in range(args.steps):
            loss = torch.zeros(())
            for name, (o, a, m, c) in pooled.items():
                learner.set_layout(ObsLayout(scens[name].k_tasks, scens[name].k_agents))
                idx = torch.randint(len(o), (64,), generator=gen)
                if choice:
                    act, w = learner.policy_and_choice(o[idx])
                else:
                    act, w = learner.policy(o[idx]), None
                loss = loss + imitation_loss(act, a[idx], m[idx], w, c[idx],
                                             args.choice_weight)
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
            save_policy(learner, meta, args.out / "dagger.safetensors", args.seed)
        log.append(row)
        print(json.dumps(row), flush=True)
    if not log:  # --iterations 0: the start under the flags, untrained, validated
        row = dict(iteration=0, loss=None, seconds=0.0)
        plain, shielded = validate(learner, val)
        row.update({f"{k}": v for k, v in plain.items() if k != "shield"})
        row.update({f"shielded_{k}": v for k, v in shielded.items() if k != "shield"})
        log.append(row)
        print(json.dumps(row), flush=True)
    save_policy(learner, meta, args.out / "dagger.safetensors", args.seed)
    write_progress(args.out / "progress.csv", log)
    command = recorded_command(__file__, sys.argv[1:] if argv is None else argv)
    atomic_write_text(args.out / "dagger.probe.json", json.dumps(
        {"command": command, "seed": args.seed, "start": str(args.start),
         "iterations": args.iterations, "steps": args.steps, "lr": args.lr,
         "sizes": args.sizes, "view": args.view, "shield": args.shield,
         "choice_head": choice, "choice_weight": args.choice_weight,
         "choice_rounds": learner.config.choice_rounds,
         "choice_regret": learner.config.choice_regret,
         "choice_accumulate": learner.config.choice_accumulate,
         "choice_sinkhorn": learner.config.choice_sinkhorn,
         "choice_sinkhorn_beta": learner.config.choice_sinkhorn_beta, "fresh": fresh,
         "teacher_share": TEACHER_SHARE, "first_share": args.first_share,
         "keep": KEEP, "batch": BATCH, "final": log[-1]}, indent=2) + "\n")
    print(f"wrote {args.out / 'dagger.safetensors'}")


if __name__ == "__main__":
    main()
