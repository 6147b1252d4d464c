"""Hungarian and greedy: brute-force oracle, metamorphic checks, rectangles, bad input."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

import allocator
from allocator.greedy import greedy_matching
from allocator.hungarian import NO_AGENT_LEFT, UNREACHABLE, solve_cost_matrix
from allocator.paths import travel_costs
from sim.world import World
from tests.allocator.conftest import spaced_points


def brute_force(cost: np.ndarray) -> float:
    """Least total cost over every way of serving min(N, M) pairs."""
    n, m = cost.shape
    best = np.inf
    if n <= m:
        for tasks in itertools.permutations(range(m), n):
            best = min(best, cost[np.arange(n), list(tasks)].sum())
    else:
        for agents in itertools.permutations(range(n), m):
            best = min(best, cost[list(agents), np.arange(m)].sum())
    return float(best)


@pytest.mark.parametrize("n, m", [(1, 1), (3, 3), (5, 5), (7, 7), (2, 6), (6, 3), (7, 4), (4, 7)])
def test_hungarian_matches_brute_force_open(n: int, m: int) -> None:
    rng = np.random.default_rng(100 * n + m)
    for _ in range(3):
        agents = rng.uniform(-1, 1, (n, 2))
        tasks = rng.uniform(-1, 1, (m, 2))
        result = allocator.assign(agents, tasks)
        cost = travel_costs(agents, tasks)
        assert result.cost == pytest.approx(brute_force(cost), abs=1e-9)
        assert result.num_served == min(n, m)


@pytest.mark.parametrize("n, m", [(3, 3), (6, 6), (7, 7), (3, 6), (6, 4)])
def test_hungarian_matches_brute_force_shelves(shelf_world: World, n: int, m: int) -> None:
    rng = np.random.default_rng(7 * n + m)
    agents = spaced_points(rng, n, shelf_world, 0.3)
    tasks = spaced_points(rng, m, shelf_world, 0.3)
    solver = allocator.make("hungarian")
    result = solver.assign(agents, tasks, world=shelf_world)
    cost = solver.cost_matrix(agents, tasks, shelf_world)
    assert np.all(np.isfinite(cost))
    assert result.cost == pytest.approx(brute_force(cost), abs=1e-9)
    # Around shelves, some pairs cost more than the straight line.
    straight = travel_costs(agents, tasks)
    assert np.all(cost >= straight - 1e-9) and np.any(cost > straight + 1e-3)


@pytest.mark.parametrize("n, m", [(5, 5), (3, 7), (7, 3)])
def test_permuting_agents_permutes_the_assignment(n: int, m: int) -> None:
    rng = np.random.default_rng(n * m)
    agents = rng.uniform(-1, 1, (n, 2))
    tasks = rng.uniform(-1, 1, (m, 2))
    perm = rng.permutation(n)
    base = allocator.assign(agents, tasks)
    permuted = allocator.assign(agents[perm], tasks)
    np.testing.assert_array_equal(permuted.task_of_agent, base.task_of_agent[perm])
    assert permuted.cost == pytest.approx(base.cost)
    tperm = rng.permutation(m)
    by_task = allocator.assign(agents, tasks[tperm])
    np.testing.assert_array_equal(by_task.agent_of_task, base.agent_of_task[tperm])


def test_rectangular_both_ways() -> None:
    agents = np.array([[0.0, 0.0], [2.0, 0.0]])
    tasks = np.array([[2.0, 1.0], [0.0, 1.0], [5.0, 5.0]])
    wide = allocator.assign(agents, tasks)
    np.testing.assert_array_equal(wide.task_of_agent, [1, 0])
    np.testing.assert_array_equal(wide.agent_of_task, [1, 0, -1])
    assert wide.unserved == {2: NO_AGENT_LEFT}
    tall = allocator.assign(tasks, agents)  # three AGVs, two tasks
    np.testing.assert_array_equal(tall.task_of_agent, [1, 0, -1])
    np.testing.assert_array_equal(tall.agent_of_task, [1, 0])
    assert tall.cost == pytest.approx(2.0)


@pytest.mark.parametrize("seed", range(20))
def test_greedy_never_beats_hungarian(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n, m = rng.integers(1, 9, size=2)
    agents = rng.uniform(-1, 1, (n, 2))
    tasks = rng.uniform(-1, 1, (m, 2))
    greedy = allocator.assign(agents, tasks, method="greedy")
    best = allocator.assign(agents, tasks)
    assert greedy.num_served == best.num_served == min(n, m)
    assert greedy.cost >= best.cost - 1e-9


def test_greedy_takes_turns_in_index_order() -> None:
    cost = np.array([[1.0, 2.0], [1.5, 10.0]])
    rows, cols = greedy_matching(cost)
    np.testing.assert_array_equal(rows, [0, 1])
    np.testing.assert_array_equal(cols, [0, 1])


def test_weights_and_priorities() -> None:
    agents = np.array([[0.0, 0.0]])
    tasks = np.array([[1.0, 0.0], [3.0, 0.0]])
    assert allocator.assign(agents, tasks).task_of_agent[0] == 0
    solver = allocator.make("hungarian")
    assert solver.assign(agents, tasks, weights=[10.0, 1.0]).task_of_agent[0] == 1
    result = solver.assign(agents, tasks, priorities=[0, 1])
    assert result.task_of_agent[0] == 1 and result.cost == pytest.approx(3.0)
    with pytest.raises(ValueError, match="weights"):
        solver.assign(agents, tasks, weights=[1.0])
    with pytest.raises(ValueError, match="priorities"):
        solver.assign(agents, tasks, priorities=[0.5, 1])


def test_unreachable_task_is_left_unserved_with_a_reason() -> None:
    # Task 1 sits in a pocket closed by shelves on every side.
    walls = np.array([[0.3, 0.3, 1.0, 0.4], [0.3, 0.4, 0.4, 1.0], [0.4, 0.9, 1.0, 1.0],
                      [0.9, 0.4, 1.0, 0.9]])
    world = World(bounds=(-1.0, -1.0, 1.2, 1.2), obstacles=walls, agent_radius=0.1)
    agents = np.array([[-0.5, -0.5], [-0.6, 0.6]])
    tasks = np.array([[0.5, -0.5], [0.65, 0.65]])
    for method in ("hungarian", "greedy"):
        result = allocator.assign(agents, tasks, method=method, world=world)
        assert result.agent_of_task[1] == -1
        assert result.unserved == {1: UNREACHABLE}
        assert result.agent_of_task[0] >= 0 and np.isfinite(result.cost)


def test_solve_cost_matrix_serves_as_many_pairs_as_possible() -> None:
    inf = np.inf
    cost = np.array([[1.0, inf], [2.0, inf], [inf, 50.0]])
    rows, cols = solve_cost_matrix(cost)
    assert sorted(zip(rows.tolist(), cols.tolist(), strict=True)) == [(0, 0), (2, 1)]


BAD = [
    ("NaN", [[np.nan, 0.0]], [[0.0, 0.0]], "NaN"),
    ("inf", [[0.0, 0.0]], [[np.inf, 0.0]], "infinite"),
    ("shape", [[0.0, 0.0, 0.0]], [[0.0, 0.0]], "shape"),
    ("1-D", [0.0, 0.0], [[0.0, 0.0]], "shape"),
    ("empty", np.zeros((0, 2)), [[0.0, 0.0]], "empty"),
    ("text", [["a", "b"]], [[0.0, 0.0]], "agents"),
]


@pytest.mark.parametrize("method", ["hungarian", "greedy"])
@pytest.mark.parametrize("what, agents, tasks, message", BAD, ids=[b[0] for b in BAD])
def test_bad_input_raises(method: str, what: str, agents, tasks, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        allocator.assign(agents, tasks, method=method)


def test_positions_outside_the_world_or_in_a_shelf(shelf_world: World) -> None:
    inside = shelf_world.obstacles[0, :2] + 0.05
    free = spaced_points(np.random.default_rng(0), 2, shelf_world, 0.3)
    with pytest.raises(ValueError, match="inside a shelf"):
        allocator.assign(free, inside[None], world=shelf_world)
    with pytest.raises(ValueError, match="outside the world"):
        allocator.assign(np.array([[100.0, 0.0]]), free, world=shelf_world)


def test_unknown_method_lists_the_registry() -> None:
    with pytest.raises(ValueError, match="hungarian"):
        allocator.make("simulated-annealing")


def test_paths_when_a_planner_is_asked_for(shelf_world: World) -> None:
    rng = np.random.default_rng(3)
    agents = spaced_points(rng, 4, shelf_world, 0.3)
    tasks = spaced_points(rng, 4, shelf_world, 0.3)
    result = allocator.assign(agents, tasks, world=shelf_world, planner="grid")
    assert result.paths is not None
    assert allocator.assign(agents, tasks, world=shelf_world).paths is None
