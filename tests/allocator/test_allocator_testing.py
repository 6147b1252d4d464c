"""allocator.testing: every helper passes on good plans and fails, with a useful message, on
deliberately wrong allocators; the strategies, the pytest plugin and the CI rule."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from importlib.metadata import entry_points
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from scipy.optimize import linear_sum_assignment
from scipy.spatial.distance import cdist

import allocator
from allocator import Assignment
from allocator.paths import travel_costs
from allocator.testing import (
    CASES,
    assert_consistent_plan,
    assert_equivariant,
    assert_no_task_served_twice,
    assert_optimal,
    assert_serves_every_reachable_task,
    check_allocator,
    in_ci,
    scenes,
    worlds,
)
from sim.world import World

pytest_plugins = ["pytester"]

PROPERTY = settings(max_examples=25, deadline=None, database=None, derandomize=True)

AGENTS, TASKS = CASES["square"]

# A corner pocket closed off by two shelves: a task at (0.7, 0.7) is unreachable from outside.
POCKET = World(obstacles=np.array([[0.3, 0.3, 0.4, 1.0], [0.3, 0.3, 1.0, 0.4]]))


def validated(agents: Any, tasks: Any) -> tuple[np.ndarray, np.ndarray]:
    """The input checks a user's allocator makes: (K, 2) arrays of finite numbers, K >= 1."""
    out = []
    for what, points in (("agents", agents), ("tasks", tasks)):
        arr = np.asarray(points, dtype=np.float64)
        if arr.ndim != 2 or arr.shape[1] != 2 or not len(arr) or not np.isfinite(arr).all():
            raise ValueError(f"{what} must be a non-empty (K, 2) array of finite numbers")
        out.append(arr)
    return out[0], out[1]


class Unchecked(Assignment):
    """An Assignment that skips validation, as a user's buggy allocator might build one."""

    def __post_init__(self) -> None:
        pass


def unchecked(t: list[int], a: list[int], cost: float, dtype: Any = np.int64,
              **kw: Any) -> Unchecked:
    return Unchecked(np.array(t, dtype=dtype), np.array(a, dtype=dtype), cost, **kw)


class Broken(allocator.ClassicalAllocator):
    """A user allocator whose ``assign`` is ``plan(agents, tasks, world)``."""

    name = "broken"

    def __init__(self, plan: Any) -> None:
        super().__init__()
        self.plan = plan

    def assign(self, agents: Any, tasks: Any, world: World | None = None) -> Any:
        agents, tasks = validated(agents, tasks)
        return self.plan(agents, tasks, world)


def serve_task_zero_by_everyone(agents: np.ndarray, tasks: np.ndarray, world: Any) -> Unchecked:
    n, m = len(agents), len(tasks)
    cost = float(np.linalg.norm(agents - tasks[0], axis=1).sum())
    a = [0] + [-1] * (m - 1)
    return unchecked([0] * n, a, cost, unserved={j: "skipped" for j in range(1, m)})


def identity_plan(agents: np.ndarray, tasks: np.ndarray, world: Any) -> Assignment:
    """AGV i serves task i: ignores where anything is."""
    k = min(len(agents), len(tasks))
    rows = np.arange(k)
    cost = float(np.linalg.norm(agents[:k] - tasks[:k], axis=1).sum())
    unserved = {j: "no AGV left" for j in range(k, len(tasks))}
    return Assignment.from_pairs(rows, rows, len(agents), len(tasks), cost, unserved=unserved)


def first_pair_only(agents: np.ndarray, tasks: np.ndarray, world: Any) -> Assignment:
    cost = float(np.linalg.norm(agents[0] - tasks[0]))
    unserved = {j: "lazy" for j in range(1, len(tasks))}
    return Assignment.from_pairs(np.array([0]), np.array([0]), len(agents), len(tasks), cost,
                                 unserved=unserved)


def silent_unserved(agents: np.ndarray, tasks: np.ndarray, world: Any) -> Assignment:
    """The optimal pairs, but unserved tasks get no reason."""
    plan = allocator.make("hungarian").assign(agents, tasks, world)
    return Assignment(plan.task_of_agent, plan.agent_of_task, plan.cost)


