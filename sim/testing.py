"""Checks that a user's own scenario or reward behaves as the simulator promises.

:func:`check_env` runs the checks the library runs on its own scenarios and rewards, the way
PettingZoo ships ``parallel_api_test``::

    import sim
    from sim.testing import check_env

    check_env("warehouse", reward=MyReward())          # a scenario (name or Scenario) and reward
    check_env(lambda num_envs, seed: sim.make_env(my_scenario, num_envs, seed=seed))

Three checks, each raising an ``AssertionError`` that says what differs, where and by how much:

- **conformance**, at every step: shapes and dtypes of the observations, rewards, reward terms,
  ``done`` and ``info``; finite values; AGVs inside the walls; ``done`` and claims never undone;
  the step counter; a finished environment frozen, with zero reward and zero reward terms;
  the terms adding up to the reward; the observation size independent of the batch size;
  ``reset(env_ids)`` starting new episodes only where asked;
- **determinism**: two environments made with the same seed start from the same scenes and,
  given the same actions, follow the same trajectory exactly; a seeded ``reset`` repeats its
  scenes;
- **batch against loop**: B environments stepped together equal B single environments stepped
  one by one from the same placed scenes (observations, rewards, reward terms, claims,
  ``done``, positions and velocities), so no rule reads another environment of the batch.

The actions drive every AGV towards its nearest open task, with seeded noise and values a little
outside [-1, 1] (which the step clips), so that claims, contacts and finished episodes occur.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import torch
from torch import Tensor

import sim

__all__ = ["check_env"]

EnvFactory = Callable[..., Any]
"""``factory(num_envs=B, seed=s) -> AGVEnv``."""

_RTOL = 1e-5
_ATOL = 1e-5
"""Batched and single environments run the same float32 code; only the order of a few sums
(matrix products over the batch) may differ, hence a tolerance on floats; claims, holdings,
``done`` and step counts must be equal."""


def _fail(check: str, where: str, what: str) -> AssertionError:
    return AssertionError(f"check_env [{check}] {where}: {what}")


def _close(check: str, where: str, name: str, got: Tensor, expected: Tensor,
           exact: bool = False) -> None:
    """Raise an AssertionError naming ``name`` unless ``got`` equals ``expected``."""
    if tuple(got.shape) != tuple(expected.shape):
        raise _fail(check, where, f"{name} has shape {tuple(got.shape)}, expected "
                    f"{tuple(expected.shape)}")
    try:
        if exact:
            torch.testing.assert_close(got, expected, rtol=0, atol=0, equal_nan=False)
        else:
            torch.testing.assert_close(got, expected, rtol=_RTOL, atol=_ATOL)
    except AssertionError as err:
        raise _fail(check, where, f"{name} differs: {err}") from None


def _factory(target: Any, reward: Any, native: bool | None) -> EnvFactory:
    if isinstance(target, (str, sim.Scenario, sim.LifelongScenario)):
        scenario = sim.get_scenario(target)
        chosen = "minidist" if reward is None else reward

        def make(num_envs: int, seed: int) -> Any:
            return sim.make_env(scenario, num_envs=num_envs, reward=chosen, seed=seed,
                                native=native)

        return make
    if callable(target):
        if reward is not None or native is not None:
            raise ValueError(
                "reward and native apply to a scenario; an env factory builds its environments "
                "itself, so pass them to the factory instead"
            )
        return target
    raise ValueError(
        "scenario_or_env_factory must be a scenario name, a Scenario or a callable "
        f"factory(num_envs, seed) -> AGVEnv, got {type(target).__name__}"
    )


def _make(factory: EnvFactory, num_envs: int, seed: int) -> Any:
    env = factory(num_envs=num_envs, seed=seed)
    needed = ("num_envs", "num_agents", "obs_dim", "step", "reset", "set_state")
    if not getattr(env, "lifelong", False):
        needed += ("num_tasks",)
    for attr in needed:
        if not hasattr(env, attr):
            raise _fail("conformance", "factory", f"the environment it made has no {attr!r}; "
                        "expected an AGVEnv")
    if env.num_envs != num_envs:
        raise _fail("conformance", "factory", f"asked for {num_envs} environments, got "
                    f"{env.num_envs}")
    return env


def _actions(env: Any, generator: torch.Generator) -> Tensor:
    """Towards each AGV's nearest open task, plus noise, in [-1.2, 1.2]^2, shape (B, N, 2)."""
    rel = env.task_pos.unsqueeze(1) - env.agent_pos.unsqueeze(2)  # (B, N, M, 2)
    dist = torch.linalg.vector_norm(rel, dim=-1).masked_fill(env.task_claimed.unsqueeze(1),
                                                             float("inf"))
    nearest = dist.argmin(dim=2)  # (B, N)
    to_task = rel.gather(2, nearest[..., None, None].expand(-1, -1, 1, 2)).squeeze(2)
    to_task = to_task * torch.isfinite(dist.min(dim=2).values).unsqueeze(-1)
    noise = torch.rand(to_task.shape, generator=generator) * 2.0 - 1.0
    drive = (3.0 * to_task.cpu()).clamp(-1.0, 1.0) + 0.6 * noise
    return drive.clamp(-1.2, 1.2).to(env.agent_pos.device)


