"""Assertion helpers for allocation plans, with failure messages that name the AGVs and tasks.

Every helper raises :class:`AssertionError` through an explicit ``raise`` (never a bare
``assert``), so the checks also run under ``python -O``. The helpers that look at one plan take
the :class:`~allocator.base.Assignment` (or any object with the same fields); the equivariance
check takes the allocator, because it has to plan twice.

>>> import numpy as np, allocator
>>> from allocator.testing import assert_consistent_plan, assert_optimal
>>> agents = np.array([[0.0, 0.0], [1.0, 0.0]])
>>> tasks = np.array([[0.9, 0.0], [0.1, 0.0]])
>>> plan = allocator.make("hungarian").assign(agents, tasks)
>>> assert_consistent_plan(plan, agents, tasks, complete=True)
>>> assert_optimal(plan, agents, tasks)
>>> greedy = allocator.make("greedy").assign([[0.0, 0.0], [1.0, 0.0]], [[0.6, 0.0], [-1.0, 0.0]])
>>> assert_optimal(greedy, [[0.0, 0.0], [1.0, 0.0]], [[0.6, 0.0], [-1.0, 0.0]])
... # doctest: +ELLIPSIS
Traceback (most recent call last):
    ...
AssertionError: the plan is not optimal: cost 2.6 > 1.4 (AGV, task) pairs [(0, 0), (1, 1)], ...
"""

from __future__ import annotations

import math
from itertools import permutations
from typing import TYPE_CHECKING, Any, NoReturn

import numpy as np
from scipy.spatial.distance import cdist

from allocator.base import Assignment

if TYPE_CHECKING:  # pragma: no cover
    from sim.world import World

__all__ = [
    "assert_consistent_plan",
    "assert_no_task_served_twice",
    "assert_serves_every_reachable_task",
    "assert_optimal",
    "assert_equivariant",
    "assert_is_assignment",
    "MAX_BRUTE_FORCE",
]

MAX_BRUTE_FORCE = 100_000
"""Most assignments :func:`assert_optimal` enumerates (8 AGVs x 8 tasks is 40,320)."""


def _fail(message: str) -> NoReturn:
    raise AssertionError(message)


