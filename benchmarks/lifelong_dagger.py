"""Lifelong imitation for issue 17: a lifelong entity policy taught by a teacher on a
warehouse floor (DAgger).

    python benchmarks/lifelong_dagger.py --start POLICY.safetensors [--floor warehouse-50 ...]
        [--teacher plan|local] [--view K] [--waypoint-drive] [--drive-sight] [--idle-token]
        [--hidden H]
        [--iterations 8] [--envs 4] [--horizon 300] [--steps 300] [--lr 1e-3]
        [--choice-weight 1.0] [--action-weight 1.0] [--keep-right 0.5]
        [--validation-steps 1000] [--validation-seeds 4242 ...] [--validation-runs 2]
        [--seed 0] [--out benchmarks/results/scale/lifelong/dagger]

Two teachers, neither of which assigns anything: the student claims orders the way every
decentralized policy does here, by reaching an open pickup, so a teacher only says where each
AGV should go.

- ``plan`` (:class:`PlanTeacher`, the default): :class:`allocator.HungarianDispatcher` whose
  plans are kept, not given. Each step it re-plans the floors where something happened (as
  the dispatcher does). That is the "hungarian-shield" row of ``shield_lifelong.py`` minus
  the assignment.
- ``local`` (:class:`LocalTeacher`): each idle AGV's share of the least-distance assignment
  among what it could see (its ``--view`` nearest open pickups and idle AGVs; default
  :data:`LOCAL_VIEW`), re-made every step: a choice that one AGV's surroundings decide.
  ``local-path``: the same, priced by the travel distances round the shelves.

Each AGV's goal is its own drop-off when it carries an order, else the pickup the teacher
gives it; it heads there as ``WaypointDriver`` drives (the first corner of the floor's
shortest path, gain 4, 1.2 units/s), the action scaled into [-1, 1]^2 with its direction
kept. AGVs without a goal brake.

The student is the actor of a lifelong entity policy file (``--start``, e.g. the shipped
``allocator/weights/lifelong/maddpg-greedy.safetensors``; its config's ``shield_keep_right``
becomes ``--keep-right``, so that the file is served behind the lanes it was taught behind),
which ends in a :class:`learners.entity.WaypointHead`: a softmax over its own target and its
K nearest open pickups (``--view K``: K pickup and AGV slots; the floor's own 4 when
omitted). With ``--waypoint-drive`` the head chooses its largest weight outright and drives
as the teacher does (``EntityConfig.waypoint_drive``), so only the choice is taught
(``--action-weight 0``); ``--drive-sight`` heads for the path's first corner, as the
teacher's driver does (``EntityConfig.drive_sight``). ``--idle-token``: the student's AGV
tokens carry each seen AGV's idle bit (``EntityConfig.idle_token``), which the teacher's
choice depends on (its rivals are the idle AGVs). ``--hidden H``: the student starts afresh
at width H (``EntityConfig.hidden``) with the start file's other settings; the file's weights
are then not loaded (the untrained head drives to the own target, or when idle toward the
nearest open pickup by path).

DAgger (Ross et al., 2011): iteration 0 rolls the teacher out, later ones a mix (each floor
driven by the teacher with probability 0.3, else by the student), every rollout through
``SafetyShield(keep_right=--keep-right)`` (the policy is served shielded); every state is
labelled with the teacher's action and the teacher's candidate (the own target, or the pickup
slot of the teacher's order when it is in view); the last 6 rollouts of each floor are kept
(with several ``--floor``, each iteration rolls out on every floor, and each Adam step draws
its batch from one floor, each as likely) and the actor takes ``--steps`` Adam steps on
``--action-weight`` times the squared error of the actions of the AGVs that can move (0: the
choice alone is taught) plus ``--choice-weight`` times the cross-entropy of the head's
softmax against the teacher's candidate (a batch of 16 joint states per step).

Writes ``--out``/``dagger.safetensors`` (a policy file that ``allocator.make(...,
weights=FILE)`` and ``shield_lifelong.py --weights FILE`` take; written after every
validation), ``best.safetensors`` (the student of the best validation so far: the largest
``share``), ``progress.csv`` (loss, the share of the labelled AGVs whose largest weight is
the teacher's candidate, and every second iteration the shielded throughput on each floor:
the mean over ``--validation-seeds`` of ``--validation-runs`` runs of ``--validation-steps``
steps, ``throughput`` for the first floor and ``throughput_<floor>`` for the others, and
``share``, the mean over the floors of the student's throughput over the teacher's) and
``dagger.probe.json`` (command, seed, settings, the start's throughput and the teacher's own
on the same validation, :class:`TeacherDriver`: the ceiling of the imitation; per floor in
``start_by_floor`` and ``teacher_by_floor``).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from dagger_probe import imitation_loss, save_policy, write_progress
from provenance import recorded_command
from scipy.optimize import linear_sum_assignment

import sim
from allocator.dispatch import HungarianDispatcher
from allocator.shield import SafetyShield
from learners.algorithms import ENTITY_ALGORITHMS, make_learner
from learners.checkpoint import load_checkpoint
from sim.io import atomic_write_text
from sim.orders import CARRYING, IDLE, OPEN

OUT = Path(__file__).parent / "results" / "scale" / "lifelong" / "dagger"
KEEP = 6
"""Rollouts kept (the oldest are dropped)."""
TEACHER_SHARE = 0.3
"""Share of the floors the teacher drives after the first iteration."""
BATCH = 16
"""Joint states per Adam step."""
VALIDATION_SEED = 4242


class PlanTeacher(HungarianDispatcher):
    """Hungarian's plan, kept to itself (see the module docstring).

    Attributes
    ----------
    plan : np.ndarray of int64, shape (B, N)
        The order slot the latest plan gives each AGV (-1: none).
    """

    def reset(self, env: Any) -> None:
        """Bind to a lifelong env and plan every floor (nothing is assigned)."""
        self.plan = np.full((env.num_envs, env.num_agents), -1, dtype=np.int64)
        super().reset(env)

    def _replan(self, floors: np.ndarray) -> None:
        self.plan[floors] = self.plan_floors(floors)[floors]
        self.replans += int(floors.sum())

    def teach(self, env: Any) -> tuple[torch.Tensor, np.ndarray, np.ndarray]:
        """Re-plan where events happened; the teacher's actions (B, N, 2), each AGV's goal
        relative to it (B, N, 2; NaN without one) and the goal's kind (B, N: 0 its own
        drop-off, 1 a planned pickup, -1 none)."""
        todo = env.events.any.cpu().numpy()
        if todo.any():
            self._replan(todo)
        pos = env.agent_pos.double().cpu().numpy()
        vel = env.agent_vel.double().cpu().numpy()
        target, has = env.targets()
        status = env.agent_status.cpu().numpy()
        order_status = env.orders.status.cpu().numpy()
        pickup = env.orders.pickup.double().cpu().numpy()
        carrying = has.cpu().numpy() & (status == CARRYING)
        slot = self.plan.clip(min=0)
        planned = (status == IDLE) & (self.plan >= 0) \
            & (np.take_along_axis(order_status, slot, 1) == OPEN)
        goal = np.full(pos.shape, np.nan)
        goal[carrying] = target.double().cpu().numpy()[carrying]
        goal[planned] = np.take_along_axis(pickup, slot[..., None].repeat(2, -1), 1)[planned]
        kind = np.where(carrying, 0, np.where(planned, 1, -1))
        aim = kind >= 0
        cmd = np.zeros_like(pos)
        if aim.any():
            a = pos[aim]
            cmd[aim] = (self.distances.next_waypoint(a, goal[aim]) - a) * self.driver.gain
        speed = np.linalg.norm(cmd, axis=-1, keepdims=True)
        cmd *= self.driver.max_speed / np.maximum(speed, self.driver.max_speed)
        ph = env.world.physics
        action = (cmd - vel * (1.0 - ph.damping)) / (ph.sensitivity * ph.dt / ph.mass)
        action /= np.maximum(1.0, np.abs(action).max(-1, keepdims=True))
        return torch.as_tensor(action, dtype=torch.float32), goal - pos, kind


MAX_HIDDEN = 1024
"""The widest student ``--hidden`` builds (wider would only fill memory on this floor's
batches)."""

LOCAL_VIEW = 16
"""The view of :class:`LocalTeacher` (pickups and AGVs), chosen on the validation seeds 10-14
of warehouse-50 behind the shield with lanes of 0.5 among 4 (the lifelong observation's own
slots), 8 and 16: 175.8, 179.2 and 210.6 deliveries per 1000 steps."""


class LocalTeacher(PlanTeacher):
    """Each idle AGV's choice from what it could see, re-made every step: among its ``view``
    nearest open pickups and its ``view`` nearest other idle AGVs, the least-total-distance
    assignment (straight lines), and the AGV takes its own share (its nearest pickup when it
    is left out). Driven as :class:`PlanTeacher` drives; no central plan, so its labels are
    a function of one AGV's surroundings, which a student with as wide a view can learn.
    With ``path`` the assignment's costs are the floor's travel distances round the shelves
    (``FloorDistances.distance``) instead of straight lines; the pickups in view are still the
    straight-line nearest (the observation's). A Python loop over the idle AGVs: a teacher
    for probes, not a hot path.

    Raises
    ------
    ValueError
        For a ``view`` that is not an integer >= 1, or a ``path`` that is not a bool.
    """

    def __init__(self, view: int = LOCAL_VIEW, path: bool = False) -> None:
        if isinstance(view, bool) or not isinstance(view, int) or view < 1:
            raise ValueError(f"view must be an integer >= 1, got {view!r}")
        if not isinstance(path, bool):
            raise ValueError(f"path must be a bool, got {path!r}")
        super().__init__()
        self.view, self.path = view, path

    def _replan(self, floors: np.ndarray) -> None:
        pass  # the plan is made every step, in teach

    def teach(self, env: Any) -> tuple[torch.Tensor, np.ndarray, np.ndarray]:
        """Every idle AGV's share of its local assignment, then :meth:`PlanTeacher.teach`."""
        pos = env.agent_pos.double().cpu().numpy()
        status = env.agent_status.cpu().numpy()
        order_status = env.orders.status.cpu().numpy()
        pickup = env.orders.pickup.double().cpu().numpy()
        self.plan = np.full(status.shape, -1, dtype=np.int64)
        for b in range(status.shape[0]):
            idle = np.flatnonzero(status[b] == IDLE)
            open_ = np.flatnonzero(order_status[b] == OPEN)
            if not len(open_) or not len(idle):
                continue
            # every idle AGV's distances, once per floor: to the open pickups and to the others
            to_pickup = np.linalg.norm(pos[b, idle][:, None] - pickup[b, open_][None], axis=-1)
            to_agent = np.linalg.norm(pos[b, idle][:, None] - pos[b, idle][None], axis=-1)
            price = self.distances.distance(pos[b, idle], pickup[b, open_]) if self.path \
                else to_pickup
            for k, i in enumerate(idle):
                near = np.argsort(to_pickup[k], kind="stable")[:self.view]  # into open_
                others = np.delete(np.arange(len(idle)), k)
                rivals = others[np.argsort(to_agent[k, others], kind="stable")[:self.view]]
                cost = price[np.concatenate([[k], rivals])][:, near]
                rows, cols = linear_sum_assignment(cost)
                mine = cols[rows == 0]
                self.plan[b, i] = open_[near[mine[0] if len(mine) else np.argmin(cost[0])]]
        return super().teach(env)


class TeacherDriver:
    """A teacher driving by itself, a controller for :func:`validate`: what the student could
    reach by imitating it perfectly (the claims made by reaching a pickup, as the
    student's). ``view``: a :class:`LocalTeacher` of that view (``path``: its costs along
    the floor's paths); None (default): the :class:`PlanTeacher`."""

    def __init__(self, view: int | None = None, path: bool = False) -> None:
        self.view, self.path = view, path

    def reset(self, env: Any) -> None:
        self.env = env
        self.teacher = make_teacher(self.view, self.path)
        self.teacher.reset(env)

    def act(self, obs: torch.Tensor) -> torch.Tensor:
        """The teacher's actions (B, N, 2); ``obs`` is not read (the teacher reads the env)."""
        return self.teacher.teach(self.env)[0]


def candidate_labels(obs: torch.Tensor, layout: Any, rel: np.ndarray,
                     kind: np.ndarray) -> torch.Tensor:
    """The :class:`learners.entity.WaypointHead` candidate of the teacher's goal, (B, N)
    int64: 0 for the AGV's own drop-off (kind 0), 1 + the pickup slot within 1e-3 of ``rel``
    (kind 1), -1 where there is none (no goal, or the pickup out of the AGV's view)."""
    B, N, _ = obs.shape
    t = obs[..., layout.pickups].reshape(B, N, layout.k_pickups, 3).double()
    gap = torch.linalg.vector_norm(t[..., :2] - torch.as_tensor(rel).unsqueeze(-2), dim=-1)
    gap = gap.masked_fill(~(t[..., 2] > 0.5), np.inf).nan_to_num(nan=np.inf)
    best, slot = gap.min(-1) if layout.k_pickups else (torch.full((B, N), np.inf), None)
    kind_t = torch.as_tensor(kind)
    out = torch.full((B, N), -1, dtype=torch.int64)
    out[kind_t == 0] = 0
    seen = (kind_t == 1) & (best < 1e-3)
    if slot is not None:
        out[seen] = 1 + slot[seen]
    return out


def make_teacher(view: int | None = None, path: bool = False) -> PlanTeacher:
    """The teacher: :class:`PlanTeacher` (``view`` None) or ``LocalTeacher(view, path)``."""
    return PlanTeacher() if view is None else LocalTeacher(view, path)


def rollout(learner: Any, floor: Any, envs: int, horizon: int, seed: int, teacher_share: float,
            keep_right: float, gen: torch.Generator, teacher_view: int | None = None,
            teacher_path: bool = False) -> tuple[torch.Tensor, ...]:
    """One batch of floors (a name or a lifelong scenario) for ``horizon`` steps through the
    shield, taught by :func:`make_teacher` (``teacher_view``, ``teacher_path``); returns the
    observations (S, N, O), the teacher's actions (S, N, 2), which AGVs can move (S, N) and
    the teacher's candidates (S, N; -1: none), S = envs x horizon."""
    env = sim.make_env(floor, num_envs=envs, seed=seed)
    obs = env.observe()
    teacher = make_teacher(teacher_view, teacher_path)
    teacher.reset(env)
    learner.reset(env)
    shield = SafetyShield(learner, keep_right=keep_right)
    shield.reset(env)
    drive = torch.rand(envs, 1, 1, generator=gen) < teacher_share
    out: list[tuple[torch.Tensor, ...]] = []
    for _ in range(horizon):
        target, rel, kind = teacher.teach(env)
        labels = candidate_labels(obs, env.obs_layout, rel, kind)
        with torch.no_grad():
            student = learner.policy(obs)
        movable = learner._movable(obs).squeeze(-1) > 0.5
        out.append((obs, target, movable, labels))
        obs, *_ = env.step(shield.filter(torch.where(drive, target, student)))
    return tuple(torch.cat(x) for x in zip(*out, strict=True))


def validate(learner: Any, floor: Any, keep_right: float, steps: int = 1000,
             seeds: tuple[int, ...] = (VALIDATION_SEED,), runs: int = 2) -> float:
    """Shielded deliveries per 1000 steps on ``floor`` (a name or a lifelong scenario), the
    mean over ``seeds`` (default :data:`VALIDATION_SEED`) of ``runs`` runs each."""
    out = []
    for seed in seeds:
        shield = SafetyShield(learner, keep_right=keep_right)
        m = sim.evaluate_lifelong(shield, floor, steps=steps, seed=seed, runs=runs)
        out.append(float(m.throughput))
    return float(np.mean(out))


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--start", required=True, type=Path,
                        help="a lifelong entity learner's policy file")
    parser.add_argument("--floor", nargs="+", default=["warehouse-50"],
                        help="the lifelong floors taught on (each iteration rolls out on "
                             "every one; the first is the primary floor)")
    parser.add_argument("--iterations", type=int, default=8)
    parser.add_argument("--envs", type=int, default=4, help="floors per rollout")
    parser.add_argument("--horizon", type=int, default=300, help="steps per rollout")
    parser.add_argument("--steps", type=int, default=300, help="Adam steps per iteration")
    parser.add_argument("--lr", type=float, default=1e-3)
    parser.add_argument("--choice-weight", type=float, default=1.0)
    parser.add_argument("--action-weight", type=float, default=1.0,
                        help="weight of the squared error on the action (0: the choice only)")
    parser.add_argument("--keep-right", type=float, default=0.5,
                        help="the shield's lane angle in the rollouts and the validation")
    parser.add_argument("--validation-steps", type=int, default=1000,
                        help="steps of each validation run (600 before 2026-12-07: too "
                             "short to show the jams)")
    parser.add_argument("--validation-seeds", type=int, nargs="+", default=[VALIDATION_SEED],
                        help="floors of the validation (the mean is reported)")
    parser.add_argument("--validation-runs", type=int, default=2,
                        help="runs per validation seed")
    parser.add_argument("--teacher", choices=("plan", "local", "local-path"), default="plan",
                        help="plan: Hungarian's plan (PlanTeacher); local: LocalTeacher; "
                             "local-path: LocalTeacher pricing by path length")
    parser.add_argument("--view", type=int, default=None,
                        help="the student's pickup and AGV slots (the floor's own when "
                             f"omitted), and LocalTeacher's view (default {LOCAL_VIEW})")
    parser.add_argument("--waypoint-drive", action="store_true",
                        help="the student chooses outright and drives as WaypointDriver "
                             "(EntityConfig.waypoint_drive); its choice alone is taught")
    parser.add_argument("--drive-sight", action="store_true",
                        help="the waypoint drive heads for the path's first corner "
                             "(EntityConfig.drive_sight); needs --waypoint-drive or a start "
                             "with it")
    parser.add_argument("--idle-token", action="store_true",
                        help="the student's AGV tokens carry the idle bit each AGV tells the "
                             "AGVs that see it (EntityConfig.idle_token); the start may lack "
                             "it (its new weights start at zero)")
    parser.add_argument("--hidden", type=int, default=None,
                        help="start the student afresh at this width (EntityConfig.hidden), "
                             "with the start file's other settings (its weights not loaded)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args(argv)
    for name in ("iterations", "envs", "horizon", "steps", "validation_steps",
                 "validation_runs"):
        if getattr(args, name) < 1:
            parser.error(f"--{name.replace('_', '-')} must be >= 1, got {getattr(args, name)}")
    if args.seed < 0:
        parser.error(f"--seed must be >= 0, got {args.seed}")
    if min(args.validation_seeds) < 0:
        parser.error(f"--validation-seeds must be >= 0, got {args.validation_seeds}")
    if args.view is not None and args.view < 1:
        parser.error(f"--view must be >= 1, got {args.view}")
    if args.hidden is not None and not 1 <= args.hidden <= MAX_HIDDEN:
        parser.error(f"--hidden must be in [1, {MAX_HIDDEN}], got {args.hidden}")
    if args.waypoint_drive and args.action_weight:
        parser.error("--waypoint-drive teaches the choice alone (no gradient reaches its "
                     "action): pass --action-weight 0")
    teacher_view = None if args.teacher == "plan" else (args.view or LOCAL_VIEW)
    teacher_path = args.teacher == "local-path"
    flags = ("waypoint_drive", "drive_sight", "idle_token")
    for name in ("lr", "choice_weight", "action_weight"):
        value = getattr(args, name)
        if not (np.isfinite(value) and value >= 0) or (name == "lr" and value == 0):
            parser.error(f"--{name.replace('_', '-')} must be a finite number "
                         f"{'> 0' if name == 'lr' else '>= 0'}, got {value}")
    if not (np.isfinite(args.keep_right) and 0 <= args.keep_right < np.pi / 2):
        parser.error(f"--keep-right must be in [0, pi/2), got {args.keep_right}")
    if len(set(args.floor)) < len(args.floor):
        parser.error(f"--floor names a floor twice: {args.floor}")
    scenarios = []
    try:
        for floor in args.floor:
            scenarios.append(sim.get_scenario(floor) if args.view is None else
                             sim.get_scenario(floor, k_pickups=args.view, k_agents=args.view))
        tensors, meta = load_checkpoint(args.start, kind="policy")
    except (ValueError, KeyError, FileNotFoundError) as err:
        parser.error(str(err))
    for floor, scenario in zip(args.floor, scenarios, strict=True):
        if not getattr(scenario, "lifelong", False):
            parser.error(f"--floor must name lifelong floors (warehouse-N), got {floor}")
        if args.view is not None and args.view > scenario.num_agents:
            parser.error(f"--view must be at most each floor's fleet ({scenario.num_agents} "
                         f"on {floor}), got {args.view}")
    if meta["algo"] not in ENTITY_ALGORITHMS or "actor.steer.gain" not in tensors:
        parser.error(f"--start must be a lifelong entity policy (its actor ends in a "
                     f"WaypointHead), got {meta['algo']} on {meta['scenario']}")
    torch.set_num_threads(1)
    torch.manual_seed(args.seed)
    gen = torch.Generator().manual_seed(args.seed)
    # the student is served behind the lanes it was taught behind
    config = dict(meta["config"], shield_keep_right=args.keep_right,
                  **{k: getattr(args, k) or meta["config"].get(k, False) for k in flags})
    if args.hidden is not None:
        config["hidden"] = args.hidden
    try:  # the config's own checks (e.g. --drive-sight without a waypoint drive)
        learner = make_learner(meta["algo"], meta["obs_dim"], meta["state_dim"],
                               meta["num_agents"], config)
    except ValueError as err:
        parser.error(str(err))
    if args.hidden is None:
        learner.load_policy_tensors(learner.adapt_init_tensors(tensors))
    opt = torch.optim.Adam(learner.actor.parameters(), lr=args.lr)
    args.out.mkdir(parents=True, exist_ok=True)
    data: list[list[tuple[torch.Tensor, ...]]] = [[] for _ in scenarios]
    reading: list[tuple[Any, Any]] = []  # each floor's layout and waypoints, for the tokens
    for scenario in scenarios:
        learner.reset(sim.make_env(scenario, num_envs=1, seed=0))
        reading.append((learner.layout, learner.floor))
    log = []
    best: dict[str, Any] | None = None
    t0 = time.perf_counter()
    checks = dict(steps=args.validation_steps, seeds=tuple(args.validation_seeds),
                  runs=args.validation_runs)

    def on(f: int) -> Any:
        """Floor ``f``'s scenario, with the learner reading that floor's kept waypoints
        (so that ``reset`` on it keeps them rather than planning the floor again)."""
        learner.set_layout(*reading[f])
        return scenarios[f]

    start = [validate(learner, on(f), args.keep_right, **checks) for f in range(len(scenarios))]
    ceiling = [validate(TeacherDriver(teacher_view, teacher_path), sc, args.keep_right,
                        **checks)
               for sc in scenarios]

    def columns(values: list[float]) -> dict[str, float]:
        """The primary floor's throughput, the others' (``throughput_<floor>``) and the
        mean share of the teacher's throughput over the floors (what selects the best)."""
        out = {"throughput": values[0]}
        out.update({f"throughput_{f}": v for f, v in zip(args.floor[1:], values[1:],
                                                          strict=True)})
        out["share"] = round(float(np.mean([v / max(c, 1e-9) for v, c in
                                            zip(values, ceiling, strict=True)])), 4)
        return out

    print(json.dumps({"iteration": 0, **columns(start), "teacher_throughput": ceiling[0]}),
          flush=True)
    for it in range(args.iterations):
        share = 1.0 if it == 0 else TEACHER_SHARE
        for f in range(len(scenarios)):
            data[f] = (data[f] + [rollout(learner, on(f), args.envs, args.horizon,
                                          args.seed * 100_000 + it + 1000 * f, share,
                                          args.keep_right, gen, teacher_view,
                                          teacher_path)])[-KEEP:]
        pooled = [tuple(torch.cat(x) for x in zip(*d, strict=True)) for d in data]
        total = hits = labelled = 0.0
        for _ in range(args.steps):
            f = int(torch.randint(len(pooled), (1,), generator=gen)) if len(pooled) > 1 else 0
            learner.set_layout(*reading[f])
            o, a, m, c = pooled[f]
            idx = torch.randint(len(o), (BATCH,), generator=gen)
            act, w = learner.policy_and_choice(o[idx])
            loss = imitation_loss(act, a[idx], m[idx], w, c[idx], args.choice_weight,
                                  args.action_weight)
            opt.zero_grad()
            loss.backward()
            torch.nn.utils.clip_grad_norm_(learner.actor.parameters(), 1.0)
            opt.step()
            total += float(loss.detach())
            has = (c[idx] >= 0) & m[idx]
            hits += float(((w.argmax(-1) == c[idx]) & has).sum())
            labelled += float(has.sum())
        seen = torch.cat([p[3].reshape(-1) for p in pooled])
        row: dict[str, Any] = dict(iteration=it + 1, loss=total / args.steps,
                                   accuracy=round(hits / max(labelled, 1.0), 4),
                                   labelled=round(float((seen >= 0).float().mean()), 3),
                                   seconds=round(time.perf_counter() - t0, 1))
        if it % 2 == 1 or it == args.iterations - 1:
            row.update(columns([validate(learner, on(f), args.keep_right, **checks)
                                for f in range(len(scenarios))]))
            save_policy(learner, meta, args.out / "dagger.safetensors", args.seed)
            if best is None or row["share"] > best["share"]:
                best = row
                save_policy(learner, meta, args.out / "best.safetensors", args.seed)
        log.append(row)
        print(json.dumps(row), flush=True)
    write_progress(args.out / "progress.csv", log)
    command = recorded_command(__file__, sys.argv[1:] if argv is None else argv)
    atomic_write_text(args.out / "dagger.probe.json", json.dumps(
        {"command": command, "seed": args.seed, "start": str(args.start),
         "floor": args.floor[0], "floors": args.floor, "iterations": args.iterations,
         "envs": args.envs,
         "horizon": args.horizon, "steps": args.steps, "lr": args.lr,
         "choice_weight": args.choice_weight, "action_weight": args.action_weight,
         "keep_right": args.keep_right,
         "validation_steps": args.validation_steps,
         "validation_seeds": args.validation_seeds, "validation_runs": args.validation_runs,
         "teacher": args.teacher, "teacher_view": teacher_view, "view": args.view,
         "hidden": config["hidden"], "fresh": args.hidden is not None,
         **{k: config[k] for k in flags},
         "teacher_share": TEACHER_SHARE, "keep": KEEP, "batch": BATCH,
         "start_throughput": start[0], "teacher_throughput": ceiling[0],
         "start_by_floor": dict(zip(args.floor, start, strict=True)),
         "teacher_by_floor": dict(zip(args.floor, ceiling, strict=True)), "final": log[-1],
         "best": best},
        indent=2) + "\n")
    print(f"wrote {args.out / 'dagger.safetensors'}")


if __name__ == "__main__":
    main()
