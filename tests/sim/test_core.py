"""The batched step: batch-versus-loop, determinism, bounds, claiming, bad input."""

import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

import sim
from sim.controllers import NearestTaskController, RandomController


def _rollout(env: sim.AGVEnv, actions: torch.Tensor) -> list[torch.Tensor]:
    out = []
    for a in actions:
        env.step(a)
        out.append(torch.cat([env.agent_pos, env.agent_vel], -1).clone())
    return out


@pytest.mark.parametrize("scenario", ["3v3", "6v6", "warehouse"])
def test_batch_equals_loop(scenario: str) -> None:
    B, T = 5, 20
    env = sim.make_env(scenario, num_envs=B, seed=3)
    n = env.num_agents
    start_a, start_t = env.agent_pos.clone(), env.task_pos.clone()
    gen = torch.Generator().manual_seed(0)
    actions = torch.rand(T, B, n, 2, generator=gen) * 2 - 1
    batched = _rollout(env, actions)
    for b in range(B):
        single = sim.make_env(scenario, num_envs=1, seed=99)
        single.set_state(start_a[b : b + 1], start_t[b : b + 1])
        traj = _rollout(single, actions[:, b : b + 1])
        for t in range(T):
            torch.testing.assert_close(traj[t][0], batched[t][b], atol=1e-6, rtol=0)


def test_same_seed_same_trajectories() -> None:
    trajs = []
    for _ in range(2):
        env = sim.make_env("6v6", num_envs=8, seed=42)
        ctrl = RandomController(seed=7)
        obs = env.reset()
        rec = []
        for _ in range(25):
            obs, r, d, _ = env.step(ctrl.act(obs))
            rec.append((env.agent_pos.clone(), r.clone()))
        trajs.append(rec)
    for (p1, r1), (p2, r2) in zip(*trajs, strict=True):
        assert torch.equal(p1, p2) and torch.equal(r1, r2)
    other = sim.make_env("6v6", num_envs=8, seed=43)
    assert not torch.equal(other.agent_pos, sim.make_env("6v6", num_envs=8, seed=42).agent_pos)


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), scale=st.floats(0.5, 1.0))
def test_agvs_stay_inside_walls_and_out_of_shelves(seed: int, scale: float) -> None:
    env = sim.make_env("warehouse", num_envs=16, seed=seed)
    gen = torch.Generator().manual_seed(seed)
    world = env.world
    for _ in range(60):
        a = (torch.rand(16, env.num_agents, 2, generator=gen) * 2 - 1) * scale
        env.step(torch.sign(a))  # full throttle, the hardest case for the walls
        pos = env.agent_pos.reshape(-1, 2).double().numpy()
        assert torch.isfinite(env.agent_pos).all()
        assert (world.wall_distance(pos) >= world.agent_radius - 1e-5).all()
        assert (world.obstacle_distance(pos) >= world.agent_radius - 1e-4).all()


def test_walls_hold_at_full_speed() -> None:
    env = sim.make_env("3v3", num_envs=4, seed=0)
    for _ in range(25):
        env.step(torch.ones(4, 3, 2))
    assert (env.agent_pos <= 1 - 0.15 + 1e-6).all()