def _points(points: object, what: str) -> np.ndarray:
    arr = np.asarray(points, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise ValueError(f"{what} must have shape (K, 2), got {arr.shape}")
    return arr


def _open(world: World | None) -> bool:
    return world is None or not world.has_obstacles


def _costs(
    agents: np.ndarray, tasks: np.ndarray, world: World | None, cost_matrix: object
) -> np.ndarray:
    """The (N, M) travel costs: given, straight lines in an open world, else the grid's."""
    n, m = len(agents), len(tasks)
    if cost_matrix is not None:
        cost = np.asarray(cost_matrix, dtype=np.float64)
        if cost.shape != (n, m):
            raise ValueError(f"cost_matrix must have shape (N, M) = ({n}, {m}), got {cost.shape}")
        if np.any(np.isnan(cost)) or np.any(cost < 0):
            raise ValueError("cost_matrix must hold non-negative costs or inf, no NaN")
        return cost
    if _open(world):
        return cdist(agents, tasks)
    from allocator.paths import travel_costs

    return travel_costs(agents, tasks, world)


def _index_array(result: Any, name: str, length: int, other: int) -> np.ndarray:
    if not hasattr(result, name):
        _fail(f"the plan has no {name!r} field ({type(result).__name__})")
    arr = np.asarray(getattr(result, name))
    if arr.dtype != np.int64:
        _fail(f"{name} has dtype {arr.dtype}, expected int64")
    if arr.shape != (length,):
        _fail(f"{name} has shape {arr.shape}, expected ({length},)")
    bad = np.flatnonzero((arr < -1) | (arr >= other))
    if len(bad):
        _fail(
            f"{name} holds values out of range [-1, {other - 1}] at "
            + ", ".join(f"[{k}] = {arr[k]}" for k in bad[:10])
        )
    return arr


def assert_no_task_served_twice(result: Any) -> None:
    """Fail if two AGVs of the plan serve the same task.

    Parameters
    ----------
    result : Assignment
        Read: ``task_of_agent`` (N,).

    Raises
    ------
    AssertionError
        Naming every task served more than once and the AGVs serving it.

    Examples
    --------
    >>> import allocator
    >>> from allocator.testing import assert_no_task_served_twice
    >>> plan = allocator.make("greedy").assign([[0.0, 0.0], [1.0, 0.0]], [[0.5, 0.5], [2.0, 0.0]])
    >>> assert_no_task_served_twice(plan)
    """
    t = np.asarray(result.task_of_agent)
    served = t[t >= 0]
    tasks, counts = np.unique(served, return_counts=True)
    twice = tasks[counts > 1]
    if len(twice):
        detail = "; ".join(
            f"task {j} by AGVs {np.flatnonzero(t == j).tolist()}" for j in twice.tolist()
        )
        _fail(f"{len(twice)} task(s) served more than once: {detail}")


def assert_consistent_plan(
    result: Any,
    agents: object,
    tasks: object,
    world: World | None = None,
    *,
    complete: bool = False,
    exact_cost: bool = True,
    cost_matrix: object = None,
    rtol: float = 1e-7,
    atol: float = 1e-9,
) -> None:
    """Fail unless ``result`` is a self-consistent plan for the scene.

    Checked: ``task_of_agent`` (N,) and ``agent_of_task`` (M,) are int64 with values in
    ``[-1, M)`` and ``[-1, N)``; they are inverse of each other; no task is served twice; every
    unserved task has a non-empty reason in ``unserved`` and no served task has one; the cost is
    finite and non-negative; ``paths``, when given, hold one entry per AGV, ``None`` for an idle
    AGV, and for a serving AGV a finite ``(K, 2)`` polyline from the AGV to its task that stays
    inside the walls and out of the shelves of ``world``.

    The cost must equal the plan's travel distance, the summed cost of its (agent, task) pairs
    under ``cost_matrix`` (default: straight lines in an open world). With shelves and no
    ``cost_matrix`` the obstacle-aware length is the solver's own, so the cost is only required
    to be at least the straight-line length of the pairs; with ``exact_cost=False`` it is only
    required to be at least the pairs' travel (and at least the length of their paths in an
    open world), as for a policy that also counts the travel of AGVs that end up idle.

    Parameters
    ----------
    result : Assignment
        The plan (any object with the :class:`~allocator.base.Assignment` fields).
    agents : array-like, shape (N, 2)
    tasks : array-like, shape (M, 2)
    world : World, optional
        The floor the plan was made for.
    complete : bool
        Also require as many served pairs as the AGVs can serve
        (:func:`assert_serves_every_reachable_task`).
    exact_cost : bool
        Require the cost to equal the pairs' travel (else: at least it).
    cost_matrix : array-like, shape (N, M), optional
        Travel costs the plan is priced with (``inf``: unreachable).
    rtol, atol : float
        Tolerance of the cost comparisons.

    Raises
    ------
    AssertionError
        Naming the field, the AGVs and the tasks that are wrong.

    Examples
    --------
    >>> import allocator
    >>> from allocator.testing import assert_consistent_plan
    >>> agents, tasks = [[0.0, 0.0], [1.0, 0.0]], [[0.0, 1.0]]
    >>> plan = allocator.make("hungarian").assign(agents, tasks)
    >>> assert_consistent_plan(plan, agents, tasks, complete=True)
    """
    agents = _points(agents, "agents")
    tasks = _points(tasks, "tasks")
    n, m = len(agents), len(tasks)
    t = _index_array(result, "task_of_agent", n, m)
    a = _index_array(result, "agent_of_task", m, n)
    assert_no_task_served_twice(result)
    served = np.flatnonzero(t >= 0)
    wrong = [int(i) for i in served if a[t[i]] != i]
    if wrong:
        _fail(
            "agent_of_task is not the inverse of task_of_agent: "
            + ", ".join(f"AGV {i} serves task {t[i]} but agent_of_task[{t[i]}] = {a[t[i]]}"
                        for i in wrong[:10])
        )
    orphans = [int(j) for j in np.flatnonzero(a >= 0) if t[a[j]] != j]
    if orphans:
        _fail(
            "agent_of_task names AGVs that serve another task: "
            + ", ".join(f"agent_of_task[{j}] = {a[j]} but task_of_agent[{a[j]}] = {t[a[j]]}"
                        for j in orphans[:10])
        )
    _check_unserved(result, a)
    _check_cost(result, agents, tasks, world, t, served, exact_cost, cost_matrix, rtol, atol)
    if getattr(result, "paths", None) is not None:
        _check_paths(result.paths, agents, tasks, world, t)
    if complete:
        assert_serves_every_reachable_task(result, agents, tasks, world, cost_matrix=cost_matrix)


def _check_unserved(result: Any, agent_of_task: np.ndarray) -> None:
    reasons = getattr(result, "unserved", None)
    if not isinstance(reasons, dict):
        _fail(f"unserved must be a dict of task -> reason, got {type(reasons).__name__}")
    unserved = [int(j) for j in np.flatnonzero(agent_of_task < 0)]
    missing = [j for j in unserved if not (isinstance(reasons.get(j), str) and reasons[j])]
    if missing:
        _fail(
            f"unserved task(s) {missing} have no reason in unserved "
            f"(got {[reasons.get(j) for j in missing]}); every unserved task needs a "
            "non-empty string saying why"
        )
    extra = sorted(set(reasons) - set(unserved), key=str)
    if extra:
        _fail(f"unserved gives reasons for task(s) {extra}, which are served or do not exist")


def _check_cost(
    result: Any,
    agents: np.ndarray,
    tasks: np.ndarray,
    world: World | None,
    t: np.ndarray,
    served: np.ndarray,
    exact: bool,
    cost_matrix: object,
    rtol: float,
    atol: float,
) -> None:
    try:
        cost = float(result.cost)
    except (TypeError, ValueError):
        _fail(f"cost must be a number, got {result.cost!r}")
    if not math.isfinite(cost) or cost < 0:
        _fail(f"cost must be finite and non-negative, got {cost}")
    straight = np.linalg.norm(agents[served] - tasks[t[served]], axis=1)
    if cost_matrix is None and not _open(world):
        if cost < straight.sum() - atol:
            _fail(
                f"cost {cost} is below {straight.sum()}, the straight-line length of the pairs"
            )
        return
    pair_costs = _costs(agents, tasks, world, cost_matrix)[served, t[served]]
    infinite = [(int(i), int(t[i])) for i, c in zip(served, pair_costs, strict=True)
                if not np.isfinite(c)]
    if infinite:
        _fail(f"the plan serves pairs (AGV, task) {infinite} whose travel cost is infinite")
    travel = float(pair_costs.sum())
    paths = getattr(result, "paths", None)
    if not exact and paths is not None and _open(world) and len(paths) == len(agents):
        lengths = [_path_length(paths[i]) for i in served if paths[i] is not None]
        travel = max(travel, float(sum(lengths)))
    gap = cost - travel
    tol = atol + rtol * abs(travel)
    if gap < -tol or (exact and gap > tol):
        detail = ", ".join(f"AGV {i} -> task {j}: {c:.6g}" for i, j, c in
                           zip(served[:10], t[served][:10], pair_costs[:10], strict=True))
        relation = "equal" if exact else "be at least"
        _fail(
            f"cost {cost!r} does not match the plan: it should {relation} {travel!r}, "
            f"the travel of its {len(served)} pair(s) ({detail})"
        )


def _path_length(path: np.ndarray) -> float:
    p = np.asarray(path, dtype=np.float64)
    return float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum()) if len(p) > 1 else 0.0


