"""Where does a choice-head student lose its time to the teacher it imitates? (issue 17)

    python benchmarks/choice_probe.py --policy FILE [--size 20v20] [--view full]
        [--episodes 100] [--seed 12345] [--out DIR]

``FILE`` is an episodic entity policy with a choice head (``dagger_probe.py --choice-head``
writes them). On the same seeded episodes this runs the student (plain and behind
:class:`allocator.shield.SafetyShield`) and its teacher, the re-planning Hungarian of
``dagger_probe.py`` (every step, the idle AGVs assigned to the open tasks by least total
distance, each driven at its task and stopped on it), and measures along the student's
own rollout, step by step:

- the idle AGVs left (the episode ends when every task is claimed; the teacher's curve
  beside it, from its own rollout of the same episodes);
- agreement: the share of idle AGVs whose pointer (the arg max of the choice weights)
  is on the task the teacher would send them to, among those whose teacher task they see;
- clashes: the share of idle AGVs whose pointed task another idle AGV points at too.

Writes ``choice.md``, ``choice.json`` (command, seed, every curve) and ``choice.png``
(the three curves against the step) to ``--out`` (default: beside the policy file,
``choice-<size>/``).
"""

from __future__ import annotations

import argparse
import datetime
import json
import platform
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
from dagger_probe import VALIDATION_SEED, choice_slots, scenario, teacher
from provenance import recorded_command

import sim
from allocator.shield import SafetyShield
from learners.algorithms import ENTITY_ALGORITHMS, make_learner
from learners.checkpoint import load_checkpoint
from sim.io import atomic_save, atomic_write_text
from sim.observations import ObsLayout


class Teacher:
    """The re-planning Hungarian as a controller for :func:`sim.evaluate`."""

    def reset(self, env: Any) -> None:
        self.env = env

    def act(self, obs: torch.Tensor) -> torch.Tensor:
        """The teacher's actions (B, N, 2); ``obs`` is not read (the teacher reads the env)."""
        return teacher(self.env)[0]


def load_student(path: Path, scen: sim.Scenario) -> Any:
    """The choice-head entity learner of the policy file ``path``, reading ``scen``'s view.

    Raises
    ------
    ValueError
        The file is not an episodic entity policy with a choice head.
    """
    tensors, meta = load_checkpoint(path, kind="policy")
    config = meta.get("config") or {}
    if meta["algo"] not in ENTITY_ALGORITHMS or not config.get("choice_head", False):
        raise ValueError(f"{path} is not an episodic entity policy with a choice head "
                         f"(algo {meta['algo']!r}, choice_head "
                         f"{config.get('choice_head', False)}); dagger_probe.py "
                         "--choice-head writes one")
    learner = make_learner(meta["algo"], meta["obs_dim"], meta["state_dim"],
                           meta["num_agents"], dict(config))
    learner.load_policy_tensors(tensors)
    learner.set_layout(ObsLayout(scen.k_tasks, scen.k_agents))
    return learner