class LinearSum(allocator.ClassicalAllocator):
    """A user's own optimal allocator written from scratch on scipy."""

    name = "linear-sum"

    def assign(self, agents: Any, tasks: Any, world: World | None = None) -> Assignment:
        agents, tasks = validated(agents, tasks)
        cost = cdist(agents, tasks)
        rows, cols = linear_sum_assignment(cost)
        unserved = {j: "no AGV left" for j in sorted(set(range(len(tasks))) - set(cols))}
        return Assignment.from_pairs(rows, cols, len(agents), len(tasks),
                                     float(cost[rows, cols].sum()), unserved=unserved)


# ---------------------------------------------------------------------- check_allocator
def test_check_allocator_passes_a_users_own_optimal_allocator() -> None:
    check_allocator(LinearSum(), episodes=1, optimal=True, equivariant="both")


def test_check_allocator_names_the_case_and_the_task_served_twice() -> None:
    with pytest.raises(AssertionError, match=r"case 'square': .*task 0 by AGVs \[0, 1, 2\]"):
        check_allocator(Broken(serve_task_zero_by_everyone), episodes=1)


def test_conformance_rejects_an_unserved_task_without_a_reason() -> None:
    # the old check `isinstance(result.unserved.get(j, ""), str)` passed whatever the plan said
    with pytest.raises(AssertionError, match=r"case 'more_tasks': unserved task\(s\) \[.*\] "
                                             r"have no reason"):
        check_allocator(Broken(silent_unserved), episodes=1)


def test_check_allocator_fails_under_python_O_on_a_broken_allocator() -> None:
    script = textwrap.dedent("""
        import numpy as np
        import allocator
        from allocator import Assignment
        from allocator.testing import check_allocator

        class Unchecked(Assignment):
            def __post_init__(self):
                pass

        class ServesTaskZeroTwice(allocator.ClassicalAllocator):
            name = "twice"

            def assign(self, agents, tasks, world=None):
                a, t = np.asarray(agents, float), np.asarray(tasks, float)
                if a.ndim != 2 or t.ndim != 2 or a.shape[1:] != (2,) or t.shape[1:] != (2,):
                    raise ValueError("agents and tasks must have shape (K, 2)")
                if not (len(a) and len(t) and np.isfinite(a).all() and np.isfinite(t).all()):
                    raise ValueError("agents and tasks must be non-empty and finite")
                return Unchecked(np.zeros(len(a), np.int64), np.full(len(t), -1, np.int64), 1.0)

        assert False, "this bare assert is stripped by -O"
        check_allocator(ServesTaskZeroTwice(), episodes=1)
    """)
    run = subprocess.run([sys.executable, "-O", "-c", script], capture_output=True, text=True,
                         timeout=300)
    assert run.returncode != 0
    assert "AssertionError: case 'square':" in run.stderr, run.stderr[-2000:]
    assert "served more than once" in run.stderr


def test_check_allocator_reports_a_wrong_error_type_for_bad_input() -> None:
    class NoValidation(allocator.ClassicalAllocator):
        name = "no-validation"

        def assign(self, agents: Any, tasks: Any, world: World | None = None) -> Assignment:
            a, t = np.asarray(agents, dtype=float), np.asarray(tasks, dtype=float)
            return LinearSum().assign(a, t) if np.isfinite(a).all() else a.shape[5]

    with pytest.raises(AssertionError, match=r"raised IndexError on bad input \(NaN\)"):
        check_allocator(NoValidation(), episodes=1)


def test_check_allocator_rejects_bad_arguments() -> None:
    solver = allocator.make("hungarian")
    with pytest.raises(ValueError, match="equivariant must be one of"):
        check_allocator(solver, equivariant="sideways")
    with pytest.raises(ValueError, match="episodes must be a positive integer"):
        check_allocator(solver, episodes=0)