def _check_paths(
    paths: Any, agents: np.ndarray, tasks: np.ndarray, world: World | None, t: np.ndarray
) -> None:
    n = len(agents)
    if len(paths) != n:
        _fail(f"paths has {len(paths)} entries, expected one per AGV ({n})")
    for i in range(n):
        p = paths[i]
        if t[i] < 0:
            if p is not None:
                _fail(f"AGV {i} is idle but has a path; an idle AGV's path must be None")
            continue
        j = int(t[i])
        if p is None:
            _fail(f"AGV {i} serves task {j} but its path is None")
        arr = np.asarray(p, dtype=np.float64)
        if arr.ndim != 2 or arr.shape[1] != 2 or len(arr) < 1:
            _fail(f"the path of AGV {i} has shape {arr.shape}, expected (K, 2) with K >= 1")
        if not np.all(np.isfinite(arr)):
            _fail(f"the path of AGV {i} holds NaN or infinite waypoints")
        if not np.allclose(arr[0], agents[i], atol=1e-6):
            _fail(f"the path of AGV {i} starts at {arr[0].tolist()}, not at the AGV "
                  f"({agents[i].tolist()})")
        if not np.allclose(arr[-1], tasks[j], atol=1e-6):
            _fail(f"the path of AGV {i} ends at {arr[-1].tolist()}, not at its task {j} "
                  f"({tasks[j].tolist()})")
        if world is not None:
            _check_path_is_free(arr, world, i)


