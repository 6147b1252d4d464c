"""allocator.assign's plan options: availability, ready positions and steps, priorities,
deadlines, kept pairs; the same rules through every classical method; validation."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

import allocator

CLASSICAL = ["hungarian", "greedy", "fifo", "auction"]
AGENTS = np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]])
TASKS = np.array([[2.0, 0.5], [0.0, 0.5]])


@pytest.mark.parametrize("method", CLASSICAL)
def test_no_option_is_the_plain_call(method: str) -> None:
    rng = np.random.default_rng(0)
    agents, tasks = rng.uniform(0, 5, (7, 2)), rng.uniform(0, 5, (5, 2))
    plain = allocator.assign(agents, tasks, method=method)
    same = allocator.assign(agents, tasks, method=method, available=np.ones(7, dtype=bool),
                            ready_steps=np.zeros(7, dtype=int), deadlines=-np.ones(5, int))
    assert np.array_equal(plain.task_of_agent, same.task_of_agent)
    assert plain.cost == pytest.approx(same.cost)


@pytest.mark.parametrize("method", CLASSICAL)
def test_an_unavailable_agv_gets_nothing(method: str) -> None:
    r = allocator.assign(AGENTS, TASKS, method=method, available=[True, True, False])
    assert r.task_of_agent[2] == -1 and r.num_served == 2


@pytest.mark.parametrize("method", CLASSICAL)
def test_a_busy_agv_counts_from_where_and_when_it_is_free(method: str) -> None:
    agents = [[10.0, 0.0], [0.0, 0.0]]  # AGV 0 is far, but will be free next to the task
    tasks = [[9.0, 0.0]]
    ready = [[8.5, 0.0], [0.0, 0.0]]
    soon = allocator.assign(agents, tasks, method=method, ready_positions=ready,
                            ready_steps=[2, 0])
    assert soon.task_of_agent.tolist() == [0, -1]
    assert soon.cost == pytest.approx(0.5)  # travel from the ready position
    if method == "greedy":
        return  # AGVs in index order: AGV 0 takes its nearest task whatever the others
    late = allocator.assign(agents, tasks, method=method, ready_positions=ready,
                            ready_steps=[20, 0])  # 20 steps cost 20 units
    assert late.task_of_agent.tolist() == [-1, 0]


@pytest.mark.parametrize("method", CLASSICAL)
def test_priorities_first(method: str) -> None:
    r = allocator.assign([[0.0, 0.0]], [[1.0, 0.0], [5.0, 0.0]], method=method,
                         priorities=[0, 1])
    assert r.task_of_agent.tolist() == [1]


@pytest.mark.parametrize("method", CLASSICAL)
def test_a_deadline_that_can_be_met_is_served_first(method: str) -> None:
    agents, tasks = [[0.0, 0.0]], [[1.0, 0.0], [5.0, 0.0]]
    met = allocator.assign(agents, tasks, method=method, deadlines=[-1, 6])
    assert met.task_of_agent.tolist() == [1]
    hopeless = allocator.assign(agents, tasks, method=method, deadlines=[-1, 3])
    assert hopeless.task_of_agent.tolist() == [0]  # it misses anyway: the near one
    # A higher priority still comes before a deadline.
    ranked = allocator.assign(agents, tasks, method=method, deadlines=[-1, 6],
                              priorities=[1, 0])
    assert ranked.task_of_agent.tolist() == [0]


@pytest.mark.parametrize("method", CLASSICAL)
def test_kept_pairs_stay(method: str) -> None:
    r = allocator.assign(AGENTS, TASKS, method=method, keep=[[0, 0]])
    assert r.task_of_agent[0] == 0 and r.agent_of_task[1] in (1, 2)
    assert r.num_served == 2


def _brute_force(cost: np.ndarray, levels: np.ndarray) -> tuple[float, int, float]:
    """The best (levels served, pairs served, -cost) over every matching of finite pairs."""
    n, m = cost.shape
    best = (-np.inf, 0, 0.0)
    for k in range(min(n, m) + 1):
        for agents in itertools.combinations(range(n), k):
            for tasks in itertools.permutations(range(m), k):
                c = cost[list(agents), list(tasks)]
                if np.isfinite(c).all():
                    best = max(best, (levels[list(tasks)].sum(), k, -c.sum()))
    return best


@pytest.mark.parametrize("seed", range(6))
def test_hungarian_with_options_against_brute_force(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n, m = 4, 5
    agents, tasks = rng.uniform(0, 4, (n, 2)), rng.uniform(0, 4, (m, 2))
    ready = rng.uniform(0, 4, (n, 2))
    steps = rng.integers(3, 8, n)
    deadlines = np.where(rng.random(m) < 0.5, rng.integers(3, 12, m), -1)
    priorities = rng.integers(0, 2, m)
    available = rng.random(n) < 0.8
    kw = dict(available=available, ready_positions=ready, ready_steps=steps,
              deadlines=deadlines, priorities=priorities, now=3)
    r = allocator.assign(agents, tasks, method="hungarian", **kw)
    # The objective by hand.
    travel = np.linalg.norm(ready[:, None] - tasks[None], axis=-1)
    eta = (steps - 3)[:, None] + travel
    latest = np.where(deadlines >= 0, deadlines - 3.0, np.inf)
    cost = travel + (steps - 3)[:, None] + np.maximum(eta - latest[None], 0)
    meetable = np.isfinite(latest) & (eta[available].min(0) <= latest) if available.any() \
        else np.zeros(m, bool)
    levels = priorities * (m + 1) + meetable
    cost = np.where(available[:, None], cost, np.inf)
    rows = np.flatnonzero(r.task_of_agent >= 0)
    got = (levels[r.task_of_agent[rows]].sum(), len(rows),
           -cost[rows, r.task_of_agent[rows]].sum())
    want = _brute_force(cost, levels.astype(float))
    assert got[:2] == want[:2] and got[2] == pytest.approx(want[2])


def test_the_auction_counts_its_messages_and_splits_by_range() -> None:
    solver = allocator.make("auction", comm_range=1.5)
    agents = [[0.0, 0.0], [1.0, 0.0], [20.0, 0.0], [21.0, 0.0]]
    tasks = [[0.5, 1.0], [20.5, 1.0], [21.5, 1.0]]
    r = solver.assign(agents, tasks)
    out = solver.last_auction
    assert out.messages > 0 and solver.messages == out.messages
    assert len(np.unique(out.component)) == 2
    # Each group serves the tasks it heard; nobody crosses to the other group's tasks.
    assert r.agent_of_task[0] in (0, 1) and set(r.agent_of_task[1:]) == {2, 3}
    # With everyone in range it is the optimum on these costs.
    full = allocator.make("auction").assign(agents, tasks)
    assert full.cost == pytest.approx(allocator.assign(agents, tasks).cost, abs=1e-2)


@pytest.mark.parametrize(("kwargs", "match"), [
    (dict(available=[True, False]), r"available must have shape \(N,\) = \(3,\)"),
    (dict(available=[1, 0, 1]), "available must be an .* array of booleans"),
    (dict(priorities=[1, 0, 2]), r"priorities must have shape \(M,\)"),
    (dict(priorities=[1.5, 0]), "priorities must be non-negative integers"),
    (dict(priorities=[np.nan, 0]), "priorities"),
    (dict(deadlines=[1, 2, 3]), r"deadlines must have shape \(M,\)"),
    (dict(deadlines=[np.nan, 3]), "deadlines holds NaN"),
    (dict(deadlines=[2.5, 3]), "deadlines must hold integers"),
    (dict(deadlines=[-2, 3]), "deadlines must be steps >= 0 or -1"),
    (dict(ready_steps=[0, 1]), r"ready_steps must have shape \(N,\)"),
    (dict(ready_steps=[5, 5, 1], now=3), r"ready_steps\[2\] = 1 is in the past \(now = 3\)"),
    (dict(ready_steps=["a", 1, 2]), "ready_steps"),
    (dict(ready_positions=[[0.0, 0.0]]), r"ready_positions must have shape \(N, 2\)"),
    (dict(ready_positions=[[0, 0], [1, np.nan], [2, 2]]), "ready_positions contain NaN"),
    (dict(keep=[[0, 0]], available=[False, True, True]), "keep pair .* not available"),
    (dict(keep=[[5, 0]]), "keep pair .* out of range"),
    (dict(keep=[[0, 0], [1, 0]]), "keep names task 0 twice"),
    (dict(keep=[0, 0, 1]), r"keep must have shape \(K, 2\)"),
    (dict(now=-1), "now must be an integer step >= 0"),
    (dict(speed=0.0), "speed must be a positive number"),
])
@pytest.mark.parametrize("method", CLASSICAL)
def test_bad_plan_options_name_the_argument(method: str, kwargs: dict, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        allocator.assign(AGENTS, TASKS, method=method, **kwargs)


@pytest.mark.parametrize("bad", [0, -1.0, float("nan"), "far", True, None])
def test_comm_range_must_be_positive(bad: object) -> None:
    with pytest.raises(ValueError, match="comm_range must be a positive number"):
        allocator.make("auction", comm_range=bad)


def test_weights_only_for_hungarian() -> None:
    with pytest.raises(ValueError, match="weights is an option of 'hungarian' only"):
        allocator.assign(AGENTS, TASKS, method="greedy", weights=[1.0, 2.0])


def test_a_learned_allocator_says_it_does_not_take_plan_options() -> None:
    learned = next(name for name in allocator.ALLOCATORS
                   if not getattr(allocator.ALLOCATORS[name], "supports_plan_options", False))
    kw = dict(scenario="3v3") if "-" in learned else {}
    with pytest.raises(ValueError, match=rf"allocator '{learned}' does not support the plan "
                                         "options available"):
        allocator.assign(AGENTS, TASKS, method=learned, available=[True, True, True], **kw)
