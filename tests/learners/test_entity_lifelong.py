"""Entity policies on lifelong floors: waypoints, obstacle points, lifelong tokens (issue 17)."""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace

import numpy as np
import pytest
import torch

import allocator
import sim
from learners.algorithms import make_config, make_learner
from learners.entity import (
    AGENT_TOKEN_FEATURES,
    DRIVE_GAIN,
    DRIVE_SPEED,
    MADDPGE,
    arrive_action,
    lifelong_tokens,
)
from learners.floor import OBSTACLE_SLOTS, FloorWaypoints, obstacle_points
from learners.policy import build_learner


@pytest.fixture(scope="module")
def floor() -> FloorWaypoints:
    return FloorWaypoints(sim.get_scenario("warehouse-20").world)


def _clear(world: sim.World, a: np.ndarray, b: np.ndarray, clearance: float) -> bool:
    ts = np.linspace(0.0, 1.0, 200)[:, None]
    return bool(world.is_free(a + ts * (b - a), clearance=clearance).all())


def test_waypoints_go_round_the_shelves(floor):
    world = floor.world
    # a station on the left, pickups in the aisles between shelf rows: straight lines cut shelves
    starts = torch.tensor([[0.4, 1.2], [0.4, 5.2], [6.9, 0.6], [3.0, 1.0]])
    goals = torch.tensor([[3.1, 3.2], [4.3, 2.8], [1.9, 4.6], [3.1, 3.2]])
    wp, length = floor.query(starts, goals)
    for a, b, w, L in zip(starts.numpy(), goals.numpy(), wp.numpy(), length.numpy(),
                          strict=True):
        assert not _clear(world, a, b, 0.0)  # the straight line runs through a shelf
        assert _clear(world, a, w, 0.0)  # the line to the waypoint does not
        assert not np.allclose(w, b)
        assert L > np.linalg.norm(b - a) + 0.1
    # in the same aisle and close: the target itself, the straight distance
    wp, length = floor.query(torch.tensor([[3.0, 3.0]]), torch.tensor([[3.1, 3.2]]))
    assert torch.equal(wp, torch.tensor([[3.1, 3.2]]))
    assert abs(float(length[0]) - float(np.hypot(0.1, 0.2))) < 0.12
    # fields are kept per target cell
    n = floor.cached_targets
    floor.query(starts, goals)
    assert floor.cached_targets == n


def test_waypoint_walk_reaches_the_target(floor):
    """Stepping to the waypoint again and again reaches a target behind two shelf rows."""
    p, goal = torch.tensor([[0.4, 0.4]]), torch.tensor([[4.9, 4.2]])
    for _ in range(60):
        wp, _ = floor.query(p, goal)
        step = wp - p
        p = p + step * min(1.0, 0.3 / max(float(step.norm()), 1e-9))
        assert _clear(floor.world, p.numpy()[0], p.numpy()[0], 0.1)  # no corner cut
        if float((p - goal).norm()) < 0.05:
            break
    assert float((p - goal).norm()) < 0.05


