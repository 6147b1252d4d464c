"""The lifelong kernels (sim.lifelong_native, sim/_native/lifelong.h) against their torch
references: sim.observations.observe_lifelong, sim.physics.pair_distances and collisions,
sim.tasks.remaining_work.

Observations, pair distances and collisions must be equal (torch.equal): the kernels compute
the same float32 values (the same subtractions, the same rounding of each length) and choose
the same entries (ties to the lower index, as torch's stable sort). States on an integer grid
make many exact ties between entries with different features, so a different tie rule would
show. The remaining work is a float32 sum whose order torch chooses: it is compared within
(Q + 1) 2**-24 of the sum (the worst-case error of any float32 summation order of Q
non-negative terms, plus the kernel's one rounding), and exactly where Q = 1.
"""

from __future__ import annotations

import ctypes
import math
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

import sim
from sim import lifelong_native as ln
from sim import native, physics, tasks
from sim.lifelong import LifelongEnv
from sim.observations import LifelongObsLayout, observe_lifelong
from sim.orders import ASSIGNED, LOADED, OPEN, Fleet, Orders

pytestmark = pytest.mark.skipif(not native.available(),
                                reason=f"kernels unavailable: {native.disabled_reason()}")

ROOT = Path(__file__).resolve().parents[2]


def _state(B: int, N: int, Q: int, seed: int, *, grid: bool = False, open_p: float = 0.5,
           shared: bool = False) -> dict[str, torch.Tensor]:
    """A random lifelong state: positions on an integer grid (many exact ties) or in a box;
    with ``shared``, the orders' pickups drawn from 3 points."""
    g = torch.Generator().manual_seed(seed)

    def pts(*shape: int) -> torch.Tensor:
        if grid:
            return torch.randint(0, 7, (*shape, 2), generator=g).float()
        return torch.rand(*shape, 2, generator=g) * 8.0

    pickup = pts(B, Q)
    if shared and Q:
        points = pts(B, 3)
        pickup = points.gather(1, torch.randint(0, 3, (B, Q, 1), generator=g).expand(B, Q, 2))
        pickup = pickup.contiguous()
    u = torch.rand(B, Q, generator=g)
    order_status = torch.where(u < open_p, OPEN,
                               torch.randint(0, 5, (B, Q), generator=g)).to(torch.int8)
    return dict(
        agent_pos=pts(B, N), agent_vel=torch.randn(B, N, 2, generator=g),
        status=torch.randint(0, 4, (B, N), generator=g).to(torch.int8),
        service_left=torch.randint(0, 3, (B, N), generator=g),
        target=pts(B, N), has_target=torch.rand(B, N, generator=g) < 0.5,
        pickup=pickup, order_status=order_status, dropoff=pts(B, Q),
        order_agent=torch.randint(-1, max(N, 1), (B, Q), generator=g),
        active=torch.rand(B, generator=g) < 0.8,
    )


def _tables(s: dict[str, torch.Tensor]) -> tuple[Fleet, Orders]:
    B, N = s["status"].shape
    Q = s["order_status"].shape[1]
    fleet = Fleet.empty(B, N, torch.device("cpu"))
    fleet.status, fleet.service_left = s["status"], s["service_left"]
    orders = Orders.empty(B, Q, torch.device("cpu"))
    orders.status, orders.pickup = s["order_status"], s["pickup"]
    orders.dropoff, orders.agent = s["dropoff"], s["order_agent"]
    return fleet, orders


def _observe_args(s: dict[str, torch.Tensor], kp: int, ka: int, rng: float) -> tuple:
    return (s["agent_pos"], s["agent_vel"], s["status"], s["service_left"], s["target"],
            s["has_target"], s["pickup"], s["order_status"], kp, ka, rng)


def _reference(s: dict[str, torch.Tensor], kp: int, ka: int,
               rng: float) -> tuple[torch.Tensor, torch.Tensor]:
    fleet, orders = _tables(s)
    N = s["agent_pos"].shape[1]
    pair = physics.pair_distances(s["agent_pos"])
    obs = observe_lifelong(s["agent_pos"], s["agent_vel"], fleet, orders, s["target"],
                           s["has_target"], LifelongObsLayout(kp, ka), rng, pair,
                           torch.eye(N, dtype=torch.bool))
    return obs, pair


