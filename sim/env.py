"""The batched AGV environment: B environments of N AGVs and M tasks.

A thin composition of the simulator's concepts: the static :class:`~sim.world.World`, the
changing :class:`~sim.state.SimState`, the physics (:mod:`sim.physics`), the task rules and the
team reward (:mod:`sim.tasks`), the observations (:mod:`sim.observations`), a reward callable
(:mod:`sim.rewards`) and, on the CPU, the fused kernels of :mod:`sim.native` that do the
claims, collisions, team reward and observations of a step in one pass. Every tensor has a
leading batch dimension and no Python loop runs over agents or environments on the step.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from torch import Tensor

from sim import native as native_kernels
from sim import physics, tasks
from sim.checks import (
    as_actions,
    check_count,
    check_device,
    check_env_ids,
    check_seed,
    real_array,
)
from sim.lifelong import LifelongEnv, LifelongScenario
from sim.observations import ObsLayout, global_state, observe
from sim.rewards import RewardFn, make_reward
from sim.rewards.base import check_reward_terms
from sim.scenarios import Scenario, get_scenario
from sim.state import SimState, StepContext
from sim.world import World

__all__ = ["AGVEnv", "make_env"]

class AGVEnv:
    """B parallel AGV task-allocation environments.

    Parameters
    ----------
    scenario : Scenario or str
        The scenario (see :func:`sim.scenarios.get_scenario`), e.g. ``"3v3"``.
    num_envs : int
        Number B of parallel environments.
    reward : str or RewardFn
        ``"minidist"``, ``"greedy"``, ``"ipf"`` or a callable ``(state, ctx) -> {term: (B, N)}``.
    seed : int, optional
        Seed of the environment's ``torch.Generator``, in [0, 2**64); every random draw comes
        from it.
    device : str or torch.device
        Where the state lives (default CPU).
    native : bool, optional
        Use the fused CPU kernels of :mod:`sim.native` for claims, collisions and observations
        (and the IPF reward) instead of the torch reference path. Default: wherever they are
        available (CPU tensors and a C compiler); ``True`` raises if they are not.

    Attributes
    ----------
    agent_pos, agent_vel : Tensor, shape (B, N, 2)
    task_pos : Tensor, shape (B, M, 2)
    task_claimed : Tensor of bool, shape (B, M)
    agent_task : Tensor of int64, shape (B, N)
    steps : Tensor of int64, shape (B,)
    done : Tensor of bool, shape (B,)
        The state. Assigning one checks its dtype, shape and device (ValueError naming it);
        the step never changes a tensor it handed out.
    obs_layout : ObsLayout
        Where each feature sits in an observation (``obs_dim == obs_layout.size``).

    Notes
    -----
    The step does not reset finished environments: a finished environment is frozen (zero
    reward, ``done`` stays True) until :meth:`reset` is called for it, so evaluation can run
    every episode to its end and training can reset exactly the finished ones.
    """

    def __init__(
        self,
        scenario: Scenario | str,
        num_envs: int = 1,
        reward: str | RewardFn = "minidist",
        seed: int | None = None,
        device: str | torch.device = "cpu",
        native: bool | None = None,
    ) -> None:
        if isinstance(scenario, str):
            scenario = get_scenario(scenario)
        if isinstance(scenario, LifelongScenario):
            raise ValueError(f"scenario {scenario.name!r} is lifelong: build it with "
                             f"sim.make_env({scenario.name!r}, ...) (a LifelongEnv)")
        if not isinstance(scenario, Scenario):
            raise ValueError(f"scenario must be a registry name (str) or a Scenario, got "
                             f"{type(scenario).__name__} {scenario!r}")
        num_envs = check_count("num_envs", num_envs)
        if native is not None and not isinstance(native, (bool, np.bool_)):
            raise ValueError(f"native must be True, False or None, got {native!r}")
        seed = 0 if seed is None else check_seed(seed)
        self.scenario = scenario
        self.world: World = scenario.world
        self.num_envs = int(num_envs)
        self.num_agents = scenario.num_agents
        self.num_tasks = scenario.num_tasks
        self.max_steps = scenario.max_steps
        self.device = check_device(device)
        self.dtype = torch.float32
        self.generator = torch.Generator(device=self.device)
        self.generator.manual_seed(seed)
        self.reward_fn = make_reward(reward)
        # The library's own rewards are trusted; a user's reward output is checked each step.
        self._check_terms = type(self.reward_fn).__module__.split(".")[0] != "sim"
        # Rewards that promise zero terms in finished environments skip the step's mask.
        self._reward_zeroes_inactive = bool(getattr(self.reward_fn, "zeroes_inactive", False))
        self.k_tasks = scenario.k_tasks
        self.k_agents = scenario.k_agents
        self.obs_layout = ObsLayout(self.k_tasks, self.k_agents)
        self.obs_dim = self.obs_layout.size
        self.state_dim = 5 * self.num_agents + 3 * self.num_tasks
        B, N, M = self.num_envs, self.num_agents, self.num_tasks
        z = dict(device=self.device, dtype=self.dtype)
        self._agent_pos = torch.zeros(B, N, 2, **z)
        self._agent_vel = torch.zeros(B, N, 2, **z)
        self._task_pos = torch.zeros(B, M, 2, **z)
        self._task_claimed = torch.zeros(B, M, dtype=torch.bool, device=self.device)
        self._agent_task = torch.full((B, N), -1, dtype=torch.long, device=self.device)
        self._steps = torch.zeros(B, dtype=torch.long, device=self.device)
        self._done = torch.zeros(B, dtype=torch.bool, device=self.device)
        self._eye = torch.eye(N, dtype=torch.bool, device=self.device)
        self._triu = torch.triu(torch.ones(N, N, dtype=torch.bool, device=self.device), 1)
        self._obstacles = torch.tensor(np.array(self.world.obstacles), **z)
        # Whether the physics needs the pairwise distances (soft contacts between AGVs).
        self._contacts = self.world.physics.contact_force > 0 and N > 1
        self._native = native_kernels.library_for(self.device, None if native is None
                                                  else bool(native))
        if self._native is not None:
            # The fused step writes the AGV-AGV distances here for the next physics step, and
            # _prepare the physics step's movable mask; only the env reads them, so one
            # buffer each serves every step.
            self._pair_buf = torch.empty(B, N, N, dtype=torch.float32)
            self._movable = torch.empty(B, N, dtype=torch.bool)
            # Spares for agent_task, task_claimed and done (see _post_step_native).
            self._spare = (torch.empty_like(self._agent_task),
                           torch.empty_like(self._task_claimed), torch.empty_like(self._done))
            # Templates of the fresh float32 outputs of every step: torch.empty_like (contiguous
            # for an expanded template, which holds no memory) costs a third less than
            # torch.empty with a dtype, which counts at small B.
            one = torch.empty((), dtype=torch.float32)
            self._like = (one.expand(B, N, M), one.expand(B, N), one.expand(B),
                          one.expand(B, N, self.obs_dim))
        # Shelves: the fused kernel, bit for bit the torch reference (sim/physics.py).
        self._shelves = (physics.shelf_kernel(self._native, self._obstacles,
                                              self.world.agent_radius)
                         if self._native is not None and self.world.has_obstacles else None)
        self._post_args = (B, N, M, self.k_tasks, self.k_agents, scenario.sensing_range,
                           self.world.capture_radius, 2.0 * self.world.agent_radius,
                           self.max_steps)
        if native and self._native is None:
            reason = ("the kernels run on CPU tensors only" if self.device.type != "cpu"
                      else native_kernels.disabled_reason())
            raise ValueError(f"native=True but the fused kernels are unavailable: {reason}")
        setup = getattr(self.reward_fn, "setup", None)
        if setup is not None:  # static facts a reward needs: the floor and the kernels' use
            setup(self.world, self._native)
        self.reset()

    # ------------------------------------------------------------------ state
    def _checked(self, name: str, value: Any, dtype: torch.dtype, shape: tuple[int, ...]
                 ) -> Tensor:
        """``value`` as a state tensor: exactly ``dtype``, ``shape`` and the env's device."""
        want = f"a {dtype} tensor of shape {shape} on {self.device}"
        if not isinstance(value, Tensor):
            raise ValueError(f"{name} must be {want}, got {type(value).__name__}")
        if value.dtype != dtype or tuple(value.shape) != shape or value.device != self.device:
            raise ValueError(f"{name} must be {want}, got a {value.dtype} tensor of shape "
                             f"{tuple(value.shape)} on {value.device}")
        if value.dtype.is_floating_point and not bool(torch.isfinite(value).all()):
            raise ValueError(f"{name} contains NaN or infinite values")
        self._pair = None
        self._task_rel = None
        return value.detach().contiguous()

    @property
    def agent_pos(self) -> Tensor:
        """AGV positions (B, N, 2), float32, world units."""
        return self._agent_pos

    @agent_pos.setter
    def agent_pos(self, value: Tensor) -> None:
        shape = (self.num_envs, self.num_agents, 2)
        self._agent_pos = self._checked("agent_pos", value, self.dtype, shape)

    @property
    def agent_vel(self) -> Tensor:
        """AGV velocities (B, N, 2), float32, world units per second."""
        return self._agent_vel

    @agent_vel.setter
    def agent_vel(self, value: Tensor) -> None:
        shape = (self.num_envs, self.num_agents, 2)
        self._agent_vel = self._checked("agent_vel", value, self.dtype, shape)

    @property
    def task_pos(self) -> Tensor:
        """Task positions (B, M, 2), float32."""
        return self._task_pos

    @task_pos.setter
    def task_pos(self, value: Tensor) -> None:
        shape = (self.num_envs, self.num_tasks, 2)
        self._task_pos = self._checked("task_pos", value, self.dtype, shape)

    @property
    def task_claimed(self) -> Tensor:
        """Whether each task is claimed (B, M), bool."""
        return self._task_claimed

    @task_claimed.setter
    def task_claimed(self, value: Tensor) -> None:
        shape = (self.num_envs, self.num_tasks)
        self._task_claimed = self._checked("task_claimed", value, torch.bool, shape)

    @property
    def agent_task(self) -> Tensor:
        """Task held by each AGV (B, N), int64, -1 for none."""
        return self._agent_task

    @agent_task.setter
    def agent_task(self, value: Tensor) -> None:
        shape = (self.num_envs, self.num_agents)
        value = self._checked("agent_task", value, torch.long, shape)
        if value.numel() and (int(value.min()) < -1 or int(value.max()) >= self.num_tasks):
            raise ValueError(f"agent_task values must lie in [-1, {self.num_tasks}), got "
                             f"values in [{int(value.min())}, {int(value.max())}]")
        self._agent_task = value

    @property
    def steps(self) -> Tensor:
        """Steps taken in each environment's episode (B,), int64."""
        return self._steps

    @steps.setter
    def steps(self, value: Tensor) -> None:
        value = self._checked("steps", value, torch.long, (self.num_envs,))
        if value.numel() and int(value.min()) < 0:
            raise ValueError(f"steps must be >= 0, got {value.tolist()}")
        self._steps = value

    @property
    def done(self) -> Tensor:
        """Whether each environment's episode has ended (B,), bool."""
        return self._done

    @done.setter
    def done(self, value: Tensor) -> None:
        self._done = self._checked("done", value, torch.bool, (self.num_envs,))

    @property
    def state(self) -> SimState:
        """The current state (views, not copies)."""
        return SimState(
            self._agent_pos, self._agent_vel, self._task_pos, self._task_claimed,
            self._agent_task, self._steps, self._done,
        )

    def _env_index(self, env_ids: Any) -> Tensor:
        return check_env_ids(env_ids, self.num_envs, self.device)

    def reset(self, env_ids: Any = None, seed: int | None = None) -> Tensor:
        """Start new episodes in all environments or in some.

        Parameters
        ----------
        env_ids : array-like of int or bool mask (B,), optional
            Environments to reset; all when omitted.
        seed : int, optional
            Re-seed the generator first (same seed, same scenes), in [0, 2**64).

        Returns
        -------
        Tensor, shape (B, N, O)
            Observations of all environments.
        """
        if seed is not None:
            self.generator.manual_seed(check_seed(seed))
        idx = self._env_index(env_ids)
        if idx.numel():
            agents, tasks_ = self.scenario.spawn(len(idx), self.generator, self.device,
                                                 kernels=self._native)
            self._place(idx, agents, tasks_, torch.zeros_like(agents))
        return self.observe()

    def set_state(
        self,
        agent_pos: Tensor | np.ndarray,
        task_pos: Tensor | np.ndarray,
        agent_vel: Tensor | np.ndarray | None = None,
        env_ids: Any = None,
    ) -> None:
        """Place AGVs and tasks by hand (new episode in those environments).

        Parameters
        ----------
        agent_pos : (K, N, 2) real numbers, K = number of selected environments
        task_pos : (K, M, 2)
        agent_vel : (K, N, 2), optional, default zero
        env_ids : which environments (default all)

        Raises
        ------
        ValueError
            On a wrong shape, values that are not real numbers, non-finite values, or
            positions outside the world or inside a shelf.
        """
        idx = self._env_index(env_ids)
        K, N, M = len(idx), self.num_agents, self.num_tasks
        z = dict(device=self.device, dtype=self.dtype)
        a = torch.as_tensor(real_array(agent_pos, "agent_pos"), **z).detach().clone()
        t = torch.as_tensor(real_array(task_pos, "task_pos"), **z).detach().clone()
        v = (torch.zeros(K, N, 2, **z) if agent_vel is None
             else torch.as_tensor(real_array(agent_vel, "agent_vel"), **z))
        v = v.detach().clone()
        for name, x, shape in (("agent_pos", a, (K, N, 2)), ("task_pos", t, (K, M, 2)),
                               ("agent_vel", v, (K, N, 2))):
            if tuple(x.shape) != shape:
                raise ValueError(f"{name} must have shape {shape}, got {tuple(x.shape)}")
            if not torch.isfinite(x).all():
                raise ValueError(f"{name} contains NaN or infinite values")
        for name, x in (("agent_pos", a), ("task_pos", t)):
            self.world.check_positions(x.reshape(-1, 2).double().cpu().numpy(), name)
        self._place(idx, a, t, v)

    def _place(self, idx: Tensor, a: Tensor, t: Tensor, v: Tensor) -> None:
        """Start episodes in environments ``idx`` from checked positions.

        Out of place, like the step: a state tensor the env handed out earlier (``info``,
        ``env.agent_pos``) is never changed afterwards.
        """
        at = (idx,)
        self._agent_pos = self._agent_pos.index_put(at, a)
        self._agent_vel = self._agent_vel.index_put(at, v)
        self._task_pos = self._task_pos.index_put(at, t)
        self._task_claimed = self._task_claimed.index_put(at, torch.tensor(False))
        self._agent_task = self._agent_task.index_put(at, torch.tensor(-1))
        self._steps = self._steps.index_put(at, torch.tensor(0))
        self._done = self._done.index_put(at, torch.tensor(False))
        self._pair = None
        self._task_rel = None

    @property
    def native(self) -> bool:
        """Whether this environment steps with the fused CPU kernels (see :mod:`sim.native`)."""
        return self._native is not None

    # ------------------------------------------------------------------ geometry caches
    def _pairwise(self) -> Tensor:
        """Pairwise AGV distances (B, N, N), cached until the AGVs move: the ones the step
        computed after the AGVs last moved (:func:`sim.physics.pair_distances`), else
        ``cdist``."""
        if self._pair is None:
            self._pair = torch.cdist(self._agent_pos, self._agent_pos,
                                     compute_mode="donot_use_mm_for_euclid_dist")
        return self._pair

    def _task_offsets(self) -> tuple[Tensor, Tensor]:
        """Task offsets ``t_j - p_i`` (B, N, M, 2) and distances (B, N, M), cached."""
        if self._task_rel is None:
            rel = self._task_pos.unsqueeze(1) - self._agent_pos.unsqueeze(2)
            self._task_rel = (rel, torch.linalg.vector_norm(rel, dim=-1))
        return self._task_rel

    # ------------------------------------------------------------------ step
    def _prepare(self, actions: Any) -> tuple[Tensor, Tensor, Tensor]:
        """Checked actions clipped to [-1, 1] (B, N, 2), the AGVs that move (B, N) bool and the
        running environments (B,) bool."""
        B, N = self.num_envs, self.num_agents
        a = as_actions(actions, (B, N, 2), self.dtype, self.device)
        if self._native is not None:
            a = a.contiguous()
            movable, active = self._movable, torch.empty_like(self._done)
            code = self._native.agv_prepare(B, N, a.data_ptr(), self._agent_task.data_ptr(),
                                            self._done.data_ptr(), movable.data_ptr(),
                                            active.data_ptr())
            if code > 0:
                raise ValueError("actions contain NaN or infinite values; expected finite values")
            return (a.clamp(-1.0, 1.0) if code else a), movable, active
        if not torch.isfinite(a).all():
            raise ValueError("actions contain NaN or infinite values; expected finite values")
        active = ~self._done
        return a.clamp(-1.0, 1.0), (self._agent_task < 0) & active.unsqueeze(1), active

    def step(self, actions: Tensor | np.ndarray) -> tuple[Tensor, Tensor, Tensor, dict]:
        """Advance every running environment by one step.

        Parameters
        ----------
        actions : Tensor or array of real numbers, shape (B, N, 2)
            Accelerations in [-1, 1] (values outside are clipped); ignored for parked AGVs.

        Returns
        -------
        obs : Tensor, shape (B, N, O)
        reward : Tensor, shape (B, N)
            The chosen reward's sum of terms; 0 in environments that were already done.
        done : Tensor, shape (B,) bool
            True once every task is claimed or the step limit is reached.
        info : dict
            ``reward_terms`` {name: (B, N)}, ``team_reward`` (B,) the paper's R_t,
            ``claimed_now`` (B, M) bool, ``agent_task`` (B, N), ``collision_pairs`` (B,),
            ``collisions_per_agent`` (B, N), ``active`` (B,) bool.

        Raises
        ------
        ValueError
            For actions that are not real numbers, of another shape, or not finite; for a
            reward callable whose output is not ``{name: finite float (B, N) tensor}``.
        """
        actions, movable, active = self._prepare(actions)
        # The step rebinds every state tensor (never writes in place), so these stay as they were.
        prev_pos, prev_claimed, prev_task = self._agent_pos, self._task_claimed, self._agent_task

        self.physics_step(actions, movable)

        # Claims (an idle AGV within the capture radius takes the task and parks), the step
        # counter and done, collisions (discs overlapping), the paper's team reward R_t and
        # the observations: fused kernels or the torch reference.
        if self._native is not None:
            claimed_now, dist, per_agent, pairs, team, team_terms, obs = self._post_step_native()
        else:
            claimed_now, dist, per_agent, pairs, team, team_terms = self._post_step_torch(active)
            obs = None
        ctx = StepContext(prev_pos, prev_claimed, prev_task, active, dist, per_agent, pairs, team,
                          *team_terms)
        terms = self.reward_fn(self.state, ctx)
        if self._check_terms:
            check_reward_terms(terms, (self.num_envs, self.num_agents), self.device)
        values = list(terms.values())
        if values:
            reward = sum(values[1:], values[0])
            # The mask also gives a single term a tensor of its own.
            if len(values) == 1 or not self._reward_zeroes_inactive:
                reward = reward * active.unsqueeze(1)
        else:
            reward = torch.zeros_like(per_agent)
        info = {
            "reward_terms": terms,
            "team_reward": team,
            "claimed_now": claimed_now,
            "agent_task": self._agent_task,
            "collision_pairs": pairs,
            "collisions_per_agent": per_agent,
            "active": active,
        }
        return self.observe() if obs is None else obs, reward, self._done.clone(), info

    def _post_step_torch(
        self, active: Tensor
    ) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, tuple[Tensor, Tensor]]:
        """Claims, step counter, done, collisions and team reward in torch (the reference)."""
        _, dist = self._task_offsets()  # (B, N, M)
        agent_task, task_claimed, claimed_now, takes = tasks.claim(
            dist, self._agent_task, self._task_claimed, active, self.world.capture_radius)
        if agent_task is not self._agent_task:
            self._agent_task, self._task_claimed = agent_task, task_claimed
            self._agent_vel = self._agent_vel * (~takes).unsqueeze(-1)
        self._steps = self._steps + active.long()
        self._done = self._done | self._task_claimed.all(dim=1) | (self._steps >= self.max_steps)
        self._pair = physics.pair_distances(self._agent_pos)
        per_agent, pairs = physics.collisions(self._pair, active, self.world.agent_radius,
                                              self._eye, self._triu)
        team = tasks.team_reward(dist, pairs, active)
        shape = (-1, self.num_agents)
        team_terms = ((team + pairs).unsqueeze(1).expand(shape),
                      (-pairs).unsqueeze(1).expand(shape))
        return claimed_now, dist, per_agent, pairs, team, team_terms

    def _post_step_native(
        self,
    ) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, tuple[Tensor, Tensor], Tensor]:
        """What :meth:`_post_step_torch` and :meth:`observe` do, in one fused kernel call.

        Tensors handed out earlier never change: the velocities the kernel stops in place are
        the physics step's fresh output, and the new ``agent_task``, ``task_claimed`` and
        ``done`` are written to spare tensors that replace the state only when they differ
        from it (the spares are then renewed).
        """
        agent_task, claimed, done = self._spare
        like_dist, like_agents, like_envs, like_obs = self._like
        claimed_now = torch.empty_like(self._task_claimed)
        steps = torch.empty_like(self._steps)
        dist = torch.empty_like(like_dist)
        per_agent = torch.empty_like(like_agents)
        pairs = torch.empty_like(like_envs)
        team = torch.empty_like(like_envs)
        team_distance = torch.empty_like(like_agents)
        team_collision = torch.empty_like(like_agents)
        obs = torch.empty_like(like_obs)
        # Every state tensor is a contiguous CPU tensor of its dtype and shape: the env makes
        # them, and the public setters check what a user assigns. The kernel stops claiming
        # AGVs in agent_vel (the physics step's fresh output) itself.
        state = (self._agent_pos, self._agent_vel, self._task_pos, self._task_claimed,
                 self._agent_task, self._steps, self._done)
        outputs = (agent_task, claimed, claimed_now, steps, done, dist, self._pair_buf,
                   per_agent, pairs, team, team_distance, team_collision, obs)
        changed = self._native.agv_post_step(
            *self._post_args, *[t.data_ptr() for t in state], *[t.data_ptr() for t in outputs]
        )
        if changed < 0:
            raise MemoryError("the fused step kernel could not allocate its scratch space")
        if changed & 1:
            self._agent_task, self._task_claimed = agent_task, claimed
            self._spare = (torch.empty_like(agent_task), torch.empty_like(claimed), done)
        if changed & 2:
            self._done = done
            self._spare = (*self._spare[:2], torch.empty_like(done))
        self._steps = steps
        self._pair = self._pair_buf
        return claimed_now, dist, per_agent, pairs, team, (team_distance, team_collision), obs

    def physics_step(self, actions: Tensor, movable: Tensor) -> None:
        """Move the AGVs by one MPE physics step (:func:`sim.physics.mpe_step`): action and
        contact forces, integration, shelves, walls. No claiming, observations or rewards
        (:meth:`step` adds those).

        Parameters
        ----------
        actions : Tensor, shape (B, N, 2)
            Checked, clipped accelerations.
        movable : Tensor of bool, shape (B, N)
            AGVs that move (idle AGVs of running environments); the others keep their state.
        """
        self._agent_pos, self._agent_vel = physics.mpe_step(
            self._agent_pos, self._agent_vel, actions, movable, self.world, self._obstacles,
            self._pairwise() if self._contacts else None, self._eye, shelves=self._shelves,
        )
        self._pair = None
        self._task_rel = None

    # ------------------------------------------------------------------ observations
    def observe(self) -> Tensor:
        """Local observations, (B, N, O) with O = ``obs_layout.size`` = 5 + 3 K_tasks +
        5 K_agents (see :mod:`sim.observations` for the features and their order)."""
        if self._native is not None:
            obs = torch.empty(self.num_envs, self.num_agents, self.obs_dim, dtype=self.dtype)
            state = (self._agent_pos, self._agent_vel, self._task_pos, self._task_claimed,
                     self._agent_task)
            if self._native.agv_observe(self.num_envs, self.num_agents, self.num_tasks,
                                        self.k_tasks, self.k_agents, self.scenario.sensing_range,
                                        *[t.data_ptr() for t in state], obs.data_ptr()):
                raise MemoryError("the observation kernel could not allocate its scratch space")
            return obs
        layout = self.obs_layout
        return observe(
            self._agent_pos, self._agent_vel, self._task_claimed, self._agent_task, layout,
            self.scenario.sensing_range, self._task_offsets() if layout.k_tasks else None,
            self._pairwise() if layout.k_agents else None, self._eye,
        )

    def global_state(self) -> Tensor:
        """Global state for centralized critics, (B, 5 N + 3 M): every AGV's position,
        velocity and holding bit, every task's position and claimed bit."""
        return global_state(self._agent_pos, self._agent_vel, self._task_pos,
                            self._task_claimed, self._agent_task)


