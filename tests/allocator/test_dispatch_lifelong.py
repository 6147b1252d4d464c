"""Lifelong dispatchers (issue 14): next orders, deadlines, churn, breakdowns, the auction."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import allocator
import sim
from allocator.dispatch import (
    AuctionDispatcher,
    FifoDispatcher,
    HungarianDispatcher,
    MatchingDispatcher,
)
from allocator.greedy import greedy_matching
from sim.orders import ASSIGNED, OPEN

IDLE, LOADED = 0, 2


def _greedy() -> MatchingDispatcher:
    return MatchingDispatcher(greedy_matching)


DISPATCHERS = {"hungarian": HungarianDispatcher, "fifo": FifoDispatcher, "greedy": _greedy,
               "auction": AuctionDispatcher}


def test_a_loaded_agv_is_matched_to_its_next_order_and_gets_it_at_delivery() -> None:
    env = sim.make_env("warehouse-20", num_envs=1, seed=0, arrivals=sim.Backlog(30))
    d = HungarianDispatcher()
    d.reset(env)
    actions = d.act(env.observe())
    handed = held_total = 0
    for _ in range(400):
        held = d.next_order[0].copy()
        was_loaded = env.agent_status[0].numpy() == LOADED
        _, *_ = env.step(actions)
        # While held, a next order stays open in the env (nobody drives to it yet).
        for slot in held[held >= 0]:
            assert int(env.orders.status[0, slot]) in (OPEN, 3, 4) or \
                int(env.orders.agent[0, slot]) != -1  # open, or picked / given since
        delivered = was_loaded & (env.agent_status[0].numpy() != LOADED)
        actions = d.act(None)
        for i in np.flatnonzero(delivered & (held >= 0)):
            held_total += 1
            handed += int(env.fleet.order[0, i]) == held[i]
    assert held_total > 10
    assert handed >= 0.8 * held_total, (handed, held_total)


def test_loaded_agvs_are_planned_from_their_drop_off() -> None:
    env = sim.make_env("warehouse-20", num_envs=1, seed=0, arrivals=sim.Backlog(30))
    d = HungarianDispatcher()
    d.reset(env)
    for _ in range(60):
        env.step(d.act(None))
    loaded = env.agent_status[0].numpy() == LOADED
    assert loaded.any()
    assert (d.next_order[0][loaded] >= 0).any()
    assert (d.next_order[0][~loaded] == -1).all()  # the others are assigned in the env
    ahead = HungarianDispatcher(plan_ahead=False)
    ahead.reset(env)
    assert (ahead.next_order == -1).all()


def _two_orders(deadline_b: int) -> tuple[HungarianDispatcher, dict, int, int]:
    env = sim.make_env("warehouse-20", num_envs=1, seed=0)
    d = HungarianDispatcher()
    d.reset(env)
    w = env.world
    start = w.stations[:1]
    dist = d.distances.distance(start, w.pickups)[0]
    a = int(np.argmin(dist))
    gap = dist - dist[a]
    b = int(np.flatnonzero((gap > 1.0) & (gap < 4.0))[0])
    trip_b = d.distances.pairwise(w.pickups[[b]], start)[0] / d.speed
    eta_b = dist[b] / d.speed
    state = dict(pos=start, status=np.array([IDLE]), current=np.array([-1]),
                 order_status=np.array([OPEN, OPEN]), pickup=w.pickups[[a, b]],
                 order_id=np.array([0, 1]), priority=np.array([0, 0]))
    extra = dict(dropoff=np.concatenate([start, start]), release=np.array([0, 0]),
                 deadline=np.array([-1, deadline_b if deadline_b < 0 else
                                    int(eta_b + trip_b) + deadline_b]), now=0)
    return d, {**state, **extra}, 0, 1


def test_a_deadline_order_is_served_first_when_it_matters() -> None:
    d, kw, near, far = _two_orders(-1)
    assert d.plan(**kw).tolist() == [near]  # no deadline: the nearer order
    d, kw, near, far = _two_orders(10)  # due just after the far order could be delivered
    assert d.plan(**kw).tolist() == [far]
    d, kw, near, far = _two_orders(-10_000 + 1)  # hopeless already: the nearer one again
    kw["deadline"] = np.array([-1, 1])
    assert d.plan(**kw).tolist() == [near]


def test_plan_keeps_its_positional_signature() -> None:
    d, kw, near, _ = _two_orders(-1)
    args = [kw[k] for k in ("pos", "status", "current", "order_status", "pickup", "order_id",
                            "priority")]
    assert d.plan(*args).tolist() == [near]
    assert d.last_next.tolist() == [-1]


def test_plans_do_not_churn() -> None:
    m = sim.evaluate_lifelong(HungarianDispatcher(), "warehouse-20", steps=300, seed=0)
    assert m.delivered > 50
    assert m.reassignments <= 0.1 * m.delivered, (m.reassignments, m.delivered)


@pytest.mark.parametrize("name", list(DISPATCHERS))
def test_breakdowns_lose_nothing(name: str) -> None:
    m = sim.evaluate_lifelong(DISPATCHERS[name](), "warehouse-20", steps=200, seed=1,
                              faults=sim.Breakdowns(0.005, 20))
    assert m.lost == 0 and m.delivered > 10


@pytest.mark.parametrize("name", list(DISPATCHERS))
def test_orders_of_a_broken_agv_are_reassigned_in_the_next_step(name: str) -> None:
    # Light load, so that idle AGVs are there when a breakdown returns an order.
    env = sim.make_env("warehouse-20", num_envs=1, seed=3, arrivals=sim.Poisson(0.1),
                       faults=sim.Breakdowns(0.01, 30))
    d = DISPATCHERS[name]()
    d.reset(env)
    actions = d.act(env.observe())
    checked = 0
    for _ in range(300):
        env.step(actions)
        returned = env.events.returned[0].clone()
        free = bool((env.agent_status[0] == IDLE).any())
        actions = d.act(None)  # the next step's plan
        if returned.any() and free:
            checked += 1
            assert (env.orders.status[0][returned] == ASSIGNED).all()
            assert not (env.orders.agent[0][returned] == -1).any()
            if checked == 3:  # enough returned orders seen
                break
    assert checked >= 3


def test_the_auction_dispatcher_counts_messages_per_replan() -> None:
    solver = allocator.make("auction", comm_range=2.0)
    m = sim.evaluate_lifelong(solver, "warehouse-20", steps=80, seed=0)
    d = solver._dispatcher
    assert isinstance(d, AuctionDispatcher) and d.comm_range == 2.0
    assert m.lost == 0 and m.delivered > 0
    assert d.messages == sum(d.replan_messages) > 0
    assert len(d.replan_messages) >= 10


def test_the_auction_is_near_the_hungarian_plan_when_everyone_hears_everyone() -> None:
    kw = dict(steps=200, seed=0)
    hungarian = sim.evaluate_lifelong(HungarianDispatcher(), "warehouse-20", **kw)
    auction = sim.evaluate_lifelong(AuctionDispatcher(), "warehouse-20", **kw)
    assert auction.throughput >= 0.8 * hungarian.throughput


def test_bad_dispatcher_options() -> None:
    for bad in (0, -2.0, float("nan"), "x"):
        with pytest.raises(ValueError, match="comm_range"):
            AuctionDispatcher(comm_range=bad)
    with pytest.raises(ValueError, match="deadline_bonus"):
        HungarianDispatcher(deadline_bonus=-1.0)
    with pytest.raises(ValueError, match="deadline_horizon"):
        HungarianDispatcher(deadline_horizon=0)
    with pytest.raises(ValueError, match="plan_ahead"):
        HungarianDispatcher(plan_ahead="yes")
    with pytest.raises(ValueError, match="max_rounds"):
        AuctionDispatcher(max_rounds=0)


def test_the_fifo_and_auction_registry_entries_drive_lifelong_floors() -> None:
    for name in ("fifo", "auction"):
        m = sim.evaluate_lifelong(allocator.make(name), "warehouse-20", steps=100, seed=0)
        assert m.lost == 0 and m.delivered > 5
    assert torch.is_tensor(sim.make_env("warehouse-20").agent_pos)
