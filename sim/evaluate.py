"""The paper's metrics, made exact (see ``DESIGN.md``), and :func:`evaluate`.

A controller is anything with ``act(obs) -> actions`` ((B, N, O) -> (B, N, 2)), or a plain
callable doing the same. If it also has ``reset(env)``, it is called after every reset of the
evaluation environments, so centralized controllers can read ``env.agent_pos``,
``env.task_pos`` and ``env.world`` and plan; ``sim`` never imports ``allocator``.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import numpy as np
import torch
from torch import Tensor

from sim.core import AGVEnv
from sim.scenarios import Scenario, get_scenario

__all__ = ["Controller", "Metrics", "evaluate", "metrics_from_episodes"]


@runtime_checkable
class Controller(Protocol):
    """What :func:`evaluate` calls: ``act(obs)`` with obs (B, N, O), returning (B, N, 2)."""

    def act(self, obs: Tensor) -> Tensor: ...


@dataclass
class Metrics:
    """Evaluation results over E episodes.

    Attributes
    ----------
    response_rate : float
        Claimed tasks / generated tasks over all episodes, in [0, 1].
    avg_reward : float
        Mean over episodes of the episode sum of R_t = -(sum over tasks of the distance to the
        nearest AGV) - (overlapping AGV pairs).
    avg_time : float
        Mean steps until every task is claimed, an unfinished episode counting the step limit.
    avg_time_finished : float
        The same over finished episodes only (NaN if none finished).
    collisions : float
        Overlapping AGV pairs summed over an episode's steps, averaged over episodes.
    finished_rate : float
        Fraction of episodes in which every task was claimed.
    episodes : int
    claims_per_episode : np.ndarray, shape (E,)
        Tasks claimed in each episode (the paper's Fig. 8).
    task_of_agent : np.ndarray, shape (E, N)
        Task claimed by each AGV in each episode, -1 if none (Figs. 10-12).
    episode_time : np.ndarray, shape (E,)
        Steps each episode ran.
    episode_reward : np.ndarray, shape (E,)
    seconds : float
        Wall-clock time of the evaluation.
    """

    response_rate: float
    avg_reward: float
    avg_time: float
    avg_time_finished: float
    collisions: float
    finished_rate: float
    episodes: int
    claims_per_episode: np.ndarray = field(repr=False)
    task_of_agent: np.ndarray = field(repr=False)
    episode_time: np.ndarray = field(repr=False)
    episode_reward: np.ndarray = field(repr=False)
    episode_collisions: np.ndarray = field(repr=False)
    num_tasks: int = 0
    seconds: float = 0.0

    def preference_matrix(self) -> np.ndarray:
        """(N, M) fraction of episodes in which AGV i claimed task j (Figs. 10-12)."""
        n = self.task_of_agent.shape[1]
        counts = np.zeros((n, self.num_tasks))
        for i in range(n):
            col = self.task_of_agent[:, i]
            np.add.at(counts[i], col[col >= 0], 1)
        return counts / max(self.episodes, 1)

    def as_dict(self) -> dict[str, float]:
        """The scalar metrics, for tables and logs."""
        return {
            "response_rate": self.response_rate,
            "avg_reward": self.avg_reward,
            "avg_time": self.avg_time,
            "avg_time_finished": self.avg_time_finished,
            "collisions": self.collisions,
            "finished_rate": self.finished_rate,
            "episodes": float(self.episodes),
        }


def metrics_from_episodes(
    claims: np.ndarray,
    num_tasks: int,
    steps: np.ndarray,
    finished: np.ndarray,
    rewards: np.ndarray,
    collisions: np.ndarray,
    task_of_agent: np.ndarray,
    seconds: float = 0.0,
) -> Metrics:
    """Build :class:`Metrics` from per-episode records (all arrays have E rows).

    Parameters
    ----------
    claims : (E,) tasks claimed per episode
    num_tasks : M, tasks generated per episode
    steps : (E,) steps each episode ran (the step limit if unfinished)
    finished : (E,) bool, every task claimed
    rewards : (E,) episode sums of R_t
    collisions : (E,) overlapping pairs summed over the episode
    task_of_agent : (E, N) task held by each AGV at the end, -1 if none
    """
    claims = np.asarray(claims, dtype=np.int64)
    e = len(claims)
    if e == 0:
        raise ValueError("no episodes to score; expected at least one")
    finished = np.asarray(finished, dtype=bool)
    steps = np.asarray(steps, dtype=np.float64)
    return Metrics(
        response_rate=float(claims.sum() / (num_tasks * e)),
        avg_reward=float(np.mean(rewards)),
        avg_time=float(steps.mean()),
        avg_time_finished=float(steps[finished].mean()) if finished.any() else float("nan"),
        collisions=float(np.mean(collisions)),
        finished_rate=float(finished.mean()),
        episodes=e,
        claims_per_episode=claims,
        task_of_agent=np.asarray(task_of_agent, dtype=np.int64),
        episode_time=steps,
        episode_reward=np.asarray(rewards, dtype=np.float64),
        episode_collisions=np.asarray(collisions, dtype=np.float64),
        num_tasks=num_tasks,
        seconds=seconds,
    )


def _as_policy(controller: Any) -> Callable[[Tensor], Tensor]:
    if hasattr(controller, "act"):
        return controller.act
    if callable(controller):
        return controller
    raise ValueError(
        "controller must have an act(obs) method or be a callable obs -> actions, "
        f"got {type(controller).__name__}"
    )


@torch.no_grad()
def run_episodes(
    env: AGVEnv, controller: Any, seed: int | None = None, record: bool = False
) -> dict[str, Any]:
    """Run one episode in every environment of ``env`` until all are done.

    Returns per-environment arrays ``claims``, ``steps``, ``finished``, ``rewards``,
    ``collisions``, ``task_of_agent`` and, if ``record``, ``agent_pos`` (T+1, B, N, 2),
    ``claimed`` (T+1, B, M) and ``agent_task`` (T+1, B, N) for rendering.
    """
    act = _as_policy(controller)
    obs = env.reset(seed=seed)
    if hasattr(controller, "reset"):
        controller.reset(env)
    B = env.num_envs
    rewards = torch.zeros(B, dtype=torch.float64)
    collisions = torch.zeros(B, dtype=torch.float64)
    frames_pos, frames_claim, frames_task = [], [], []
    if record:
        frames_pos.append(env.agent_pos.clone())
        frames_claim.append(env.task_claimed.clone())
        frames_task.append(env.agent_task.clone())
    while not bool(env.done.all()):
        actions = act(obs)
        if not isinstance(actions, Tensor):
            actions = torch.as_tensor(np.asarray(actions), dtype=env.dtype)
        obs, _, _, info = env.step(actions)
        rewards += info["team_reward"].double().cpu()
        collisions += info["collision_pairs"].double().cpu()
        if record:
            frames_pos.append(env.agent_pos.clone())
            frames_claim.append(env.task_claimed.clone())
            frames_task.append(env.agent_task.clone())
    out = {
        "claims": env.task_claimed.sum(dim=1).cpu().numpy(),
        "steps": env.steps.cpu().numpy(),
        "finished": env.task_claimed.all(dim=1).cpu().numpy(),
        "rewards": rewards.numpy(),
        "collisions": collisions.numpy(),
        "task_of_agent": env.agent_task.cpu().numpy(),
    }
    if record:
        out["agent_pos"] = torch.stack(frames_pos).cpu().numpy()
        out["claimed"] = torch.stack(frames_claim).cpu().numpy()
        out["agent_task"] = torch.stack(frames_task).cpu().numpy()
    return out


def evaluate(
    controller: Any,
    scenario: str | Scenario = "3v3",
    episodes: int = 300,
    seed: int = 0,
    batch_size: int = 1024,
    device: str | torch.device = "cpu",
) -> Metrics:
    """Score a controller on the paper's metrics over seeded test episodes.

    Parameters
    ----------
    controller : Controller or callable
        ``act(obs)`` / ``controller(obs)`` mapping (B, N, O) observations to (B, N, 2) actions;
        an optional ``reset(env)`` is called after each batch of episodes starts.
    scenario : str or Scenario
    episodes : int
        Number of test episodes E, run ``batch_size`` at a time in parallel environments.
    seed : int
        Seed of the test episodes: the same seed gives the same scenes for every controller.
    batch_size : int
        Parallel environments per batch.

    Returns
    -------
    Metrics
        ``response_rate``, ``avg_reward``, ``avg_time``, ``collisions`` and the per-episode
        records (``claims_per_episode``, ``task_of_agent``).

    Examples
    --------
    >>> import sim, torch
    >>> m = sim.evaluate(lambda obs: torch.zeros(*obs.shape[:2], 2), "3v3", episodes=8, seed=0)
    >>> 0.0 <= m.response_rate <= 1.0
    True
    """
    if not isinstance(episodes, (int, np.integer)) or episodes < 1:
        raise ValueError(f"episodes must be a positive integer, got {episodes!r}")
    if batch_size < 1:
        raise ValueError(f"batch_size must be positive, got {batch_size!r}")
    scn = get_scenario(scenario)
    _as_policy(controller)
    start = time.perf_counter()
    parts: list[dict[str, Any]] = []
    done_eps = 0
    chunk = 0
    while done_eps < episodes:
        b = min(batch_size, episodes - done_eps)
        env = AGVEnv(scn, num_envs=b, reward="minidist", seed=seed, device=device)
        parts.append(run_episodes(env, controller, seed=seed * 1_000_003 + chunk))
        done_eps += b
        chunk += 1
    cat = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    return metrics_from_episodes(
        cat["claims"], scn.num_tasks, cat["steps"], cat["finished"], cat["rewards"],
        cat["collisions"], cat["task_of_agent"], seconds=time.perf_counter() - start,
    )