def test_check_allocator_refuses_an_object_without_the_allocator_methods() -> None:
    class AssignOnly:
        name = "assign-only"

        def assign(self, agents: Any, tasks: Any, world: Any = None) -> Assignment:
            return LinearSum().assign(agents, tasks)

    with pytest.raises(AssertionError, match=r"AssignOnly is not an Allocator: it lacks "
                                             r"\['reset', 'act'\]"):
        check_allocator(AssignOnly())


def test_check_allocator_catches_an_allocator_that_edits_its_input() -> None:
    class Mutating(LinearSum):
        def assign(self, agents: Any, tasks: Any, world: World | None = None) -> Assignment:
            plan = super().assign(agents, tasks, world)
            agents[0] += 0.01
            return plan

    with pytest.raises(AssertionError, match="assign modified the agents or tasks array"):
        check_allocator(Mutating(), episodes=1)


def test_check_allocator_catches_a_non_deterministic_allocator() -> None:
    rng = np.random.default_rng(0)

    def shuffled(agents: np.ndarray, tasks: np.ndarray, world: Any) -> Assignment:
        k = min(len(agents), len(tasks))
        rows, cols = rng.permutation(len(agents))[:k], rng.permutation(len(tasks))[:k]
        cost = float(np.linalg.norm(agents[rows] - tasks[cols], axis=1).sum())
        unserved = {j: "no AGV left" for j in sorted(set(range(len(tasks))) - set(cols))}
        return Assignment.from_pairs(rows, cols, len(agents), len(tasks), cost, unserved=unserved)

    with pytest.raises(AssertionError, match="assign is not deterministic"):
        check_allocator(Broken(shuffled), episodes=1, complete=True)


# ---------------------------------------------------------------------- assert_no_task_served_twice
def test_assert_no_task_served_twice_names_the_task_and_its_agvs() -> None:
    plan = unchecked([1, 0, 1], [1, 0, -1], 1.0)
    with pytest.raises(AssertionError, match=r"task 1 by AGVs \[0, 2\]"):
        assert_no_task_served_twice(plan)
    assert_no_task_served_twice(allocator.assign(AGENTS, TASKS))


# ---------------------------------------------------------------------- assert_consistent_plan
def test_assert_consistent_plan_passes_the_libraries_plans(shelf_world: World) -> None:
    for agents, tasks in CASES.values():
        for name in ("hungarian", "greedy"):
            plan = allocator.make(name, planner="grid").assign(agents, tasks)
            assert_consistent_plan(plan, agents, tasks, complete=True)
    agents = np.array([[-1.8, -1.3], [0.0, -1.3], [1.8, -1.3]])
    tasks = np.array([[-1.0, 0.2], [1.0, 0.2], [0.0, 1.3]])
    for planner in ("grid", "ompl"):
        plan = allocator.make("hungarian", planner=planner).assign(agents, tasks, shelf_world)
        assert_consistent_plan(plan, agents, tasks, shelf_world, complete=True)


@pytest.mark.parametrize(
    "plan, message",
    [
        (unchecked([0, 1, 2], [0, 1, 2], 1.0, dtype=np.int32),
         r"task_of_agent has dtype int32, expected int64"),
        (unchecked([0, 1], [0, 1, -1], 1.0), r"task_of_agent has shape \(2,\), expected \(3,\)"),
        (unchecked([0, 1, 3], [0, 1, -1], 1.0),
         r"task_of_agent holds values out of range \[-1, 2\] at \[2\] = 3"),
        (unchecked([0, 1, 2], [0, 2, 1], 1.0),
         r"AGV 1 serves task 1 but agent_of_task\[1\] = 2"),
        (unchecked([0, 1, -1], [0, 1, 0], 1.0, unserved={}),
         r"agent_of_task\[2\] = 0 but task_of_agent\[0\] = 0"),
        (unchecked([0, 1, -1], [0, 1, -1], 1.0, unserved={2: ""}),
         r"unserved task\(s\) \[2\] have no reason in unserved \(got \[''\]\)"),
        (unchecked([0, 1, 2], [0, 1, 2], 1.0, unserved={1: "busy"}),
         r"unserved gives reasons for task\(s\) \[1\], which are served"),
        (unchecked([0, 1, 2], [0, 1, 2], float("nan")), r"cost must be finite"),
        (unchecked([0, 1, 2], [0, 1, 2], 1.0), r"cost 1.0 does not match the plan: it should "
                                               r"equal 4.346.*AGV 0 -> task 0: 1.55563"),
    ],
    ids=["dtype", "shape", "range", "inverse", "orphan", "reason", "extra-reason", "nan-cost",
         "cost"],
)
def test_assert_consistent_plan_names_what_is_wrong(plan: Unchecked, message: str) -> None:
    with pytest.raises(AssertionError, match=message):
        assert_consistent_plan(plan, AGENTS, TASKS)