def _check_path_is_free(path: np.ndarray, world: World, agent: int) -> None:
    """Fail if the polyline leaves the walls or crosses a shelf (its centre line)."""
    step = 0.02
    if world.has_obstacles:
        o = world.obstacles
        step = min(step, float(np.min(o[:, 2:] - o[:, :2])) / 4)
    points = [path[:1]]
    for p0, p1 in zip(path[:-1], path[1:], strict=True):
        k = max(1, int(math.ceil(np.linalg.norm(p1 - p0) / step)))
        s = np.linspace(0.0, 1.0, k + 1)[1:, None]
        points.append(p0 + s * (p1 - p0))
    pts = np.concatenate(points)
    blocked = ~world.is_free(pts, clearance=0.0)
    if blocked.any():
        _fail(f"the path of AGV {agent} passes through a shelf or a wall near "
              f"{pts[np.argmax(blocked)].round(4).tolist()}")


def _max_matching(reachable: np.ndarray) -> tuple[int, np.ndarray]:
    """Size of a maximum matching of the (N, M) reachability graph and its matched tasks."""
    from scipy.sparse import csr_matrix
    from scipy.sparse.csgraph import maximum_bipartite_matching

    graph = csr_matrix(reachable.astype(np.int8))
    agent_of_task = maximum_bipartite_matching(graph, perm_type="row")
    return int(np.count_nonzero(agent_of_task >= 0)), agent_of_task


def assert_serves_every_reachable_task(
    result: Any,
    agents: object,
    tasks: object,
    world: World | None = None,
    *,
    cost_matrix: object = None,
) -> None:
    """Fail unless the plan serves as many tasks as its AGVs can reach.

    When the AGVs suffice (every reachable task can get its own AGV, e.g. N >= M in an open
    world), every reachable task must be served. When they do not, the plan must serve as many
    pairs as a maximum matching of AGVs to the tasks they can reach.

    Parameters
    ----------
    result : Assignment
    agents : array-like, shape (N, 2)
    tasks : array-like, shape (M, 2)
    world : World, optional
        With shelves, reachability comes from ``cost_matrix`` (default: the library's
        obstacle-aware grid costs, :func:`allocator.paths.travel_costs`).
    cost_matrix : array-like, shape (N, M), optional
        ``inf`` marks a pair the AGV cannot travel.

    Raises
    ------
    AssertionError
        Naming the reachable tasks left unserved (with their stated reasons) and the idle AGVs
        that could reach them.

    Examples
    --------
    >>> import allocator
    >>> from allocator.testing import assert_serves_every_reachable_task
    >>> agents, tasks = [[0.0, 0.0], [1.0, 0.0], [0.5, 0.5]], [[0.0, 1.0], [1.0, 1.0]]
    >>> plan = allocator.make("greedy").assign(agents, tasks)
    >>> assert_serves_every_reachable_task(plan, agents, tasks)
    """
    agents = _points(agents, "agents")
    tasks = _points(tasks, "tasks")
    t = _index_array(result, "task_of_agent", len(agents), len(tasks))
    a = _index_array(result, "agent_of_task", len(tasks), len(agents))
    reachable = np.isfinite(_costs(agents, tasks, world, cost_matrix))
    best, _ = _max_matching(reachable)
    served = int(np.count_nonzero(t >= 0))
    if served >= best:
        return
    reasons = getattr(result, "unserved", {}) or {}
    idle = np.flatnonzero(t < 0)
    left = [int(j) for j in np.flatnonzero((a < 0) & reachable.any(axis=0))]
    detail = "; ".join(
        f"task {j} (reason given: {reasons.get(j)!r}) is reachable by idle AGV(s) "
        f"{[int(i) for i in idle if reachable[i, j]]}"
        for j in left[:10]
    )
    suffice = best == int(np.count_nonzero(reachable.any(axis=0)))
    what = ("the AGVs suffice for every reachable task" if suffice
            else f"at most {best} of the reachable tasks can be served at once")
    _fail(f"the plan serves {served} task(s) but {best} can be served ({what}): {detail}")


