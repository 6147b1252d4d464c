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

from sim import native
from sim.checks import check_count, check_device, check_seed
from sim.env import AGVEnv
from sim.scenarios import Scenario, get_scenario

__all__ = ["Controller", "Metrics", "evaluate", "metrics_from_episodes", "run_episodes",
           "evaluation_scenes"]


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


_SEED_MIX = 1_000_003
"""The evaluation seed is mixed into the scene generator's seed as ``seed * _SEED_MIX``."""

_SEED_LIMIT = 2**63
"""Seeds lie in [0, 2**63); the mixed seed is reduced modulo 2**63."""


def _controller_name(controller: Any) -> str:
    return getattr(controller, "__qualname__", type(controller).__name__)


def _as_policy(controller: Any) -> Callable[[Tensor], Any]:
    act = getattr(controller, "act", None)
    if callable(act):
        return act
    if callable(controller):
        return controller
    raise ValueError(
        "controller must have an act(obs) method or be a callable obs -> actions, "
        f"got {type(controller).__name__}"
    )


def _describe(value: Any) -> str:
    """A short description of what a controller returned, for error messages."""
    if value is None:
        return "None"
    if isinstance(value, (str, bytes)):
        return f"a {type(value).__name__} {value[:40]!r}"
    if isinstance(value, (Tensor, np.ndarray)):
        return f"a {type(value).__name__} of shape {tuple(value.shape)} and dtype {value.dtype}"
    return f"a {type(value).__name__}"


def _checked_actions(out: Any, controller: Any, shape: tuple[int, int, int]) -> Tensor:
    """The controller's output as a tensor of real actions of ``shape`` (B, N, 2).

    Raises
    ------
    ValueError
        Naming the controller and what it returned, for anything but finite real numbers of
        the right shape.
    """
    def fail(problem: str) -> ValueError:
        return ValueError(
            f"controller {_controller_name(controller)} returned {problem}; expected actions "
            f"of shape (B, N, 2) = {shape} with finite real values"
        )

    if isinstance(out, Tensor):
        actions = out
        if actions.dtype == torch.bool or actions.is_complex():
            raise fail(_describe(out))
    else:
        try:
            arr = np.asarray(out)
        except (TypeError, ValueError):
            raise fail(_describe(out)) from None
        if arr.dtype.kind not in "iuf":
            raise fail(_describe(out))
        actions = torch.as_tensor(arr, dtype=torch.float32)
    if tuple(actions.shape) != shape:
        raise fail(_describe(out))
    if actions.is_floating_point() and not bool(torch.isfinite(actions).all()):
        raise fail(f"{_describe(out)} with NaN or infinite values")
    return actions


@torch.no_grad()
def _play(env: AGVEnv, obs: Tensor, controller: Any, record: bool) -> dict[str, Any]:
    """Run the episodes that start in every environment of ``env`` (observations ``obs``)
    until all are done, calling ``controller.reset(env)`` first if it has one."""
    act = _as_policy(controller)
    if callable(getattr(controller, "reset", None)):
        controller.reset(env)
    B = env.num_envs
    shape = (B, env.num_agents, 2)
    rewards = torch.zeros(B, dtype=torch.float64)
    collisions = torch.zeros(B, dtype=torch.float64)
    frames_pos, frames_claim, frames_task = [], [], []
    if record:
        frames_pos.append(env.agent_pos.clone())
        frames_claim.append(env.task_claimed.clone())
        frames_task.append(env.agent_task.clone())
    while not bool(env.done.all()):
        actions = _checked_actions(act(obs), controller, shape)
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


def run_episodes(
    env: AGVEnv, controller: Any, seed: int | None = None, record: bool = False
) -> dict[str, Any]:
    """Reset every environment of ``env`` (with ``seed``) and run one episode in each until
    all are done.

    Returns per-environment arrays ``claims``, ``steps``, ``finished``, ``rewards``,
    ``collisions``, ``task_of_agent`` and, if ``record``, ``agent_pos`` (T+1, B, N, 2),
    ``claimed`` (T+1, B, M) and ``agent_task`` (T+1, B, N) for rendering.
    """
    _as_policy(controller)
    return _play(env, env.reset(seed=seed), controller, record)