def _check_observe(s: dict[str, torch.Tensor], kp: int, ka: int, rng: float) -> torch.Tensor:
    obs, pair = ln.lifelong_observe(*_observe_args(s, kp, ka, rng))
    ref_obs, ref_pair = _reference(s, kp, ka, rng)
    assert obs.shape == ref_obs.shape == (*s["status"].shape, LifelongObsLayout(kp, ka).size)
    assert torch.equal(pair, ref_pair)
    assert torch.equal(obs, ref_obs), (obs - ref_obs).abs().max()
    return obs


@pytest.mark.parametrize("B, N, Q, kp, ka, rng", [
    (1, 1, 1, 4, 4, math.inf),  # no other AGV
    (3, 5, 7, 4, 4, 3.0),  # the range cuts some
    (4, 8, 70, 4, 4, math.inf),  # Q > 64
    (2, 6, 3, 8, 10, math.inf),  # more slots than candidates
    (5, 12, 100, 4, 4, 2.5),
    (2, 3, 0, 4, 2, math.inf),  # no order slots
    (3, 9, 20, 0, 3, 4.0),  # no pickup slots
    (3, 9, 20, 3, 0, 4.0),  # no AGV slots
    (4, 50, 100, 4, 4, math.inf),  # warehouse-50 sizes
    (1, 100, 200, 4, 4, 5.0),  # warehouse-100 sizes
])
@pytest.mark.parametrize("grid", [False, True])
def test_observe_equals_observe_lifelong(B: int, N: int, Q: int, kp: int, ka: int, rng: float,
                                         grid: bool) -> None:
    for seed in range(3):
        _check_observe(_state(B, N, Q, seed, grid=grid), kp, ka, rng)


def test_grid_states_do_tie() -> None:
    # The grid states above hold what the tie rule is tested on: equal distances with
    # different features among the candidates a slot chooses from.
    s = _state(4, 50, 100, 0, grid=True)
    rel = s["pickup"].unsqueeze(1) - s["agent_pos"].unsqueeze(2)
    d = torch.linalg.vector_norm(rel, dim=-1)[0, 0]
    same = d.unsqueeze(0) == d.unsqueeze(1)
    differ = (rel[0, 0].unsqueeze(0) != rel[0, 0].unsqueeze(1)).any(-1)
    assert bool((same & differ).any())


def test_ties_go_to_the_lower_slot() -> None:
    # Four open pickups at distance 1 in four directions, one at 2: two slots get the two
    # lowest open slots of the ring, as torch's stable sort gives them.
    pick = torch.tensor([[[0.0, 2.0], [0.0, 1.0], [-1.0, 0.0], [1.0, 0.0], [0.0, -1.0]]])
    s = _state(1, 1, 5, 0)
    s.update(agent_pos=torch.zeros(1, 1, 2), pickup=pick,
             order_status=torch.tensor([[OPEN, ASSIGNED, OPEN, OPEN, OPEN]], dtype=torch.int8))
    obs = _check_observe(s, 2, 0, math.inf)
    lay = LifelongObsLayout(2, 0)
    assert obs[0, 0, lay.pickup_rel(0)].tolist() == [-1.0, 0.0]
    assert obs[0, 0, lay.pickup_rel(1)].tolist() == [1.0, 0.0]


@pytest.mark.parametrize("seed", range(4))
def test_orders_sharing_pickup_points(seed: int) -> None:
    # Many orders on 3 pickup points: the k slots show the nearest point several times over
    # (each order at it is a candidate), whichever equal entries are chosen the features agree.
    for kp in (1, 4, 9):
        s = _state(6, 10, 80, seed, shared=True, open_p=0.7)
        obs = _check_observe(s, kp, 4, math.inf)
        if kp > 1:  # some AGV sees one point twice
            lay = LifelongObsLayout(kp, 4)
            twice = (obs[..., lay.pickup_rel(0)] == obs[..., lay.pickup_rel(1)]).all(-1)
            assert bool((twice & (obs[..., lay.pickup_mask(1)][..., 0] == 1)).any())


