"""The conformance check every allocator passes, the library's own and a user's.

>>> import allocator
>>> from allocator.testing import check_allocator
>>> check_allocator(allocator.make("hungarian"), episodes=2, optimal=True, equivariant="both")
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from allocator.base import Allocator
from allocator.testing.assertions import (
    _fail,
    assert_consistent_plan,
    assert_equivariant,
    assert_is_assignment,
    assert_optimal,
    assert_serves_every_reachable_task,
)

if TYPE_CHECKING:  # pragma: no cover
    from sim.world import World

__all__ = ["check_allocator", "check_plans", "CASES"]

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

_EQUIVARIANCE = (None, "both", "agents", "tasks")


def _world_scenes(world: World, count: int, seed: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """``count`` scenes of 3 AGVs and 3 tasks on the free floor of ``world``, spaced apart."""
    rng = np.random.default_rng(seed)
    xmin, ymin, xmax, ymax = world.bounds
    r = world.agent_radius
    gap = 2 * r + 1e-3
    scenes = []
    while len(scenes) < count:
        points: list[np.ndarray] = []
        for _ in range(2000):
            p = rng.uniform([xmin + r, ymin + r], [xmax - r, ymax - r])
            if world.is_free(p[None])[0] and all(np.linalg.norm(p - q) >= gap for q in points):
                points.append(p)
                if len(points) == 6:
                    break
        else:
            raise ValueError(f"world {world} has no room for 3 AGVs and 3 tasks")
        scenes.append((np.array(points[:3]), np.array(points[3:])))
    return scenes


def check_plans(
    solver: Any,
    agents: np.ndarray,
    tasks: np.ndarray,
    world: World | None = None,
    *,
    complete: bool = True,
    exact_cost: bool = True,
    optimal: bool = False,
    equivariant: str | None = None,
) -> None:
    """Plan one scene and run every plan check on it.

    Checked: ``assign`` returns an :class:`~allocator.base.Assignment` that is a consistent
    plan (:func:`~allocator.testing.assert_consistent_plan`), leaves the caller's arrays as
    they were, and gives the same plan again for copies of the scene; optionally it serves as
    many tasks as can be served, is optimal, and is equivariant.

    Parameters
    ----------
    solver : Allocator
    agents : np.ndarray, shape (N, 2)
    tasks : np.ndarray, shape (M, 2)
    world : World, optional
    complete, exact_cost, optimal, equivariant
        See :func:`check_allocator`.

    Raises
    ------
    AssertionError
        On the first failed check.
    """
    before = agents.copy(), tasks.copy()
    result = assert_is_assignment(solver.assign(agents, tasks, world))
    if not (np.array_equal(agents, before[0]) and np.array_equal(tasks, before[1])):
        _fail("assign modified the agents or tasks array it was given")
    assert_consistent_plan(result, agents, tasks, world, exact_cost=exact_cost)
    if complete:
        assert_serves_every_reachable_task(result, agents, tasks, world)
    again = solver.assign(agents.copy(), tasks.copy(), world)
    if not np.array_equal(np.asarray(again.task_of_agent), result.task_of_agent):
        _fail(
            f"assign is not deterministic: task_of_agent {result.task_of_agent.tolist()} "
            f"then {np.asarray(again.task_of_agent).tolist()} for the same scene"
        )
    if optimal:
        assert_optimal(result, agents, tasks, world)
    if equivariant is not None:
        assert_equivariant(solver, agents, tasks, world, permute=equivariant)


def check_allocator(
    solver: Any,
    scenario: str = "3v3",
    episodes: int = 4,
    seed: int = 0,
    complete: bool = True,
    *,
    exact_cost: bool | None = None,
    optimal: bool = False,
    equivariant: str | None = None,
    world: World | None = None,
    world_scenes: int = 3,
) -> None:
    """Run the checks that every allocator must pass; raise AssertionError on a failure.

    1. It satisfies the :class:`~allocator.base.Allocator` protocol (``name``, ``assign``,
       ``reset``, ``act``) and has a non-empty string ``name``.
    2. On every scene of :data:`CASES` (square and rectangular, in the open MPE box), and on
       ``world_scenes`` scenes drawn on ``world`` when one is given, :func:`check_plans`:
       a consistent :class:`~allocator.base.Assignment`, input arrays untouched, the same plan
       twice; with ``complete`` as many pairs as can be served, with ``optimal`` the
       brute-force optimum, with ``equivariant`` the same plan for a permuted scene.
    3. Bad input (NaN, infinite, wrong shape, empty) raises ValueError.
    4. As a controller, ``act`` returns finite (B, N, 2) actions in [-1, 1] after ``reset``,
       and ``sim.evaluate`` runs ``episodes`` episodes of ``scenario``.

    Every check raises through an explicit ``raise AssertionError`` (never a bare ``assert``),
    so it works under ``python -O`` as well.

    Parameters
    ----------
    solver : Allocator
        The allocator under test.
    scenario : str
        Scenario of the controller check (a learned allocator's own scenario).
    episodes : int
        Episodes of the controller check.
    seed : int
        Seed of the controller check and of the scenes drawn on ``world``.
    complete : bool
        Require as many served pairs as the AGVs can serve (``min(N, M)`` in an open world).
        A decentralized policy promises no complete plan: pass False.
    exact_cost : bool, optional
        Require the cost to equal the travel of the served pairs (default: ``complete``; a
        policy that also counts the travel of AGVs that end up idle passes False).
    optimal : bool
        Require the brute-force optimum (for optimal solvers).
    equivariant : {None, "both", "agents", "tasks"}
        Require the plan to follow a permutation of the AGVs, the tasks or both.
    world : World, optional
        A floor (e.g. with shelves) to draw extra scenes on.
    world_scenes : int
        How many scenes to draw on ``world``.

    Raises
    ------
    AssertionError
        Naming the case and what is wrong.
    ValueError
        For a bad argument of this function.

    Examples
    --------
    >>> import allocator
    >>> from allocator.testing import check_allocator
    >>> from sim.scenarios import warehouse_world
    >>> check_allocator(allocator.make("greedy"), episodes=2, world=warehouse_world())
    """
    if equivariant not in _EQUIVARIANCE:
        raise ValueError(f"equivariant must be one of {list(_EQUIVARIANCE)}, got {equivariant!r}")
    if not isinstance(episodes, int) or isinstance(episodes, bool) or episodes < 1:
        raise ValueError(f"episodes must be a positive integer, got {episodes!r}")
    exact = complete if exact_cost is None else exact_cost
    if not isinstance(solver, Allocator):
        missing = [k for k in ("name", "assign", "reset", "act") if not hasattr(solver, k)]
        _fail(f"{type(solver).__name__} is not an Allocator: it lacks {missing}")
    if not (isinstance(solver.name, str) and solver.name):
        _fail(f"{type(solver).__name__}.name must be a non-empty string, got {solver.name!r}")
    cases = [(name, a, t, None) for name, (a, t) in CASES.items()]
    if world is not None:
        cases += [(f"world scene {k}", a, t, world)
                  for k, (a, t) in enumerate(_world_scenes(world, world_scenes, seed))]
    for name, agents, tasks, floor in cases:
        try:
            check_plans(solver, agents.copy(), tasks.copy(), floor, complete=complete,
                        exact_cost=exact, optimal=optimal, equivariant=equivariant)
        except AssertionError as err:
            raise AssertionError(f"case {name!r}: {err}") from None
    _check_bad_inputs(solver)
    _check_controller(solver, scenario, episodes, seed)


def _check_bad_inputs(solver: Any) -> None:
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
        except Exception as err:
            _fail(f"assign raised {type(err).__name__} on bad input ({what}), "
                  f"expected ValueError: {err}")
        _fail(f"assign accepted bad input ({what}) without a ValueError")


def _check_controller(solver: Any, scenario: str, episodes: int, seed: int) -> None:
    import torch

    import sim

    env = sim.make_env(scenario, num_envs=2, seed=seed)
    obs = env.reset()
    solver.reset(env)
    actions = torch.as_tensor(solver.act(obs))
    shape = (2, env.num_agents, 2)
    if tuple(actions.shape) != shape:
        _fail(f"act returned actions of shape {tuple(actions.shape)}, expected {shape}")
    if not bool(torch.isfinite(actions).all()):
        _fail("act returned NaN or infinite actions")
    if float(actions.abs().max()) > 1.0 + 1e-6:
        _fail(f"act returned actions outside [-1, 1] (max |a| = {float(actions.abs().max())})")
    metrics = sim.evaluate(solver, scenario, episodes=episodes, seed=seed)
    if not 0.0 <= metrics.response_rate <= 1.0:
        _fail(f"sim.evaluate gave a response rate of {metrics.response_rate}, not in [0, 1]")
    if metrics.episodes != episodes:
        _fail(f"sim.evaluate ran {metrics.episodes} episodes, expected {episodes}")