def test_assert_consistent_plan_checks_the_paths() -> None:
    good = allocator.make("hungarian", planner="grid").assign(AGENTS, TASKS)
    paths = list(good.paths)
    t = good.task_of_agent
    wrong_start = [np.stack([TASKS[t[0]], TASKS[t[0]]])] + paths[1:]
    with pytest.raises(AssertionError, match="the path of AGV 0 starts at"):
        assert_consistent_plan(Unchecked(t, good.agent_of_task, good.cost, paths=wrong_start),
                               AGENTS, TASKS)
    with pytest.raises(AssertionError, match="AGV 1 serves task .* but its path is None"):
        assert_consistent_plan(Unchecked(t, good.agent_of_task, good.cost,
                                         paths=[paths[0], None, paths[2]]), AGENTS, TASKS)
    # a straight path from outside the pocket to the task inside crosses a shelf
    agents, tasks = np.array([[-0.5, -0.5]]), np.array([[0.7, 0.7]])
    through = Unchecked(np.array([0]), np.array([0]), float(np.hypot(1.2, 1.2)),
                        paths=[np.concatenate([agents, tasks])])
    with pytest.raises(AssertionError, match="the path of AGV 0 passes through a shelf"):
        assert_consistent_plan(through, agents, tasks, POCKET)


def test_assert_consistent_plan_in_a_shelf_world_only_bounds_the_cost(shelf_world: World) -> None:
    agents = np.array([[-1.8, -1.3], [1.8, -1.3]])
    tasks = np.array([[-1.0, 0.2], [1.0, 1.3]])
    plan = allocator.make("hungarian").assign(agents, tasks, shelf_world)
    straight = float(np.linalg.norm(agents - tasks[plan.task_of_agent], axis=1).sum())
    low = Unchecked(plan.task_of_agent, plan.agent_of_task, straight - 0.1)
    with pytest.raises(AssertionError, match="below .* the straight-line length"):
        assert_consistent_plan(low, agents, tasks, shelf_world)
    exact = travel_costs(agents, tasks, shelf_world)
    off = Unchecked(plan.task_of_agent, plan.agent_of_task, plan.cost + 0.1)
    assert_consistent_plan(off, agents, tasks, shelf_world)
    with pytest.raises(AssertionError, match="does not match the plan"):
        assert_consistent_plan(off, agents, tasks, shelf_world, cost_matrix=exact)


def test_assert_consistent_plan_accepts_idle_travel_without_exact_cost() -> None:
    plan = allocator.assign(AGENTS, TASKS)
    more = Unchecked(plan.task_of_agent, plan.agent_of_task, plan.cost + 0.5)
    assert_consistent_plan(more, AGENTS, TASKS, exact_cost=False)
    less = Unchecked(plan.task_of_agent, plan.agent_of_task, plan.cost - 0.5)
    with pytest.raises(AssertionError, match="it should be at least"):
        assert_consistent_plan(less, AGENTS, TASKS, exact_cost=False)


def test_assert_consistent_plan_rejects_a_bad_cost_matrix() -> None:
    with pytest.raises(ValueError, match=r"cost_matrix must have shape \(N, M\) = \(3, 3\)"):
        assert_consistent_plan(allocator.assign(AGENTS, TASKS), AGENTS, TASKS,
                               cost_matrix=np.zeros((2, 3)))