def _scenario(scenario: Any) -> Scenario:
    if not isinstance(scenario, (str, Scenario)):
        raise ValueError(
            f"scenario must be a registry name such as '3v3' or a Scenario, "
            f"got {type(scenario).__name__}"
        )
    scn = get_scenario(scenario)
    if not isinstance(scn, Scenario):
        raise ValueError(f"scenario {scn.name!r} is a lifelong scenario; score it with "
                         f"sim.evaluate_lifelong(controller, {scn.name!r}, steps=...)")
    return scn


def evaluation_scenes(
    scenario: str | Scenario, episodes: int, seed: int, device: str | torch.device = "cpu"
) -> tuple[Tensor, Tensor]:
    """The start scenes of :func:`evaluate`'s ``episodes`` test episodes for ``seed``.

    All E scenes are drawn at once, as an environment of E environments reset with the
    generator seed ``seed * 1_000_003`` (modulo 2**63) draws them, so that the scenes do not
    depend on the batch size they are run with. They do depend on E: the spawner draws all E
    at once, so the first 20 scenes of E = 200 are not those of E = 20. The draw needs memory
    for all of them at once (positions and the spawner's candidates): about 0.6 kB per
    episode for ``6v6`` and 1.7 kB for ``warehouse`` at its peak, e.g. 0.6 GB and 1.7 GB for a
    million episodes.

    Parameters
    ----------
    scenario : str or Scenario
    episodes : int
        Number of scenes E.
    seed : int
        The evaluation seed, in [0, 2**63).
    device : str or torch.device

    Returns
    -------
    agents : Tensor, shape (E, N, 2)
    tasks : Tensor, shape (E, M, 2)

    Raises
    ------
    ValueError
        Naming a scenario, episode count, seed or device that is not valid.
    """
    scenario = _scenario(scenario)
    episodes = check_count("episodes", episodes)
    seed = check_seed(seed, bits=63)
    dev = check_device(device)
    generator = torch.Generator(device=dev)
    generator.manual_seed(seed * _SEED_MIX % _SEED_LIMIT)
    return scenario.spawn(episodes, generator, dev, kernels=native.library_for(dev))


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
        ``act(obs)`` / ``controller(obs)`` mapping (B, N, O) observations to (B, N, 2) actions
        (a tensor or anything numpy turns into real numbers); an optional ``reset(env)`` is
        called after each batch of episodes has its scenes placed.
    scenario : str or Scenario
    episodes : int
        Number of test episodes E, run ``batch_size`` at a time in parallel environments.
    seed : int
        Seed of the test episodes, in [0, 2**63): the same seed gives the same scenes for
        every controller and every ``batch_size`` (see :func:`evaluation_scenes`), for the
        same ``episodes``; another count draws other scenes (the first 20 of 200 episodes
        are not the 20 of a 20-episode run).
    batch_size : int
        Parallel environments per batch.
    device : str or torch.device
        Where the environments run (default CPU).

    Returns
    -------
    Metrics
        ``response_rate``, ``avg_reward``, ``avg_time``, ``collisions`` and the per-episode
        records (``claims_per_episode``, ``task_of_agent``), E rows each.

    Raises
    ------
    ValueError
        Naming the argument: a controller without ``act`` that is not callable, or one that
        returns anything but finite real (B, N, 2) actions; an unknown scenario; ``episodes``
        or ``batch_size`` that is not a positive integer (bool, float and str are refused);
        a seed outside [0, 2**63) or not an integer; a device that does not exist here.

    Examples
    --------
    >>> import sim, torch
    >>> m = sim.evaluate(lambda obs: torch.zeros(*obs.shape[:2], 2), "3v3", episodes=8, seed=0)
    >>> 0.0 <= m.response_rate <= 1.0
    True
    """
    _as_policy(controller)
    scn = _scenario(scenario)
    episodes = check_count("episodes", episodes)
    seed = check_seed(seed, bits=63)
    batch_size = check_count("batch_size", batch_size)
    dev = check_device(device)
    start = time.perf_counter()
    agents, tasks = evaluation_scenes(scn, episodes, seed, dev)
    parts: list[dict[str, Any]] = []
    for first in range(0, episodes, batch_size):
        rows = slice(first, min(first + batch_size, episodes))
        env = AGVEnv(scn, num_envs=rows.stop - first, reward="minidist", seed=seed, device=dev)
        env.set_state(agents[rows], tasks[rows])
        parts.append(_play(env, env.observe(), controller, record=False))
    cat = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    return metrics_from_episodes(
        cat["claims"], scn.num_tasks, cat["steps"], cat["finished"], cat["rewards"],
        cat["collisions"], cat["task_of_agent"], seconds=time.perf_counter() - start,
    )
