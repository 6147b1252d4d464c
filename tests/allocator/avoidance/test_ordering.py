"""Plan untangling (allocator/avoidance/ordering.py) and the 6v6 scene it serves."""

from __future__ import annotations

import numpy as np
import pytest

import allocator
import sim
from allocator.avoidance.ordering import closed_gates, parking_conflicts, untangle
from sim.scenarios import Scenario, get_scenario

MODEL = dict(clearance=0.33, capture=0.1, step=0.15)

# 6v6, evaluation seed 0, episode 86 (coordinates rounded to 1e-3): the Hungarian plan sends
# AGV 4 from (0.649, 0.559) to task 0 at (-0.798, 0.463) between the tasks of AGVs 2 and 5,
# which both park before it gets there, 0.60 apart (an AGV needs 0.62); with AGV 1 parked on
# task 3 the way round is closed too, and AGV 4 stood still from step 10 to the limit.
AGENTS = np.array([[-0.084, -0.015], [0.67, 0.009], [0.391, 0.734], [0.22, -0.029],
                   [0.649, 0.559], [0.262, 0.304]])
TASKS = np.array([[-0.798, 0.463], [-0.34, 0.705], [-0.113, 0.099], [0.496, 0.014],
                  [-0.352, -0.846], [-0.734, -0.04]])


def _served(options: dict) -> sim.Metrics:
    scn = Scenario.given_scene(get_scenario("6v6"), AGENTS, TASKS)
    solver = allocator.make("hungarian", avoidance_options=options)
    return sim.evaluate(solver, scn, episodes=1, seed=0)


def test_the_boxed_in_6v6_scene_is_served_with_the_untangled_plan() -> None:
    before = _served({"untangle": False})
    assert before.claims_per_episode.tolist() == [5]  # the miss this module removes
    after = _served({})
    assert after.claims_per_episode.tolist() == [6]
    assert after.collisions == 0.0
    assert after.avg_time < 25


def test_the_conflict_and_the_closed_gate_of_that_plan_are_seen_and_removed() -> None:
    plan = allocator.make("hungarian").assign(AGENTS, TASKS).task_of_agent
    conflicts = parking_conflicts(AGENTS, TASKS, plan, **MODEL)
    assert np.argwhere(conflicts).tolist() == [[4, 2]]  # AGV 4 passes where AGV 2 parks
    gates = closed_gates(AGENTS, TASKS, plan, radius=0.15, bounds=(-1, -1, 1, 1), **MODEL)
    assert gates.tolist() == [0, 0, 0, 0, 1, 0]
    new = untangle(AGENTS, TASKS, plan, radius=0.15, bounds=(-1, -1, 1, 1), weight=0.2,
                   **MODEL)
    assert sorted(new.tolist()) == sorted(plan.tolist())  # the same tasks are served
    assert not parking_conflicts(AGENTS, TASKS, new, **MODEL).any()
    assert not closed_gates(AGENTS, TASKS, new, radius=0.15, bounds=(-1, -1, 1, 1),
                            **MODEL).any()

    def length(p: np.ndarray) -> float:
        return float(np.linalg.norm(TASKS[p] - AGENTS, axis=1).sum())

    # it paid at most weight * (score removed) = 0.2 * (1 conflict + 3 * 1 gate)
    assert 0 < length(new) - length(plan) <= 0.2 * 4 + 1e-9


def test_a_leg_past_a_task_reached_first_conflicts_and_one_reached_later_does_not() -> None:
    agents = np.array([[0.0, 0.0], [0.5, 0.6]])
    tasks = np.array([[1.0, 0.0], [0.5, 0.1]])  # AGV 1 parks at (0.5, 0.2) after 4 steps
    c = parking_conflicts(agents, tasks, np.array([0, 1]), **MODEL)
    assert c.tolist() == [[False, True], [False, False]]
    # the same leg, but AGV 1 starts far away: it parks long after AGV 0 has passed
    far = np.array([[0.0, 0.0], [0.5, 3.0]])
    c = parking_conflicts(far, tasks, np.array([0, 1]), **MODEL)
    assert not c.any()
    # an AGV without a task neither parks nor drives
    assert not parking_conflicts(agents, tasks, np.array([0, -1]), **MODEL).any()