# ---------------------------------------------------------------------- assert_serves_every_...
def test_assert_serves_every_reachable_task_names_the_task_and_the_idle_agvs() -> None:
    plan = first_pair_only(AGENTS, TASKS, None)
    with pytest.raises(AssertionError, match=r"serves 1 task\(s\) but 3 can be served \(the AGVs "
                                             r"suffice.*task 1 \(reason given: 'lazy'\) is "
                                             r"reachable by idle AGV\(s\) \[1, 2\]"):
        assert_serves_every_reachable_task(plan, AGENTS, TASKS)


def test_assert_serves_every_reachable_task_when_agvs_do_not_suffice() -> None:
    agents, tasks = CASES["more_tasks"]
    plan = first_pair_only(agents, tasks, None)
    with pytest.raises(AssertionError, match=r"at most 2 of the reachable tasks"):
        assert_serves_every_reachable_task(plan, agents, tasks)
    assert_serves_every_reachable_task(allocator.assign(agents, tasks), agents, tasks)


def test_assert_serves_every_reachable_task_allows_an_unreachable_one() -> None:
    agents = np.array([[-0.6, -0.6], [0.6, -0.6], [-0.6, 0.6]])
    tasks = np.array([[0.7, 0.7], [0.0, 0.0]])
    plan = allocator.make("hungarian").assign(agents, tasks, POCKET)
    assert plan.agent_of_task[0] == -1
    assert_serves_every_reachable_task(plan, agents, tasks, POCKET)
    assert_consistent_plan(plan, agents, tasks, POCKET, complete=True)
    with pytest.raises(AssertionError, match=r"task 0 \(reason given: 'unreachable"):
        assert_serves_every_reachable_task(plan, agents, tasks)  # in the open box it is not


# ---------------------------------------------------------------------- assert_optimal
def test_assert_optimal_fails_a_suboptimal_allocator_with_both_plans() -> None:
    agents, tasks = [[0.0, 0.0], [1.0, 0.0]], [[0.6, 0.0], [-1.0, 0.0]]
    greedy = allocator.make("greedy").assign(agents, tasks)
    with pytest.raises(AssertionError, match=r"not optimal: cost 2.6 > 1.4 \(AGV, task\) pairs "
                                             r"\[\(0, 0\), \(1, 1\)\], optimal pairs "
                                             r"\[\(0, 1\), \(1, 0\)\]"):
        assert_optimal(greedy, agents, tasks)


def test_assert_optimal_fails_a_wrong_reported_cost_and_a_short_plan() -> None:
    plan = allocator.assign(AGENTS, TASKS)
    wrong = Unchecked(plan.task_of_agent, plan.agent_of_task, plan.cost * 1.01)
    with pytest.raises(AssertionError, match="are optimal .* but it reports cost"):
        assert_optimal(wrong, AGENTS, TASKS)
    with pytest.raises(AssertionError, match=r"serves 1 pair\(s\) \[\(0, 0\)\], but 3 can be"):
        assert_optimal(first_pair_only(AGENTS, TASKS, None), AGENTS, TASKS)


def test_assert_optimal_accepts_a_tie_broken_either_way() -> None:
    agents, tasks = np.array([[0.0, 0.0], [1.0, 0.0]]), np.array([[0.0, 1.0], [1.0, 1.0]])
    assert_optimal(Assignment.from_pairs(np.array([0, 1]), np.array([0, 1]), 2, 2, 2.0),
                   agents, tasks)
    with pytest.raises(AssertionError, match="not optimal"):  # crossing costs 2 sqrt(2)
        assert_optimal(Assignment.from_pairs(np.array([0, 1]), np.array([1, 0]), 2, 2,
                                             2 * np.sqrt(2)), agents, tasks)
    corners, other_corners = np.array([[0.0, 0.0], [1.0, 1.0]]), np.array([[1.0, 0.0], [0.0, 1.0]])
    for cols in ([0, 1], [1, 0]):  # both pairings cost 2
        assert_optimal(Assignment.from_pairs(np.array([0, 1]), np.array(cols), 2, 2, 2.0),
                       corners, other_corners)