def test_claiming_rules() -> None:
    env = sim.make_env("3v3", num_envs=1, seed=0)
    # AGV 0 and AGV 1 both next to task 0; AGV 0 is nearer and wins it.
    agents = torch.tensor([[[0.0, 0.05], [0.0, -0.08], [-0.8, -0.8]]])
    tasks = torch.tensor([[[0.0, 0.0], [0.7, 0.7], [-0.7, 0.7]]])
    env.set_state(agents, tasks)
    obs, _, done, info = env.step(torch.zeros(1, 3, 2))
    assert env.agent_task[0].tolist() == [0, -1, -1]
    assert info["claimed_now"][0].tolist() == [True, False, False]
    assert not done[0]
    assert torch.all(env.agent_vel[0, 0] == 0)
    # A claimed task leaves the observations: AGV 1's nearest task is now task 1 or 2.
    rel = obs[0, 1, 4:6]
    assert torch.allclose(rel, tasks[0, 1] - env.agent_pos[0, 1], atol=1e-6) or torch.allclose(
        rel, tasks[0, 2] - env.agent_pos[0, 1], atol=1e-6
    )
    visible = obs[0, 1, 4 : 4 + 9].reshape(3, 3)[:, 2]
    assert visible.tolist() == [1.0, 1.0, 0.0]
    # A parked AGV ignores actions and holds one task.
    pos0 = env.agent_pos[0, 0].clone()
    env.set_state(env.agent_pos, env.task_pos)  # a fresh episode from here ...
    env.task_pos[0, 1] = env.agent_pos[0, 0] + torch.tensor([0.5, 0.0])
    env.step(torch.zeros(1, 3, 2))
    assert env.agent_task[0, 0] == 0
    for _ in range(5):
        env.step(torch.ones(1, 3, 2))
    assert torch.equal(env.agent_pos[0, 0], pos0)
    assert env.agent_task[0, 0] == 0  # one task per AGV, never a second


def test_episode_ends_when_all_tasks_claimed() -> None:
    env = sim.make_env("3v3", num_envs=64, seed=1)
    ctrl = NearestTaskController(env.world.physics)
    obs = env.reset()
    done = torch.zeros(64, dtype=torch.bool)
    for _ in range(25):
        obs, r, done, _ = env.step(ctrl.act(obs))
    finished = env.task_claimed.all(1)
    assert finished.any()
    assert torch.all(env.steps[finished] < 25) or torch.all(done[finished])
    # A finished episode is frozen: another step changes nothing and rewards zero.
    before = env.agent_pos.clone()
    _, r, done2, _ = env.step(torch.ones(64, 3, 2))
    assert torch.equal(env.agent_pos[done], before[done])
    assert torch.all(r[done] == 0)
    assert torch.equal(done2, done)


def test_observation_padding_and_any_n() -> None:
    for name in ["1v1", "2v5", "10v4", "20v20"]:
        env = sim.make_env(name, num_envs=3, seed=0)
        obs = env.reset()
        assert obs.shape == (3, env.num_agents, env.obs_dim)
        assert torch.isfinite(obs).all()
        assert env.global_state().shape == (3, env.state_dim)


def test_partial_reset_touches_only_selected() -> None:
    env = sim.make_env("3v3", num_envs=4, seed=0)
    before = env.agent_pos.clone()
    env.reset(env_ids=torch.tensor([False, True, False, True]))
    assert torch.equal(env.agent_pos[[0, 2]], before[[0, 2]])
    assert not torch.equal(env.agent_pos[[1, 3]], before[[1, 3]])


def test_spawn_spacing() -> None:
    for name in ["3v3", "6v6", "warehouse", "12v12"]:
        env = sim.make_env(name, num_envs=256, seed=5)
        w = env.world
        da = torch.cdist(env.agent_pos, env.agent_pos) + torch.eye(env.num_agents) * 9
        dt = torch.cdist(env.task_pos, env.task_pos) + torch.eye(env.num_tasks) * 9
        assert da.min() >= 2 * w.agent_radius - 1e-5
        assert dt.min() >= w.task_spacing - 1e-5
        pts = torch.cat([env.agent_pos, env.task_pos], 1).reshape(-1, 2).double().numpy()
        assert w.is_free(pts, w.agent_radius - 1e-5).all()


@pytest.mark.parametrize(
    "bad, match",
    [
        (torch.zeros(2, 3), "shape"),
        (torch.zeros(2, 4, 2), "shape"),
        (torch.full((2, 3, 2), float("nan")), "NaN"),
        (torch.full((2, 3, 2), float("inf")), "NaN or infinite"),
    ],
)
def test_bad_actions(bad: torch.Tensor, match: str) -> None:
    env = sim.make_env("3v3", num_envs=2, seed=0)
    with pytest.raises(ValueError, match=match):
        env.step(bad)


