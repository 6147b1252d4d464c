"""The incremental Hungarian dispatcher: every re-plan an optimum of its own cost matrix."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import linear_sum_assignment

import allocator.dispatch as dispatch
import sim
from allocator.dispatch import HungarianDispatcher


@pytest.fixture(autouse=True)
def _always_incremental(monkeypatch):
    """warehouse-20's matrices are small enough for scipy alone: test the warm path."""
    monkeypatch.setattr(dispatch, "_INCREMENTAL_MIN_SIZE", 0)


def _run(d: HungarianDispatcher, steps: int, num_envs: int = 2, **options) -> None:
    env = sim.make_env("warehouse-20", num_envs=num_envs, seed=1, arrivals=sim.Backlog(30),
                       **options)
    d.reset(env)
    for _ in range(steps):
        env.step(d.act(None))


def test_every_replan_is_optimal_and_the_travel_cache_is_exact(monkeypatch) -> None:
    d = HungarianDispatcher()
    checked = {"plans": 0, "warm": 0}
    match, travel = d._match, d._travel

    def checked_match(cost, positions, targets):
        rows, cols = match(cost, positions, targets)
        r, c = linear_sum_assignment(cost)
        want = float(cost[r, c].sum())
        assert abs(float(cost[rows, cols].sum()) - want) <= 1e-9 * max(1.0, abs(want))
        assert len(rows) == len(r) and len(np.unique(cols)) == len(cols)
        checked["plans"] += 1
        checked["warm"] += d.lap[d._floor].last_mode == "warm"
        return rows, cols

    def checked_travel(origin, targets, row_keys, col_keys):
        out = travel(origin, targets, row_keys, col_keys)
        np.testing.assert_array_equal(out, d.distances.distance(origin, targets))
        return out

    monkeypatch.setattr(d, "_match", checked_match)
    monkeypatch.setattr(d, "_travel", checked_travel)
    _run(d, 200, faults=sim.Breakdowns(rate=0.002, repair_steps=20))
    assert checked["plans"] > 50
    assert checked["warm"] > 0.5 * checked["plans"]
    assert set(d.lap) == {0, 1}  # one solver state per floor


def test_incremental_and_scipy_dispatchers_deliver_alike() -> None:
    # Tied optima may differ, so the runs may drift apart; the throughput stays close.
    delivered = {}
    for incremental in (True, False):
        env = sim.make_env("warehouse-20", num_envs=1, seed=2, arrivals=sim.Backlog(30))
        d = HungarianDispatcher(incremental=incremental)
        d.reset(env)
        total = 0
        for _ in range(300):
            env.step(d.act(None))
            total += int(env.events.delivered.sum())
        delivered[incremental] = total
    assert abs(delivered[True] - delivered[False]) <= max(3, 0.15 * delivered[False])


def test_incremental_must_be_a_bool() -> None:
    with pytest.raises(ValueError, match="incremental"):
        HungarianDispatcher(incremental=1)


def test_ahead_steps_limits_which_loaded_agvs_hold_a_next_order() -> None:
    env = sim.make_env("warehouse-20", num_envs=1, seed=0, arrivals=sim.Backlog(30))
    d = HungarianDispatcher(ahead_steps=0.0)
    d.reset(env)
    held = 0
    for _ in range(120):
        env.step(d.act(None))
        loaded = env.agent_status[0].numpy() == 2
        held += int((d.next_order[0][loaded] >= 0).sum())
    assert held == 0  # every loaded AGV is still on its way: none is planned ahead
    with pytest.raises(ValueError, match="ahead_steps"):
        HungarianDispatcher(ahead_steps=-1.0)