def test_all_hidden_and_range_zero() -> None:
    s = _state(3, 8, 30, 1, grid=True, open_p=0.0)
    s["order_status"] = torch.where(s["order_status"] == OPEN, ASSIGNED,
                                    s["order_status"]).to(torch.int8)
    obs = _check_observe(s, 4, 4, 0.0)  # AGVs on the same grid point stay visible at range 0
    lay = LifelongObsLayout(4, 4)
    assert not bool(obs[..., lay.pickups].any())
    _check_observe(_state(3, 8, 30, 2), 4, 4, 0.0)


def _boundary_ranges(s: dict[str, torch.Tensor], count: int = 8) -> list[float]:
    """Sensing ranges at AGV-pickup lengths whose two float32 roundings (with or without fused
    multiply-add) differ, the lower of the two: with every order open and a slot for each,
    only the rounding torch uses shows the same pickups as the reference."""
    rel = (s["pickup"].unsqueeze(1) - s["agent_pos"].unsqueeze(2)).numpy()
    x, y = rel[..., 0], rel[..., 1]
    plain = np.sqrt(x * x + y * y)
    fused = np.sqrt((np.float64(1.0) * (x * x) + y.astype(np.float64) ** 2).astype(np.float32))
    differ = np.argwhere(plain != fused)[:count]
    assert len(differ)
    return [float(min(plain[tuple(at)], fused[tuple(at)])) for at in differ]


def test_range_boundary_rounds_as_torch() -> None:
    s = _state(2, 16, 64, 5)
    s["order_status"] = torch.full_like(s["order_status"], OPEN)
    for rng in _boundary_ranges(s):
        _check_observe(s, 64, 2, rng)


def test_torch_rounding_found_without_fma() -> None:
    # With torch's portable CPU kernels (no fused multiply-add) the probe says so and the
    # kernels still match the references.
    code = (
        "import torch\n"
        "import tests.sim.test_lifelong_native as t\n"
        "from sim import lifelong_native as ln\n"
        "print(ln.torch_norm_rounding())\n"
        "t.test_range_boundary_rounds_as_torch()\n"
        "t.test_remaining_work_each_order_exact(7)\n"
        "t.test_remaining_work_each_order_exact(60)\n"
        "print('ok')\n")
    env = {**os.environ, "ATEN_CPU_CAPABILITY": "default"}
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env,
                         cwd=ROOT, timeout=120)
    assert out.returncode == 0, out.stderr[-3000:]
    assert out.stdout.split() == ["(False,", "False)", "ok"]


@pytest.mark.parametrize("B, N, Q", [(3, 4, 5), (5, 20, 70), (2, 50, 100)])
def test_collisions_in_the_same_pass(B: int, N: int, Q: int) -> None:
    overlaps, touching = 0.0, False
    for seed in range(3):
        s = _state(B, N, Q, seed, grid=seed == 0)
        # Crowded, many overlaps; on the grid, discs touching exactly (distance 1 = 2 r).
        radius = 0.5 if seed == 0 else 0.15
        if seed:
            s["agent_pos"] = s["agent_pos"] * 0.08
        obs, pair, per_agent, pairs = ln.lifelong_observe_collisions(
            *_observe_args(s, 4, 4, math.inf), s["active"], radius)
        ref_obs, ref_pair = _reference(s, 4, 4, math.inf)
        eye = torch.eye(N, dtype=torch.bool)
        triu = torch.triu(torch.ones(N, N, dtype=torch.bool), 1)
        ref_per, ref_pairs = physics.collisions(ref_pair, s["active"], radius, eye, triu)
        assert torch.equal(obs, ref_obs) and torch.equal(pair, ref_pair)
        assert torch.equal(per_agent, ref_per) and torch.equal(pairs, ref_pairs)
        assert per_agent.dtype == pairs.dtype == torch.float32
        overlaps += float(pairs.sum())
        touching |= seed == 0 and bool((pair == 2 * radius).any())
    assert overlaps > 0 and (touching or N < 20)


def _work_args(s: dict[str, torch.Tensor]) -> tuple:
    return (s["agent_pos"], s["order_status"], s["pickup"], s["dropoff"], s["order_agent"],
            s["status"], s["active"])