def test_bad_world_and_scenario() -> None:
    with pytest.raises(ValueError, match="agent_radius"):
        sim.World(agent_radius=0.0)
    with pytest.raises(ValueError, match="do not enclose"):
        sim.World(bounds=(1, 1, -1, -1))
    with pytest.raises(ValueError, match="no room"):
        sim.make_env(sim.Scenario("full", sim.World(obstacles=np.array([[-0.9, -0.9, 0.9, 0.9]])),
                                  3, 3))
    with pytest.raises(ValueError, match="unknown scenario"):
        sim.make_env("7x7")
    with pytest.raises(ValueError, match="unknown reward"):
        sim.make_env("3v3", reward="nope")
    with pytest.raises(ValueError, match="unknown scenario option"):
        sim.make_env("3v3", max_step=3)
    env = sim.make_env("warehouse", num_envs=1)
    shelf = env.world.obstacles[0]
    inside = [(shelf[0] + shelf[2]) / 2, (shelf[1] + shelf[3]) / 2]
    with pytest.raises(ValueError, match="inside a shelf"):
        env.set_state(torch.tensor([[inside] + [[0.0, -1.4]] * 5]), env.task_pos)
    with pytest.raises(ValueError, match="outside the world"):
        env.set_state(env.agent_pos + 10, env.task_pos)


def test_handed_out_tensors_are_never_changed_later() -> None:
    # A training loop reads info after resetting the finished environments.
    env = sim.make_env("3v3", num_envs=4, seed=0)
    env.set_state(torch.tensor([[[0.0, 0.05], [0.5, -0.5], [-0.5, -0.5]]]).expand(4, 3, 2),
                  torch.tensor([[[0.0, 0.0], [0.7, 0.7], [-0.7, 0.7]]]).expand(4, 3, 2))
    _, _, _, info = env.step(torch.zeros(4, 3, 2))
    pos, claims = env.agent_pos, info["agent_task"].clone()
    before = pos.clone()
    env.reset(env_ids=[0, 2])
    assert torch.equal(info["agent_task"], claims)
    assert torch.equal(pos, before)


@pytest.mark.parametrize("native", [False, True])
def test_earlier_outputs_survive_claims_and_finishing(native: bool) -> None:
    # The fused step stops parked AGVs in the physics output and writes agent_task,
    # task_claimed and done to spare tensors: nothing handed out before may change.
    if native and not sim.native.available():
        pytest.skip("kernels unavailable")
    env = sim.make_env("3v3", num_envs=2, seed=0, native=native)
    env.set_state(torch.tensor([[[0.0, 0.03], [0.5, -0.5], [-0.5, -0.5]]]).expand(2, 3, 2),
                  torch.tensor([[[0.0, 0.0], [0.5, -0.45], [-0.5, -0.45]]]).expand(2, 3, 2),
                  agent_vel=torch.full((2, 3, 2), 0.3))
    held = [env.agent_vel, env.agent_task, env.task_claimed, env.done, env.steps]
    copies = [t.clone() for t in held]
    obs, reward, done, info = env.step(torch.zeros(2, 3, 2))
    assert int(info["claimed_now"].sum()) == 6 and done.all()  # every AGV claimed its task
    assert (env.agent_vel == 0).all()
    for t, c in zip(held, copies, strict=True):
        assert torch.equal(t, c)
    outputs = [obs, reward, done, info["agent_task"], info["claimed_now"],
               info["collisions_per_agent"], *info["reward_terms"].values()]
    snapshots = [t.clone() for t in outputs]
    env.step(torch.ones(2, 3, 2))
    env.reset()
    env.step(torch.ones(2, 3, 2))
    for t, c in zip(outputs, snapshots, strict=True):
        assert torch.equal(t, c)