def test_sight_gives_the_paths_first_corner(floor):
    """``FloorWaypoints.sight``: the target when in a straight line of sight, else a path
    corner the disc reaches in a straight line, heading where the dispatchers' driver heads
    (``FloorDistances.next_waypoint``); walking to it again and again reaches the target."""
    from allocator.distances import FloorDistances

    world = floor.world
    starts = torch.tensor([[0.4, 1.2], [0.4, 5.2], [6.9, 0.6], [3.0, 1.0], [3.0, 3.0]])
    goals = torch.tensor([[3.1, 3.2], [4.3, 2.8], [1.9, 4.6], [3.1, 3.2], [3.1, 3.2]])
    wp = floor.sight(starts, goals)
    assert torch.equal(wp[-1], goals[-1])  # in sight: the target itself
    lookahead, _ = floor.query(starts, goals)
    driver = FloorDistances(world).next_waypoint(starts.double().numpy(), goals.double().numpy())
    for a, w, near, d in zip(starts.numpy(), wp.numpy(), lookahead.numpy(), driver,
                             strict=True):
        assert sim.world.segments_clear(a[None], w[None].astype(np.float64), world)[0]
        assert np.linalg.norm(w - a) >= np.linalg.norm(near - a) - 1e-6  # at least as far
        cos = np.dot(w - a, d - a) / max(np.linalg.norm(w - a) * np.linalg.norm(d - a), 1e-9)
        assert cos > 0.98  # within 11 degrees of the driver's heading
    p, goal = torch.tensor([[0.4, 0.4]]), torch.tensor([[4.9, 4.2]])
    for _ in range(60):
        step = floor.sight(p, goal) - p
        p = p + step * min(1.0, 0.3 / max(float(step.norm()), 1e-9))
        assert _clear(world, p.numpy()[0], p.numpy()[0], 0.1)  # no corner cut
        if float((p - goal).norm()) < 0.05:
            break
    assert float((p - goal).norm()) < 0.05
    # masked pairs: the target, and no field computed
    n = floor.cached_targets
    pts = torch.tensor([[0.4, 1.2], [0.4, 5.2]])
    far = torch.tensor([[9.5, 0.3], [9.5, 7.7]])
    assert torch.equal(floor.sight(pts, far, torch.zeros(2, dtype=torch.bool)), far)
    assert floor.cached_targets == n
    for bad in (0, -3, 2.5, float("nan"), "8", None, True):
        with pytest.raises(ValueError, match="reach must be an integer >= 1"):
            floor.sight(pts, far, reach=bad)
    with pytest.raises(ValueError, match="reach must be at most the floor's"):
        floor.sight(pts, far, reach=10**12)  # refused before any walk
    with pytest.raises(ValueError, match="same shape"):
        floor.sight(pts, far[:1])
    with pytest.raises(ValueError, match="mask must have shape"):
        floor.sight(pts, far, torch.ones(3, dtype=torch.bool))


def test_floor_bad_inputs(floor):
    with pytest.raises(ValueError, match="sim.World"):
        FloorWaypoints("warehouse-20")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="resolution"):
        FloorWaypoints(floor.world, resolution=0.0)
    with pytest.raises(ValueError, match="resolution"):
        FloorWaypoints(floor.world, resolution=1e-4)
    with pytest.raises(ValueError, match="lookahead"):
        FloorWaypoints(floor.world, lookahead=0)
    with pytest.raises(ValueError, match="same shape"):
        floor.query(torch.zeros(3, 2), torch.zeros(2, 2))


def test_obstacle_points(floor):
    world = floor.world  # shelves [1.6, 2.0, 6.4, 2.6], ...; bounds (0, 0, 7.2, 6.2)
    rel, mask = obstacle_points(world, torch.tensor([[3.0, 1.8], [0.5, 0.3], [3.6, 3.0]]))
    assert rel.shape == (3, OBSTACLE_SLOTS, 2) and mask.shape == (3, OBSTACLE_SLOTS)
    assert torch.allclose(rel[0, 0], torch.tensor([0.0, 0.2]))  # the shelf face above
    assert mask[0].sum() == 1  # the floor's bottom wall is 1.8 away
    assert torch.allclose(rel[1, :2], torch.tensor([[0.0, -0.3], [-0.5, 0.0]]))
    assert torch.allclose(rel[2, :2].abs(), torch.tensor([[0.0, 0.4], [0.0, 0.4]]))
    assert torch.equal(rel[~mask], torch.zeros(int((~mask).sum()), 2))


def _lifelong(algo: str, env: sim.LifelongEnv):
    learner = build_learner(algo, env.obs_dim, env.global_state().shape[-1], env.num_agents,
                            {"hidden": 16}, lifelong=True)
    learner.reset(env)
    return learner


def _permute_slots(obs: torch.Tensor, start: int, k: int, width: int,
                   perm: list[int]) -> torch.Tensor:
    out = obs.clone()
    block = obs[..., start:start + k * width].reshape(*obs.shape[:-1], k, width)
    out[..., start:start + k * width] = block[..., perm, :].reshape(*obs.shape[:-1], k * width)
    return out


