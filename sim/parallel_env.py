"""A PettingZoo ``ParallelEnv`` over one environment of the batched simulator.

Per-agent dicts live only here, at the edge; inside, everything stays batched tensors.
All AGVs end together (terminated when every task is claimed, truncated at the step limit);
a parked AGV keeps receiving observations and its actions are ignored. In lifelong mode
(``"warehouse-N"`` or a floor) nothing terminates: the run is truncated at the scenario's
horizon ``max_steps``.
"""

from __future__ import annotations

import functools
from typing import Any

import numpy as np
import torch
from gymnasium import spaces
from pettingzoo import ParallelEnv

from sim.env import AGVEnv
from sim.lifelong import LifelongEnv, LifelongScenario
from sim.scenarios import Scenario, get_scenario

__all__ = ["AGVParallelEnv", "pettingzoo_env"]


class AGVParallelEnv(ParallelEnv):
    """PettingZoo parallel API over :class:`sim.env.AGVEnv` with B = 1.

    Agents are named ``"agv_0" ... "agv_{N-1}"``; observations are float32 vectors of length
    O; actions are accelerations in ``[-1, 1]^2``. Every agent's info holds ``"task"`` (int,
    the task it holds or -1; in lifelong mode the slot of its order or -1) and ``"terms"``
    ({term name: float}, its reward terms), at :meth:`reset` (terms 0.0) as at :meth:`step`,
    so that wrappers that build their info layout from the reset (TorchRL's
    ``PettingZooWrapper``) keep them; in lifelong mode also ``"status"`` (its
    :data:`sim.orders.AGENT_STATUS` name).
    """

    metadata = {"name": "agv_task_allocation_v0", "render_modes": ["rgb_array"],
                "is_parallelizable": True}

    def __init__(self, scenario: str | Scenario | LifelongScenario = "3v3",
                 reward: str = "minidist",
                 seed: int | None = None, render_mode: str | None = None) -> None:
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        self.scenario = get_scenario(scenario)
        self.lifelong = isinstance(self.scenario, LifelongScenario)
        self._env = self._make(reward, seed)
        self.render_mode = render_mode
        self.possible_agents = [f"agv_{i}" for i in range(self.scenario.num_agents)]
        self.agents: list[str] = []
        self._index = {a: i for i, a in enumerate(self.possible_agents)}
        self._obs_dim = self._env.obs_dim
        self._term_names = self._reward_term_names(reward)

    def _make(self, reward: Any, seed: int | None) -> AGVEnv | LifelongEnv:
        if self.lifelong:
            return LifelongEnv(self.scenario, num_envs=1, reward=reward, seed=seed)
        return AGVEnv(self.scenario, num_envs=1, reward=reward, seed=seed)

    def _reward_term_names(self, reward: Any) -> list[str]:
        """The names of the reward's terms, read from one step of a separate environment, so
        that :meth:`reset` can report the same info keys as :meth:`step`."""
        probe = self._make(reward, 0)
        _, _, _, info = probe.step(torch.zeros(1, self.scenario.num_agents, 2))
        return list(info["reward_terms"])

    @functools.cache  # noqa: B019 - spaces must be the same object each call
    def observation_space(self, agent: str) -> spaces.Box:
        return spaces.Box(-np.inf, np.inf, shape=(self._obs_dim,), dtype=np.float32)

    @functools.cache  # noqa: B019
    def action_space(self, agent: str) -> spaces.Box:
        return spaces.Box(-1.0, 1.0, shape=(2,), dtype=np.float32)

    def _obs_dict(self, obs: torch.Tensor) -> dict[str, np.ndarray]:
        arr = obs[0].cpu().numpy().astype(np.float32)
        return {a: arr[i] for i, a in enumerate(self.possible_agents)}

    def reset(self, seed: int | None = None, options: dict | None = None) -> tuple[dict, dict]:
        obs = self._env.reset(seed=seed)
        self.agents = list(self.possible_agents)
        infos = self._infos(dict.fromkeys(self._term_names, 0.0), None)
        return self._obs_dict(obs), infos

    def _infos(self, zero_terms: dict[str, float] | None, terms: dict | None) -> dict:
        env = self._env
        held = (env.fleet.order if self.lifelong else env.agent_task)[0].cpu().numpy()
        infos = {}
        for i, a in enumerate(self.possible_agents):
            own = dict(zero_terms) if terms is None else \
                {k: float(v[0, i]) for k, v in terms.items()}
            infos[a] = {"task": int(held[i]), "terms": own}
        if self.lifelong:
            from sim.orders import AGENT_STATUS

            status = env.agent_status[0].cpu().numpy()
            for i, a in enumerate(self.possible_agents):
                infos[a]["status"] = AGENT_STATUS[int(status[i])]
        return infos

    def step(self, actions: dict[str, Any]) -> tuple[dict, dict, dict, dict, dict]:
        if not self.agents:
            raise ValueError("step() called on a finished episode; call reset() first")
        missing = [a for a in self.agents if a not in actions]
        if missing:
            raise ValueError(f"actions are missing for agents {missing}")
        unknown = [a for a in actions if a not in self._index]
        if unknown:
            raise ValueError(f"actions given for unknown agents {unknown}")
        batch = np.zeros((1, len(self.possible_agents), 2), dtype=np.float32)
        for agent, act in actions.items():
            arr = np.asarray(act, dtype=np.float32)
            if arr.shape != (2,):
                raise ValueError(f"action of {agent} must have shape (2,), got {arr.shape}")
            batch[0, self._index[agent]] = arr
        obs, reward, done, info = self._env.step(torch.from_numpy(batch))
        all_claimed = not self.lifelong and bool(self._env.task_claimed.all())
        ended = bool(done[0])
        r = reward[0].cpu().numpy()
        infos = self._infos(None, info["reward_terms"])
        obs_d = self._obs_dict(obs)
        rewards = {a: float(r[i]) for i, a in enumerate(self.possible_agents)}
        terminated = {a: ended and all_claimed for a in self.possible_agents}
        truncated = {a: ended and not all_claimed for a in self.possible_agents}
        if ended:
            self.agents = []
        return obs_d, rewards, terminated, truncated, infos

    def render(self) -> np.ndarray | None:
        if self.render_mode is None:
            return None
        from sim.render import _plt, render_scene

        if self.lifelong:
            raise ValueError("render_mode='rgb_array' draws episodic scenes only; for "
                             "lifelong runs use sim.render.render_lifelong")
        fig = render_scene(self._env)
        fig.canvas.draw()
        image = np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()
        _plt().close(fig)
        return image

    def state(self) -> np.ndarray:
        return self._env.global_state()[0].cpu().numpy().astype(np.float32)

    def close(self) -> None:
        pass


def pettingzoo_env(scenario: str | Scenario | LifelongScenario = "3v3", reward: str = "minidist",
                   seed: int | None = None, render_mode: str | None = None) -> AGVParallelEnv:
    """A PettingZoo ``ParallelEnv`` of one AGV environment.

    Examples
    --------
    >>> import sim
    >>> env = sim.pettingzoo_env("3v3", seed=0)
    >>> obs, infos = env.reset(seed=0)
    >>> sorted(obs)
    ['agv_0', 'agv_1', 'agv_2']
    """
    return AGVParallelEnv(scenario, reward=reward, seed=seed, render_mode=render_mode)