def pointed_tasks(env: Any, obs: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """The task index each AGV's pointer is on, (B, N) int64, -1 where no task is visible:
    the arg max slot's relative position matched to the nearest task of the scene."""
    L = env.obs_layout
    B, N, _ = obs.shape
    t = obs[..., L.tasks].reshape(B, N, L.k_tasks, 3)
    slot = w.argmax(-1)
    rel = torch.gather(t[..., :2], 2, slot[..., None, None].expand(B, N, 1, 2)).squeeze(2)
    at = obs[..., L.pos] + rel
    task = torch.cdist(at.double(), env.task_pos.double()).argmin(-1)
    return torch.where((t[..., 2] > 0.5).any(-1), task, torch.full_like(task, -1))


def curves(learner: Any, scen: sim.Scenario, episodes: int, seed: int) -> dict[str, list]:
    """Step-by-step curves of the student's rollout and the teacher's (see the module
    docstring): ``idle``, ``teacher_idle`` (idle AGVs per episode, the finished episodes
    counting 0), ``agreement`` and ``clashes`` (shares, None where no idle AGV counts) and
    ``agreement_pooled`` (one value: the agreement over every idle AGV and step)."""
    env = sim.make_env(scen, num_envs=episodes, seed=seed)
    obs = env.observe()
    learner.reset(env)
    idle_n, agree, clash, hits, seen_n = [], [], [], 0, 0
    while not bool(env.done.all()):
        _, chosen = teacher(env)
        slots = choice_slots(obs, env.obs_layout, chosen)
        with torch.no_grad():
            act, w = learner.policy_and_choice(obs)
        idle = (env.agent_task < 0) & ~env.done[:, None]
        seen = idle & (slots >= 0)
        hit = (w.argmax(-1) == slots) & seen
        task = pointed_tasks(env, obs, w)
        mine = task.unsqueeze(-1) == task.unsqueeze(-2)  # (B, N, N)
        both = idle.unsqueeze(-1) & idle.unsqueeze(-2) & (task >= 0).unsqueeze(-1)
        both &= ~torch.eye(task.shape[1], dtype=torch.bool)
        clashed = (mine & both).any(-1) & idle
        n, k_seen, k_hit = int(idle.sum()), int(seen.sum()), int(hit.sum())
        hits, seen_n = hits + k_hit, seen_n + k_seen
        idle_n.append(n / episodes)
        agree.append(k_hit / k_seen if k_seen else None)
        clash.append(float(clashed.sum()) / n if n else None)
        obs, *_ = env.step(act)
    env = sim.make_env(scen, num_envs=episodes, seed=seed)
    teacher_idle = []
    while not bool(env.done.all()):
        idle = (env.agent_task < 0) & ~env.done[:, None]
        teacher_idle.append(int(idle.sum()) / episodes)
        env.step(teacher(env)[0])
    return dict(idle=idle_n, teacher_idle=teacher_idle, agreement=agree, clashes=clash,
                agreement_pooled=[hits / max(seen_n, 1)])


def plot(data: dict[str, list], title: str, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(10, 4))

    def line(key: str) -> list[float]:
        return [np.nan if v is None else v for v in data[key]]

    ax1.plot(data["idle"], marker=".", label="student")
    ax1.plot(data["teacher_idle"], marker=".", label="teacher (re-planning Hungarian)")
    ax1.set_ylabel("idle AGVs per episode")
    ax2.plot(line("agreement"), marker=".", label="pointer on the teacher's task")
    ax2.plot(line("clashes"), marker=".", label="pointer on a task another idle AGV points at")
    ax2.set_ylabel("share of the idle AGVs")
    ax2.set_ylim(0, 1)
    for ax in (ax1, ax2):
        ax.set_xlabel("step")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    atomic_save(lambda f: fig.savefig(f, format="png", dpi=120), path)
    plt.close(fig)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--policy", required=True, type=Path,
                        help="an episodic entity policy file with a choice head")
    parser.add_argument("--size", default="20v20", help="an 'NvN' scenario")
    parser.add_argument("--view", default="full", help="'KT:KA' slots or 'full'")
    parser.add_argument("--episodes", type=int, default=100)
    parser.add_argument("--seed", type=int, default=VALIDATION_SEED)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)
    if args.episodes < 1 or args.seed < 0:
        parser.error("--episodes must be >= 1 and --seed >= 0")
    try:
        scen = scenario(args.size, args.view)
        student = load_student(args.policy, scen)
    except (ValueError, KeyError, FileNotFoundError) as err:
        parser.error(str(err))
    out = args.out or args.policy.parent / f"choice-{args.size}"
    torch.set_num_threads(1)
    t0 = time.perf_counter()
    rows = []
    for name, ctl in (("teacher", Teacher()), ("student", student),
                      ("student + shield", SafetyShield(student))):
        m = sim.evaluate(ctl, scen, episodes=args.episodes, seed=args.seed)
        rows.append(dict(controller=name, response=m.response_rate, avg_time=m.avg_time,
                         finished=m.finished_rate, overlaps=m.collisions))
        print(json.dumps(rows[-1]), flush=True)
    data = curves(student, scen, args.episodes, args.seed)
    def to_last_tenth(idle: list[float]) -> int:
        """The first step with at most a tenth of the start's idle AGVs."""
        return int(np.argmax(np.asarray(idle) <= 0.1 * idle[0]))

    summary = dict(
        agreement=data["agreement_pooled"][0],
        agreement_first_step=data["agreement"][0],
        clashes_first_step=data["clashes"][0],
        steps_to_last_tenth=to_last_tenth(data["idle"]),
        teacher_steps_to_last_tenth=to_last_tenth(data["teacher_idle"]))
    command = recorded_command(__file__, sys.argv[1:] if argv is None else argv)
    stamp = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    out.mkdir(parents=True, exist_ok=True)
    lines = [f"# Choice probe: {args.policy} on {args.size} (view {args.view})", "",
             f"`{command}` on {platform.machine()}, Python {platform.python_version()}, "
             f"torch {torch.__version__}, {stamp}; seed {args.seed}, {args.episodes} "
             f"episodes, {time.perf_counter() - t0:.0f} s.", "",
             "| controller | response | avg time | finished | overlapping pairs per episode |",
             "|---|---|---|---|---|"]
    lines += [f"| {r['controller']} | {r['response']:.3f} | {r['avg_time']:.2f} | "
              f"{r['finished']:.2f} | {r['overlaps']:.2f} |" for r in rows]
    lines += ["", f"Along the student's rollout: its pointer is on the teacher's task for "
              f"{summary['agreement']:.1%} of the idle AGVs over all steps, "
              f"{summary['agreement_first_step']:.1%} at the first step; there "
              f"{summary['clashes_first_step']:.1%} point at a task another idle AGV "
              f"points at; the idle AGVs fall to a tenth of the start in "
              f"{summary['steps_to_last_tenth']} steps (teacher: "
              f"{summary['teacher_steps_to_last_tenth']}). Curves: `choice.png`, "
              "`choice.json`."]
    atomic_write_text(out / "choice.md", "\n".join(lines) + "\n")
    atomic_write_text(out / "choice.json", json.dumps(
        dict(command=command, seed=args.seed, date=stamp, policy=str(args.policy),
             size=args.size, view=args.view, episodes=args.episodes, rows=rows,
             summary=summary, curves=data), indent=1) + "\n")
    plot(data, f"{args.policy} on {args.size}, view {args.view}", out / "choice.png")
    print(f"wrote {out / 'choice.md'}")


if __name__ == "__main__":
    main()