@pytest.mark.parametrize("algo", ["maddpg-e", "bicnet-e"])
def test_lifelong_policy_reads_the_floor_and_ignores_slot_order(algo):
    env = sim.make_env("warehouse-20", num_envs=2, reward="ipf", seed=3)
    torch.manual_seed(0)
    learner = _lifelong(algo, env)
    for _ in range(30):
        obs, *_ = env.step(learner.act(env.observe()))
    layout = env.obs_layout
    a = learner.act(obs)
    assert a.shape == (2, 20, 2) and bool(torch.isfinite(a).all())
    # the order of the pickup slots and of the AGV slots does not matter
    perm = [2, 0, 3, 1]
    p = _permute_slots(obs, layout.pickups.start, layout.k_pickups, 3, perm)
    p = _permute_slots(p, layout.agents.start, layout.k_agents, 5, perm)
    assert torch.allclose(learner.act(p), a, atol=1e-6)
    # a masked slot's content does not reach the output
    tok = lifelong_tokens(obs, layout, learner.floor)
    assert tok.target is not None and tok.obstacle is not None
    assert tok.target.shape == (2, 20, 1, 6) and tok.obstacle.shape == (2, 20, OBSTACLE_SLOTS, 3)
    s = layout.pickups.start + 3 * (layout.k_pickups - 1)
    h0, h7 = obs.clone(), obs.clone()
    h0[0, 0, s:s + 3] = torch.tensor([0.0, 0.0, 0.0])
    h7[0, 0, s:s + 3] = torch.tensor([7.0, -7.0, 0.0])
    assert torch.equal(learner.act(h0), learner.act(h7))
    assert not torch.equal(learner.act(h0)[0, 0], a[0, 0])
    # a broken AGV's or one in service's action is zero
    still = obs.clone()
    still[0, 0, layout.status] = torch.tensor([0.0, 0.0, 0.0, 1.0])
    still[0, 1, layout.service] = 1.0
    act = learner.act(still)
    assert torch.equal(act[0, :2], torch.zeros(2, 2)) and bool(act[0, 2:].abs().sum() > 0)


def test_modes_do_not_mix():
    life = sim.make_env("warehouse-20", num_envs=1, seed=0)
    epi = sim.make_env("6v6", num_envs=1, seed=0)
    lifelong = build_learner("maddpg-e", life.obs_dim, 1, 20, lifelong=True)
    with pytest.raises(ValueError, match="reset\\(env\\)"):
        lifelong.act(life.observe())  # no layout or floor yet
    with pytest.raises(ValueError, match="read lifelong observations"):
        lifelong.reset(epi)
    with pytest.raises(ValueError, match="FloorWaypoints"):
        lifelong.set_layout(life.obs_layout)
    episodic = make_learner("maddpg-e", epi.obs_dim, epi.state_dim, 6)
    with pytest.raises(ValueError, match="read episodic observations"):
        episodic.reset(life)
    with pytest.raises(ValueError, match="lifelong"):
        MADDPGE(life.obs_dim, 1, 20, lifelong="yes")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="only the entity learners"):
        build_learner("maddpg", life.obs_dim, 1, 20, lifelong=True)


def test_make_learner_infers_the_mode_from_the_sizes():
    """learners.algorithms.make_learner (what checkpoint checks build) passes no mode: the
    sizes say it (11 N state features and no episodic layout: a lifelong floor)."""
    life = sim.make_env("warehouse-20", num_envs=1, seed=0)
    assert make_learner("bicnet-e", life.obs_dim, life.state_dim, 20).lifelong
    for name in ("3v3", "6v6", "20v20", "4v8"):
        epi = sim.make_env(name, num_envs=1, seed=0)
        assert not make_learner("maddpg-e", epi.obs_dim, epi.state_dim,
                                epi.num_agents).lifelong


def test_masked_pairs_are_not_planned(floor):
    """A masked slot's zero offset (target = the AGV's own point) adds no field to the table,
    and a masked pair answers the target and the straight line."""
    pts = torch.rand(50, 2, generator=torch.Generator().manual_seed(0)) * 6.0 + 0.5
    n = floor.cached_targets
    wp, length = floor.query(pts, pts + 0.3, torch.zeros(50, dtype=torch.bool))
    assert floor.cached_targets == n
    assert torch.equal(wp, pts + 0.3)
    assert torch.allclose(length, torch.full((50,), 0.3 * 2 ** 0.5))
    with pytest.raises(ValueError, match="mask must have shape"):
        floor.query(pts, pts, torch.ones(49, dtype=torch.bool))


