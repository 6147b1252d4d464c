"""Lifelong operation: the order rules, arrivals, breakdowns, events, dispatch, observations,
rewards and evaluation (``DESIGN.md``, "Lifelong operation")."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import sim
from sim.controllers import NearestTaskController
from sim.lifelong import LifelongEnv, LifelongScenario
from sim.orders import (
    ASSIGNED,
    BROKEN,
    CARRYING,
    DELIVERED,
    FREE,
    IDLE,
    LOADED,
    OPEN,
    TO_PICKUP,
    Backlog,
    Breakdowns,
    Poisson,
    read_trace,
)
from sim.world import World

SHELVES = np.array([[-1.5, 0.4, -0.5, 0.8], [0.5, 0.4, 1.5, 0.8]])


def floor(pickups=((-1.0, 0.2), (1.0, 0.2)), stations=((-1.7, -0.5), (1.7, -0.5))) -> World:
    """A small floor: two shelves, pickups under them, a station at each side, a depot."""
    return World(bounds=(-2.0, -1.5, 2.0, 1.5), obstacles=SHELVES, pickups=np.array(pickups),
                 stations=np.array(stations), depot=np.array([[-1.0, -1.5, 1.0, -1.0]]))


def scenario(n: int = 2, **options) -> LifelongScenario:
    options.setdefault("arrivals", Backlog(1))
    return LifelongScenario(name="test", world=floor(((0.0, 0.2),), ((1.7, -0.5),)),
                            num_agents=n, **options)


def still(env: LifelongEnv) -> torch.Tensor:
    return torch.zeros(env.num_envs, env.num_agents, 2)


def run(env: LifelongEnv, controller, steps: int) -> list[dict]:
    """Step a controller; check the order balance every step; return the event counts."""
    controller.reset(env)
    obs = env.observe()
    log = []
    for _ in range(steps):
        obs, _, _, _ = env.step(controller.act(obs))
        assert torch.equal(env.order_balance(), torch.zeros_like(env.released))
        log.append({k: v.clone() for k, v in env.events.counts().items()})
    return log


# ---------------------------------------------------------------------- the order life
def test_an_order_is_picked_up_and_delivered() -> None:
    env = LifelongEnv(scenario(1), num_envs=1, seed=0)
    o = env.orders
    assert env.events.arrived.sum() == 1 and int(o.count(OPEN)[0]) == 1
    slot = int(env.events.arrived[0].nonzero()[0])
    assert torch.allclose(o.pickup[0, slot], torch.tensor([0.0, 0.2]))
    assert torch.allclose(o.dropoff[0, slot], torch.tensor([1.7, -0.5]))
    ctl = NearestTaskController()
    ctl.reset(env)
    obs = env.observe()
    seen = []
    for _ in range(200):
        obs, _, _, _ = env.step(ctl.act(obs))
        if env.events.picked_up[0, slot]:
            seen.append("picked")
            assert env.agent_status[0, 0] == CARRYING
            assert env.orders.status[0, slot] == LOADED and env.orders.agent[0, slot] == 0
            # The backlog refills at once: the next order is open.
            assert int(env.orders.count(OPEN)[0]) == 1
            # A loaded AGV's target is its drop-off.
            target, has = env.targets()
            assert has[0, 0] and torch.allclose(target[0, 0], torch.tensor([1.7, -0.5]))
            lay = env.obs_layout
            assert torch.allclose(obs[0, 0, lay.target_rel], target[0, 0] - env.agent_pos[0, 0])
            assert obs[0, 0, lay.status][CARRYING] == 1
        if env.events.delivered[0, slot]:
            seen.append("delivered")
            assert env.orders.status[0, slot] == DELIVERED
            assert env.orders.finished[0, slot] == env.steps[0]
            assert env.agent_status[0, 0] == IDLE
            break
    assert seen == ["picked", "delivered"]
    assert int(env.delivered[0]) == 1
    env.step(still(env))
    assert env.orders.status[0, slot] in (FREE, OPEN)  # freed (and maybe reused)


def test_service_steps_hold_the_agv_still() -> None:
    sc = scenario(1, service_steps=2)
    env = LifelongEnv(sc, num_envs=1, seed=0)
    env.set_state(np.array([[[0.0, 0.25]]]))
    push = torch.ones(1, 1, 2)
    env.step(push)
    assert env.events.picked_up.any() and env.fleet.service_left[0, 0] == 2
    held = env.agent_pos.clone()
    env.step(push)
    env.step(push)
    assert torch.equal(env.agent_pos, held)
    assert torch.equal(env.agent_vel, torch.zeros(1, 1, 2))
    env.step(push)  # moving again (MPE: the position follows the velocity a step later)
    assert bool((env.agent_vel != 0).all())


def test_reassignment_until_pickup_and_breakdown_returns_the_order() -> None:
    env = LifelongEnv(scenario(2, faults=[(2, 0, 3)]), num_envs=1, seed=0)
    env.set_state(np.array([[[-0.8, -1.2], [0.8, -1.2]]]))
    slot = int(env.orders.status[0].eq(OPEN).nonzero()[0])
    plan = torch.full((1, 2), -1)
    plan[0, 0] = slot
    env.assign(plan)
    assert env.orders.status[0, slot] == ASSIGNED and env.agent_status[0, 0] == TO_PICKUP
    env.step(still(env))
    env.assign(plan.flip(1))  # to AGV 1
    assert env.orders.agent[0, slot] == 1 and int(env.reassignments[0]) == 1
    env.assign(plan)  # back to AGV 0
    assert int(env.reassignments[0]) == 2
    # An idle AGV does not take an order given to another.
    assert env.agent_status[0, 1] == IDLE
    env.step(still(env))  # step 2: AGV 0 breaks down
    assert env.events.breakdown[0, 0] and env.events.returned[0, slot]
    assert env.orders.status[0, slot] == OPEN and env.orders.agent[0, slot] == -1
    assert env.agent_status[0, 0] == BROKEN
    with pytest.raises(ValueError, match="AGV 0 is broken"):
        env.assign(plan)
    pos = env.agent_pos.clone()
    for step in (3, 4):
        env.step(torch.ones(1, 2, 2))
        assert torch.equal(env.agent_pos[0, 0], pos[0, 0]), step
        assert env.agent_status[0, 0] == BROKEN
    env.step(still(env))
    assert env.events.repaired[0, 0] and env.agent_status[0, 0] == IDLE


def test_a_loaded_order_waits_with_its_broken_agv() -> None:
    env = LifelongEnv(scenario(1, faults=[(2, 0, 2)]), num_envs=1, seed=0)
    env.set_state(np.array([[[0.0, 0.25]]]))
    env.step(still(env))
    slot = int(env.fleet.order[0, 0])
    assert env.orders.status[0, slot] == LOADED
    env.step(still(env))
    assert env.agent_status[0, 0] == BROKEN and env.orders.status[0, slot] == LOADED
    assert not env.events.returned.any()
    env.step(still(env))
    env.step(still(env))
    assert env.events.repaired[0, 0] and env.agent_status[0, 0] == CARRYING


def test_assign_refuses_bad_plans() -> None:
    env = LifelongEnv(scenario(2, arrivals=Backlog(3)), num_envs=2, seed=0)
    Q = env.orders.capacity
    with pytest.raises(ValueError, match="shape"):
        env.assign(torch.full((2, 3), -1))
    with pytest.raises(ValueError, match="outside"):
        env.assign(torch.full((2, 2), Q))
    with pytest.raises(ValueError, match="several AGVs"):
        env.assign(torch.zeros(2, 2, dtype=torch.long))
    free = int(env.orders.status[0].eq(FREE).nonzero()[0])
    with pytest.raises(ValueError, match="free order"):
        env.assign(torch.tensor([[free, -1], [-1, -1]]))
    with pytest.raises(ValueError, match="integer"):
        env.assign(torch.full((2, 2), 0.5))
    with pytest.raises(ValueError, match="real numbers"):
        env.assign("all")


def test_loaded_agv_keeps_its_order_in_a_plan() -> None:
    env = LifelongEnv(scenario(2, arrivals=Backlog(2)), num_envs=1, seed=0)
    env.set_state(np.array([[[0.0, 0.25], [0.8, -1.2]]]))
    env.step(still(env))
    mine = int(env.fleet.order[0, 0])
    other = int(env.orders.status[0].eq(OPEN).nonzero()[0])
    with pytest.raises(ValueError, match="AGV 0 is loaded"):
        env.assign(torch.tensor([[other, -1]]))
    env.assign(torch.tensor([[-1, other]]))  # -1 leaves the loaded AGV as it is
    assert int(env.fleet.order[0, 0]) == mine and env.orders.status[0, mine] == LOADED


# ---------------------------------------------------------------------- arrivals
def test_poisson_arrivals_have_the_rate() -> None:
    env = LifelongEnv(scenario(1, arrivals=Poisson(0.3)), num_envs=8, seed=3)
    for _ in range(500):
        env.step(still(env))
    expected = 0.3 * 8 * 501
    assert abs(int(env.released.sum()) - expected) < 5 * math.sqrt(expected)
    assert env.orders.capacity > 200  # the table grew, nothing was dropped
    assert torch.equal(env.order_balance(), torch.zeros(8, dtype=torch.long))


def test_backlog_keeps_k_open() -> None:
    env = LifelongEnv(LifelongScenario(name="b", world=floor(), num_agents=3,
                                       arrivals=Backlog(4)), num_envs=2, seed=0)
    ctl = NearestTaskController()
    ctl.reset(env)
    obs = env.observe()
    for _ in range(150):
        obs, *_ = env.step(ctl.act(obs))
        assert torch.equal(env.orders.count(OPEN) + env.orders.count(ASSIGNED),
                           torch.full((2,), 4))
    assert int(env.delivered.sum()) > 0


def test_an_empty_backlog_releases_nothing() -> None:
    # Backlog(0): a floor whose orders are kept elsewhere (the service's simulator).
    env = LifelongEnv(LifelongScenario(name="b", world=floor(), num_agents=3,
                                       arrivals=Backlog(0)), num_envs=2, seed=0)
    ctl = NearestTaskController()
    ctl.reset(env)
    obs = env.observe()
    for _ in range(20):
        obs, reward, _, info = env.step(ctl.act(obs))
        assert not bool(info["events"].arrived.any())
        assert torch.isfinite(reward).all()
    assert int(env.released.sum()) == 0 and int(env.delivered.sum()) == 0
    assert bool((env.agent_status == 0).all())  # every AGV idle
    with pytest.raises(ValueError, match="backlog open must be an integer >= 0, got -1"):
        Backlog(-1)


def test_a_backlog_larger_than_the_order_table_grows_it_at_reset() -> None:
    # The table starts with max(2 N, 8) slots; a backlog beyond it used to break the reset.
    env = LifelongEnv(LifelongScenario(name="b", world=floor(), num_agents=3,
                                       arrivals=Backlog(20)), num_envs=2, seed=0)
    assert env.orders.capacity >= 20
    assert torch.equal(env.orders.count(OPEN), torch.full((2,), 20))
    assert env.events.arrived.shape == (2, env.orders.capacity)
    env.reset(env_ids=[1])
    env.step(still(env))
    assert torch.equal(env.order_balance(), torch.zeros(2, dtype=torch.long))


def test_a_trace_is_replayed_as_given(tmp_path) -> None:
    path = tmp_path / "day.csv"
    path.write_text("release,pickup_x,pickup_y,dropoff_x,dropoff_y,priority,deadline\n"
                    "0,-1.0,0.2,-1.7,-0.5,0,\n"
                    "0,1.0,0.2,1.7,-0.5,2,40\n"
                    "3,0.0,-0.4,1.7,-0.5,,\n")
    trace = read_trace(path, floor())
    sc = LifelongScenario(name="t", world=floor(), num_agents=1, arrivals=trace)
    env = LifelongEnv(sc, num_envs=2, seed=0)
    o = env.orders
    assert env.events.arrived.sum(1).tolist() == [2, 2]
    got = sorted(o.id[0][env.events.arrived[0]].tolist())
    assert got == [0, 1]
    row1 = int((o.id[0] == 1).nonzero()[0])
    assert o.priority[0, row1] == 2 and o.deadline[0, row1] == 40
    assert torch.allclose(o.pickup[0, row1], torch.tensor([1.0, 0.2]))
    for step in (1, 2, 3):
        env.step(still(env))
        assert env.events.arrived.sum().item() == (2 if step == 3 else 0)
    assert env.released.tolist() == [3, 3]
    for _ in range(20):
        env.step(still(env))
    assert env.released.tolist() == [3, 3]


@pytest.mark.parametrize(("row", "match"), [
    ("0,9.0,0.2,-1.7,-0.5,0,", "row 0: pickup .* outside"),
    ("0,-1.0,0.6,-1.7,-0.5,0,", "row 0: pickup .* shelf"),
    ("0,-1.0,0.2,-1.7,nan,0,", "row 0: dropoff_y must be a finite number"),
    ("0,-1.0,0.2,-1.7,-0.5,x,", "row 0: priority must be an integer"),
    ("0,-1.0,0.2,-1.7", "row 0: 4 fields"),
])
def test_bad_trace_rows_are_named(tmp_path, row, match) -> None:
    path = tmp_path / "bad.csv"
    path.write_text("release,pickup_x,pickup_y,dropoff_x,dropoff_y,priority,deadline\n"
                    + row + "\n")
    with pytest.raises(ValueError, match=match):
        read_trace(path, floor())


def test_trace_release_going_backwards_is_refused(tmp_path) -> None:
    path = tmp_path / "back.csv"
    path.write_text("release,pickup_x,pickup_y,dropoff_x,dropoff_y,priority,deadline\n"
                    "5,-1.0,0.2,-1.7,-0.5,0,\n3,-1.0,0.2,-1.7,-0.5,0,\n")
    with pytest.raises(ValueError, match="row 1: release 3 goes backwards"):
        read_trace(path)


def test_trace_header_is_checked(tmp_path) -> None:
    path = tmp_path / "h.csv"
    path.write_text("t,x,y\n0,1,2\n")
    with pytest.raises(ValueError, match="header must be"):
        read_trace(path)


def test_trace_point_cut_off_by_shelves_is_refused(tmp_path) -> None:
    # A pocket closed on all sides by shelves.
    shelves = np.array([[-0.6, -0.6, 0.6, -0.4], [-0.6, 0.4, 0.6, 0.6], [-0.6, -0.6, -0.4, 0.6],
                        [0.4, -0.6, 0.6, 0.6]])
    world = World(bounds=(-2, -1.5, 2, 1.5), obstacles=shelves)
    path = tmp_path / "pocket.csv"
    path.write_text("release,pickup_x,pickup_y,dropoff_x,dropoff_y,priority,deadline\n"
                    "0,-1.5,1.0,1.5,1.0,0,\n1,0.0,0.0,1.5,1.0,0,\n")
    with pytest.raises(ValueError, match="row 1: pickup .* cannot be reached"):
        read_trace(path, world)


@pytest.mark.parametrize("rate", [0, -1.0, float("nan"), float("inf"), "fast", True])
def test_bad_arrival_rates(rate) -> None:
    with pytest.raises(ValueError, match="arrival rate"):
        Poisson(rate)


def test_bad_fault_schedules_name_the_row() -> None:
    with pytest.raises(ValueError, match="fault row 1: AGV 5 does not exist"):
        scenario(2, faults=[(3, 0, 5), (4, 5, 2)])
    with pytest.raises(ValueError, match="fault row 0: step must be >= 1"):
        scenario(2, faults=[(0, 0, 5)])
    with pytest.raises(ValueError, match="fault row 0: expected three integers"):
        scenario(2, faults=[(1, 0)])
    with pytest.raises(ValueError, match="fault rate"):
        Breakdowns(1.5, 10)
    with pytest.raises(ValueError, match="repair_steps"):
        Breakdowns(0.01, 0)


def test_generated_orders_need_pickups_and_stations() -> None:
    bare = World(bounds=(-2, -1.5, 2, 1.5))
    with pytest.raises(ValueError, match="pickup points and stations"):
        LifelongScenario(name="x", world=bare, num_agents=2)
    with pytest.raises(ValueError, match="num_agents"):
        sim.make_env(floor())


# ---------------------------------------------------------------------- invariants
class GreedyDispatcher:
    """A test dispatcher: every step, each AGV without an order is given the nearest open
    one (one by one), then the AGVs drive at their targets."""

    def reset(self, env: LifelongEnv) -> None:
        self.env = env
        self.drive = NearestTaskController()
        self.drive.reset(env)

    def act(self, obs: torch.Tensor) -> torch.Tensor:
        env = self.env
        plan = env.fleet.order.clone()
        plan[env.agent_status == CARRYING] = -1
        for b in range(env.num_envs):
            open_ = (env.orders.status[b] == OPEN).nonzero().flatten().tolist()
            for a in range(env.num_agents):
                if plan[b, a] >= 0 or env.agent_status[b, a] != IDLE or not open_:
                    continue
                d = (env.orders.pickup[b, open_] - env.agent_pos[b, a]).norm(dim=1)
                plan[b, a] = open_.pop(int(d.argmin()))
        env.assign(plan)
        return self.drive.act(env.observe())


def test_no_order_is_lost_with_breakdowns() -> None:
    env = sim.make_env("warehouse-20", num_envs=3, seed=1,
                       faults=Breakdowns(0.01, 20), arrivals=Poisson(0.4))
    at_reset = env.events.arrived.sum(1)
    log = run(env, GreedyDispatcher(), 300)  # checks the balance at every step
    total = {k: sum(e[k] for e in log) for k in log[0]}
    assert int(total["breakdown"].sum()) > 10 and int(total["delivered"].sum()) > 5
    assert int(total["returned"].sum()) > 0
    assert torch.equal(env.released, at_reset + total["arrived"])
    assert torch.equal(env.delivered, total["delivered"])


@pytest.mark.slow
def test_ten_thousand_steps_of_warehouse_50_with_breakdowns_lose_nothing() -> None:
    env = sim.make_env("warehouse-50", num_envs=1, seed=0, max_steps=10_000,
                       faults=Breakdowns(0.002, 40))
    log = run(env, NearestTaskController(), 10_000)
    assert sum(int(e["breakdown"].sum()) for e in log) > 100
    assert int(env.delivered[0]) > 100
    assert bool(env.done[0])


def test_orders_and_breakdowns_do_not_depend_on_the_controller() -> None:
    def history(controller) -> tuple[list, list]:
        env = sim.make_env("warehouse-20", num_envs=2, seed=4, arrivals=Poisson(0.5),
                           faults=Breakdowns(0.01, 5))
        orders, faults = [], []
        obs = env.observe()
        for _ in range(80):
            ev = env.events
            o = env.orders
            for b in range(2):
                for q in ev.arrived[b].nonzero().flatten().tolist():
                    orders.append((b, int(o.id[b, q]), int(o.release[b, q]),
                                   *o.pickup[b, q].tolist(), *o.dropoff[b, q].tolist()))
            obs, *_ = env.step(controller(obs))
            faults.append(env.events.breakdown.clone())
        return sorted(orders), faults

    a = history(NearestTaskController().act)
    b = history(lambda obs: torch.zeros(*obs.shape[:2], 2))
    assert a[0] == b[0] and len(a[0]) > 50
    assert all(torch.equal(x, y) for x, y in zip(a[1], b[1], strict=True))


def test_evaluation_does_not_depend_on_the_batching() -> None:
    kw = dict(steps=120, seed=2, runs=3, faults=Breakdowns(0.005, 10))
    one = sim.evaluate_lifelong(NearestTaskController(), "warehouse-20", batch_size=1, **kw)
    all3 = sim.evaluate_lifelong(NearestTaskController(), "warehouse-20", batch_size=3, **kw)
    assert one.summary() == all3.summary()
    np.testing.assert_array_equal(one.throughput_series, all3.throughput_series)


def test_evaluate_lifelong_metrics() -> None:
    m = sim.evaluate_lifelong(NearestTaskController(), "warehouse-20", steps=300, seed=0,
                              runs=2, arrival_rate=0.3, window=50)
    assert m.lost == 0 and m.released == m.delivered + m.open_at_end
    assert 0 < m.throughput <= m.throughput_bound
    assert m.throughput_bound <= 1000 * 0.3 + 1e-9
    assert m.wait_mean <= m.lead_mean and m.wait_p95 >= m.wait_mean
    assert 0 < m.utilization <= 1
    assert m.time.tolist() == [50, 100, 150, 200, 250, 300]
    assert math.isclose(float(np.mean(m.throughput_series)), m.throughput)
    with pytest.raises(ValueError, match="episodic"):
        sim.evaluate_lifelong(NearestTaskController(), "3v3", steps=10)
    with pytest.raises(ValueError, match="lifelong"):
        sim.evaluate(NearestTaskController(), "warehouse-20", episodes=2)
    with pytest.raises(ValueError, match="steps"):
        sim.evaluate_lifelong(NearestTaskController(), "warehouse-20", steps=0)
    with pytest.raises(ValueError, match="at most one"):
        sim.evaluate_lifelong(NearestTaskController(), "warehouse-20", steps=5,
                              arrival_rate=0.2, trace=read_trace)


def test_deadlines_are_counted(tmp_path) -> None:
    path = tmp_path / "due.csv"
    path.write_text("release,pickup_x,pickup_y,dropoff_x,dropoff_y,priority,deadline\n"
                    "0,-1.0,0.2,-1.7,-0.5,0,1\n0,1.0,0.2,1.7,-0.5,0,1000\n")
    m = sim.evaluate_lifelong(NearestTaskController(), floor(), steps=150, seed=0, trace=path,
                              num_agents=2)
    assert m.delivered == 2 and m.deadline_miss_rate == 0.5


# ---------------------------------------------------------------------- observations
def test_observations_have_one_size_at_any_n() -> None:
    dims = {sim.make_env(name, num_envs=1).obs_dim for name in ("warehouse-20", "warehouse-50")}
    assert len(dims) == 1
    env = LifelongEnv(scenario(1), num_envs=1)
    assert env.obs_dim in dims and env.observe().shape == (1, 1, env.obs_dim)


def test_observations_show_open_pickups_only() -> None:
    env = LifelongEnv(scenario(2, arrivals=Backlog(1)), num_envs=1, seed=0)
    lay = env.obs_layout
    obs = env.observe()
    assert obs[0, :, lay.pickup_mask(0)].eq(1).all()
    slot = int(env.orders.status[0].eq(OPEN).nonzero()[0])
    env.assign(torch.tensor([[slot, -1]]))
    obs = env.observe()
    assert obs[0, :, lay.pickup_mask(0)].eq(0).all()  # assigned: no longer open
    assert obs[0, 0, lay.target_mask] == 1 and obs[0, 1, lay.target_mask] == 0


# ---------------------------------------------------------------------- rewards
def _reference_work(env: LifelongEnv) -> float:
    """remaining_work of environment 0, from its definition, with plain loops."""
    o, pos, st = env.orders, env.agent_pos[0].double(), env.agent_status[0]
    total = 0.0
    for q in range(o.capacity):
        s = int(o.status[0, q])
        p, d = o.pickup[0, q].double(), o.dropoff[0, q].double()
        if s in (OPEN, ASSIGNED):
            avail = [i for i in range(env.num_agents) if int(st[i]) in (IDLE, TO_PICKUP)]
            cand = avail or list(range(env.num_agents))
            total += min(float((pos[i] - p).norm()) for i in cand) + float((d - p).norm())
        elif s == LOADED:
            total += float((pos[int(o.agent[0, q])] - d).norm())
    return total


def test_minidist_is_the_remaining_work() -> None:
    env = sim.make_env("warehouse-20", num_envs=1, seed=0, reward="minidist",
                       arrivals=Poisson(0.5))
    ctl = NearestTaskController()
    ctl.reset(env)
    obs = env.observe()
    for t in range(120):
        obs, reward, _, info = env.step(ctl.act(obs))
        if t % 20 == 19:
            pairs = float(info["collision_pairs"][0])
            want = -_reference_work(env) - pairs
            assert math.isclose(float(info["team_reward"][0]), want, rel_tol=1e-4, abs_tol=1e-3)
            assert torch.allclose(reward[0], torch.full((20,), want), rtol=1e-4, atol=1e-3)


def test_greedy_rewards_progress_to_the_own_target() -> None:
    env = LifelongEnv(scenario(1), num_envs=1, seed=0, reward="greedy")
    env.set_state(np.array([[[0.0, -0.8]]]))
    target = torch.tensor([0.0, 0.2])
    before = float((env.agent_pos[0, 0] - target).norm())
    _, reward, _, info = env.step(torch.tensor([[[0.0, 1.0]]]))
    after = float((env.agent_pos[0, 0] - target).norm())
    assert math.isclose(float(info["reward_terms"]["progress"][0, 0]), before - after,
                        rel_tol=1e-5)
    assert set(info["reward_terms"]) == {"progress", "collision"}


def test_greedy_progress_is_measured_along_the_paths_round_the_shelves() -> None:
    """On a floor with shelves the progress is the decrease of the shortest-path length to
    the own target (an independent path table agrees), not of the straight line."""
    from sim.floor_paths import FloorWaypoints
    from sim.orders import CARRYING, TO_PICKUP
    from sim.rewards import LifelongGreedy

    env = sim.make_env("warehouse-20", num_envs=2, seed=1, reward="greedy")
    paths = FloorWaypoints(env.world)
    ctl = NearestTaskController()
    ctl.reset(env)
    obs = env.observe()
    checked = differs = 0
    for _ in range(60):
        f, o = env.fleet, env.orders
        has = (f.status == CARRYING) | (f.status == TO_PICKUP)
        slot = f.order.clamp_min(0).unsqueeze(-1).expand(-1, -1, 2)
        own = torch.where((f.status == CARRYING).unsqueeze(-1), o.dropoff.gather(1, slot),
                          o.pickup.gather(1, slot))
        before = env.agent_pos.clone()
        obs, _, _, info = env.step(ctl.act(obs))
        want = paths.query(before, own)[1] - paths.query(env.agent_pos, own)[1]
        straight = (before - own).norm(dim=-1) - (env.agent_pos - own).norm(dim=-1)
        got = info["reward_terms"]["progress"]
        assert torch.allclose(got[has], want[has], atol=1e-4)
        checked += int(has.sum())
        differs += int(((got - straight).abs() > 1e-3)[has].sum())
    assert checked > 100 and differs > 0
    with pytest.raises(ValueError, match="setup"):
        LifelongGreedy()(env.state, None)
    with pytest.raises(ValueError, match="path must be True or False"):
        LifelongGreedy(path=1)


def test_user_reward_output_is_checked() -> None:
    env = LifelongEnv(scenario(1), num_envs=1, reward=lambda s, c: {"x": torch.zeros(3)})
    with pytest.raises(ValueError, match="reward term 'x' must have shape"):
        env.step(still(env))


# ---------------------------------------------------------------------- the adapters
def test_pettingzoo_lifelong_passes_the_conformance_tests() -> None:
    from pettingzoo.test import parallel_api_test, parallel_seed_test

    parallel_api_test(sim.pettingzoo_env("warehouse-20", seed=0), num_cycles=30)
    parallel_seed_test(lambda: sim.pettingzoo_env("warehouse-20", seed=0))


def test_pettingzoo_lifelong_truncates_at_the_horizon() -> None:
    env = sim.pettingzoo_env(sim.get_scenario("warehouse-20", max_steps=5), seed=0)
    obs, infos = env.reset(seed=0)
    assert infos["agv_0"]["status"] == "idle"
    for _step in range(5):
        obs, rew, term, trunc, infos = env.step({a: np.zeros(2, np.float32) for a in env.agents})
        assert not any(term.values())
    assert all(trunc.values()) and env.agents == []


def test_nearest_controller_delivers_in_a_warehouse() -> None:
    m = sim.evaluate_lifelong(NearestTaskController(), "warehouse-20", steps=400, seed=0)
    assert m.delivered > 20


def test_bad_lifelong_env_arguments() -> None:
    with pytest.raises(ValueError, match="num_envs"):
        sim.make_env("warehouse-20", num_envs=0)
    with pytest.raises(ValueError, match="native must be"):
        sim.make_env("warehouse-20", native="yes")
    with pytest.raises(ValueError, match="unknown scenario option"):
        sim.make_env("warehouse-20", shelves=3)
    with pytest.raises(ValueError, match="actions must have shape"):
        env = sim.make_env("warehouse-20", num_envs=2)
        env.step(torch.zeros(2, 3, 2))
    with pytest.raises(ValueError, match="NaN"):
        env.step(torch.full((2, 20, 2), float("nan")))
    with pytest.raises(ValueError, match="lifelong"):
        sim.AGVEnv(sim.get_scenario("warehouse-20"))


@pytest.mark.parametrize("name, field", [("warehouse-5", "k_pickups"), ("warehouse-5", "k_agents"),
                                         ("3v3", "k_tasks"), ("3v3", "k_agents")])
@pytest.mark.parametrize("value", [-1, 1025, 10**9, 2.5, float("nan"), True, "4", "", None])
def test_observation_slots_are_bounded(name, field, value) -> None:
    """A billion slots asked for 60 GB deep in torch; now any count outside [0, 1024] is
    named before a tensor is made, and the bound itself is served (padded slots)."""
    with pytest.raises(ValueError, match=rf"{field} must be an integer in \[0, 1024\]"):
        sim.get_scenario(name, **{field: value})
    assert getattr(sim.get_scenario(name, **{field: 1024}), field) == 1024


@pytest.mark.parametrize("reward, arrivals", [
    ("minidist", Poisson(0.4)), ("greedy", Poisson(0.4)),
    ("minidist", Backlog(30)),
    ("minidist", Backlog(50, deadline=40)),  # more than the 40 slots: the table grows
])
def test_the_kernels_and_the_torch_path_agree(reward, arrivals) -> None:
    from sim import native

    if not native.available():
        pytest.skip("no C compiler here")
    runs, tables_of = [], []
    for use in (True, False):
        tables: list[list[torch.Tensor]] = []
        tables_of.append(tables)
        env = sim.make_env("warehouse-20", num_envs=3, seed=5, reward=reward, native=use,
                           faults=Breakdowns(0.01, 10), arrivals=arrivals)
        assert env.native is use
        ctl = NearestTaskController()
        ctl.reset(env)
        obs = env.observe()
        trace = []
        for _ in range(60):
            obs, r, _, info = env.step(ctl.act(obs))
            trace.append((obs.clone(), r.clone(), info["collision_pairs"].clone(),
                          env.agent_pos.clone(), env.orders.status.clone(),
                          env.agent_status.clone(), *env.targets()))
            # Every field of the order table, and the arrivals, bit for bit.
            tables.append([t.clone() for t in vars(env.orders).values()]
                          + [info["events"].arrived.clone(), env.released.clone()])
        runs.append(trace)
    for t1, t2 in zip(*tables_of, strict=True):
        assert all(torch.equal(a, b) for a, b in zip(t1, t2, strict=True))
    for (o1, r1, c1, p1, s1, *st1), (o2, r2, c2, p2, s2, *st2) in zip(*runs, strict=True):
        assert torch.equal(o1, o2) and torch.equal(p1, p2) and torch.equal(s1, s2)
        assert all(torch.equal(a, b) for a, b in zip(st1, st2, strict=True))
        assert torch.equal(c1, c2)
        torch.testing.assert_close(r1, r2, rtol=1e-5, atol=1e-4)  # sums in another order


def test_pickup_and_dropoff_kernel_is_the_torch_rule() -> None:
    from sim import lifelong_native, native, orders

    if not native.available():
        pytest.skip("no C compiler here")
    g = torch.Generator().manual_seed(0)
    reached = 0
    for trial in range(30):
        B, N, Q = 4, 7, 9
        # A coarse grid of points so that AGVs reach several orders at once, with ties.
        pos = torch.randint(0, 4, (B, N, 2), generator=g).float() * 0.05
        o = orders.Orders.empty(B, Q, torch.device("cpu"))
        o.pickup = torch.randint(0, 4, (B, Q, 2), generator=g).float() * 0.05
        o.status = torch.randint(0, 5, (B, Q), generator=g).to(torch.int8)
        o.id = torch.randperm(B * Q, generator=g).view(B, Q)
        o.priority = torch.randint(0, 2, (B, Q), generator=g)
        o.dropoff = torch.randint(0, 4, (B, Q, 2), generator=g).float() * 0.05
        ready = torch.rand(B, N, generator=g) > 0.2
        own = torch.where(torch.rand(B, N, generator=g) > 0.6,
                          torch.randint(0, Q, (B, N), generator=g), -1)
        want = orders.pickups(pos, ready, own, o, 0.1)
        got = lifelong_native.lifelong_pickups(pos, ready, own, o.pickup, o.dropoff, o.status,
                                               orders.tie_key(o), 0.1)
        assert torch.equal(want[0], got[0]), trial
        assert torch.equal(torch.where(want[0], want[1], 0), got[1]), trial
        drops = orders.dropoffs(pos, ready, own, o, 0.1)
        assert torch.equal(drops, got[2]), trial
        reached += int(drops.sum())
    assert reached > 0  # the coarse grid makes drop-offs happen


def test_lifelong_ipf_is_the_converged_jacobi_field(tmp_path) -> None:
    from sim.ipf import ipf_grid
    from sim.ipf.jacobi import jacobi_field
    from sim.rewards import LifelongIPF

    world = World(bounds=(-1.0, -1.0, 1.0, 1.0), obstacles=np.array([[-0.2, -0.1, 0.2, 0.1]]),
                  pickups=np.array([[-0.6, 0.5], [0.6, 0.5], [0.0, 0.6]]),
                  stations=np.array([[0.0, -0.8]]))
    path = tmp_path / "t.csv"
    path.write_text("release,pickup_x,pickup_y,dropoff_x,dropoff_y,priority,deadline\n"
                    "0,0.0,0.6,0.0,-0.8,0,\n0,-0.6,0.5,0.0,-0.8,0,\n0,0.6,0.5,0.0,-0.8,0,\n")
    sc = LifelongScenario(name="ipf", world=world, num_agents=3, arrivals=read_trace(path))
    env = LifelongEnv(sc, num_envs=1, seed=0, reward=LifelongIPF(resolution=0.1))
    # Positions inside grid cells, not on their edges (x = -0.6 is one at resolution 0.1).
    env.set_state(np.array([[[-0.57, -0.43], [0.63, -0.37], [0.02, 0.62]]]))
    _, _, _, info = env.step(still(env))  # AGV 2 picks order 0 up
    assert env.agent_status[0].tolist() == [IDLE, IDLE, CARRYING]
    grid = ipf_grid(world, 0.1)
    cell = grid.cell_of(env.agent_pos[0].double().numpy()).tolist()
    o = env.orders  # the float32 points the env holds
    pickups = grid.cell_of(o.pickup[0][o.status[0] == OPEN].double().numpy()).tolist()
    drop = grid.cell_of(o.dropoff[0, :1].double().numpy()).tolist()
    assert len(pickups) == 2
    for i in range(3):
        others = [c for j, c in enumerate(cell) if j != i]
        targets = drop if i == 2 else pickups
        field = jacobi_field(grid, np.array(targets + others),
                             np.array([5.0] * len(targets) + [-3.0] * len(others)), tol=1e-9)
        want = field.ravel()[cell[i]]
        got = float(info["reward_terms"]["ipf"][0, i])
        assert abs(got - want) < 1e-5, (i, got, want)  # float32 result


def test_stream_kernel_gives_the_reference_draws() -> None:
    from sim import native, streams

    if not native.available():
        pytest.skip("no C compiler here")
    lib = native.library()
    g = torch.Generator().manual_seed(0)
    key = torch.randint(0, 2**62, (6, 1), generator=g)
    for counters in [(), (3,), (streams.FAULTS, torch.arange(9).view(1, -1)),
                     (1, torch.arange(4).view(1, -1), torch.tensor([[7]]), 2)]:
        want = streams.uniform(key, *counters)
        assert torch.equal(streams.uniform(key, *counters, kernels=lib), want)
    # Negative keys and counters wrap as the reference does.
    assert torch.equal(streams.uniform(torch.tensor([-5]), -2, kernels=lib),
                       streams.uniform(torch.tensor([-5]), -2))


def test_fault_draw_kernel_gives_the_reference_breakdowns() -> None:
    from sim import native, streams

    if not native.available():
        pytest.skip("no C compiler here")
    g = torch.Generator().manual_seed(1)
    B, N = 5, 11
    keys = torch.randint(0, 2**62, (B,), generator=g)
    steps = torch.randint(1, 10_000, (B,), generator=g)
    can = torch.rand(B, N, generator=g) > 0.3
    want = can & (streams.uniform(keys.view(-1, 1), streams.FAULTS, steps.view(-1, 1),
                                  torch.arange(N).view(1, -1)) < 0.4)
    out = torch.empty(B, N, dtype=torch.bool)
    native.library().agv_fault_draws(B, N, keys.data_ptr(), streams.FAULTS, steps.data_ptr(),
                                     0.4, can.data_ptr(), out.data_ptr())
    assert torch.equal(out, want) and 0 < int(want.sum()) < B * N


def test_the_design_names_work_as_written(tmp_path) -> None:
    """DESIGN.md, "Lifelong operation": the snippet's names, as written."""
    controller = NearestTaskController()
    m = sim.evaluate_lifelong(controller, "warehouse-50", steps=60, seed=0,
                              arrival_rate=None, faults=None, trace=None)
    for name in ("throughput", "throughput_bound", "wait_mean", "wait_p95", "lead_mean",
                 "lead_p95", "deadline_miss_rate", "collisions_per_1000", "utilization",
                 "reassignments"):
        assert isinstance(getattr(m, name), float), name
    assert m.lost == 0
    path = tmp_path / "kiva.map"
    path.write_text("type octile\nheight 4\nwidth 8\nmap\nr..e..e.\nr.@@@@@.\nr..e..e.\n"
                    "........\n")
    world = sim.load_floor(path, cell_size=0.8)
    env = sim.make_env(world, num_agents=3, faults=sim.Breakdowns(rate=0.01, repair_steps=5))
    env.step(torch.zeros(1, 3, 2))
    assert env.events.arrived.shape == env.orders.status.shape
    faulty = sim.make_env("warehouse-20", faults=[(1, 0, 3)])
    faulty.step(torch.zeros(1, 20, 2))
    assert bool(faulty.events.breakdown[0, 0])


def test_waits_count_the_orders_left_waiting() -> None:
    """An order no AGV picks up is in no wait of the picked-up orders, but it is in
    wait_*_all with its age so far and in oldest_open."""
    def still(obs: torch.Tensor) -> torch.Tensor:
        return torch.zeros(*obs.shape[:2], 2)

    m = sim.evaluate_lifelong(still, "warehouse-20", steps=80, seed=0, runs=2)
    assert m.delivered == 0 and math.isnan(m.wait_mean) and math.isnan(m.wait_p95)
    assert m.oldest_open == 80  # the backlog released at step 0 waits for the whole run
    assert m.wait_mean_all == 80 and m.wait_p95_all == 80
    s = sim.evaluate_lifelong(NearestTaskController(), "warehouse-20", steps=300, seed=0)
    assert s.delivered > 0 and 0 < s.oldest_open <= 300
    assert {"wait_mean_all", "wait_p95_all", "oldest_open"} <= set(s.summary())