def test_assert_optimal_uses_the_cost_matrix_with_forbidden_pairs() -> None:
    cost = np.array([[1.0, np.inf], [2.0, 5.0]])
    agents, tasks = np.zeros((2, 2)), np.ones((2, 2))
    both = Assignment.from_pairs(np.array([0, 1]), np.array([0, 1]), 2, 2, 6.0)
    assert_optimal(both, agents, tasks, cost_matrix=cost)
    one = Assignment.from_pairs(np.array([1]), np.array([0]), 2, 2, 2.0, unserved={1: "x"})
    with pytest.raises(AssertionError, match=r"serves 1 pair\(s\) \[\(1, 0\)\], but 2 can be"):
        assert_optimal(one, agents, tasks, cost_matrix=cost)


def test_assert_optimal_refuses_a_scene_too_large_to_enumerate() -> None:
    rng = np.random.default_rng(0)
    agents, tasks = rng.uniform(-1, 1, (9, 2)), rng.uniform(-1, 1, (9, 2))
    with pytest.raises(ValueError, match="brute force over 362880 assignments"):
        assert_optimal(allocator.assign(agents, tasks), agents, tasks)


# ---------------------------------------------------------------------- assert_equivariant
def test_assert_equivariant_fails_an_allocator_that_ignores_the_permutation() -> None:
    solver = Broken(identity_plan)
    with pytest.raises(AssertionError, match=r"not equivariant under agent_perm=\[2, 0, 1\], "
                                             r"task_perm=\[0, 1, 2\]: AGV 0 \(AGV 2 before\) "
                                             r"serves task 0 .* expected 2"):
        assert_equivariant(solver, AGENTS, TASKS, agent_perm=[2, 0, 1], task_perm=[0, 1, 2])


def test_assert_equivariant_permutes_agents_tasks_or_both() -> None:
    hungarian, greedy = allocator.make("hungarian"), allocator.make("greedy")
    for agents, tasks in CASES.values():
        for seed in range(3):
            assert_equivariant(hungarian, agents, tasks, seed=seed)
            assert_equivariant(greedy, agents, tasks, permute="tasks", seed=seed)
    # greedy takes the AGVs in index order: reversing them changes its plan
    agents, tasks = [[0.0, 0.0], [1.0, 0.0]], [[0.6, 0.0], [-1.0, 0.0]]
    with pytest.raises(AssertionError, match="not equivariant"):
        assert_equivariant(greedy, agents, tasks, permute="agents")


def test_assert_equivariant_accepts_a_tie_broken_differently() -> None:
    agents, tasks = np.array([[0.0, 0.0], [1.0, 1.0]]), np.array([[1.0, 0.0], [0.0, 1.0]])

    def first_index(a: np.ndarray, t: np.ndarray, world: Any) -> Assignment:
        return Assignment.from_pairs(np.array([0, 1]), np.array([0, 1]), 2, 2,
                                     float(cdist(a, t)[[0, 1], [0, 1]].sum()))

    assert_equivariant(Broken(first_index), agents, tasks, agent_perm=[1, 0])


def test_helpers_report_an_out_of_range_plan_instead_of_crashing() -> None:
    bad = unchecked([0, 1, 7], [0, 1, -1], 1.0)
    for check in (assert_optimal, assert_serves_every_reachable_task):
        with pytest.raises(AssertionError, match=r"task_of_agent holds values out of range"):
            check(bad, AGENTS, TASKS)
    with pytest.raises(AssertionError, match=r"permuted scene: task_of_agent holds values out"):
        assert_equivariant(Broken(lambda a, t, w: bad if a[0, 0] != AGENTS[0, 0]
                                  else allocator.assign(a, t)), AGENTS, TASKS)