def test_untrained_lifelong_actor_steers_to_its_waypoint():
    """The WaypointHead starts as a follower: an AGV with a target heads for the target's
    waypoint, an idle one for an open pickup's (cosine > 0.8 for every AGV that has one)."""
    env = sim.make_env("warehouse-20", num_envs=2, seed=3)
    obs = env.observe()
    for algo, seed in (("maddpg-e", 0), ("maddpg-e", 1), ("bicnet-e", 0), ("bicnet-e", 1)):
        torch.manual_seed(seed)
        learner = make_learner(algo, env.obs_dim, env.state_dim, env.num_agents)
        learner.reset(env)
        for _ in range(40):  # some AGVs get orders
            obs, *_ = env.step(learner.policy(obs))
        tok, _ = learner._read(obs)
        with torch.no_grad():
            action = learner.policy(obs)
        has = tok.target_mask[..., 0]
        # idle: the open pickup of the shortest path (the head's prior)
        length = tok.task[..., 5].masked_fill(~tok.task_mask, float("inf"))
        best = length.argmin(-1, keepdim=True)
        pick = tok.task[..., 3:5].gather(2, best.unsqueeze(-1).expand(-1, -1, 1, 2))[..., 0, :]
        aim = torch.where(has.unsqueeze(-1), tok.target[..., 0, 0:2], pick)
        moving = learner._movable(obs)[..., 0] > 0.5
        idle = ~has & tok.task_mask.any(-1)
        cos = torch.nn.functional.cosine_similarity(action, aim, dim=-1)
        assert bool((has & moving).any()) and bool((idle & moving).any())
        assert float(cos[has & moving].min()) > 0.8
        assert float(cos[idle & moving].median()) > 0.8
    # the floor table holds the floor's pickups and stations, not every AGV position
    assert learner.floor.cached_targets < 80


@pytest.mark.parametrize("algo", ["maddpg-e", "bicnet-e"])
@pytest.mark.parametrize("key", ["margin_moving", "parked_token"])
def test_parked_agv_settings_are_refused_on_a_lifelong_floor(algo, key):
    env = sim.make_env("warehouse-20", num_envs=1, reward="ipf", seed=0)
    with pytest.raises(ValueError, match=f"{key} is for episodic scenarios"):
        build_learner(algo, env.obs_dim, env.global_state().shape[-1], env.num_agents,
                      {"hidden": 16, key: True}, lifelong=True)


@pytest.mark.parametrize("algo", ["maddpg-e", "bicnet-e"])
def test_waypoint_drive_chooses_one_candidate_and_drives_at_its_waypoint(algo):
    """``waypoint_drive``: every AGV that can move drives as WaypointDriver would at the next
    waypoint of the candidate of its largest weight (its own target, or an open pickup in
    view), brakes with none in view, and the weights' cross-entropy still trains the choice."""
    env = sim.make_env("warehouse-20", num_envs=2, seed=4)
    torch.manual_seed(0)
    learner = build_learner(algo, env.obs_dim, env.state_dim, env.num_agents,
                            {"hidden": 16, "waypoint_drive": True}, lifelong=True)
    learner.reset(env)
    obs = env.observe()
    for _ in range(40):  # some AGVs get orders
        obs, *_ = env.step(learner.policy(obs))
    tok, _ = learner._read(obs)
    act, w = learner.policy_and_choice(obs)
    wp = torch.cat([tok.target[..., 0:2], tok.task[..., 3:5]], dim=-2)
    pick = w.argmax(-1)
    goal = wp.gather(2, pick[..., None, None].expand(-1, -1, 1, 2))[..., 0, :]
    goal = goal * w.sum(-1, keepdim=True).gt(0)  # none in view: stand still
    want = arrive_action(goal, tok.own[..., 0:2], max_speed=DRIVE_SPEED, gain=DRIVE_GAIN)
    want = want * learner._movable(obs)
    torch.testing.assert_close(act.detach(), want.detach())
    assert float(act.abs().max()) <= 1.0 + 1e-6
    assert bool((tok.target_mask[..., 0] & (act.abs().sum(-1) > 0)).any())
    # the driver's own constants, so that the taught head drives as its teacher
    assert (DRIVE_GAIN, DRIVE_SPEED) == (allocator.WaypointDriver().gain,
                                         allocator.WaypointDriver().max_speed)
    # a far-off candidate: the speed cap; the same one nearby: slower
    far = arrive_action(torch.tensor([[3.0, 4.0]]), torch.zeros(1, 2), max_speed=DRIVE_SPEED,
                        gain=DRIVE_GAIN)
    near = arrive_action(torch.tensor([[0.03, 0.04]]), torch.zeros(1, 2),
                         max_speed=DRIVE_SPEED, gain=DRIVE_GAIN)
    assert float(near.norm()) < float(far.norm())
    # the choice is trained through the weights; the action carries no gradient
    loss = -torch.log(w.clamp_min(1e-9)).mean()
    loss.backward()
    score = [p for n, p in learner.actor.named_parameters() if "score" in n]
    assert score and all(p.grad is not None and bool(p.grad.abs().sum() > 0) for p in score)
    assert not act.requires_grad
    # the same parameters as without it: a policy file trained without it loads
    plain = build_learner(algo, env.obs_dim, env.state_dim, env.num_agents, {"hidden": 16},
                          lifelong=True)
    plain.load_policy_tensors(learner.policy_tensors())