def _record(env: Any, obs: Tensor, reward: Tensor, done: Tensor, info: dict) -> dict[str, Any]:
    rec = {"obs": obs, "reward": reward, "done": done, "agent_pos": env.agent_pos,
           "agent_vel": env.agent_vel, "task_claimed": env.task_claimed,
           "agent_task": env.agent_task, "steps": env.steps,
           "claimed_now": info["claimed_now"], "team_reward": info["team_reward"],
           "collision_pairs": info["collision_pairs"],
           "collisions_per_agent": info["collisions_per_agent"]}
    rec = {k: v.detach().clone() for k, v in rec.items()}
    rec["terms"] = {k: v.detach().clone() for k, v in info["reward_terms"].items()}
    return rec


def _check_types(where: str, name: str, x: Any, shape: tuple[int, ...],
                 dtype: torch.dtype) -> None:
    if not isinstance(x, Tensor):
        raise _fail("conformance", where, f"{name} is a {type(x).__name__}, expected a Tensor")
    if tuple(x.shape) != shape:
        raise _fail("conformance", where, f"{name} has shape {tuple(x.shape)}, expected {shape}")
    if x.dtype != dtype:
        raise _fail("conformance", where, f"{name} has dtype {x.dtype}, expected {dtype}")
    if x.is_floating_point() and not bool(torch.isfinite(x).all()):
        raise _fail("conformance", where, f"{name} contains NaN or infinite values")


def _check_step(env: Any, where: str, before: dict[str, Tensor], obs: Tensor, reward: Tensor,
                done: Tensor, info: dict) -> None:
    """Conformance of one step of ``env``; ``before`` holds its state before the step."""
    B, N, M = env.num_envs, env.num_agents, env.num_tasks
    f32, flag, index = torch.float32, torch.bool, torch.int64
    _check_types(where, "obs", obs, (B, N, env.obs_dim), f32)
    _check_types(where, "reward", reward, (B, N), f32)
    _check_types(where, "done", done, (B,), flag)
    for name, shape, dtype in (("team_reward", (B,), f32), ("claimed_now", (B, M), flag),
                               ("agent_task", (B, N), index), ("collision_pairs", (B,), f32),
                               ("collisions_per_agent", (B, N), f32), ("active", (B,), flag)):
        if name not in info:
            raise _fail("conformance", where, f"info has no {name!r}; it has {sorted(info)}")
        _check_types(where, f"info[{name!r}]", info[name], shape, dtype)
    terms = info.get("reward_terms")
    if not isinstance(terms, dict) or not terms:
        raise _fail("conformance", where, "info['reward_terms'] must be a non-empty dict of "
                    f"(B, N) tensors, got {terms!r}")
    for name, term in terms.items():
        _check_types(where, f"reward term {name!r}", term, (B, N), f32)
    _check_types(where, "agent_pos", env.agent_pos, (B, N, 2), f32)
    _check_types(where, "agent_vel", env.agent_vel, (B, N, 2), f32)
    ran = ~before["done"]
    _close("conformance", where, "info['active'] (the environments not done before the step)",
           info["active"], ran, exact=True)
    if bool((before["done"] & ~done).any()):
        raise _fail("conformance", where, "done went from True back to False without a reset")
    if bool((before["task_claimed"] & ~env.task_claimed).any()):
        raise _fail("conformance", where, "a claimed task became unclaimed without a reset")
    _close("conformance", where, "steps", env.steps, before["steps"] + ran.long(), exact=True)
    finished = env.task_claimed.all(dim=1) | (env.steps >= env.max_steps)
    _close("conformance", where, "done (every task claimed or the step limit reached)", done,
           before["done"] | finished, exact=True)
    stopped = before["done"]
    if bool(stopped.any()):
        for name in ("agent_pos", "agent_vel", "task_claimed", "agent_task"):
            _close("conformance", where, f"{name} of an environment that was already done",
                   getattr(env, name)[stopped], before[name][stopped], exact=True)
        zero = torch.zeros_like(reward[stopped])
        _close("conformance", where, "reward of an environment that was already done",
               reward[stopped], zero, exact=True)
        for name, term in terms.items():
            _close("conformance", where, f"reward term {name!r} of an environment that was "
                   "already done", term[stopped], zero, exact=True)
    if bool(ran.any()):
        total = sum(terms.values())
        _close("conformance", where, "reward against the sum of its terms", reward[ran],
               total[ran])
    parked = before["agent_task"] >= 0
    _close("conformance", where, "positions of parked AGVs", env.agent_pos[parked],
           before["agent_pos"][parked], exact=True)
    held = env.agent_task
    if bool(((held < -1) | (held >= M)).any()):
        raise _fail("conformance", where, f"agent_task holds values outside [-1, {M})")
    counts = torch.zeros(B, M + 1, dtype=torch.int64, device=held.device)
    counts.scatter_add_(1, held + 1, torch.ones_like(held))
    _close("conformance", where, "AGVs holding each task (1 for a claimed task, else 0)",
           counts[:, 1:], env.task_claimed.long(), exact=True)
    world = env.world
    pos = env.agent_pos.reshape(-1, 2).double().cpu().numpy()
    if bool((world.wall_distance(pos) < world.agent_radius - 1e-5).any()):
        raise _fail("conformance", where, "an AGV's disc crosses the walls")


