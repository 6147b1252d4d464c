"""The batched AGV environment: B environments of N AGVs and M tasks, stepped in torch.

Physics follow ``mpe2`` (dt, damping, sensitivity, soft contacts, its integration order); on
top of that come walls at the world bounds, rectangular shelves, task claiming and parking (see
``docs/simulator.md`` for where and why this differs from MPE). Every tensor has a leading batch
dimension and no Python loop runs over agents or environments on the step.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from torch import Tensor

from sim.state import SimState, StepContext
from sim.world import World

if TYPE_CHECKING:  # pragma: no cover
    from sim.rewards import RewardFn
    from sim.scenarios import Scenario

__all__ = ["AGVEnv", "SimState", "StepContext", "make_env"]


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
        Seed of the environment's ``torch.Generator``; every random draw comes from it.
    device : str or torch.device
        Where the state lives (default CPU).
    native : bool, optional
        Use the fused CPU kernels of :mod:`sim.native` for claims, collisions and observations
        (and the IPF reward) instead of the torch reference path. Default: wherever they are
        available (CPU tensors and a C compiler); ``True`` raises if they are not.

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
        from sim import native as native_kernels
        from sim.rewards import make_reward
        from sim.scenarios import get_scenario

        if isinstance(scenario, str):
            scenario = get_scenario(scenario)
        if not isinstance(num_envs, (int, np.integer)) or num_envs < 1:
            raise ValueError(f"num_envs must be a positive integer, got {num_envs!r}")
        self.scenario = scenario
        self.world: World = scenario.world
        self.num_envs = int(num_envs)
        self.num_agents = scenario.num_agents
        self.num_tasks = scenario.num_tasks
        self.max_steps = scenario.max_steps
        self.device = torch.device(device)
        self.dtype = torch.float32
        self.generator = torch.Generator(device=self.device)
        self.generator.manual_seed(0 if seed is None else int(seed))
        self.reward_fn = make_reward(reward)
        # Rewards that promise zero terms in finished environments skip the step's mask.
        self._reward_zeroes_inactive = bool(getattr(self.reward_fn, "zeroes_inactive", False))
        self.k_tasks = scenario.k_tasks
        self.k_agents = scenario.k_agents
        self.obs_dim = 5 + 3 * self.k_tasks + 5 * self.k_agents
        self.state_dim = 5 * self.num_agents + 3 * self.num_tasks
        B, N, M = self.num_envs, self.num_agents, self.num_tasks
        z = dict(device=self.device, dtype=self.dtype)
        self.agent_pos = torch.zeros(B, N, 2, **z)
        self.agent_vel = torch.zeros(B, N, 2, **z)
        self.task_pos = torch.zeros(B, M, 2, **z)
        self.task_claimed = torch.zeros(B, M, dtype=torch.bool, device=self.device)
        self.agent_task = torch.full((B, N), -1, dtype=torch.long, device=self.device)
        self.steps = torch.zeros(B, dtype=torch.long, device=self.device)
        self.done = torch.zeros(B, dtype=torch.bool, device=self.device)
        self._eye = torch.eye(N, dtype=torch.bool, device=self.device)
        self._triu = torch.triu(torch.ones(N, N, dtype=torch.bool, device=self.device), 1)
        self._obstacles = torch.tensor(np.array(self.world.obstacles), **z)
        self._native = native_kernels.library_for(self.device, native)
        if self._native is not None:
            # The fused step writes the AGV-AGV distances here for the next physics step, and
            # _prepare the physics step's movable mask; only the env reads them, so one
            # buffer each serves every step.
            self._pair_buf = torch.empty(B, N, N, dtype=torch.float32)
            self._movable = torch.empty(B, N, dtype=torch.bool)
            # Spares for agent_task, task_claimed and done (see _post_step_native).
            self._spare = (torch.empty_like(self.agent_task), torch.empty_like(self.task_claimed),
                           torch.empty_like(self.done))
            # Templates of the fresh float32 outputs of every step: torch.empty_like (contiguous
            # for an expanded template, which holds no memory) costs a third less than
            # torch.empty with a dtype, which counts at small B.
            one = torch.empty((), dtype=torch.float32)
            self._like = (one.expand(B, N, M), one.expand(B, N), one.expand(B),
                          one.expand(B, N, self.obs_dim))
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
    @property
    def state(self) -> SimState:
        """The current state (views, not copies)."""
        return SimState(
            self.agent_pos, self.agent_vel, self.task_pos, self.task_claimed,
            self.agent_task, self.steps, self.done,
        )

    def _env_index(self, env_ids: Any) -> Tensor:
        if env_ids is None:
            return torch.arange(self.num_envs, device=self.device)
        idx = torch.as_tensor(env_ids, device=self.device)
        if idx.dtype == torch.bool:
            if idx.shape != (self.num_envs,):
                raise ValueError(
                    f"a boolean env mask must have shape ({self.num_envs},), got {tuple(idx.shape)}"
                )
            return idx.nonzero().flatten()
        idx = idx.long().flatten()
        if idx.numel() and (idx.min() < 0 or idx.max() >= self.num_envs):
            raise ValueError(f"env ids must lie in [0, {self.num_envs}), got {idx.tolist()}")
        return idx

    def reset(self, env_ids: Any = None, seed: int | None = None) -> Tensor:
        """Start new episodes in all environments or in some.

        Parameters
        ----------
        env_ids : array-like of int or bool mask (B,), optional
            Environments to reset; all when omitted.
        seed : int, optional
            Re-seed the generator first (same seed, same scenes).

        Returns
        -------
        Tensor, shape (B, N, O)
            Observations of all environments.
        """
        if seed is not None:
            self.generator.manual_seed(int(seed))
        idx = self._env_index(env_ids)
        if idx.numel():
            agents, tasks = self.scenario.spawn(len(idx), self.generator, self.device,
                                               native=self.native)
            self._place(idx, agents, tasks, torch.zeros_like(agents))
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
        agent_pos : (K, N, 2) positions, K = number of selected environments
        task_pos : (K, M, 2)
        agent_vel : (K, N, 2), optional, default zero
        env_ids : which environments (default all)

        Raises
        ------
        ValueError
            On a wrong shape, non-finite values, or positions outside the world or inside a shelf.
        """
        idx = self._env_index(env_ids)
        K, N, M = len(idx), self.num_agents, self.num_tasks
        z = dict(device=self.device, dtype=self.dtype)
        a = torch.as_tensor(agent_pos, **z).clone()
        t = torch.as_tensor(task_pos, **z).clone()
        v = torch.zeros(K, N, 2, **z) if agent_vel is None else torch.as_tensor(agent_vel, **z)
        v = v.clone()
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
        self.agent_pos = self.agent_pos.index_put(at, a)
        self.agent_vel = self.agent_vel.index_put(at, v)
        self.task_pos = self.task_pos.index_put(at, t)
        self.task_claimed = self.task_claimed.index_put(at, torch.tensor(False))
        self.agent_task = self.agent_task.index_put(at, torch.tensor(-1))
        self.steps = self.steps.index_put(at, torch.tensor(0))
        self.done = self.done.index_put(at, torch.tensor(False))
        self._pair = None
        self._task_rel = None

    @property
    def native(self) -> bool:
        """Whether this environment steps with the fused CPU kernels (see :mod:`sim.native`)."""
        return self._native is not None

    # ------------------------------------------------------------------ geometry
    def _pairwise(self) -> Tensor:
        """Pairwise AGV distances (B, N, N), cached until the AGVs move: the ones the step
        computed after the AGVs last moved (see :meth:`_pair_distances`), else ``cdist``."""
        if self._pair is None:
            self._pair = torch.cdist(self.agent_pos, self.agent_pos,
                                     compute_mode="donot_use_mm_for_euclid_dist")
        return self._pair

    def _pair_distances(self) -> Tensor:
        """The step's pairwise AGV distances as the fused kernel computes them, cached for the
        next physics step, so that both paths move the AGVs by the same forces.

        ``sqrt(dx * dx + dy * dy)`` with float32 products and sum and a correctly rounded
        square root (C's ``sqrtf``; torch's float32 ``sqrt`` and ``cdist`` may differ in the
        last bit, hence the square root in float64, which rounds to the same float32).
        """
        d = self.agent_pos.unsqueeze(2) - self.agent_pos.unsqueeze(1)
        self._pair = d.mul_(d).sum(dim=-1).double().sqrt_().float()
        return self._pair

    def _task_offsets(self) -> tuple[Tensor, Tensor]:
        """Task offsets ``t_j - p_i`` (B, N, M, 2) and distances (B, N, M), cached."""
        if self._task_rel is None:
            rel = self.task_pos.unsqueeze(1) - self.agent_pos.unsqueeze(2)
            self._task_rel = (rel, torch.linalg.vector_norm(rel, dim=-1))
        return self._task_rel

    def _contact_forces(self, dist: Tensor) -> Tensor:
        """MPE's soft contact force on every AGV, (B, N, 2).

        ``f_i = sum_j c * k * softplus((2r - d_ij) / k) * (p_i - p_j) / d_ij``, computed as
        ``p_i * sum_j s_ij - sum_j s_ij p_j`` with one batched matmul.
        """
        ph = self.world.physics
        dist_min = 2.0 * self.world.agent_radius
        penetration = torch.nn.functional.softplus(dist_min - dist, beta=1.0 / ph.contact_margin)
        scale = (ph.contact_force * penetration / dist.clamp_min(1e-12)).masked_fill(self._eye, 0.0)
        return self.agent_pos * scale.sum(dim=2, keepdim=True) - torch.bmm(scale, self.agent_pos)

    def _collide_obstacles(self, pos: Tensor, vel: Tensor) -> tuple[Tensor, Tensor]:
        """Push discs out of shelves and cancel the velocity into them."""
        r = self.world.agent_radius
        lo = self._obstacles[:, :2]  # (K, 2)
        hi = self._obstacles[:, 2:]
        p = pos.unsqueeze(2)  # (B, N, 1, 2)
        closest = torch.minimum(torch.maximum(p, lo), hi)  # (B, N, K, 2)
        d = p - closest
        dist = torch.linalg.vector_norm(d, dim=-1)  # (B, N, K)
        # Centre inside a shelf: leave through the nearest face.
        to_face = torch.cat([p - lo, hi - p], dim=-1)  # (B, N, K, 4): left, bottom, right, top
        face = to_face.argmin(dim=-1)
        normals = torch.tensor(
            [[-1.0, 0.0], [0.0, -1.0], [1.0, 0.0], [0.0, 1.0]], device=pos.device, dtype=pos.dtype
        )
        inside = dist <= 1e-9
        normal = torch.where(
            inside.unsqueeze(-1), normals[face], d / dist.clamp_min(1e-9).unsqueeze(-1)
        )
        face_depth = to_face.gather(-1, face.unsqueeze(-1)).squeeze(-1)
        depth = torch.where(inside, face_depth + r, r - dist)
        hit = depth > 0
        push = (normal * (depth * hit).unsqueeze(-1)).sum(dim=2)
        inward = (vel.unsqueeze(2) * normal).sum(-1).clamp_max(0.0) * hit  # (B, N, K)
        vel = vel - (normal * inward.unsqueeze(-1)).sum(dim=2)
        return pos + push, vel

    def _collide_walls(self, pos: Tensor, vel: Tensor) -> tuple[Tensor, Tensor]:
        r = self.world.agent_radius
        xmin, ymin, xmax, ymax = self.world.bounds
        lo = torch.tensor([xmin + r, ymin + r], device=pos.device, dtype=pos.dtype)
        hi = torch.tensor([xmax - r, ymax - r], device=pos.device, dtype=pos.dtype)
        clamped = torch.minimum(torch.maximum(pos, lo), hi)
        hit_lo = pos < lo
        hit_hi = pos > hi
        vel = torch.where((hit_lo & (vel < 0)) | (hit_hi & (vel > 0)), torch.zeros_like(vel), vel)
        return clamped, vel

    # ------------------------------------------------------------------ step
    def _prepare(self, actions: Any) -> tuple[Tensor, Tensor, Tensor]:
        """Checked actions clipped to [-1, 1] (B, N, 2), the AGVs that move (B, N) bool and the
        running environments (B,) bool."""
        a = actions
        if not (type(a) is Tensor and a.dtype == self.dtype and a.device == self.device):
            a = torch.as_tensor(actions, device=self.device, dtype=self.dtype)
        B, N = self.num_envs, self.num_agents
        if tuple(a.shape) != (B, N, 2):
            raise ValueError(
                f"actions must have shape (B, N, 2) = {(B, N, 2)}, got {tuple(a.shape)}"
            )
        if self._native is not None:
            a = a.contiguous()
            movable, active = self._movable, torch.empty_like(self.done)
            code = self._native.agv_prepare(B, N, a.data_ptr(), self.agent_task.data_ptr(),
                                            self.done.data_ptr(), movable.data_ptr(),
                                            active.data_ptr())
            if code > 0:
                raise ValueError("actions contain NaN or infinite values; expected finite values")
            return (a.clamp(-1.0, 1.0) if code else a), movable, active
        if not torch.isfinite(a).all():
            raise ValueError("actions contain NaN or infinite values; expected finite values")
        active = ~self.done
        return a.clamp(-1.0, 1.0), (self.agent_task < 0) & active.unsqueeze(1), active

    def step(self, actions: Tensor | np.ndarray) -> tuple[Tensor, Tensor, Tensor, dict]:
        """Advance every running environment by one step.

        Parameters
        ----------
        actions : Tensor, shape (B, N, 2)
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
        """
        actions, movable, active = self._prepare(actions)
        # The step rebinds every state tensor (never writes in place), so these stay as they were.
        prev_pos, prev_claimed, prev_task = self.agent_pos, self.task_claimed, self.agent_task

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
            "agent_task": self.agent_task,
            "collision_pairs": pairs,
            "collisions_per_agent": per_agent,
            "active": active,
        }
        return self.observe() if obs is None else obs, reward, self.done.clone(), info

    def _post_step_torch(
        self, active: Tensor
    ) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, tuple[Tensor, Tensor]]:
        """Claims, step counter, done, collisions and team reward in torch (the reference)."""
        _, dist = self._task_offsets()  # (B, N, M)
        claimed_now = self._claim(dist, active)
        self.steps = self.steps + active.long()
        self.done = self.done | self.task_claimed.all(dim=1) | (self.steps >= self.max_steps)
        pair_dist = self._pair_distances()
        overlap = (pair_dist < 2.0 * self.world.agent_radius) & ~self._eye
        overlap = overlap & active.view(-1, 1, 1)
        per_agent = overlap.sum(dim=2).to(self.dtype)
        pairs = (overlap & self._triu).sum(dim=(1, 2)).to(self.dtype)
        nearest = dist.min(dim=1).values.sum(dim=1) if self.num_tasks else pairs * 0
        team = torch.where(active, -nearest - pairs, torch.zeros_like(pairs))
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
        claimed_now = torch.empty_like(self.task_claimed)
        steps = torch.empty_like(self.steps)
        dist = torch.empty_like(like_dist)
        per_agent = torch.empty_like(like_agents)
        pairs = torch.empty_like(like_envs)
        team = torch.empty_like(like_envs)
        team_distance = torch.empty_like(like_agents)
        team_collision = torch.empty_like(like_agents)
        obs = torch.empty_like(like_obs)
        # The state tensors are contiguous (the env creates them); the list keeps any copy
        # alive until the call returns. The kernel stops claiming AGVs in agent_vel itself.
        self.agent_vel = self.agent_vel.contiguous()
        state = [self.agent_pos.contiguous(), self.agent_vel,
                 *[t.contiguous() for t in (self.task_pos, self.task_claimed, self.agent_task,
                                            self.steps, self.done)]]
        outputs = (agent_task, claimed, claimed_now, steps, done, dist, self._pair_buf,
                   per_agent, pairs, team, team_distance, team_collision, obs)
        changed = self._native.agv_post_step(
            *self._post_args, *[t.data_ptr() for t in state], *[t.data_ptr() for t in outputs]
        )
        if changed < 0:
            raise MemoryError("the fused step kernel could not allocate its scratch space")
        if changed & 1:
            self.agent_task, self.task_claimed = agent_task, claimed
            self._spare = (torch.empty_like(agent_task), torch.empty_like(claimed), done)
        if changed & 2:
            self.done = done
            self._spare = (*self._spare[:2], torch.empty_like(done))
        self.steps = steps
        self._pair = self._pair_buf
        return claimed_now, dist, per_agent, pairs, team, (team_distance, team_collision), obs

    def physics_step(self, actions: Tensor, movable: Tensor) -> None:
        """Move the AGVs by one MPE physics step: action and contact forces, integration,
        shelves, walls. No claiming, observations or rewards (:meth:`step` adds those).

        Parameters
        ----------
        actions : Tensor, shape (B, N, 2)
            Checked, clipped accelerations.
        movable : Tensor of bool, shape (B, N)
            AGVs that move (idle AGVs of running environments); the others keep their state.
        """
        ph = self.world.physics
        # MPE physics: force from the action and soft contacts, then integrate.
        force = actions * ph.sensitivity
        if ph.contact_force > 0 and self.num_agents > 1:
            force = force + self._contact_forces(self._pairwise())
        m = movable.unsqueeze(-1)
        pos = self.agent_pos + self.agent_vel * (ph.dt * m)
        vel = self.agent_vel * (1.0 - ph.damping) + force * (ph.dt / ph.mass)
        if ph.max_speed is not None:
            speed = torch.linalg.vector_norm(vel, dim=-1, keepdim=True)
            vel = vel * (ph.max_speed / speed.clamp_min(ph.max_speed))
        vel = torch.where(m, vel, self.agent_vel)
        if self.world.has_obstacles:
            pos, vel = self._collide_obstacles(pos, vel)
        if self.world.walls:
            pos, vel = self._collide_walls(pos, vel)
        self.agent_pos = torch.where(m, pos, self.agent_pos)
        self.agent_vel = vel
        self._pair = None
        self._task_rel = None

    def _claim(self, dist: Tensor, active: Tensor) -> Tensor:
        """Resolve claims in one round: each task goes to its nearest eligible AGV, and an AGV
        that wins several takes its nearest (the others wait for the next step)."""
        eligible = (
            (dist <= self.world.capture_radius)
            & (self.agent_task < 0).unsqueeze(2)
            & ~self.task_claimed.unsqueeze(1)
            & active.view(-1, 1, 1)
        )
        if not bool(eligible.any()):
            return torch.zeros_like(self.task_claimed)
        inf = torch.full_like(dist, float("inf"))
        best_agent = torch.where(eligible, dist, inf).min(dim=1, keepdim=True).indices  # (B,1,M)
        agents = torch.arange(self.num_agents, device=self.device).view(1, -1, 1)
        won = eligible & (agents == best_agent)
        min_d, best_task = torch.where(won, dist, inf).min(dim=2)  # (B, N)
        takes = torch.isfinite(min_d)
        self.agent_task = torch.where(takes, best_task, self.agent_task)
        self.agent_vel = self.agent_vel * (~takes).unsqueeze(-1)
        onehot = torch.nn.functional.one_hot(best_task, self.num_tasks).bool() & takes.unsqueeze(-1)
        claimed_now = onehot.any(dim=1)
        self.task_claimed = self.task_claimed | claimed_now
        return claimed_now

    # ------------------------------------------------------------------ observations
    def observe(self) -> Tensor:
        """Local observations, (B, N, O) with O = 5 + 3 K_tasks + 5 K_agents.

        Per AGV: own velocity (2) and position (2); for each of the K nearest unclaimed tasks
        within the sensing range its relative position (2) and a mask bit; for each of the K
        nearest other AGVs in range its relative position (2), velocity (2) and a mask bit;
        finally whether the AGV holds a task (1). Missing entries are zero with mask 0.
        """
        B, N = self.num_envs, self.num_agents
        rng = self.scenario.sensing_range
        if self._native is not None:
            obs = torch.empty(B, N, self.obs_dim, dtype=self.dtype)
            state = [t.contiguous() for t in (self.agent_pos, self.agent_vel, self.task_pos,
                                              self.task_claimed, self.agent_task)]
            if self._native.agv_observe(B, N, self.num_tasks, self.k_tasks, self.k_agents, rng,
                                        *[t.data_ptr() for t in state], obs.data_ptr()):
                raise MemoryError("the observation kernel could not allocate its scratch space")
            return obs
        parts = [self.agent_vel, self.agent_pos]
        if self.k_tasks:
            rel_t, d_t = self._task_offsets()
            hidden = self.task_claimed.unsqueeze(1) | (d_t > rng)
            feats = torch.cat([rel_t, torch.ones_like(d_t).unsqueeze(-1)], dim=-1)
            parts.append(self._nearest(feats, d_t.masked_fill(hidden, float("inf")), self.k_tasks))
        if self.k_agents:
            d_a = self._pairwise()
            delta = self.agent_pos.unsqueeze(2) - self.agent_pos.unsqueeze(1)
            vel_j = self.agent_vel.unsqueeze(1).expand(B, N, N, 2)
            feats = torch.cat([-delta, vel_j, torch.ones_like(d_a).unsqueeze(-1)], dim=-1)
            d_a = d_a.masked_fill(self._eye | (d_a > rng), float("inf"))
            parts.append(self._nearest(feats, d_a, self.k_agents))
        parts.append((self.agent_task >= 0).to(self.dtype).unsqueeze(-1))
        return torch.cat(parts, dim=-1)

    @staticmethod
    def _nearest(feats: Tensor, dist: Tensor, k: int) -> Tensor:
        """Features (B, N, C, F) of the k nearest finite-distance entries, flattened to
        (B, N, k F), zeroed where missing (the last feature is the mask bit, 1 when present).
        A full stable sort is used (ties go to the lower index, as in the fused kernel); it is
        faster than ``topk`` for the small C of these scenes."""
        B, N, C, F = feats.shape
        d_sorted, idx = torch.sort(dist, dim=-1, stable=True)
        kk = min(k, C)
        d_sorted, idx = d_sorted[..., :kk], idx[..., :kk]
        picked = feats.gather(2, idx.unsqueeze(-1).expand(B, N, kk, F))
        picked = picked * torch.isfinite(d_sorted).unsqueeze(-1)
        if kk < k:
            picked = torch.cat([picked, picked.new_zeros(B, N, k - kk, F)], dim=2)
        return picked.reshape(B, N, k * F)

    def global_state(self) -> Tensor:
        """Global state for centralized critics, (B, 5 N + 3 M): every AGV's position,
        velocity and holding bit, every task's position and claimed bit."""
        B = self.num_envs
        agents = torch.cat(
            [self.agent_pos, self.agent_vel, (self.agent_task >= 0).to(self.dtype).unsqueeze(-1)],
            dim=-1,
        )
        tasks = torch.cat([self.task_pos, self.task_claimed.to(self.dtype).unsqueeze(-1)], dim=-1)
        return torch.cat([agents.reshape(B, -1), tasks.reshape(B, -1)], dim=-1)