def _check_work(s: dict[str, torch.Tensor]) -> torch.Tensor:
    _, orders = _tables(s)
    got = ln.remaining_work(*_work_args(s))
    ref = tasks.remaining_work(s["agent_pos"], orders, s["status"], s["active"])
    Q = s["order_status"].shape[1]
    assert got.shape == ref.shape and got.dtype == torch.float32
    assert torch.equal(got[~s["active"]], torch.zeros_like(got[~s["active"]]))
    torch.testing.assert_close(got, ref, rtol=(Q + 1) * 2.0 ** -24, atol=0.0)
    return got


@pytest.mark.parametrize("B, N, Q", [(4, 1, 3), (6, 5, 17), (3, 20, 70), (8, 50, 100),
                                     (2, 100, 200)])
def test_remaining_work_equals_torch(B: int, N: int, Q: int) -> None:
    for seed in range(3):
        s = _state(B, N, Q, seed, grid=seed == 1)
        assert bool(_check_work(s)[s["active"]].gt(0).any())


def test_remaining_work_when_no_agv_is_available() -> None:
    # Every AGV carrying or broken: an open order counts its distance to the nearest AGV.
    s = _state(5, 6, 30, 3)
    s["status"] = torch.where(s["status"] < 2, 3, s["status"]).to(torch.int8)
    s["status"][0] = 2
    _check_work(s)


@pytest.mark.parametrize("N", [7, 60])
def test_remaining_work_each_order_exact(N: int) -> None:
    # One order per floor: the sum is the order's own term, which must be the same float32.
    s = _state(400, N, 1, 4, open_p=0.3)
    s["status"][:100] = torch.where(s["status"][:100] < 2, 2, s["status"][:100])
    s["order_status"][200:300] = LOADED
    s["active"] = torch.ones(400, dtype=torch.bool)
    _, orders = _tables(s)
    got = ln.remaining_work(*_work_args(s))
    ref = tasks.remaining_work(s["agent_pos"], orders, s["status"], s["active"])
    assert torch.equal(got, ref)


def test_lifelong_env_states() -> None:
    # States a lifelong warehouse reaches (breakdowns on, so every status occurs): the
    # kernels give what LifelongEnv computes with the references.
    env = sim.make_env("warehouse-20", num_envs=4, seed=2,
                       faults=sim.Breakdowns(0.02, 5))
    assert isinstance(env, LifelongEnv)
    env.reset()
    g = torch.Generator().manual_seed(0)
    lay = env.obs_layout
    seen = set()
    for t in range(40):
        if t % 4 == 0:  # a dispatcher's plan: idle AGVs get open orders (TO_PICKUP, ASSIGNED)
            f, o = env.fleet, env.orders
            plan = torch.where((f.status == 1) | (f.status == 2), f.order, -1)
            for b in range(4):
                free = (o.status[b] == OPEN).nonzero()[:, 0].tolist()
                for i in (f.status[b] == 0).nonzero()[:, 0].tolist()[:len(free)]:
                    plan[b, i] = free.pop()
            env.assign(plan)
        _, _, _, info = env.step(torch.rand(4, env.num_agents, 2, generator=g) * 2 - 1)
        f, o = env.fleet, env.orders
        target, has = env.targets()
        obs, pair, per_agent, pairs = ln.lifelong_observe_collisions(
            env.agent_pos, env.agent_vel, f.status, f.service_left, target, has, o.pickup,
            o.status, lay.k_pickups, lay.k_agents, env.scenario.sensing_range, info["active"],
            env.world.agent_radius)
        assert torch.equal(obs, env.observe())
        assert torch.equal(pair, physics.pair_distances(env.agent_pos))
        assert torch.equal(per_agent, info["collisions_per_agent"])
        assert torch.equal(pairs, info["collision_pairs"])
        work = ln.remaining_work(env.agent_pos, o.status, o.pickup, o.dropoff, o.agent,
                                 f.status, info["active"])
        ref = tasks.remaining_work(env.agent_pos, o, f.status, info["active"])
        torch.testing.assert_close(work, ref, rtol=(o.capacity + 1) * 2.0 ** -24, atol=0.0)
        torch.testing.assert_close(-work - pairs, info["team_reward"],
                                   rtol=(o.capacity + 2) * 2.0 ** -24, atol=0.0)
        seen |= set(f.status.unique().tolist()) | {10 + v for v in o.status.unique().tolist()}
    assert {0, 1, 2, 3, 11, 12, 13} <= seen