def test_check_allocator_fails_an_allocator_that_returns_no_assignment() -> None:
    with pytest.raises(AssertionError, match="assign returned dict, expected an allocator"):
        check_allocator(Broken(lambda a, t, w: {"task_of_agent": [0, 1, 2]}), episodes=1)


def test_assert_equivariant_rejects_bad_arguments() -> None:
    solver = allocator.make("hungarian")
    with pytest.raises(ValueError, match=r"agent_perm must be a permutation of range\(3\)"):
        assert_equivariant(solver, AGENTS, TASKS, agent_perm=[0, 0, 1])
    with pytest.raises(ValueError, match="permute must be 'both', 'agents' or 'tasks'"):
        assert_equivariant(solver, AGENTS, TASKS, permute="rows")


# ---------------------------------------------------------------------- strategies
@PROPERTY
@given(scenes(min_agents=2, max_agents=6, min_tasks=1, max_tasks=6))
def test_scenes_are_spaced_points_on_the_free_floor(scene: tuple[np.ndarray, np.ndarray]) -> None:
    agents, tasks = scene
    assert agents.dtype == tasks.dtype == np.float64
    assert 2 <= len(agents) <= 6 and 1 <= len(tasks) <= 6
    points = np.concatenate([agents, tasks])
    world = World()
    assert world.is_free(points).all()
    d = cdist(points, points) + np.eye(len(points)) * 9
    assert d.min() >= 2 * world.agent_radius


@PROPERTY
@given(worlds(min_shelves=1, max_shelves=8).flatmap(
    lambda w: scenes(max_agents=3, max_tasks=3, world=w).map(lambda s: (w, *s))))
def test_hungarian_is_optimal_on_drawn_warehouse_floors(case: tuple) -> None:
    world, agents, tasks = case
    assert 1 <= len(world.obstacles) <= 8
    assert world.is_free(np.concatenate([agents, tasks])).all()
    # the aisles connect the floor: every task is reachable
    assert np.isfinite(travel_costs(agents, tasks, world)).all()
    plan = allocator.make("hungarian").assign(agents, tasks, world)
    assert_consistent_plan(plan, agents, tasks, world, complete=True)
    assert_optimal(plan, agents, tasks, world)


@PROPERTY
@given(scenes(max_agents=5, max_tasks=5))
def test_hungarian_is_optimal_and_equivariant_on_drawn_scenes(scene: tuple) -> None:
    agents, tasks = scene
    plan = allocator.make("hungarian").assign(agents, tasks)
    assert_consistent_plan(plan, agents, tasks, complete=True)
    assert_optimal(plan, agents, tasks)
    assert_equivariant(allocator.make("hungarian"), agents, tasks)


@PROPERTY
@given(worlds(max_shelves=0))
def test_worlds_without_shelves_are_open_floors(world: World) -> None:
    assert not world.has_obstacles


def test_strategies_reject_bad_arguments() -> None:
    with pytest.raises(ValueError, match="min_agents .* must not exceed max_agents"):
        scenes(min_agents=4, max_agents=2)
    with pytest.raises(ValueError, match="max_tasks must be a positive integer"):
        scenes(max_tasks=0)
    with pytest.raises(ValueError, match="min_agents \\+ min_tasks = 40 points"):
        scenes(min_agents=20, max_agents=20, min_tasks=20, max_tasks=20)
    with pytest.raises(ValueError, match="world must be a sim.World"):
        scenes(world="warehouse")
    with pytest.raises(ValueError, match=r"max_shelves must be an integer in \[0, 16\]"):
        worlds(max_shelves=17)


def test_allocator_testing_imports_without_hypothesis() -> None:
    script = textwrap.dedent("""
        import sys
        sys.modules["hypothesis"] = None  # as if hypothesis were not installed
        import allocator.testing as t
        from allocator.testing import *
        t.check_allocator, t.assert_optimal, check_allocator
        try:
            t.scenes
        except ImportError as err:
            print("ImportError:", err)
    """)
    run = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                         timeout=120)
    assert run.returncode == 0, run.stderr
    assert "ImportError: allocator.testing.scenes and allocator.testing.worlds need hypothesis: " \
           "pip install hypothesis" in run.stdout


