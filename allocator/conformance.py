"""The shared conformance check every registry entry must pass (classical and learned).

>>> import allocator
>>> from allocator.conformance import check_allocator
>>> check_allocator(allocator.make("greedy"), episodes=2)
"""

from __future__ import annotations

from typing import Any

import numpy as np

from allocator.base import Allocator, Assignment

__all__ = ["check_allocator", "check_assignment", "CASES"]

CASES: dict[str, tuple[np.ndarray, np.ndarray]] = {
    "square": (
        np.array([[-0.6, -0.6], [0.6, -0.6], [0.0, 0.6]]),
        np.array([[0.5, 0.5], [-0.5, 0.4], [0.1, -0.7]]),
    ),
    "more_tasks": (
        np.array([[-0.5, 0.0], [0.5, 0.0]]),
        np.array([[0.6, 0.6], [-0.6, 0.6], [0.0, -0.6], [0.6, -0.6]]),
    ),
    "more_agents": (
        np.array([[-0.6, -0.6], [0.6, -0.6], [0.0, 0.6], [-0.6, 0.6]]),
        np.array([[0.5, 0.5], [0.0, -0.2]]),
    ),
    "single": (np.array([[0.0, 0.0]]), np.array([[0.5, 0.5]])),
}
"""Scenes in the MPE box ``[-1, 1]^2``: square, M > N, N > M and 1 x 1."""


def check_assignment(
    result: Assignment, agents: np.ndarray, tasks: np.ndarray, complete: bool = True
) -> None:
    """Assert that ``result`` is a consistent plan for the scene (open world)."""
    n, m = len(agents), len(tasks)
    assert isinstance(result, Assignment), f"assign returned {type(result).__name__}"
    t, a = result.task_of_agent, result.agent_of_task
    assert t.shape == (n,) and t.dtype == np.int64, f"task_of_agent {t.shape} {t.dtype}"
    assert a.shape == (m,) and a.dtype == np.int64, f"agent_of_task {a.shape} {a.dtype}"
    served = np.flatnonzero(t >= 0)
    assert np.array_equal(a[t[served]], served), "agent_of_task is not the inverse"
    assert len(np.unique(t[served])) == len(served), "a task is served twice"
    if complete:
        assert len(served) == min(n, m), f"{len(served)} pairs served, expected {min(n, m)}"
    straight = float(np.linalg.norm(agents[served] - tasks[t[served]], axis=1).sum())
    assert np.isfinite(result.cost) and result.cost >= straight - 1e-9, (
        f"cost {result.cost} below the straight-line length {straight} of its pairs"
    )
    for j in np.flatnonzero(a < 0):
        assert isinstance(result.unserved.get(int(j), ""), str)
    if result.paths is not None:
        assert len(result.paths) == n
        for i in served:
            p = result.paths[i]
            assert p is not None and p.ndim == 2 and p.shape[1] == 2
            assert np.allclose(p[0], agents[i]) and np.allclose(p[-1], tasks[t[i]])


def check_allocator(
    solver: Any,
    scenario: str = "3v3",
    episodes: int = 4,
    seed: int = 0,
    complete: bool = True,
) -> None:
    """Run the checks that every allocator must pass; raises AssertionError on a failure.

    1. It satisfies the :class:`~allocator.base.Allocator` protocol (``name``, ``assign``,
       ``reset``, ``act``).
    2. ``assign`` returns a consistent :class:`~allocator.base.Assignment` on square and
       rectangular scenes (``min(N, M)`` pairs when ``complete``), deterministically.
    3. Bad input (NaN, wrong shape, empty) raises ValueError.
    4. As a controller, ``sim.evaluate`` runs it and ``act`` returns (B, N, 2) in [-1, 1].

    Parameters
    ----------
    solver : Allocator
    scenario : str
        Scenario of the controller check (a learned allocator's own scenario).
    episodes : int
        Episodes of the controller check.
    complete : bool
        Require ``min(N, M)`` served pairs in an open world.
    """
    import torch

    import sim

    assert isinstance(solver, Allocator), f"{type(solver).__name__} lacks the Allocator methods"
    assert isinstance(solver.name, str) and solver.name
    for name, (agents, tasks) in CASES.items():
        result = solver.assign(agents, tasks)
        try:
            check_assignment(result, agents, tasks, complete=complete)
        except AssertionError as err:
            raise AssertionError(f"case {name!r}: {err}") from None
        again = solver.assign(agents.copy(), tasks.copy())
        assert np.array_equal(again.task_of_agent, result.task_of_agent), (
            f"case {name!r}: assign is not deterministic"
        )
    agents, tasks = CASES["square"]
    bad_inputs = {
        "NaN": (np.where(np.eye(3, 2, dtype=bool), np.nan, agents), tasks),
        "inf": (agents, np.full_like(tasks, np.inf)),
        "shape": (agents[:, :1], tasks),
        "3-D": (agents[None], tasks),
        "empty agents": (np.zeros((0, 2)), tasks),
        "empty tasks": (agents, np.zeros((0, 2))),
    }
    for what, (a, t) in bad_inputs.items():
        try:
            solver.assign(a, t)
        except ValueError:
            continue
        raise AssertionError(f"assign accepted bad input ({what}) without a ValueError")

    env = sim.make_env(scenario, num_envs=2, seed=seed)
    obs = env.reset()
    solver.reset(env)
    actions = torch.as_tensor(solver.act(obs))
    assert tuple(actions.shape) == (2, env.num_agents, 2), f"act gave {tuple(actions.shape)}"
    assert torch.isfinite(actions).all() and actions.abs().max() <= 1.0 + 1e-6
    metrics = sim.evaluate(solver, scenario, episodes=episodes, seed=seed)
    assert 0.0 <= metrics.response_rate <= 1.0
    assert metrics.episodes == episodes