def _brute_force(cost: np.ndarray) -> tuple[int, float, list[tuple[int, int]]]:
    """Most servable pairs, their least total cost and one optimal set of pairs."""
    n, m = cost.shape
    k = min(n, m)
    count = math.perm(max(n, m), k)
    if count > MAX_BRUTE_FORCE:
        raise ValueError(
            f"brute force over {count} assignments of {n} AGVs and {m} tasks is too slow; "
            f"use a scene with at most {MAX_BRUTE_FORCE} assignments (e.g. 8 AGVs and 8 tasks)"
        )
    perms = np.array(list(permutations(range(max(n, m)), k)), dtype=np.int64).reshape(-1, k)
    fixed = np.broadcast_to(np.arange(k), perms.shape)
    rows, cols = (fixed, perms) if n <= m else (perms, fixed)
    pair_cost = cost[rows, cols]  # (P, k)
    finite = np.isfinite(pair_cost)
    served = finite.sum(axis=1)
    total = np.where(finite, pair_cost, 0.0).sum(axis=1)
    most = int(served.max())
    total = np.where(served == most, total, np.inf)
    best = int(np.argmin(total))
    pairs = [(int(r), int(c))
             for r, c, f in zip(rows[best], cols[best], finite[best], strict=True) if f]
    return most, float(total[best]), sorted(pairs)


def assert_optimal(
    result: Any,
    agents: object,
    tasks: object,
    world: World | None = None,
    *,
    cost_matrix: object = None,
    rtol: float = 1e-7,
    atol: float = 1e-9,
) -> None:
    """Fail unless the plan is optimal: compared with brute force over all assignments.

    The optimum serves as many (AGV, task) pairs of finite cost as possible and, among those,
    has the least total cost. Ties are fine: the plan's pairs may differ from the brute-force
    ones as long as the costs agree within ``atol + rtol * optimum``. Meant for small scenes
    (at most :data:`MAX_BRUTE_FORCE` assignments, e.g. 8 x 8).

    Parameters
    ----------
    result : Assignment
    agents : array-like, shape (N, 2)
    tasks : array-like, shape (M, 2)
    world : World, optional
        With shelves and no ``cost_matrix``, the library's grid travel costs are the yardstick
        (:func:`allocator.paths.travel_costs`).
    cost_matrix : array-like, shape (N, M), optional
        The costs the solver minimises (``inf``: forbidden pair); default straight lines.
    rtol, atol : float
        Tolerance on the total cost.

    Raises
    ------
    AssertionError
        Giving the plan's pairs and cost, an optimal set of pairs and its cost.
    ValueError
        For a scene too large to enumerate.

    Examples
    --------
    >>> import allocator
    >>> from allocator.testing import assert_optimal
    >>> agents, tasks = [[0.0, 0.0], [2.0, 0.0]], [[2.0, 1.0], [0.0, 1.0], [5.0, 5.0]]
    >>> assert_optimal(allocator.make("hungarian").assign(agents, tasks), agents, tasks)
    """
    agents = _points(agents, "agents")
    tasks = _points(tasks, "tasks")
    cost = _costs(agents, tasks, world, cost_matrix)
    most, optimum, best_pairs = _brute_force(cost)
    t = _index_array(result, "task_of_agent", len(agents), len(tasks))
    served = np.flatnonzero(t >= 0)
    plan_pairs = [(int(i), int(t[i])) for i in served]
    plan_cost = float(cost[served, t[served]].sum()) if len(served) else 0.0
    tol = atol + rtol * abs(optimum)
    if len(served) < most:
        _fail(
            f"the plan serves {len(served)} pair(s) {plan_pairs}, but {most} can be served, "
            f"e.g. {best_pairs} at cost {optimum:.6g}"
        )
    if not np.isfinite(plan_cost) or plan_cost > optimum + tol:
        _fail(
            f"the plan is not optimal: cost {plan_cost:.6g} > {optimum:.6g} "
            f"(AGV, task) pairs {plan_pairs}, optimal pairs {best_pairs}"
        )
    reported = float(result.cost)
    if abs(reported - optimum) > tol:
        _fail(
            f"the plan's pairs {plan_pairs} are optimal ({optimum:.6g}) but it reports "
            f"cost {reported!r}"
        )


def _permutation(perm: object, size: int, rng: np.random.Generator, what: str) -> np.ndarray:
    if perm is None:
        p = rng.permutation(size)
        if size > 1 and np.array_equal(p, np.arange(size)):
            p = np.roll(p, 1)
        return p
    p = np.asarray(perm)
    if p.shape != (size,) or not np.array_equal(np.sort(p), np.arange(size)):
        raise ValueError(f"{what} must be a permutation of range({size}), got {perm!r}")
    return p.astype(np.int64)