def _check_partial_reset(env: Any) -> None:
    """``reset(env_ids=[0])`` starts a new episode in environment 0 and leaves the rest."""
    before = _state(env)
    obs = env.reset(env_ids=[0])
    where = "reset(env_ids=[0])"
    _check_types(where, "obs", obs, (env.num_envs, env.num_agents, env.obs_dim), torch.float32)
    fresh = {"steps": torch.zeros_like(before["steps"][:1]),
             "done": torch.zeros_like(before["done"][:1]),
             "task_claimed": torch.zeros_like(before["task_claimed"][:1]),
             "agent_task": torch.full_like(before["agent_task"][:1], -1),
             "agent_vel": torch.zeros_like(before["agent_vel"][:1])}
    for name, value in fresh.items():
        _close("conformance", where, f"{name} of the reset environment", getattr(env, name)[:1],
               value, exact=True)
    for name, value in before.items():
        _close("conformance", where, f"{name} of the environments not reset",
               getattr(env, name)[1:], value[1:], exact=True)


def _state(env: Any) -> dict[str, Tensor]:
    return {name: getattr(env, name).clone() for name in
            ("agent_pos", "agent_vel", "task_claimed", "agent_task", "steps", "done")}


@torch.no_grad()
def _step(env: Any, actions: Tensor, where: str, conform: bool) -> dict[str, Any]:
    """One step of ``env``, checked for conformance if ``conform``, as a record of clones."""
    before = _state(env)
    obs, reward, done, info = env.step(actions)
    if conform:
        _check_step(env, where, before, obs, reward, done, info)
    return _record(env, obs, reward, done, info)


def _rollout(env: Any, actions: list[Tensor], label: str,
             conform: bool) -> list[dict[str, Any]]:
    return [_step(env, a, f"{label}, step {t}", conform) for t, a in enumerate(actions)]


def _compare(check: str, label: str, got: list[dict[str, Any]], expected: list[dict[str, Any]],
             rows: slice) -> None:
    """Compare two rollouts step by step (``expected`` restricted to environments ``rows``)."""
    exact = {"done", "task_claimed", "agent_task", "steps", "claimed_now"}
    for t, (g, e) in enumerate(zip(got, expected, strict=True)):
        where = f"{label}, step {t}"
        if sorted(g["terms"]) != sorted(e["terms"]):
            raise _fail(check, where, f"reward terms {sorted(g['terms'])} differ from "
                        f"{sorted(e['terms'])}")
        for name, value in g["terms"].items():
            _close(check, where, f"reward term {name!r}", value, e["terms"][name][rows],
                   exact=check == "determinism")
        for name, value in g.items():
            if name != "terms":
                _close(check, where, name, value, e[name][rows],
                       exact=check == "determinism" or name in exact)