def make_env(
    scenario: Scenario | str = "3v3",
    num_envs: int = 1,
    reward: str | RewardFn = "minidist",
    seed: int | None = None,
    device: str | torch.device = "cpu",
    native: bool | None = None,
    **scenario_options: Any,
) -> AGVEnv:
    """Build a batched AGV environment.

    Parameters
    ----------
    scenario : str or Scenario
        A registry name (``"3v3"``, ``"6v6"``, any ``"NvM"``, ``"warehouse"``) or a Scenario.
    num_envs : int
        Number of parallel environments B.
    reward : str or callable
        ``"minidist"``, ``"greedy"`` or ``"ipf"``.
    seed : int, optional
        Seed of the environment's generator.
    device : str or torch.device
        Where the state lives (default CPU).
    native : bool, optional
        Fused CPU kernels (default: when available) or the torch reference path (``False``).
    **scenario_options
        Overrides for the scenario (e.g. ``max_steps=50``, ``sensing_range=1.0``).

    Returns
    -------
    AGVEnv

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
    from sim.scenarios import get_scenario

    if isinstance(scenario, str) or scenario_options:
        scenario = get_scenario(scenario, **scenario_options)
    return AGVEnv(scenario, num_envs=num_envs, reward=reward, seed=seed, device=device,
                  native=native)