def _bad_cases() -> list[tuple[str, dict, str]]:
    s = _state(2, 3, 4, 0)
    return [
        ("agent_pos", dict(agent_pos=s["agent_pos"].double()), "agent_pos.*float32"),
        ("agent_vel", dict(agent_vel=torch.zeros(2, 4, 2)), r"agent_vel.*shape \(2, 3, 2\)"),
        ("status", dict(status=s["status"].long()), "status.*int8"),
        ("service_left", dict(service_left=s["service_left"].int()), "service_left.*int64"),
        ("target", dict(target=torch.zeros(2, 3, 2).transpose(0, 1).contiguous()
                        .transpose(0, 1)), "target.*non-contiguous"),
        ("has_target", dict(has_target=s["has_target"].to(torch.uint8)), "has_target.*bool"),
        ("pickup", dict(pickup=torch.zeros(3, 4, 2)),
         r"pickup.*shape \(2, 4, 2\), got.*\(3, 4, 2\)"),
        ("order_status", dict(order_status=torch.zeros(2, 5, dtype=torch.int8)),
         r"order_status.*shape \(2, 4\)"),
        ("status code", dict(status=torch.tensor([[0, 1, 2], [3, 4, 0]], dtype=torch.int8)),
         r"AGENT_STATUS codes 0..3, got 4 at \(env 1, AGV 1\)"),
        ("numpy", dict(agent_pos=s["agent_pos"].numpy()), "agent_pos.*got ndarray"),
    ]


@pytest.mark.parametrize("name, change, match", _bad_cases(), ids=[c[0] for c in _bad_cases()])
def test_observe_refuses_bad_inputs(name: str, change: dict, match: str) -> None:
    s = {**_state(2, 3, 4, 0), **change}
    with pytest.raises(ValueError, match=match):
        ln.lifelong_observe(*_observe_args(s, 4, 4, math.inf))


@pytest.mark.parametrize("kp, ka, rng, match", [
    (-1, 4, 1.0, "k_pickups"), (True, 4, 1.0, "k_pickups"), (4, 2.0, 1.0, "k_agents"),
    (4, 4, math.nan, "sensing_range"), (4, 4, -1.0, "sensing_range"),
    (4, 4, "far", "sensing_range"),
])
def test_observe_refuses_bad_counts_and_range(kp: object, ka: object, rng: object,
                                              match: str) -> None:
    s = _state(2, 3, 4, 0)
    with pytest.raises(ValueError, match=match):
        ln.lifelong_observe(*_observe_args(s, kp, ka, rng))


def test_collisions_refuse_bad_active_and_radius() -> None:
    s = _state(2, 3, 4, 0)
    args = _observe_args(s, 4, 4, math.inf)
    for active, radius, match in [(s["active"].long(), 0.1, "active.*bool"),
                                  (torch.ones(3, dtype=torch.bool), 0.1, r"active.*\(2,\)"),
                                  (None, 0.1, "active"), (s["active"], math.inf, "agent_radius"),
                                  (s["active"], -0.1, "agent_radius")]:
        with pytest.raises(ValueError, match=match):
            ln.lifelong_observe_collisions(*args, active, radius)


def test_remaining_work_refuses_bad_inputs() -> None:
    s = _state(2, 3, 4, 0)
    cases = [
        (dict(order_agent=torch.tensor([[0, 1, 2, -1], [3, 0, 0, 0]])),
         r"order_agent must hold AGV indices < N = 3.*got 3 at \(env 1, slot 0\)"),
        (dict(order_agent=s["order_agent"].int()), "order_agent.*int64"),
        (dict(dropoff=torch.zeros(2, 5, 2)), r"dropoff.*shape \(2, 4, 2\)"),
        (dict(status=s["status"].long()), "agent_status.*int8"),
        (dict(active=torch.ones(2)), "active.*bool"),
        (dict(agent_pos=torch.zeros(2, 0, 2), status=torch.zeros(2, 0, dtype=torch.int8)),
         "at least one AGV"),
    ]
    for change, match in cases:
        with pytest.raises(ValueError, match=match):
            ln.remaining_work(*_work_args({**s, **change}))