# ---------------------------------------------------------------------- CI rule
def test_in_ci_reads_the_ci_variable() -> None:
    assert in_ci({"CI": "true"}) and in_ci({"CI": "1"})
    assert not in_ci({}) and not in_ci({"CI": ""}) and not in_ci({"CI": "false"})


USER_WEIGHTS_TEST = """
    from allocator.testing import make_or_skip, skip_or_fail_in_ci

    def test_missing_file():
        skip_or_fail_in_ci("no weights at /nowhere")

    def test_missing_weights():
        make_or_skip("maddpg-ipf", scenario="9v9")
"""


def test_missing_weights_skip_locally_and_fail_on_ci(
    pytester: pytest.Pytester, monkeypatch: pytest.MonkeyPatch
) -> None:
    pytester.makepyfile(USER_WEIGHTS_TEST)
    monkeypatch.delenv("CI", raising=False)
    pytester.runpytest("-p", "no:cacheprovider").assert_outcomes(skipped=2)
    monkeypatch.setenv("CI", "true")
    result = pytester.runpytest("-p", "no:cacheprovider")
    result.assert_outcomes(failed=2)
    result.stdout.fnmatch_lines(["*no weights at /nowhere (CI is set*",
                                 "*9v9/maddpg-ipf.safetensors*"])


# ---------------------------------------------------------------------- pytest plugin
def test_the_plugin_is_registered_as_a_pytest11_entry_point() -> None:
    found = {ep.name: ep.value for ep in entry_points(group="pytest11")}
    assert found.get("agv_allocation") == "allocator.testing.plugin"


USER_PLUGIN_TEST = """
    import pytest
    import allocator
    from allocator.testing import assert_consistent_plan

    def test_every_world(agv_world):
        agents = [[-0.6, -0.6], [0.6, -0.6]] if not agv_world.has_obstacles else \\
            [[-1.8, -1.3], [1.8, -1.3]]
        tasks = [[0.0, 0.6]] if not agv_world.has_obstacles else [[0.0, 1.3]]
        plan = allocator.make("hungarian").assign(agents, tasks, agv_world)
        assert_consistent_plan(plan, agents, tasks, agv_world, complete=True)

    def test_default_scenario(agv_scenario):
        assert agv_scenario.name == "3v3"
        assert agv_scenario.agents.shape == (3, 2) and agv_scenario.tasks.shape == (3, 2)
        plan = allocator.make("greedy").assign(agv_scenario.agents, agv_scenario.tasks,
                                               agv_scenario.world)
        assert_consistent_plan(plan, agv_scenario.agents, agv_scenario.tasks, complete=True)

    @pytest.mark.parametrize("agv_scenario", ["6v6", "warehouse"], indirect=True)
    def test_chosen_scenarios(agv_scenario):
        assert agv_scenario.agents.shape == (6, 2)
        assert agv_scenario.world.is_free(agv_scenario.agents).all()

    @pytest.mark.parametrize("agv_world", ["warehouse"], indirect=True)
    def test_shelves_only(agv_world):
        assert agv_world.has_obstacles

    @pytest.mark.parametrize("agv_world", ["moon"], indirect=True)
    def test_unknown_world(agv_world):
        pass
"""


def test_plugin_fixtures_in_a_users_test_file(pytester: pytest.Pytester) -> None:
    pytester.makepyfile(USER_PLUGIN_TEST)
    result = pytester.runpytest("-v", "-p", "no:cacheprovider")
    result.assert_outcomes(passed=6, errors=1)
    result.stdout.fnmatch_lines([
        "*test_every_world?open? PASSED*",
        "*test_every_world?warehouse? PASSED*",
        "*test_chosen_scenarios?6v6? PASSED*",
        "*test_chosen_scenarios?warehouse? PASSED*",
    ])
    assert ("agv_world must be one of ['open', 'warehouse'] or a sim.World, got 'moon'"
            in result.stdout.str())
