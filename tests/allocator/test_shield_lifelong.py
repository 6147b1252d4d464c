"""The safety shield's liveness rules (allocator/shield.py, ``liveness=``): on by default on
lifelong floors, off on episodic scenes (whose actions stay what they were)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import allocator
import sim
from allocator.avoidance import VelocityAvoidance
from allocator.avoidance.liveness import DeadlockResolver
from allocator.shield import SafetyShield
from sim.controllers import NearestTaskController
from sim.lifelong import lifelong_scenario
from tests.benchmarks.benchmark_scripts import load


def _bench():
    """``benchmarks/shield_lifelong.py`` (its scripted :class:`PathFollower`)."""
    return load("shield_lifelong")


class Swap:
    """Every AGV drives straight for where the AGV listed opposite it started: two AGVs on a
    line swap places, head on and perfectly symmetric (a scripted obs -> act controller)."""

    name = "swap"

    def reset(self, env) -> None:
        self.env = env
        self.goal = env.agent_pos.flip(1).clone()

    def act(self, obs: torch.Tensor) -> torch.Tensor:
        env = self.env
        v = (self.goal - env.agent_pos) * 4.0
        v = v * (1.2 / v.norm(dim=-1, keepdim=True).clamp_min(1.2))
        return ((v - 0.75 * env.agent_vel) / 0.5).clamp(-1, 1)


def _rollout(env, ctl, steps: int) -> tuple[torch.Tensor, int]:
    ctl.reset(env)
    obs = env.observe()
    actions, pairs = [], 0
    for _ in range(steps):
        a = ctl.act(obs)
        actions.append(a.clone())
        obs, _, _, info = env.step(a)
        pairs += int(info["collision_pairs"].sum())
        if bool(env.done.all()):
            break
    return torch.stack(actions), pairs


@pytest.mark.parametrize("controller", ["maddpg-ipf", "nearest"])
def test_episodic_actions_are_unchanged_by_default(controller: str) -> None:
    def make():
        return allocator.make("maddpg-ipf", scenario="3v3") if controller == "maddpg-ipf" \
            else NearestTaskController()

    runs = {}
    for live in (None, False, True):
        shield = SafetyShield(make(), liveness=live)
        runs[live] = _rollout(sim.make_env("3v3", num_envs=4, seed=3), shield, 30)[0]
        assert shield.live is (live is True) and (shield.resolver is None) is (live is not True)
        if live is not True:
            assert shield.interventions["liveness"] == 0
    assert torch.equal(runs[None], runs[False])  # bit for bit: the episodic path as before
    # forcing the rules on does change the actions, so the comparison above can fail
    assert runs[True].shape != runs[False].shape or not torch.equal(runs[True], runs[False])


def test_default_is_on_for_lifelong_floors_and_the_learned_allocator_gets_it() -> None:
    env = sim.make_env("warehouse-20", num_envs=1, seed=0)
    shield = SafetyShield(NearestTaskController(), seed=5)
    shield.reset(env)
    assert shield.live and isinstance(shield.resolver, DeadlockResolver)
    assert shield.interventions == {"any": 0, "qp": 0, "brake": 0, "liveness": 0, "detour": 0}
    off = SafetyShield(NearestTaskController(), liveness=False)
    off.reset(env)
    assert not off.live and off.resolver is None
    # a fresh resolver at every reset, with the shield's seed
    first = shield.resolver
    shield.reset(env)
    assert shield.resolver is not first
    assert np.array_equal(shield.resolver.priority, DeadlockResolver(1, 20, 0.15, seed=5).priority)
    learned = allocator.make("maddpg-ipf", scenario="3v3", shield=True)
    assert learned.safety.liveness is None  # the default reaches allocator.make(shield=True)


@pytest.mark.parametrize("row", [1.0, 3.0])  # the open front of the floor, a shelf aisle
def test_a_symmetric_head_on_swap_freezes_without_the_rules_and_passes_with_them(
        row: float) -> None:
    world = sim.make_env("warehouse-20", num_envs=1, seed=0).world
    ends = {}
    for live in (None, False):  # None: on, the env is lifelong
        env = sim.make_env(lifelong_scenario(world, 2, arrivals=sim.Poisson(1e-9)),
                           num_envs=1, seed=0)
        env.set_state(np.array([[[3.0, row], [4.6, row]]]))
        shield = SafetyShield(Swap(), liveness=live)
        _, pairs = _rollout(env, shield, 80)
        assert pairs == 0
        ends[live] = (env.agent_pos - shield.controller.goal).norm(dim=-1)
        assert int(env.released.sum()) == 0  # nothing but the two AGVs in play
    assert bool((ends[False] > 0.5).all())  # the QP and the brakes hold both, face to face
    assert bool((ends[None] < 0.05).all())  # the resolver breaks the tie: both arrive


def test_shielded_path_follower_delivers_on_a_lifelong_floor_without_overlaps() -> None:
    follower = _bench().PathFollower()
    shield = SafetyShield(follower)
    m = sim.evaluate_lifelong(shield, "warehouse-20", steps=300, seed=0)
    assert shield.live and shield.resolver is not None and shield.resolver.yields > 0
    assert m.delivered > 0
    assert m.collisions_per_1000 == 0
    assert shield.interventions["liveness"] > 0 and shield.agent_steps > 0


def test_the_qp_sees_shelves_and_walls_as_in_safe_driver() -> None:
    env = sim.make_env("warehouse-20", num_envs=1, seed=0)
    shield = SafetyShield(NearestTaskController())
    shield.reset(env)
    driver = allocator.SafeDriver()
    driver.reset(env)
    assert shield._avoid.world is env.world and driver._avoid.world is env.world
    assert shield._avoid.config.max_shelves == driver._avoid.config.max_shelves > 0
    x0, y0 = env.world.obstacles[0, :2]  # lower-left corner of a shelf
    r = env.world.agent_radius
    pos = np.array([[[x0 + 1.0, y0 - r - 0.02], [r + 0.02, 1.0]]])  # by a shelf, by a wall
    vel = np.zeros_like(pos)
    pref = np.array([[[0.0, 1.2], [-1.2, 0.0]]])  # straight into the shelf and the wall
    for qp in (shield._avoid, driver._avoid):  # 0.02 from each: slow down to about 0.04
        out = qp.solve(pos, vel, pref).velocity
        assert out[0, 0, 1] < 0.1 and out[0, 1, 0] > -0.1
    # without the world the same QP goes on at what one action reaches (0.5 from rest)
    blind = VelocityAvoidance(None, shield._avoid.config).solve(pos, vel, pref).velocity
    assert blind[0, 0, 1] > 0.4 and blind[0, 1, 0] < -0.4


def test_path_follower_bad_input() -> None:
    bench = _bench()
    with pytest.raises(ValueError, match="gain must be a finite number > 0"):
        bench.PathFollower(gain=0)
    with pytest.raises(ValueError, match="reset\\(env\\) must be called"):
        bench.PathFollower().act(torch.zeros(1, 1, 40))
    with pytest.raises(ValueError, match="lifelong floors"):
        bench.PathFollower().reset(sim.make_env("3v3", num_envs=1, seed=0))


def test_the_benchmark_runs_the_auction_at_both_ranges(tmp_path) -> None:
    """The decentralized reference rows: the auction with unlimited range (as the learned
    policies sense) and at 3.0, both driven by SafeDriver (0 overlaps); a bad name is refused."""
    bench = _bench()
    out = tmp_path / "t.md"
    table = bench.main(["--floor", "warehouse-20", "--steps", "40", "--seeds", "0", "1",
                        "--baselines", "auction", "auction-3", "--out", str(out)])
    assert [r["method"] for r in table] == ["auction (range inf) + SafeDriver",
                                            "auction (range 3) + SafeDriver"]
    assert all(r["overlaps"] == 0 and len(r["per_seed"]) == 2 for r in table)
    assert all(r["throughput"] == pytest.approx(sum(r["per_seed"]) / 2) for r in table)
    assert "auction (range 3) + SafeDriver" in out.read_text()
    for bad in (["--baselines", "nope"], ["--keep-right", "2"], ["--seeds", "-1"],
                ["--variants", "maybe"]):
        with pytest.raises(SystemExit):
            bench.main(bad + ["--out", str(out)])


def test_shield_keep_right_turns_the_intended_velocity_right() -> None:
    """keep_right (with the liveness rules) turns what the policy intends to the right; 0, the
    default, leaves it; a bad angle is refused."""
    from allocator import SafetyShield

    env = sim.make_env("warehouse-20", num_envs=1, seed=0)
    env.reset()
    toward_x = torch.zeros(1, env.num_agents, 2)
    toward_x[..., 0] = 1.0
    out = {}
    for angle in (0.0, 0.5):
        shield = SafetyShield(_Const(toward_x), qp=False, keep_right=angle)
        shield.reset(env)
        out[angle] = shield.filter(toward_x)
    movable = out[0.0].abs().sum(-1) > 0
    # driving along +x, turning right means a component along -y
    assert out[0.5][..., 1][movable].mean() < out[0.0][..., 1][movable].mean() - 0.05
    for bad in (-0.1, 1.6, float("nan"), True):
        with pytest.raises(ValueError, match="keep_right"):
            SafetyShield(_Const(toward_x), keep_right=bad)


class _Const:
    """A controller that always gives the same actions."""

    def __init__(self, actions: torch.Tensor) -> None:
        self.actions = actions

    def reset(self, env) -> None:
        pass

    def act(self, obs: torch.Tensor) -> torch.Tensor:
        return self.actions


def test_hungarians_choices_behind_the_shield_deliver_without_overlaps() -> None:
    """``ShieldedIntent``: a dispatcher's intentions through the shield, both action forms."""
    bench = _bench()
    for keep in (False, True):
        driver = bench.ShieldedIntent(keep_right=0.5, keep_direction=keep)
        ctl = allocator.HungarianDispatcher(driver=driver)
        m = sim.evaluate_lifelong(ctl, "warehouse-20", steps=200, seed=0)
        assert m.delivered > 0 and m.collisions_per_1000 == 0
        assert driver.shield.agent_steps > 0 and driver.shield.keep_right == 0.5
    env = sim.make_env("warehouse-20", num_envs=1, seed=0)
    driver = bench.ShieldedIntent(keep_direction=True)
    allocator.HungarianDispatcher(driver=driver).reset(env)
    a = driver.intent(env).numpy()
    assert np.abs(a).max() <= 1.0 + 1e-6
    plain = allocator.WaypointDriver()
    plain.reset(env)
    b = plain.act(env).numpy()
    free = np.abs(b).max(-1) < 1.0 - 1e-6  # the clipped action did not saturate: the same
    np.testing.assert_allclose(a[free], b[free], atol=1e-5)
    assert (~free).any()  # from rest every AGV with a target saturates
    # where it saturated, the direction-keeping action keeps the command's direction
    cmd = np.asarray(a[~free] / np.linalg.norm(a[~free], axis=-1, keepdims=True))
    clipped = b[~free] / np.linalg.norm(b[~free], axis=-1, keepdims=True)
    assert np.abs(a[~free]).max(-1).min() == pytest.approx(1.0)  # on the box's edge
    assert ((cmd * clipped).sum(-1) > 0.5).all()  # close to, not always equal to, the clip