def test_kernels_are_in_the_signature_table() -> None:
    table = native.signatures()
    assert table["agv_lifelong_observe"] == (
        ctypes.c_int, [ctypes.c_int64] * 5 + [ctypes.c_float, ctypes.c_int, ctypes.c_float]
        + [ctypes.c_void_p] * 13)
    assert table["agv_lifelong_remaining_work"] == (
        ctypes.c_int, [ctypes.c_int64] * 3 + [ctypes.c_int] * 2 + [ctypes.c_void_p] * 8)


def _best_ms(fn, repeats: int = 5, number: int = 10) -> float:  # noqa: ANN001
    fn()
    best = math.inf
    for _ in range(repeats):
        t0 = time.process_time()
        for _ in range(number):
            fn()
        best = min(best, (time.process_time() - t0) / number)
    return best * 1e3


@pytest.mark.slow
@pytest.mark.parametrize("name, B", [("warehouse-50", 64), ("warehouse-100", 16)])
def test_speed_against_torch(name: str, B: int) -> None:
    """Prints torch reference vs kernel milliseconds (CPU time of this process, best of 5)
    on a state the warehouse reaches after 60 random steps, at one torch thread."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        env = sim.make_env(name, num_envs=B, seed=0, faults=sim.Breakdowns(1e-3, 50))
        env.reset()
        g = torch.Generator().manual_seed(0)
        for _ in range(60):
            _, _, _, info = env.step(torch.rand(B, env.num_agents, 2, generator=g) * 2 - 1)
        f, o, lay = env.fleet, env.orders, env.obs_layout
        target, has = env.targets()
        act = info["active"]
        N = env.num_agents
        eye = torch.eye(N, dtype=torch.bool)
        triu = torch.triu(torch.ones(N, N, dtype=torch.bool), 1)
        rng, rad = env.scenario.sensing_range, env.world.agent_radius

        def torch_all() -> None:
            pair = physics.pair_distances(env.agent_pos)
            physics.collisions(pair, act, rad, eye, triu)
            observe_lifelong(env.agent_pos, env.agent_vel, f, o, target, has, lay, rng, pair,
                             eye)
            tasks.remaining_work(env.agent_pos, o, f.status, act)

        def kernel_all() -> None:
            ln.lifelong_observe_collisions(env.agent_pos, env.agent_vel, f.status,
                                           f.service_left, target, has, o.pickup, o.status,
                                           lay.k_pickups, lay.k_agents, rng, act, rad)
            ln.remaining_work(env.agent_pos, o.status, o.pickup, o.dropoff, o.agent, f.status,
                              act)

        rows = {
            "observe (+pair)": (
                lambda: observe_lifelong(env.agent_pos, env.agent_vel, f, o, target, has, lay,
                                         rng, physics.pair_distances(env.agent_pos), eye),
                lambda: ln.lifelong_observe(env.agent_pos, env.agent_vel, f.status,
                                            f.service_left, target, has, o.pickup, o.status,
                                            lay.k_pickups, lay.k_agents, rng)),
            "remaining_work": (
                lambda: tasks.remaining_work(env.agent_pos, o, f.status, act),
                lambda: ln.remaining_work(env.agent_pos, o.status, o.pickup, o.dropoff,
                                          o.agent, f.status, act)),
            "pair+collisions+observe+work": (torch_all, kernel_all),
        }
        print(f"\n{name} B={B} N={N} Q={o.capacity} open={int((o.status == OPEN).sum())}")
        for label, (ref, fast) in rows.items():
            t_ref, t_fast = _best_ms(ref), _best_ms(fast)
            print(f"  {label:30s} torch {t_ref:8.3f} ms  kernel {t_fast:7.3f} ms  "
                  f"x{t_ref / t_fast:5.1f}")
            assert t_fast < t_ref
    finally:
        torch.set_num_threads(threads)
