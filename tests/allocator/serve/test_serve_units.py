"""The service's pieces without a server: trip reachability, the store, the path cache."""

from __future__ import annotations

import numpy as np
import pytest

import sim
from allocator.distances import FloorDistances
from allocator.serve.cli import make_dispatcher
from allocator.serve.fleet import Conflict, Fleet, Invalid, PathPlanner, Reachability
from allocator.serve.store import Store


def _split_world() -> sim.World:
    # A wall across the whole floor at x = 2: the left and right halves never meet.
    return sim.World(bounds=(0.0, 0.0, 4.0, 2.0), obstacles=np.array([[1.9, 0.0, 2.1, 2.0]]))


def test_reachability_sees_a_wall_across_the_floor() -> None:
    r = Reachability(_split_world(), 0.075)
    assert r.connected((0.5, 0.5), (1.5, 1.5))
    assert r.connected((2.5, 0.5), (3.5, 1.5))
    assert not r.connected((0.5, 0.5), (3.5, 1.5))


def test_an_unreachable_dropoff_is_refused_naming_it(tmp_path) -> None:
    w = _split_world()
    fleet = Fleet(w, make_dispatcher("hungarian"), Store(tmp_path / "s.db"),
                  FloorDistances(w))
    with pytest.raises(Invalid) as err:
        fleet.add_orders([{"id": "x", "pickup": [0.5, 0.5], "dropoff": [3.5, 1.0]}])
    assert err.value.loc == ("body", "dropoff")
    ok = fleet.add_orders([{"id": "y", "pickup": [0.5, 0.5], "dropoff": [1.5, 1.0]}])
    assert ok[0][1] is True
    with pytest.raises(Conflict):
        fleet.add_orders([{"id": "y", "pickup": [0.5, 0.6], "dropoff": [1.5, 1.0]}])
    # A restart on the same file sees the order, once.
    again = Fleet(w, make_dispatcher("fifo"), Store(tmp_path / "s.db"), FloorDistances(w))
    assert list(again.orders) == ["y"] and again.accepted == 1


def test_store_refuses_another_schema(tmp_path) -> None:
    s = Store(tmp_path / "a.db")
    s.db.execute("UPDATE meta SET value='99' WHERE key='schema'")
    s.close()
    with pytest.raises(ValueError, match="schema version 99"):
        Store(tmp_path / "a.db")
    assert Store(tmp_path / "b.db").journal_mode == "wal"


def test_paths_between_fixed_points_are_cached() -> None:
    w = sim.warehouse_floor(20)
    fd = FloorDistances(w)
    pp = PathPlanner(fd, budget=10.0)
    start = w.stations[:3] + 0.05  # within the snap distance of the stations
    goal = w.pickups[[5, 20, 40]]
    first = pp.paths(start, goal, [None] * 3)
    n = pp.computed
    second = pp.paths(start, goal, [None] * 3)
    assert pp.computed == n  # no new search
    for p, s, g in zip(second, start, goal, strict=True):
        assert np.allclose(p[0], s) and np.allclose(p[-1], g)
    assert first == second
    # No time left: an AGV keeps its previous path for the same leg.
    pp.budget = -1.0
    out = pp.paths(np.array([[3.0, 0.6]]), w.pickups[[7]], [[[3.0, 0.6], [1.0, 1.0]]])
    assert out == [[[3.0, 0.6], [1.0, 1.0]]]


def test_an_order_due_soon_goes_first(tmp_path) -> None:
    # One idle AGV, two orders: the nearer one has no deadline, the farther one is due in
    # 3 s (at the dispatcher's 1 unit/s the AGV reaches it in about 1.5 s). The plan serves
    # the order due soon; without its deadline it would serve the nearer one.
    w = sim.World(bounds=(0.0, 0.0, 4.0, 2.0))
    clock = [1000.0]
    for due, want in ((3.0, "late-soon"), (None, "near")):
        fleet = Fleet(w, make_dispatcher("hungarian"), Store(tmp_path / f"d{due}.db"),
                      FloorDistances(w), clock=lambda: clock[0])
        fleet.put_agent("agv", (0.5, 1.0), "idle")
        fleet.add_orders([{"id": "near", "pickup": [1.0, 1.0], "dropoff": [0.5, 0.5]},
                          {"id": "late-soon", "pickup": [2.0, 1.0], "dropoff": [0.5, 0.5],
                           "deadline": None if due is None else clock[0] + due}])
        snap = fleet.snapshot()
        plan, _ = fleet.compute_plan(snap)
        assert snap.order_ids[int(plan[0])] == want, due