def test_the_benchmark_runs_the_dagger_teacher_behind_the_shield(tmp_path) -> None:
    """``hungarian-plan``: Hungarian's plan kept to itself (the orders claimed by reaching
    them), behind the shield with the lanes asked for: it delivers, with 0 overlaps."""
    bench = _bench()
    out = tmp_path / "t.md"
    table = bench.main(["--floor", "warehouse-20", "--steps", "150", "--seeds", "0",
                        "--baselines", "hungarian-plan", "--keep-right", "0.5",
                        "--out", str(out)])
    assert [(r["method"], r["liveness"]) for r in table] == [
        ("hungarian's plan, not assigned (the DAgger teacher) + shield", "on, lanes 0.5 rad")]
    assert table[0]["overlaps"] == 0 and table[0]["throughput"] > 0


def test_the_benchmark_runs_the_local_teacher_behind_the_shield(tmp_path) -> None:
    bench = _bench()
    out = tmp_path / "t.md"
    table = bench.main(["--floor", "warehouse-20", "--steps", "120", "--seeds", "0",
                        "--baselines", "local-plan", "local-path-plan", "--keep-right", "0.5",
                        "--out", str(out)])
    assert [r["method"] for r in table] == [
        "each AGV's local assignment, 16 nearest (a teacher) + shield",
        "each AGV's local assignment, 16 nearest, priced by path (a teacher) + shield"]
    assert all(r["overlaps"] == 0 and r["throughput"] > 0 for r in table)


def test_view_widens_the_policy_files_rows_only(tmp_path, monkeypatch) -> None:
    """``--view K``: a policy file's row sees K pickups and AGVs, the baselines the floor's
    own; a bad K is refused."""
    from allocator.learned import any_n_weights_path

    seen = []
    run = sim.evaluate_lifelong

    def spy(ctl, scenario, **kw):
        seen.append(sim.get_scenario(scenario).k_pickups)
        return run(ctl, scenario, **kw)

    monkeypatch.setattr(sim, "evaluate_lifelong", spy)
    weights = str(any_n_weights_path("maddpg", "greedy", lifelong=True))
    _bench().main(["--steps", "10", "--weights", weights, "--variants", "lanes",
                   "--keep-right", "0.5", "--baselines", "fifo", "--view", "8",
                   "--out", str(tmp_path / "v.md")])
    assert seen == [8, 4]
    for bad in ("0", "-2", "x", "", str(10**9)):
        with pytest.raises(SystemExit):
            _bench().main(["--steps", "10", "--view", bad, "--out", str(tmp_path / "b.md")])