def _floor_after(steps: int, seed: int = 3) -> tuple[sim.LifelongEnv, torch.Tensor]:
    """warehouse-20 with 8 pickup and AGV slots after ``steps`` steps of random actions (the
    AGVs that ran into an open pickup carry its order, the others are idle)."""
    env = sim.make_env(sim.get_scenario("warehouse-20", k_pickups=8, k_agents=8), num_envs=2,
                       seed=seed)
    gen = torch.Generator().manual_seed(seed)
    obs = env.observe()
    for _ in range(steps):
        obs, *_ = env.step(torch.rand(2, env.num_agents, 2, generator=gen) * 2 - 1)
    return env, obs


def test_idle_token_hears_each_visible_agvs_status(floor):
    """``idle_token``: each AGV slot's sixth feature is the idle bit of the AGV at that
    position (told by it), and the pickups' margin counts only the idle AGVs."""
    from sim.orders import IDLE

    env, obs = _floor_after(60)
    status = env.agent_status
    assert bool((status == IDLE).any()) and bool((status != IDLE).any())
    lay = env.obs_layout
    plain = lifelong_tokens(obs, lay, floor)
    heard = lifelong_tokens(obs, lay, floor, idle_token=True)
    assert heard.agent.shape[-1] == AGENT_TOKEN_FEATURES + 1
    assert torch.equal(heard.agent[..., :-1], plain.agent)
    slots = obs[..., lay.agents].reshape(2, env.num_agents, 8, 5)
    pos = env.agent_pos
    checked = 0
    for b in range(2):
        for i in range(env.num_agents):
            for k in range(8):
                if slots[b, i, k, 4] < 0.5:
                    assert heard.agent[b, i, k, -1] == 0  # masked slot
                    continue
                j = int((pos[b] - pos[b, i] - slots[b, i, k, :2]).norm(dim=-1).argmin())
                assert j != i
                assert float(heard.agent[b, i, k, -1]) == float(status[b, j] == IDLE)
                checked += 1
    assert checked > 100
    # margin: the nearest idle AGV's distance to the pickup minus the AGV's own
    idle_rel = torch.where(heard.agent[..., -1:] > 0.5, heard.agent[..., :2],
                           torch.full_like(heard.agent[..., :2], 1e6))
    other = (heard.task[..., None, :2] - idle_rel[..., None, :, :]).norm(dim=-1).amin(-1)
    want = (other - heard.task[..., 2]).clamp(-1.0, 1.0) * heard.task_mask
    torch.testing.assert_close(heard.task[..., 6], want)
    assert not torch.equal(heard.task[..., 6], plain.task[..., 6])
    # renumbering the AGVs renumbers the bits
    perm = torch.randperm(env.num_agents, generator=torch.Generator().manual_seed(0))
    again = lifelong_tokens(obs[:, perm], lay, floor, idle_token=True)
    assert torch.equal(again.agent, heard.agent[:, perm])