def test_a_leg_between_two_parking_points_closer_than_two_clearances_crosses_a_gate() -> None:
    agents = np.array([[-1.0, 0.0], [0.0, 0.9], [0.0, -0.9]])
    for half, closed in ((0.3, 1), (0.4, 0)):  # parking points 0.6 / 0.8 apart
        tasks = np.array([[1.0, 0.0], [0.0, half - 0.1], [0.0, 0.1 - half]])
        g = closed_gates(agents, tasks, np.array([0, 1, 2]), radius=0.15, **MODEL)
        assert g.tolist() == [closed, 0, 0]
    # a parking point 0.45 from a wall (below r + clearance = 0.48) closes the way to the wall
    agents = np.array([[-1.0, 0.75], [0.0, 0.0]])
    tasks = np.array([[1.0, 0.75], [0.0, 0.6]])  # AGV 1 parks at (0, 0.5)
    g = closed_gates(agents, tasks, np.array([0, 1]), radius=0.15, bounds=(-2, -2, 2, 0.95),
                     **MODEL)
    assert g.tolist() == [1, 0]
    assert closed_gates(agents, tasks, np.array([0, 1]), radius=0.15, **MODEL).tolist() \
        == [0, 0]


def test_a_plan_without_conflicts_is_kept_even_where_a_shorter_one_exists() -> None:
    agents = np.array([[0.0, 0.0], [3.0, 0.0]])
    tasks = np.array([[3.0, 1.0], [0.0, 1.0]])  # crossed legs, far apart in time and space
    plan = np.array([0, 1])
    assert not parking_conflicts(agents, tasks, plan, **MODEL).any()
    assert untangle(agents, tasks, plan, **MODEL).tolist() == [0, 1]
    assert untangle(AGENTS, TASKS, np.arange(6), weight=0.0, **MODEL).tolist() == list(range(6))


@pytest.mark.parametrize("kwargs, match", [
    (dict(agents=np.zeros((2, 3))), "agents"),
    (dict(tasks=np.array([[np.nan, 0.0], [0.0, 0.0]])), "tasks"),
    (dict(task_of_agent=np.array([0, 0])), "two AGVs"),
    (dict(task_of_agent=np.array([0, 5])), "task indices"),
    (dict(task_of_agent=np.array([0.0, 1.0])), "integers"),
    (dict(clearance=0.0), "clearance"),
    (dict(weight=-1.0), "weight"),
    (dict(bounds=(1, 0, 0, 1), radius=0.15), "bounds"),
])
def test_bad_input_names_the_problem(kwargs: dict, match: str) -> None:
    args = dict(agents=np.zeros((2, 2)) + [[0, 0], [1, 1]], tasks=np.array([[0.5, 0], [2, 2]]),
                task_of_agent=np.array([0, 1]), **MODEL)
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        untangle(**args)


@pytest.mark.parametrize("value", [-0.1, float("nan")])
def test_bad_untangle_weight_option_names_the_option(value: float) -> None:
    from allocator.controller import AllocatorController

    with pytest.raises(ValueError, match="untangle_weight"):
        AllocatorController(allocator.make("hungarian"),
                            avoidance_options={"untangle_weight": value})


def test_the_batched_score_counts_what_the_single_plan_functions_count() -> None:
    from allocator.avoidance.ordering import _scores

    rng = np.random.default_rng(7)
    for _ in range(20):
        n = int(rng.integers(2, 9))
        agents = rng.uniform(-1, 1, (n, 2))
        tasks = rng.uniform(-1, 1, (n + 1, 2))
        plans = np.stack([rng.permutation(n + 1)[:n] for _ in range(4)])
        plans[1, 0] = -1
        total, involved = _scores(agents, tasks, plans, 0.33, 0.1, 0.15, 0.15,
                                  np.array([-1.0, -1.0, 1.0, 1.0]), 3.0, 2.0, 2.0)
        for k, plan in enumerate(plans):
            c = parking_conflicts(agents, tasks, plan, **MODEL)
            g = closed_gates(agents, tasks, plan, radius=0.15, bounds=(-1, -1, 1, 1), **MODEL)
            assert total[k] == c.sum() + 3 * g.sum()
            assert (involved[k] == (c.any(0) | c.any(1) | (g > 0))).all()
