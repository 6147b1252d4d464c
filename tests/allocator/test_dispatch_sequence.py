"""Sequence-aware costs of the lifelong dispatchers (issue 14): the loaded trip and the empty
trip an order leaves behind, on a tiny built floor and against brute force."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

import allocator
import sim
from allocator.dispatch import (
    HUNGARIAN_MAX_WAIT,
    HUNGARIAN_OVERDUE_WEIGHT,
    HungarianDispatcher,
    MatchingDispatcher,
    next_empty,
)
from allocator.distances import FloorDistances

IDLE, OPEN = 0, 1
ROOM = """type octile
height 6
width 12
map
@@@@@@@@@@@@
@r........e@
@..........@
@..........@
@e........r@
@@@@@@@@@@@@
"""


@pytest.fixture(scope="module")
def room(tmp_path_factory) -> sim.World:
    path = Path(tmp_path_factory.mktemp("floor")) / "room.map"
    path.write_text(ROOM)
    return sim.load_floor(path, cell_size=1.0)  # an open 10 x 4 room, no shelves


def _bound(room: sim.World, **options) -> HungarianDispatcher:
    d = HungarianDispatcher(**options)
    d.reset(sim.make_env(room, num_envs=1, seed=0, num_agents=1))
    return d


def _one_agv_two_orders() -> dict:
    # X: the nearer pickup, but it ends at the far right, away from Y's pickup.
    # Y: one unit farther, and it ends right next to X's pickup.
    return dict(pos=np.array([[1.5, 2.5]]), status=np.array([IDLE]), current=np.array([-1]),
                order_status=np.array([OPEN, OPEN]),
                pickup=np.array([[3.5, 2.5], [4.5, 2.5]]), order_id=np.array([0, 1]),
                priority=np.array([0, 0]), dropoff=np.array([[10.5, 4.5], [2.5, 1.5]]),
                release=np.array([0, 0]), deadline=np.array([-1, -1]), now=0)


def test_next_empty_is_the_mean_travel_to_the_nearest_other_pickups() -> None:
    scenario = sim.get_scenario("warehouse-20")
    fd = FloorDistances(scenario.world)
    rng = np.random.default_rng(3)
    pickup = scenario.pickups[rng.integers(0, len(scenario.pickups), 40)]
    dropoff = scenario.stations[rng.integers(0, len(scenario.stations), 40)]
    table = fd.distance(dropoff, pickup)
    np.fill_diagonal(table, np.inf)  # an order's own pickup is not its next one
    ranked = np.sort(table, axis=1)
    for k in (1, 3, 39, 100):
        want = ranked[:, :min(k, 39)].mean(axis=1)
        np.testing.assert_allclose(next_empty(fd, dropoff, pickup, k), want, rtol=1e-12)
    assert next_empty(fd, dropoff[:1], pickup[:1]).tolist() == [0.0]  # a lone order


def test_the_plain_cost_takes_the_nearer_pickup(room) -> None:
    d = _bound(room, trip_weight=0.0, next_weight=0.0)
    assert d.plan(**_one_agv_two_orders()).tolist() == [0]


def test_next_weight_takes_the_order_that_ends_near_the_other_pickups(room) -> None:
    d = _bound(room, trip_weight=0.0, next_weight=1.0)
    state = _one_agv_two_orders()
    assert d.plan(**state).tolist() == [1]
    fd = d.distances
    travel = fd.distance(state["pos"], state["pickup"])[0]
    after = fd.pairwise(state["dropoff"], state["pickup"][::-1])
    np.testing.assert_allclose(d.last_cost[0], travel + d.switching_cost + after)


def test_trip_weight_takes_the_shorter_loaded_trip(room) -> None:
    d = _bound(room, trip_weight=1.0, next_weight=0.0)
    state = _one_agv_two_orders()
    assert d.plan(**state).tolist() == [1]
    trip = d.distances.pairwise(state["pickup"], state["dropoff"])
    travel = d.distances.distance(state["pos"], state["pickup"])[0]
    np.testing.assert_allclose(d.last_cost[0], travel + d.switching_cost + trip)


def test_bad_sequence_options() -> None:
    with pytest.raises(ValueError, match="next_weight"):
        HungarianDispatcher(next_weight=-1.0)
    with pytest.raises(ValueError, match="next_k"):
        HungarianDispatcher(next_k=0)
    with pytest.raises(ValueError, match="next_k"):
        HungarianDispatcher(next_k=True)
    for bad in (0, -5.0, float("nan"), "150", None, True):
        with pytest.raises(ValueError, match="max_wait"):
            HungarianDispatcher(max_wait=bad)
    for bad in (-1.0, float("nan"), "1", None, True):
        with pytest.raises(ValueError, match="overdue_weight"):
            HungarianDispatcher(overdue_weight=bad)
    assert HungarianDispatcher(max_wait=1e18).max_wait == 1e18  # huge: never overdue


def test_max_wait_is_on_by_default_for_hungarian_only() -> None:
    assert HungarianDispatcher().max_wait == HUNGARIAN_MAX_WAIT == 150.0
    assert HungarianDispatcher().overdue_weight == HUNGARIAN_OVERDUE_WEIGHT == 1.0
    assert HungarianDispatcher(max_wait=math.inf).max_wait == math.inf  # the plain plan
    assert allocator.make("hungarian").lifelong_dispatcher().max_wait == HUNGARIAN_MAX_WAIT
    assert MatchingDispatcher().max_wait == math.inf  # greedy's and the auction's: unchanged
    assert MatchingDispatcher().overdue_weight == 0.0


def test_overdue_weight_serves_the_older_overdue_order_first(room) -> None:
    # Both overdue (max_wait 150, now 200): X (nearer, 2 units) by 45 steps, Y (3 units) by 50.
    state = {**_one_agv_two_orders(), "release": np.array([5, 0]), "now": 200}
    d = _bound(room, overdue_weight=0.0)
    assert d.plan(**state).tolist() == [0]  # the same credit: the nearer one
    d = _bound(room)  # the default weight 1.0: Y's 5 steps more are worth 5 units
    assert d.plan(**state).tolist() == [1]
    travel = d.distances.distance(state["pos"], state["pickup"])[0]
    np.testing.assert_allclose(d.last_cost[0],
                               travel + d.switching_cost - 1e3 - np.array([45.0, 50.0]))


def test_max_wait_serves_an_overdue_order_first(room) -> None:
    # Y (farther) was released at step 0, X at step 90; now is step 100.
    state = {**_one_agv_two_orders(), "release": np.array([90, 0]), "now": 100}
    assert _bound(room, max_wait=math.inf).plan(**state).tolist() == [0]  # never overdue
    assert _bound(room).plan(**state).tolist() == [0]  # the default 150: Y waited 100 < 150
    later = {**state, "release": np.array([140, 0]), "now": 150}
    assert _bound(room).plan(**later).tolist() == [1]  # Y waited 150: overdue
    assert _bound(room, max_wait=200).plan(**state).tolist() == [0]  # Y waited 100 < 200
    d = _bound(room, max_wait=100)                                   # Y waited 100 >= 100
    assert d.plan(**state).tolist() == [1]
    travel = d.distances.distance(state["pos"], state["pickup"])[0]
    np.testing.assert_allclose(d.last_cost[0], travel + d.switching_cost - np.array([0, 1e3]))


def test_an_order_is_never_starved_under_the_default() -> None:
    """Warehouse-20 at saturation: with the default max_wait every order still open at the
    end has waited less than max_wait plus the time to drive to it and pick it up (600
    steps without it)."""
    steps, max_wait = 600, HUNGARIAN_MAX_WAIT
    env = sim.make_env("warehouse-20", num_envs=1, seed=0, arrivals=sim.Backlog(30))
    d = HungarianDispatcher()
    d.reset(env)
    for _ in range(steps):
        env.step(d.act(env))
    o = env.orders
    waiting = (o.status[0] == OPEN) | (o.status[0] == 2)  # open or assigned
    age = steps - o.release[0][waiting]
    assert age.numel() and int(age.max()) < max_wait + 120