@pytest.mark.parametrize("native", [False, True])
def test_out_of_range_actions_are_clipped_and_not_modified(native: bool) -> None:
    if native and not sim.native.available():
        pytest.skip("kernels unavailable")
    envs = [sim.make_env("3v3", num_envs=3, seed=1, native=native) for _ in range(2)]
    actions = torch.tensor([5.0, -7.0, 0.25]).repeat(3, 3, 1)[..., :2].contiguous()
    given = actions.clone()
    envs[0].step(actions)
    envs[1].step(actions.clamp(-1, 1))
    assert torch.equal(actions, given)
    assert torch.equal(envs[0].agent_pos, envs[1].agent_pos)
    assert torch.equal(envs[0].agent_vel, envs[1].agent_vel)


def test_rewards_without_the_promise_are_masked_in_finished_environments() -> None:
    def ones(state, ctx):
        return {"a": torch.ones(env.num_envs, env.num_agents),
                "b": torch.ones(env.num_envs, env.num_agents)}

    env = sim.make_env("3v3", num_envs=2, seed=0, reward=ones)
    env.steps = torch.tensor([env.max_steps - 1, 0])
    _, reward, done, _ = env.step(torch.zeros(2, 3, 2))
    assert done.tolist() == [True, False] and (reward == 2).all()
    _, reward, _, _ = env.step(torch.zeros(2, 3, 2))
    assert reward[0].tolist() == [0, 0, 0] and reward[1].tolist() == [2, 2, 2]


def test_nearest_task_controller_reads_the_task_slot_by_name_when_there_is_none() -> None:
    # With no task slots (k_tasks=0) the features after the own state are the other AGVs':
    # a controller reading obs[..., 4:7] chased an AGV as if it were a task.
    env = sim.make_env("3v3", num_envs=4, seed=0, k_tasks=0)
    ctrl = NearestTaskController(env.world.physics)
    ctrl.reset(env)
    obs = env.reset()
    assert obs[..., env.obs_layout.agents].abs().sum() > 0  # AGVs are visible
    assert torch.equal(ctrl.act(obs), torch.zeros(4, 3, 2))  # at rest, no task: no command
    # With task slots it drives at the nearest task, read through the layout.
    env = sim.make_env("3v3", num_envs=4, seed=0)
    ctrl.reset(env)
    obs = env.reset()
    lay = env.obs_layout
    action = ctrl.act(obs)
    toward = (action * obs[..., lay.task_rel(0)]).sum(-1)
    assert bool((toward[obs[..., lay.task_mask(0)][..., 0] > 0] > 0).all())


def test_contact_forces_stay_bounded_in_a_pile():
    """16 AGVs within 1e-6 of one point far from the origin: every contact force stays below
    the physical bound (15 neighbours x c x 2r); the matmul form with a 1/d scale gave 3e8."""
    from sim.physics import CONTACT_MIN_DISTANCE, contact_forces

    world = sim.get_scenario("warehouse-20").world
    ph = world.physics
    bound = 15 * ph.contact_force * (2 * world.agent_radius + ph.contact_margin)
    gen = torch.Generator().manual_seed(0)
    eye = torch.eye(16, dtype=torch.bool)
    for spread in (0.0, 1e-6, 1e-5, 1e-4, 1e-2):
        pos = torch.tensor([7.0, 5.0]) + (torch.rand(1, 16, 2, generator=gen) - 0.5) * spread
        dist = torch.cdist(pos, pos, compute_mode="donot_use_mm_for_euclid_dist")
        force = contact_forces(pos, dist, world, eye)
        assert torch.isfinite(force).all()
        assert float(force.norm(dim=-1).max()) <= bound
    # two AGVs at a normal contact distance: the force is MPE's, unchanged
    pos = torch.tensor([[[1.0, 1.0], [1.2, 1.0]]])
    dist = torch.cdist(pos, pos)
    force = contact_forces(pos, dist, world, torch.eye(2, dtype=torch.bool))
    k = ph.contact_margin
    want = ph.contact_force * k * math.log1p(math.exp((2 * world.agent_radius - 0.2) / k))
    assert abs(float(force[0, 1, 0]) - want) < 1e-3 * want and 0.2 > CONTACT_MIN_DISTANCE