def make_env(
    scenario: Scenario | LifelongScenario | World | str = "3v3",
    num_envs: int = 1,
    reward: str | RewardFn = "minidist",
    seed: int | None = None,
    device: str | torch.device = "cpu",
    native: bool | None = None,
    **scenario_options: Any,
) -> AGVEnv | LifelongEnv:
    """Build a batched AGV environment: episodic (the paper's) or lifelong.

    Parameters
    ----------
    scenario : str, Scenario, LifelongScenario or World
        A registry name (``"3v3"``, ``"6v6"``, any ``"NvM"``, ``"warehouse"``; lifelong: any
        ``"warehouse-N"``), a scenario, or a floor with pickups and stations (e.g. from
        :func:`sim.load_floor`, with ``num_agents=N``), which gives a
        :class:`sim.lifelong.LifelongEnv`.
    num_envs : int
        Number of parallel environments B.
    reward : str or callable
        ``"minidist"``, ``"greedy"``, ``"ipf"`` or a callable ``(state, ctx) -> {term: (B, N)
        tensor}``.
    seed : int, optional
        Seed of the environment's generator, in [0, 2**64).
    device : str or torch.device
        Where the state lives (default CPU).
    native : bool, optional
        Fused CPU kernels (default: when available) or the torch reference path (``False``).
    **scenario_options
        Overrides for the scenario (e.g. ``max_steps=50``, ``sensing_range=1.0``; lifelong:
        ``arrivals=sim.Poisson(0.4)``, ``faults=sim.Breakdowns(1e-3, 50)``, ...).

    Returns
    -------
    AGVEnv

    Raises
    ------
    ValueError
        Naming the argument, for any argument of the wrong type or out of range.

    Examples
    --------
    >>> import sim, torch
    >>> env = sim.make_env("3v3", num_envs=4, seed=0)
    >>> obs = env.reset()
    >>> obs.shape
    torch.Size([4, 3, 24])
    >>> obs, reward, done, info = env.step(torch.zeros(4, 3, 2))
    >>> reward.shape, done.shape
    (torch.Size([4, 3]), torch.Size([4]))
    """
    if not isinstance(scenario, (str, Scenario, LifelongScenario, World)):
        raise ValueError(f"scenario must be a registry name (str), a Scenario or a floor "
                         f"(World), got {type(scenario).__name__} {scenario!r:.80}")
    if isinstance(scenario, (str, World)) or scenario_options:
        scenario = get_scenario(scenario, **scenario_options)
    if isinstance(scenario, LifelongScenario):
        return LifelongEnv(scenario, num_envs=num_envs, reward=reward, seed=seed,
                           device=device, native=native)
    return AGVEnv(scenario, num_envs=num_envs, reward=reward, seed=seed, device=device,
                  native=native)