@pytest.mark.parametrize("algo", ["maddpg-e", "bicnet-e"])
def test_idle_token_networks_start_from_a_lifelong_policy_without_it(algo):
    env, obs = _floor_after(30)
    sizes = (env.obs_dim, env.state_dim, env.num_agents)
    old = build_learner(algo, *sizes, {"hidden": 16, "waypoint_drive": True}, lifelong=True)
    new = build_learner(algo, *sizes, {"hidden": 16, "waypoint_drive": True,
                                       "idle_token": True}, lifelong=True)
    for learner in (old, new):
        learner.reset(env)
    new.load_policy_tensors(new.adapt_init_tensors(old.policy_tensors()))
    assert new.actor.encoder.agent[0].weight.shape[-1] == AGENT_TOKEN_FEATURES + 1
    assert float(new.actor.encoder.agent[0].weight[:, -1].detach().abs().sum()) == 0.0
    act, w = new.policy_and_choice(obs)
    assert act.shape == (2, env.num_agents, 2) and bool(torch.isfinite(act).all())
    with pytest.raises(ValueError, match="without idle_token cannot start from one with it"):
        old.adapt_init_tensors(new.policy_tensors())
    with pytest.raises(ValueError, match="idle_token is for lifelong floors"):
        epi = sim.make_env("6v6", num_envs=1, seed=0)
        build_learner(algo, epi.obs_dim, epi.state_dim, epi.num_agents,
                      {"hidden": 16, "idle_token": True}, lifelong=False)
    for bad in ("yes", 1, None):
        with pytest.raises(ValueError, match="idle_token"):
            make_config(algo, {"idle_token": bad})


@pytest.mark.parametrize("algo", ["maddpg-e", "bicnet-e"])
def test_drive_sight_heads_for_the_chosen_candidates_first_corner(algo):
    """``drive_sight``: the same choice as the token drive, but each AGV heads for the first
    corner of its chosen candidate's path (``FloorWaypoints.sight``); no parameter added."""
    env, obs = _floor_after(40, seed=5)
    sizes = (env.obs_dim, env.state_dim, env.num_agents)
    torch.manual_seed(0)
    token = build_learner(algo, *sizes, {"hidden": 16, "waypoint_drive": True},
                          lifelong=True)
    sight = build_learner(algo, *sizes, {"hidden": 16, "waypoint_drive": True,
                                         "drive_sight": True}, lifelong=True)
    sight.load_policy_tensors(token.policy_tensors())
    for learner in (token, sight):
        learner.reset(env)
    act, w = sight.policy_and_choice(obs)
    _, w_token = token.policy_and_choice(obs)
    torch.testing.assert_close(w, w_token)
    tok, _ = sight._read(obs)
    off = torch.cat([tok.target[..., 4:6], tok.task[..., 0:2]], dim=-2)
    mask = torch.cat([tok.target_mask, tok.task_mask], dim=-1)
    pick = w.argmax(-1)
    has = mask.gather(-1, pick.unsqueeze(-1)).squeeze(-1)
    chosen = off.gather(2, pick[..., None, None].expand(-1, -1, 1, 2))[..., 0, :]
    pos = obs[..., env.obs_layout.pos]
    goal = sight.floor.sight(pos, pos + chosen, has) - pos
    want = arrive_action(goal, tok.own[..., 0:2], max_speed=DRIVE_SPEED, gain=DRIVE_GAIN)
    torch.testing.assert_close(act.detach(), want * sight._movable(obs))
    assert not torch.equal(act, token.policy(obs))  # the corners differ from the waypoints
    for bad in ({"drive_sight": True}, {"drive_sight": 1, "waypoint_drive": True}):
        with pytest.raises(ValueError, match="drive_sight"):
            make_config(algo, bad)


def test_waypoint_drive_is_refused_where_it_cannot_drive():
    epi = sim.make_env("6v6", num_envs=1, seed=0)
    with pytest.raises(ValueError, match="waypoint_drive is for lifelong floors"):
        build_learner("maddpg-e", epi.obs_dim, epi.state_dim, epi.num_agents,
                      {"hidden": 16, "waypoint_drive": True}, lifelong=False)
    for bad in ("yes", 1, None):
        with pytest.raises(ValueError, match="waypoint_drive"):
            make_config("maddpg-e", {"waypoint_drive": bad})
    env = sim.make_env("warehouse-20", num_envs=1, seed=0)
    learner = build_learner("bicnet-e", env.obs_dim, env.state_dim, env.num_agents,
                            {"hidden": 16, "waypoint_drive": True}, lifelong=True)
    other = SimpleNamespace(obs_layout=env.obs_layout, world=SimpleNamespace(
        physics=dataclasses.replace(env.world.physics, damping=0.5)))
    with pytest.raises(ValueError, match="waypoint-drive actor drives with the default"):
        learner.reset(other)
