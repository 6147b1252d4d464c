"""Lifelong dispatchers (allocator/dispatch.py): re-planning on events, no order lost."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import sim
from allocator.dispatch import FifoDispatcher, HungarianDispatcher, WaypointDriver
from sim.controllers import NearestTaskController
from sim.orders import ASSIGNED, BROKEN, OPEN


@pytest.mark.parametrize("make", [FifoDispatcher, HungarianDispatcher])
def test_dispatchers_deliver_and_lose_nothing_with_breakdowns(make) -> None:
    m = sim.evaluate_lifelong(make(), "warehouse-20", steps=250, seed=0,
                              faults=sim.Breakdowns(0.003, 20))
    assert m.lost == 0 and m.delivered > 10


def test_hungarian_beats_the_nearest_task_controller() -> None:
    kw = dict(steps=300, seed=0, runs=2)
    nearest = sim.evaluate_lifelong(NearestTaskController(), "warehouse-20", **kw)
    hungarian = sim.evaluate_lifelong(HungarianDispatcher(), "warehouse-20", **kw)
    assert hungarian.throughput > 1.1 * nearest.throughput


def test_an_order_returned_by_a_breakdown_is_reassigned_in_the_next_step() -> None:
    env = sim.make_env("warehouse-20", num_envs=1, seed=0, faults=[(3, 0, 50)],
                       arrivals=sim.Backlog(10))
    d = HungarianDispatcher()
    d.reset(env)
    obs = env.observe()
    slot0 = int(env.fleet.order[0, 0])
    assert slot0 >= 0 and env.orders.status[0, slot0] == ASSIGNED  # AGV 0 was given one
    for _ in range(3):
        obs, *_ = env.step(d.act(obs))
    assert env.agent_status[0, 0] == BROKEN and env.events.returned[0, slot0]
    assert env.orders.status[0, slot0] == OPEN
    d.act(obs)  # the next step's plan
    assert env.orders.status[0, slot0] == ASSIGNED
    assert int(env.orders.agent[0, slot0]) != 0


def test_a_plan_does_not_churn_without_events() -> None:
    env = sim.make_env("warehouse-20", num_envs=2, seed=1)
    d = HungarianDispatcher()
    d.reset(env)
    before = env.fleet.order.clone()
    d._replan(np.ones(2, dtype=bool))
    assert torch.equal(env.fleet.order, before) and int(env.reassignments.sum()) == 0


def test_fifo_gives_the_oldest_order_first() -> None:
    env = sim.make_env("warehouse-20", num_envs=1, seed=0, arrivals=sim.Backlog(30))
    d = FifoDispatcher()
    d.reset(env)
    o = env.orders
    given = o.id[0][o.status[0] == ASSIGNED]
    waiting = o.id[0][o.status[0] == OPEN]
    assert len(given) == 20 and int(given.max()) < int(waiting.min())  # all 20 AGVs free


def test_bad_input() -> None:
    with pytest.raises(ValueError, match="lifelong env"):
        HungarianDispatcher().reset(sim.make_env("3v3"))
    with pytest.raises(ValueError, match="switching_cost"):
        HungarianDispatcher(switching_cost=-1.0)
    with pytest.raises(ValueError, match="gain"):
        WaypointDriver(gain=float("nan"))
    with pytest.raises(ValueError, match="reset"):
        FifoDispatcher().act(None)


@pytest.mark.parametrize("name", ["hungarian", "greedy"])
def test_the_registry_allocators_dispatch_lifelong_floors(name) -> None:
    import allocator

    m = sim.evaluate_lifelong(allocator.make(name), "warehouse-20", steps=150, seed=0)
    assert m.lost == 0 and m.delivered > 5
    # The same object still drives the paper's episodes afterwards.
    assert sim.evaluate(allocator.make(name), "3v3", episodes=4, seed=0).response_rate > 0.5


def test_a_learned_allocator_refuses_a_lifelong_floor() -> None:
    import allocator

    with pytest.raises(ValueError, match="cannot drive a lifelong floor"):
        sim.evaluate_lifelong(allocator.make("bicnet-ipf", scenario="3v3"), "warehouse-20",
                              steps=5)