def assert_equivariant(
    solver: Any,
    agents: object,
    tasks: object,
    world: World | None = None,
    *,
    permute: str = "both",
    agent_perm: object = None,
    task_perm: object = None,
    seed: int = 0,
    rtol: float = 1e-7,
    atol: float = 1e-9,
) -> None:
    """Fail unless permuting the AGVs and tasks of a scene permutes the plan the same way.

    The solver plans the scene, then the scene with AGV ``k`` moved to place ``i`` where
    ``agent_perm[i] == k`` (and the tasks likewise). Each AGV must serve the same task as
    before. A tie (two plans of equal cost) may be broken differently: when the plans differ
    but serve as many pairs at a cost equal within ``atol + rtol * cost``, the check passes.

    Parameters
    ----------
    solver : Allocator
        Anything with ``assign(agents, tasks, world)``.
    agents : array-like, shape (N, 2)
    tasks : array-like, shape (M, 2)
    world : World, optional
    permute : {"both", "agents", "tasks"}
        Which entities to permute (a solver that takes AGVs in index order, like greedy, is
        equivariant under task permutations only).
    agent_perm, task_perm : array-like of int, optional
        The permutations (default: random ones from ``seed``, never the identity).
    seed : int
    rtol, atol : float
        Tolerance when comparing the costs of differing plans.

    Raises
    ------
    AssertionError
        Naming the AGVs whose task changed, with both plans' costs.

    Examples
    --------
    >>> import allocator
    >>> from allocator.testing import assert_equivariant
    >>> agents, tasks = [[0.0, 0.0], [1.0, 0.0], [2.0, 0.3]], [[0.1, 0.9], [2.0, 1.0], [1.1, 0.8]]
    >>> assert_equivariant(allocator.make("hungarian"), agents, tasks)
    >>> assert_equivariant(allocator.make("greedy"), agents, tasks, permute="tasks")
    """
    if permute not in ("both", "agents", "tasks"):
        raise ValueError(f"permute must be 'both', 'agents' or 'tasks', got {permute!r}")
    agents = _points(agents, "agents")
    tasks = _points(tasks, "tasks")
    n, m = len(agents), len(tasks)
    rng = np.random.default_rng(seed)
    pa = (_permutation(agent_perm, n, rng, "agent_perm") if permute != "tasks"
          else np.arange(n))
    pt = (_permutation(task_perm, m, rng, "task_perm") if permute != "agents"
          else np.arange(m))
    base = solver.assign(agents.copy(), tasks.copy(), world)
    moved = solver.assign(agents[pa].copy(), tasks[pt].copy(), world)
    new_index_of_task = np.empty(m, dtype=np.int64)
    new_index_of_task[pt] = np.arange(m)
    t0 = _index_array(base, "task_of_agent", n, m)[pa]
    expected = np.where(t0 >= 0, new_index_of_task[np.maximum(t0, 0)], -1)
    try:
        got = _index_array(moved, "task_of_agent", n, m)
    except AssertionError as err:
        raise AssertionError(f"the plan of the permuted scene: {err}") from None
    if np.array_equal(got, expected):
        return
    c0, c1 = float(base.cost), float(moved.cost)
    same_size = np.count_nonzero(got >= 0) == np.count_nonzero(expected >= 0)
    if same_size and abs(c0 - c1) <= atol + rtol * max(abs(c0), abs(c1)):
        return
    diffs = [
        f"AGV {i} (AGV {pa[i]} before) serves task {got[i]} "
        f"(task {pt[got[i]] if got[i] >= 0 else -1} before), expected {expected[i]}"
        for i in np.flatnonzero(got != expected)[:10]
    ]
    _fail(
        f"the plan is not equivariant under agent_perm={pa.tolist()}, task_perm={pt.tolist()}: "
        + "; ".join(diffs)
        + f" (cost {c0!r} before, {c1!r} after)"
    )


def assert_is_assignment(result: Any) -> Assignment:
    """Fail unless ``result`` is an :class:`~allocator.base.Assignment`; return it."""
    if not isinstance(result, Assignment):
        _fail(f"assign returned {type(result).__name__}, expected an allocator.Assignment")
    return result