def check_env(
    scenario_or_env_factory: str | sim.Scenario | EnvFactory,
    reward: Any = None,
    *,
    num_envs: int = 4,
    steps: int | None = None,
    seed: int = 0,
    native: bool | None = None,
) -> None:
    """Check an environment for conformance, determinism and batch-against-loop equality.

    Parameters
    ----------
    scenario_or_env_factory : str, Scenario, LifelongScenario or callable
        A scenario (registry name, :class:`sim.Scenario` or a lifelong one such as
        ``"warehouse-20"``), whose environments :func:`sim.make_env` builds, or a factory
        ``factory(num_envs=B, seed=s) -> AGVEnv or LifelongEnv`` for environments built some
        other way. Lifelong environments get the same three checks, with lifelong rules: no
        order lost at any step, statuses valid, ``done`` only at the horizon, and B floors
        stepped together equal to each stepped alone from the same fleet and stream key.
    reward : str or reward callable, optional
        The reward of a scenario's environments (default ``"minidist"``); a callable is
        shared by every environment the check makes, so it must keep no per-environment state.
        Not allowed with a factory.
    num_envs : int
        Environments B stepped together (and then one by one).
    steps : int, optional
        Steps per rollout; default the scenario's step limit + 1, so every episode ends and a
        finished environment is stepped once more (lifelong: 60).
    seed : int
        Seed of the environments and of the actions.
    native : bool, optional
        Passed to :func:`sim.make_env` with a scenario: the fused kernels (default where
        available) or the torch path (``False``).

    Raises
    ------
    AssertionError
        Naming the check (``conformance``, ``determinism`` or ``batch against loop``), the
        step and environment, and what differs.
    ValueError
        For arguments of the wrong kind.

    Examples
    --------
    >>> from sim.testing import check_env
    >>> check_env("3v3", reward="greedy", num_envs=2)
    """
    factory = _factory(scenario_or_env_factory, reward, native)
    for name, value in (("num_envs", num_envs), ("steps", 1 if steps is None else steps)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
            raise ValueError(f"{name} must be a positive integer, got {value!r}")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
    B, seed = int(num_envs), int(seed)

    first = _make(factory, B, seed)
    if getattr(first, "lifelong", False):
        _check_lifelong(factory, first, 60 if steps is None else int(steps), seed)
        return
    T = first.max_steps + 1 if steps is None else int(steps)
    one = _make(factory, 1, seed)
    if one.obs_dim != first.obs_dim:
        raise _fail("conformance", "observation size", f"{one.obs_dim} with one environment, "
                    f"{first.obs_dim} with {B}; it must not depend on the batch size")
    start_obs = first.observe()
    _check_types("reset", "obs", start_obs, (B, first.num_agents, first.obs_dim), torch.float32)
    start = {name: getattr(first, name).clone() for name in ("agent_pos", "task_pos",
                                                               "agent_vel")}
    generator = torch.Generator().manual_seed(seed)
    actions = []
    reference = []
    for t in range(T):
        actions.append(_actions(first, generator))
        reference.append(_step(first, actions[-1], f"{B} environments, step {t}", conform=True))

    _check_partial_reset(first)

    # Determinism: the same seed gives the same scenes and, with the same actions, the same
    # trajectory; a seeded reset repeats its scenes.
    second = _make(factory, B, seed)
    for name in ("agent_pos", "task_pos"):
        _close("determinism", "the start scenes of two environments made with the same seed",
               name, getattr(second, name), start[name], exact=True)
    _compare("determinism", "a second environment made with the same seed",
             _rollout(second, actions, "second", conform=False), reference, slice(None))
    scenes = []
    for _ in range(2):
        second.reset(seed=seed + 1)
        scenes.append((second.agent_pos.clone(), second.task_pos.clone()))
    for i, name in enumerate(("agent_pos", "task_pos")):
        _close("determinism", "two resets with the same seed", name, scenes[1][i], scenes[0][i],
               exact=True)

    # Batch against loop: each environment alone, from the same placed scene.
    for b in range(B):
        single = _make(factory, 1, seed + 1 + b)
        rows = slice(b, b + 1)
        single.set_state(start["agent_pos"][rows], start["task_pos"][rows],
                         start["agent_vel"][rows])
        _close("batch against loop", f"environment {b} of {B} alone, after set_state", "obs",
               single.observe(), start_obs[rows])
        alone = _rollout(single, [a[rows] for a in actions], f"environment {b} alone",
                         conform=False)
        _compare("batch against loop", f"environment {b} of {B} stepped alone", alone,
                 reference, rows)


# ---------------------------------------------------------------------- lifelong mode
def _lifelong_actions(env: Any, obs: Tensor, generator: torch.Generator) -> Tensor:
    """Towards each AGV's target, else its nearest open pickup, plus noise, (B, N, 2)."""
    lay = env.obs_layout
    rel = obs[..., lay.target_rel]
    if lay.k_pickups:
        near = obs[..., lay.pickup_rel(0)] * obs[..., lay.pickup_mask(0)]
        rel = torch.where(obs[..., lay.target_mask] > 0, rel, near)
    noise = torch.rand(rel.shape, generator=generator) * 2.0 - 1.0
    return ((3.0 * rel.cpu()).clamp(-1.0, 1.0) + 0.6 * noise).clamp(-1.2, 1.2).to(obs.device)


def _lifelong_step(env: Any, actions: Tensor, where: str, conform: bool) -> dict[str, Any]:
    """One checked lifelong step as a record of clones."""
    done_before = env.done.clone()
    steps_before = env.steps.clone()
    obs, reward, done, info = env.step(actions)
    B, N = env.num_envs, env.num_agents
    if conform:
        _check_types(where, "obs", obs, (B, N, env.obs_dim), torch.float32)
        _check_types(where, "reward", reward, (B, N), reward.dtype)
        if not reward.dtype.is_floating_point:
            raise _fail("conformance", where, f"reward has dtype {reward.dtype}")
        _check_types(where, "done", done, (B,), torch.bool)
        if bool((done_before & ~done).any()):
            raise _fail("conformance", where, "done was undone")
        want_steps = steps_before + (~done_before).long()
        if not torch.equal(env.steps, want_steps):
            raise _fail("conformance", where, f"steps {env.steps.tolist()}, expected "
                        f"{want_steps.tolist()}")
        terms = info["reward_terms"]
        if terms:
            total = sum(terms.values())
            _close("conformance", where, "the sum of the reward terms", reward, total)
        balance = env.order_balance()
        if bool((balance != 0).any()):
            b = int(balance.ne(0).nonzero()[0])
            raise _fail("conformance", where, f"environment {b} lost orders: released - "
                        f"(delivered + open + assigned + loaded) = {int(balance[b])}")
        status = env.agent_status
        if bool(((status < 0) | (status > 3)).any()):
            raise _fail("conformance", where, "an AGV status outside the four codes")
        inside = env.world.wall_distance(env.agent_pos.double().cpu().numpy())
        if np.any(inside < env.world.agent_radius - 1e-4):
            raise _fail("conformance", where, "an AGV left the walls")
    return {"obs": obs.clone(), "reward": reward.clone(), "done": done.clone(),
            "pos": env.agent_pos.clone(), "status": env.orders.status.clone(),
            "delivered": env.delivered.clone(), "fleet": env.agent_status.clone()}


def _check_lifelong(factory: EnvFactory, first: Any, T: int, seed: int) -> None:
    B = first.num_envs
    one = _make(factory, 1, seed)
    if one.obs_dim != first.obs_dim:
        raise _fail("conformance", "observation size", f"{one.obs_dim} with one environment, "
                    f"{first.obs_dim} with {B}; it must not depend on the batch size")
    start_obs = first.observe()
    start_pos, keys = first.agent_pos.clone(), first.keys.clone()
    generator = torch.Generator().manual_seed(seed)
    actions, reference = [], []
    obs = start_obs
    for t in range(T):
        actions.append(_lifelong_actions(first, obs, generator))
        reference.append(_lifelong_step(first, actions[-1], f"{B} floors, step {t}", True))
        obs = reference[-1]["obs"]

    def replay(env: Any, rows: slice, label: str, check: str) -> None:
        for t, a in enumerate(actions):
            got = _lifelong_step(env, a[rows], f"{label}, step {t}", False)
            for name in ("obs", "reward", "pos"):
                _close(check, f"{label}, step {t}", name, got[name], reference[t][name][rows])
            for name in ("done", "delivered", "fleet"):
                _close(check, f"{label}, step {t}", name, got[name], reference[t][name][rows],
                       exact=True)

    # Determinism: the same seed, the same fleets and keys and trajectory.
    second = _make(factory, B, seed)
    _close("determinism", "the start of two environments made with the same seed",
           "agent_pos", second.agent_pos, start_pos, exact=True)
    _close("determinism", "the start of two environments made with the same seed", "keys",
           second.keys, keys, exact=True)
    replay(second, slice(None), "a second environment made with the same seed", "determinism")
    # Batch against loop: each floor alone from the same fleet and stream key.
    for b in range(B):
        single = _make(factory, 1, seed + 1 + b)
        rows = slice(b, b + 1)
        single.set_state(start_pos[rows], keys[rows])
        _close("batch against loop", f"floor {b} of {B} alone, after set_state", "obs",
               single.observe(), start_obs[rows])
        replay(single, rows, f"floor {b} of {B} stepped alone", "batch against loop")
