"""The entity-token learners (``learners/entity.py``): shapes, masks, permutation invariance
over the tokens and equivariance over the AGVs, any-N forward, parameter counts independent of
N, the updates, bad input."""

from __future__ import annotations

import pytest
import torch

import sim
from learners.algorithms import ENTITY_ALGORITHMS, make_learner
from learners.entity import (
    AGENT_TOKEN_FEATURES,
    MARGIN_CLIP,
    TASK_TOKEN_FEATURES,
    EntityConfig,
    agent_order,
    infer_layout,
    tokens,
)
from sim.observations import AGENT_FEATURES, TASK_FEATURES, ObsLayout
from tests.learners.conftest import TINY, make_batch

ALGOS = list(ENTITY_ALGORITHMS)
VARIANTS = [pytest.param(a, {}, id=a) for a in ALGOS] + [
    pytest.param(a, {"choice_head": True}, id=f"{a}-choice") for a in ALGOS] + [
    pytest.param("bicnet-e", {"choice_head": True, "choice_rounds": 2},
                 id="bicnet-e-intents"),
    pytest.param("bicnet-e", {"choice_head": True, "choice_rounds": 2, "choice_sinkhorn": 5},
                 id="bicnet-e-sinkhorn")]
"""Every learner, with its MLP head and with the choice head (EntityConfig.choice_head);
BiCNet-E's also with two rounds of intent exchange (EntityConfig.choice_rounds), and with
those and the assignment exchange (EntityConfig.choice_sinkhorn)."""


def _obs(scenario: str, num_envs: int = 8, seed: int = 0, steps: int = 3) -> tuple:
    """Observations after a few random steps (AGVs moving, some tasks claimed)."""
    env = sim.make_env(scenario, num_envs=num_envs, seed=seed)
    obs = env.reset()
    gen = torch.Generator().manual_seed(seed)
    for _ in range(steps):
        obs, *_ = env.step(torch.rand(num_envs, env.num_agents, 2, generator=gen) * 2 - 1)
    return env, obs


def _learner(algo: str, env: sim.AGVEnv, **over) -> torch.nn.Module:
    torch.manual_seed(0)
    return make_learner(algo, env.obs_dim, env.state_dim, env.num_agents, {**TINY, **over})


def _permute_slots(obs: torch.Tensor, layout: ObsLayout, perm_t: torch.Tensor,
                   perm_a: torch.Tensor) -> torch.Tensor:
    out = obs.clone()
    B, N, _ = obs.shape
    t = obs[..., layout.tasks].reshape(B, N, layout.k_tasks, len(TASK_FEATURES))
    a = obs[..., layout.agents].reshape(B, N, layout.k_agents, len(AGENT_FEATURES))
    out[..., layout.tasks] = t[:, :, perm_t].reshape(B, N, -1)
    out[..., layout.agents] = a[:, :, perm_a].reshape(B, N, -1)
    return out


@pytest.mark.parametrize(("algo", "over"), VARIANTS)
def test_shapes_and_any_n_forward_with_one_set_of_weights(algo, over):
    env, obs = _obs("6v6")
    learner = _learner(algo, env, **over)
    n_params = sum(p.numel() for p in learner.parameters())
    for scenario in ("1v1", "2v3", "3v3", "6v6", "10v10", "20v20", "50v50"):
        e, o = _obs(scenario, num_envs=2, steps=1)
        learner.reset(e)
        a = learner.act(o)
        assert a.shape == (2, e.num_agents, 2) and torch.isfinite(a).all()
        assert a.abs().max() <= 1.0
        q = learner.q_values(o, a)
        assert q.shape == (2, e.num_agents) and torch.isfinite(q).all()
    # the weights do not depend on N
    other, _ = _obs("20v20", num_envs=1, steps=0)
    assert sum(p.numel() for p in _learner(algo, other, **over).parameters()) == n_params


@pytest.mark.parametrize(("algo", "over"), VARIANTS)
def test_padded_slots_do_not_change_the_output(algo, over):
    env, obs = _obs("3v3", num_envs=16, steps=6)  # some tasks claimed: masked task slots
    layout = env.obs_layout
    learner = _learner(algo, env, **over)
    base = learner.act(obs)
    q_base = learner.q_values(obs, base)
    masked_t = obs[..., layout.tasks].reshape(16, 3, layout.k_tasks, 3)[..., 2] < 0.5
    assert masked_t.any(), "the test needs masked task slots"
    # 1. garbage in the masked slots (their mask bit stays 0)
    noisy = obs.clone()
    gen = torch.Generator().manual_seed(3)
    t = noisy[..., layout.tasks].reshape(16, 3, layout.k_tasks, 3)
    garbage = torch.randn(t[..., :2].shape, generator=gen) * 5
    t[..., :2] = torch.where(masked_t.unsqueeze(-1), garbage, t[..., :2])
    noisy[..., layout.tasks] = t.reshape(16, 3, -1)
    assert not torch.equal(noisy, obs)
    assert torch.equal(learner.act(noisy), base)
    assert torch.equal(learner.q_values(noisy, base), q_base)
    # 2. more slots, all padding: the same scene read with K = 6 task and 5 AGV slots
    wide = ObsLayout(6, 5)
    padded = torch.zeros(16, 3, wide.size)
    padded[..., wide.vel] = obs[..., layout.vel]
    padded[..., wide.pos] = obs[..., layout.pos]
    padded[..., wide.holding] = obs[..., layout.holding]
    padded[..., wide.tasks.start:wide.tasks.start + 3 * layout.k_tasks] = obs[..., layout.tasks]
    padded[..., wide.agents.start:wide.agents.start + 5 * layout.k_agents] = \
        obs[..., layout.agents]
    learner.set_layout(wide)
    torch.testing.assert_close(learner.act(padded), base, rtol=0, atol=1e-6)
    torch.testing.assert_close(learner.q_values(padded, base), q_base, rtol=0, atol=1e-5)


@pytest.mark.parametrize(("algo", "over"), VARIANTS)
def test_the_order_of_the_token_slots_does_not_matter(algo, over):
    env, obs = _obs("6v6", num_envs=16, steps=4)
    layout = env.obs_layout
    learner = _learner(algo, env, **over)
    a = learner.act(obs)
    q = learner.q_values(obs, a)
    for seed in range(3):
        gen = torch.Generator().manual_seed(seed)
        perm_t = torch.randperm(layout.k_tasks, generator=gen)
        perm_a = torch.randperm(layout.k_agents, generator=gen)
        shuffled = _permute_slots(obs, layout, perm_t, perm_a)
        assert not torch.equal(shuffled, obs)
        torch.testing.assert_close(learner.act(shuffled), a, rtol=0, atol=1e-6)
        torch.testing.assert_close(learner.q_values(shuffled, a), q, rtol=0, atol=1e-5)


@pytest.mark.parametrize(("algo", "over"), VARIANTS)
def test_renumbering_the_agvs_renumbers_the_actions(algo, over):
    """Equivariance over AGV indices: MADDPG-E trivially, BiCNet-E because its recurrence
    orders the AGVs by position, not by index."""
    env, obs = _obs("10v10", num_envs=4, steps=2)
    learner = _learner(algo, env, **over)
    a = learner.act(obs)
    q = learner.q_values(obs, a)
    perm = torch.randperm(10, generator=torch.Generator().manual_seed(1))
    torch.testing.assert_close(learner.act(obs[:, perm]), a[:, perm], rtol=0, atol=1e-6)
    torch.testing.assert_close(learner.q_values(obs[:, perm], a[:, perm]), q[:, perm],
                               rtol=0, atol=1e-5)


def test_bicnet_e_communicates_and_maddpg_e_actor_does_not():
    env, obs = _obs("6v6", num_envs=4, steps=2)
    moved = obs.clone()
    moved[:, 5, env.obs_layout.vel] += 0.3  # AGV 5's own velocity: only its own input
    for algo, shared in (("maddpg-e", False), ("bicnet-e", True)):
        learner = _learner(algo, env)
        a, b = learner.act(obs), learner.act(moved)
        assert not torch.equal(a[:, 5], b[:, 5])
        assert torch.equal(a[:, :5], b[:, :5]) is not shared, algo
        # both critics are centralized: AGV 0's Q depends on AGV 5's observation
        assert not torch.equal(learner.q_values(obs, a)[:, 0], learner.q_values(moved, a)[:, 0])


def test_tokens_features_and_margin():
    layout = ObsLayout(2, 1)
    obs = torch.zeros(1, 1, layout.size)
    obs[0, 0, layout.vel] = torch.tensor([0.1, -0.2])
    obs[0, 0, layout.task_rel(0)] = torch.tensor([0.3, 0.4])  # distance 0.5
    obs[0, 0, layout.task_mask(0)] = 1.0
    obs[0, 0, layout.agent_rel(0)] = torch.tensor([0.3, 0.0])  # 0.4 from task 0
    obs[0, 0, layout.agent_mask(0)] = 1.0
    tok = tokens(obs, layout)
    assert tok.own.shape == (1, 1, 3) and tok.task.shape == (1, 1, 2, TASK_TOKEN_FEATURES)
    assert tok.agent.shape == (1, 1, 1, AGENT_TOKEN_FEATURES)
    torch.testing.assert_close(tok.task[0, 0, 0], torch.tensor([0.3, 0.4, 0.5, -0.1, 1.0]))
    assert torch.equal(tok.task[0, 0, 1], torch.zeros(5))  # padded slot: all zero
    assert tok.task_mask.tolist() == [[[True, False]]]
    obs[0, 0, layout.agent_mask(0)] = 0.0  # no other AGV visible: margin +clip, seen 0
    tok = tokens(obs, layout)
    assert tok.task[0, 0, 0, 3] == MARGIN_CLIP and tok.task[0, 0, 0, 4] == 0
    assert torch.equal(tok.agent, torch.zeros(1, 1, 1, AGENT_TOKEN_FEATURES))


def test_margin_moving_leaves_out_agvs_that_stand_still():
    # the visible AGV is 0.4 from task 0, nearer than this AGV (0.5), but stands still (parked)
    layout = ObsLayout(1, 1)
    obs = torch.zeros(1, 1, layout.size)
    obs[0, 0, layout.task_rel(0)] = torch.tensor([0.3, 0.4])
    obs[0, 0, layout.task_mask(0)] = 1.0
    obs[0, 0, layout.agent_rel(0)] = torch.tensor([0.3, 0.0])
    obs[0, 0, layout.agent_mask(0)] = 1.0
    every = tokens(obs, layout)
    moving = tokens(obs, layout, margin_moving=True)
    assert every.task[0, 0, 0, 3:].tolist() == pytest.approx([-0.1, 1.0])
    assert moving.task[0, 0, 0, 3:].tolist() == [MARGIN_CLIP, 0.0]
    assert torch.equal(moving.agent, every.agent) and torch.equal(moving.own, every.own)
    obs[0, 0, layout.agent_vel(0)] = torch.tensor([0.0, 0.2])  # now it moves: it counts
    torch.testing.assert_close(tokens(obs, layout, margin_moving=True).task,
                               tokens(obs, layout).task)


@pytest.mark.parametrize("algo", ALGOS)
def test_the_learner_reads_tokens_with_its_margin_setting(algo):
    env, obs = _obs("6v6", steps=12)  # some AGVs parked by now (velocity exactly 0)
    assert bool((env.agent_task >= 0).any())
    for flag in (False, True):
        learner = _learner(algo, env, margin_moving=flag)
        got = learner._read(obs)[0].task
        assert torch.equal(got, tokens(obs, infer_layout(6, obs.shape[-1]), flag).task)
    assert not torch.equal(tokens(obs, infer_layout(6, obs.shape[-1]), True).task,
                           tokens(obs, infer_layout(6, obs.shape[-1])).task)
    with pytest.raises(ValueError, match="margin_moving"):
        _learner(algo, env, margin_moving="yes")


def test_parked_token_marks_the_visible_agvs_that_stand_still():
    layout = ObsLayout(1, 3)
    obs = torch.zeros(1, 1, layout.size)
    obs[0, 0, layout.agent_rel(0)] = torch.tensor([0.3, 0.0])  # visible, still: parked
    obs[0, 0, layout.agent_rel(1)] = torch.tensor([0.0, 0.4])  # visible, moving
    obs[0, 0, layout.agent_vel(1)] = torch.tensor([0.1, 0.0])
    for i in (0, 1):
        obs[0, 0, layout.agent_mask(i)] = 1.0  # slot 2 stays padding (mask 0)
    plain, flagged = tokens(obs, layout), tokens(obs, layout, parked_token=True)
    assert plain.agent.shape[-1] == AGENT_TOKEN_FEATURES
    assert flagged.agent.shape[-1] == AGENT_TOKEN_FEATURES + 1
    assert flagged.agent[0, 0, :, -1].tolist() == [1.0, 0.0, 0.0]
    assert torch.equal(flagged.agent[..., :-1], plain.agent)
    assert torch.equal(flagged.task, plain.task) and torch.equal(flagged.own, plain.own)


@pytest.mark.parametrize("algo", ALGOS)
def test_parked_token_networks_start_from_weights_without_it(algo):
    env, obs = _obs("6v6", steps=12)  # some AGVs parked by now (velocity exactly 0)
    assert bool(tokens(obs, env.obs_layout, parked_token=True).agent[..., -1].any())
    old = _learner(algo, env)
    a_old = old.act(obs)
    q_old = old.q_values(obs, a_old)
    new = _learner(algo, env, parked_token=True)
    assert new._read(obs)[0].agent.shape[-1] == AGENT_TOKEN_FEATURES + 1
    new.load_training_tensors(new.adapt_init_tensors(old.training_tensors()))
    # the parked bit's column starts at zero: the same actions and Q values
    torch.testing.assert_close(new.act(obs), a_old, rtol=0, atol=1e-6)
    torch.testing.assert_close(new.q_values(obs, a_old), q_old, rtol=0, atol=1e-5)
    assert new.updates == old.updates
    deployed = _learner(algo, env, parked_token=True)
    deployed.load_policy_tensors(deployed.adapt_init_tensors(old.policy_tensors()))
    torch.testing.assert_close(deployed.act(obs), a_old, rtol=0, atol=1e-6)
    # the new column learns, and the Adam moments fit
    _, batch = make_batch("6v6", num_envs=32, reward="ipf")
    for _ in range(3):
        new.update(batch)
    assert new.critic.encoder.agent[0].weight[:, -1].abs().sum() > 0
    assert new.adapt_init_tensors(new.training_tensors()).keys() == \
        new.training_tensors().keys()  # already wide: unchanged
    with pytest.raises(ValueError, match="without parked_token cannot start from one with it"):
        old.adapt_init_tensors(new.training_tensors())
    with pytest.raises(ValueError, match="parked_token"):
        _learner(algo, env, parked_token=1)


def test_agent_order_is_by_x_then_y():
    layout = ObsLayout(0, 0)
    obs = torch.zeros(1, 4, layout.size)
    obs[0, :, layout.pos] = torch.tensor([[0.5, 0.0], [-0.5, 1.0], [-0.5, -1.0], [0.1, 0.0]])
    assert agent_order(obs, layout).tolist() == [[2, 1, 3, 0]]


@pytest.mark.parametrize(("algo", "over"), VARIANTS)
def test_updates_change_the_weights_and_keep_them_finite(algo, over):
    env, batch = make_batch("6v6", num_envs=32, reward="ipf")
    learner = _learner(algo, env, **over)
    before = {k: v.clone() for k, v in learner.training_tensors().items()}
    for _ in range(3):
        out = learner.update(batch)
    assert set(out) == {"critic_loss", "actor_loss", "q"}
    after = learner.training_tensors()
    assert all(torch.isfinite(v).all() for v in after.values() if v.is_floating_point())
    for prefix in ("actor.", "critic."):
        assert any(not torch.equal(before[k], after[k]) for k in after if k.startswith(prefix))
    # the same batches on another N: the same weights keep training
    env3, batch3 = make_batch("3v3", num_envs=32, reward="ipf")
    learner.update(batch3)
    assert learner.updates == 4


def test_layout_inference_and_bad_input():
    assert infer_layout(3, 24) == ObsLayout(3, 2)
    assert infer_layout(50, 48) == ObsLayout(6, 5)
    with pytest.raises(ValueError, match="cannot read observations of size 25"):
        infer_layout(3, 25)
    env, obs = _obs("3v3", num_envs=2, steps=0)
    learner = _learner("maddpg-e", env)
    with pytest.raises(ValueError, match="cannot read observations"):
        learner.act(obs[..., :-1])
    with pytest.raises(ValueError, match=r"shape \(B, N, O\)"):
        learner.act(obs[0])
    with pytest.raises(ValueError, match="ObsLayout"):
        learner.set_layout((3, 2))
    with pytest.raises(ValueError, match="lifelong|ObsLayout"):
        learner.reset(sim.make_env("warehouse-20", num_envs=1, seed=0))
    with pytest.raises(ValueError, match="shield"):
        EntityConfig(shield="yes")
    with pytest.raises(ValueError, match="hidden"):
        EntityConfig(hidden=0)


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -1.0, "1", None, True])
def test_shield_penalty_is_checked(bad):
    from learners.entity import BiCNetEConfig

    with pytest.raises(ValueError, match="shield_penalty"):
        BiCNetEConfig(shield=True, shield_penalty=bad).validate()
    BiCNetEConfig(shield=True, shield_penalty=1e6).validate()  # huge but finite: allowed


# ---------------------------------------------------------------------- the choice head
def test_arrive_action_reaches_a_near_goal_in_one_step_and_keeps_direction_far_away():
    from learners.entity import EPISODIC_PHYSICS, arrive_action

    ph = EPISODIC_PHYSICS
    gain = ph.sensitivity * ph.dt / ph.mass
    vel = torch.tensor([[0.3, -0.2]], dtype=torch.float64)
    near = torch.tensor([[0.05, 0.02]], dtype=torch.float64)
    a = arrive_action(near, vel)
    assert a.abs().max() < 1.0  # not scaled: the command is met exactly
    new_vel = vel * (1 - ph.damping) + a * gain
    torch.testing.assert_close(new_vel * ph.dt, near)  # on the goal after one step
    far = torch.tensor([[3.0, 4.0]], dtype=torch.float64)
    a = arrive_action(far, torch.zeros(1, 2, dtype=torch.float64))
    assert a.abs().max() == 1.0
    torch.testing.assert_close(a / a.norm(), far / far.norm())  # scaled, not clipped
    assert torch.equal(arrive_action(torch.zeros(1, 2), torch.zeros(1, 2)), torch.zeros(1, 2))


@pytest.mark.parametrize("algo", ALGOS)
def test_choice_head_points_at_the_visible_tasks_and_starts_near_first(algo):
    env, obs = _obs("6v6", num_envs=16, steps=6)  # some tasks claimed: masked slots
    learner = _learner(algo, env, choice_head=True)
    act, w = learner.policy_and_choice(obs)
    assert act.shape == (16, 6, 2) and w.shape == (16, 6, env.obs_layout.k_tasks)
    assert act.abs().max() <= 1.0
    torch.testing.assert_close(learner.act(obs), act.detach())
    tok = tokens(obs, env.obs_layout)
    assert torch.equal(w[~tok.task_mask], torch.zeros_like(w[~tok.task_mask]))
    seen = tok.task_mask.any(-1)
    torch.testing.assert_close(w.sum(-1)[seen], torch.ones(int(seen.sum())))
    # untrained, the pointer prefers the nearest visible task for most AGVs
    dist = tok.task[..., 2].masked_fill(~tok.task_mask, float("inf"))
    agree = (w.argmax(-1) == dist.argmin(-1))[seen].float().mean()
    assert agree > 0.7
    # the pointer carries the gradient to the encoder (what a cross-entropy trains)
    torch.log(w[seen].amax(-1)).sum().backward()
    assert learner.actor.encoder.task[0].weight.grad.abs().sum() > 0


@pytest.mark.parametrize("algo", ALGOS)
def test_choice_head_bad_uses_are_clear_errors(algo):
    env, obs = _obs("3v3", num_envs=2, steps=0)
    with pytest.raises(ValueError, match="needs a choice-head actor"):
        _learner(algo, env).policy_and_choice(obs)
    with pytest.raises(ValueError, match="choice_head"):
        EntityConfig(choice_head="yes")
    floor = sim.make_env("warehouse-20", num_envs=1, seed=0)
    with pytest.raises(ValueError, match="choice_head is for episodic"):
        make_learner(algo, floor.obs_dim, floor.state_dim, floor.num_agents,
                     {**TINY, "choice_head": True})
    import dataclasses

    from sim.world import Physics

    learner = _learner(algo, env, choice_head=True)
    learner.reset(env)  # the default physics: accepted
    scen = sim.get_scenario("3v3")
    slow = dataclasses.replace(scen, world=dataclasses.replace(
        scen.world, physics=Physics(damping=0.5)))
    with pytest.raises(ValueError, match="default physics"):
        learner.reset(sim.make_env(slow, num_envs=1, seed=0))


# ---------------------------------------------------------------------- the intent exchange
def _stir_intents(learner: torch.nn.Module) -> None:
    """Give the (zero-started) intent layer weights that change the pointer."""
    gen = torch.Generator().manual_seed(1)
    with torch.no_grad():
        for p in learner.actor.choose.intent.parameters():
            p.copy_(torch.randn(p.shape, generator=gen) * 3)


def _scene(agents: list[tuple[float, float]], tasks: list[tuple[float, float]],
           parked: tuple[int, ...] = (), k_agents: int | None = None):
    """Observations of one hand-placed episodic scene (AGVs at rest, all tasks open but
    those the ``parked`` AGVs hold), full view unless ``k_agents``."""
    n = len(agents)
    scen = sim.get_scenario(f"{n}v{len(tasks)}", k_tasks=len(tasks),
                            k_agents=n - 1 if k_agents is None else k_agents)
    env = sim.make_env(scen, num_envs=1, seed=0)
    env.reset()
    env._agent_pos[0] = torch.tensor(agents, dtype=env.dtype)
    env._agent_vel.zero_()
    env._task_pos[0] = torch.tensor(tasks, dtype=env.dtype)
    for i in parked:
        env._agent_task[0, i] = i
        env._task_claimed[0, i] = True
        env._agent_pos[0, i] = env._task_pos[0, i]
    return env, env.observe()


def test_intents_count_who_points_at_each_task_and_who_is_nearer():
    from learners.entity import _Intents

    # AGVs 0, 1 and 2 on a line; the tasks at x = 0.5 and x = 1.5
    env, obs = _scene([(0.0, 0.0), (0.4, 0.0), (1.0, 0.0)], [(0.5, 0.0), (1.5, 0.0), (-1, 1)])
    tok = tokens(obs, env.obs_layout)
    heard = _Intents(tok)
    assert heard.hears[0].sum().item() == 6  # every idle AGV hears the two others
    # every pointer on the task at x = 0.5 (slot order differs per AGV: find it by position)
    at = heard.tasks[0]  # (N, Kt, 2)
    target = torch.tensor([0.5, 0.0], dtype=at.dtype)
    slot = torch.linalg.vector_norm(at - target, dim=-1).argmin(-1)
    w = torch.nn.functional.one_hot(slot, at.shape[1]).to(obs.dtype).unsqueeze(0)
    f = heard.features(w)[0]  # (N, Kt, 2): any, nearer
    got = f[torch.arange(3), slot]
    # AGV 0 (0.5 away) hears 2 pointers, both nearer (0.1 and 0.5: 0.5 is not < 0.5);
    torch.testing.assert_close(got, torch.tensor([[2.0, 1.0], [2.0, 0.0], [2.0, 1.0]],
                                                 dtype=got.dtype))
    # no pointer on the other tasks
    other = torch.ones_like(f[..., 0], dtype=torch.bool)
    other[torch.arange(3), slot] = False
    assert f[other].abs().sum() == 0


def test_intent_regrets_say_how_much_the_nearer_pointer_would_lose():
    from learners.entity import REGRET_CAP, _Intents

    # AGVs at x = 0 and 0.4 both point at the task at x = 0.5 (0.5 and 0.1 away); AGV 0's
    # second task is 1.0 away (regret 0.5), AGV 1's 0.78 away (regret 0.68)
    env, obs = _scene([(0.0, 0.0), (0.4, 0.0)], [(0.5, 0.0), (-1.0, 0.0), (1.0, 0.5)])
    tok = tokens(obs, env.obs_layout)
    heard = _Intents(tok, regret=True)
    at = heard.tasks[0]
    dist = tok.task[0, :, :, 2]
    order = dist.argsort(-1)  # each AGV's slots, nearest first
    # pointers mostly on the nearest task, a little on the second nearest
    w = torch.zeros_like(dist)
    w[torch.arange(2), order[:, 0]] = 0.7
    w[torch.arange(2), order[:, 1]] = 0.2
    w[torch.arange(2), order[:, 2]] = 0.1
    f = heard.features(w.unsqueeze(0))[0]  # (N, Kt, 4)
    assert f.shape[-1] == 4
    target = torch.tensor([0.5, 0.0], dtype=at.dtype)
    slot = torch.linalg.vector_norm(at - target, dim=-1).argmin(-1)
    own = dist.sort(-1).values
    regret = (own[:, 1] - own[:, 0]).clamp(0, REGRET_CAP)
    torch.testing.assert_close(regret, torch.tensor([0.5, 0.61 ** 0.5 - 0.1], dtype=regret.dtype))
    got = f[torch.arange(2), slot]
    # AGV 0 hears AGV 1 (nearer) with its regret; AGV 1 hears nobody nearer: the cap
    torch.testing.assert_close(got[0], torch.stack([torch.tensor(1.0, dtype=got.dtype),
                                                    torch.tensor(1.0, dtype=got.dtype),
                                                    regret[1], regret[0]]))
    torch.testing.assert_close(got[1], torch.stack([torch.tensor(1.0, dtype=got.dtype),
                                                    torch.tensor(0.0, dtype=got.dtype),
                                                    torch.tensor(REGRET_CAP, dtype=got.dtype),
                                                    regret[1]]))
    # every slot carries the AGV's own regret; the counts are those without regrets
    torch.testing.assert_close(f[..., 3], regret.unsqueeze(-1).expand(2, 3))
    torch.testing.assert_close(f[..., :2], _Intents(tok).features(w.unsqueeze(0))[0])


def test_an_agv_with_one_task_in_view_has_the_capped_regret():
    from learners.entity import REGRET_CAP, _Intents

    env, obs = _scene([(0.0, 0.0), (0.4, 0.0)], [(0.5, 0.0)])
    tok = tokens(obs, env.obs_layout)
    f = _Intents(tok, regret=True).features(torch.ones(1, 2, 1, dtype=obs.dtype))[0]
    torch.testing.assert_close(f[:, 0, 3], torch.full((2,), REGRET_CAP, dtype=f.dtype))
    torch.testing.assert_close(f[0, 0, 2], torch.tensor(REGRET_CAP, dtype=f.dtype))


def test_intents_leave_out_parked_agvs_and_those_out_of_view():
    from learners.entity import _Intents

    env, obs = _scene([(0.0, 0.0), (0.3, 0.0), (1.2, 0.0)], [(0.5, 0.0), (0.6, 0.6), (1.0, 1.0)],
                      parked=(2,))
    heard = _Intents(tokens(obs, env.obs_layout))
    assert not heard.hears[0, :, 2].any()  # nobody hears the parked AGV
    assert heard.hears[0, 0, 1] and heard.hears[0, 1, 0]
    # a one-slot view: AGV 2 (idle now) sees only its nearest AGV, 1
    env, obs = _scene([(0.0, 0.0), (0.9, 0.0), (1.2, 0.0)], [(0.5, 0.0), (0.6, 0.6), (1, 1)],
                      k_agents=1)
    heard = _Intents(tokens(obs, env.obs_layout))
    assert heard.hears[0, 2].tolist() == [False, True, False]
    assert heard.hears[0, 0].tolist() == [False, True, False]


def test_intent_exchange_starts_as_none_and_stays_equivariant_once_trained():
    env, obs = _obs("6v6", num_envs=8, steps=4)
    plain = _learner("bicnet-e", env, choice_head=True)
    talk = _learner("bicnet-e", env, choice_head=True, choice_rounds=2)
    talk.load_state_dict(plain.state_dict(), strict=False)  # all but the intent layer
    a0, w0 = plain.policy_and_choice(obs)
    a1, w1 = talk.policy_and_choice(obs)
    torch.testing.assert_close(a1, a0)  # zero-started: no change
    torch.testing.assert_close(w1, w0)
    _stir_intents(talk)
    a2, w2 = talk.policy_and_choice(obs)
    assert not torch.allclose(w2, w0)
    # the AGVs' order does not matter (BiCNet-E sorts them itself)
    perm = torch.randperm(6, generator=torch.Generator().manual_seed(3))
    layout = env.obs_layout
    a3, w3 = talk.policy_and_choice(obs[:, perm])
    torch.testing.assert_close(a3, a2[:, perm], atol=1e-5, rtol=1e-4)
    # nor the order of the task and AGV slots
    pt = torch.randperm(layout.k_tasks, generator=torch.Generator().manual_seed(4))
    pa = torch.randperm(layout.k_agents, generator=torch.Generator().manual_seed(5))
    a4, w4 = talk.policy_and_choice(_permute_slots(obs, layout, pt, pa))
    torch.testing.assert_close(a4, a2, atol=1e-5, rtol=1e-4)
    torch.testing.assert_close(w4, w2[..., pt], atol=1e-5, rtol=1e-4)
    # the cross-entropy trains the intent layer
    torch.log(w2.amax(-1).clamp_min(1e-9)).sum().backward()
    assert talk.actor.choose.intent[0].weight.grad.abs().sum() > 0


class _ConstantBias(torch.nn.Module):
    """An intent layer that ignores what it hears: the same bias every round."""

    def __init__(self, bias: torch.Tensor) -> None:
        super().__init__()
        self.bias = bias

    def forward(self, heard: torch.Tensor) -> torch.Tensor:
        return self.bias.expand(*heard.shape[:-1], 1)


def test_accumulated_rounds_add_their_biases_up():
    from learners.entity import TaskChoiceHead

    env, obs = _obs("6v6", num_envs=2, steps=2)
    tok = tokens(obs, env.obs_layout)
    B, N, K = tok.task_mask.shape
    gen = torch.Generator().manual_seed(1)
    h, emb = torch.randn(B, N, 16, generator=gen), torch.randn(B, N, K, 16, generator=gen)
    bias = torch.randn(B, N, K, 1, generator=gen)
    heads = {}
    for name, rounds, accumulate, b in (("acc", 3, True, bias), ("once", 1, False, 3 * bias),
                                        ("replace", 3, False, bias)):
        torch.manual_seed(0)
        heads[name] = TaskChoiceHead(16, rounds, accumulate=accumulate)
        heads[name].intent = _ConstantBias(b)
    _, w_acc = heads["acc"](h, emb, tok)
    _, w_once = heads["once"](h, emb, tok)
    _, w_replace = heads["replace"](h, emb, tok)
    torch.testing.assert_close(w_acc, w_once)  # three rounds of b: one of 3b
    assert not torch.allclose(w_acc, w_replace)


def test_choice_rounds_bad_values_are_clear_errors():
    env, _ = _obs("3v3", num_envs=1, steps=0)
    for bad in (-1, 9, 1.5, True, "2"):
        with pytest.raises(ValueError, match="choice_rounds"):
            EntityConfig(choice_head=True, choice_rounds=bad)
    with pytest.raises(ValueError, match="needs choice_head=True"):
        EntityConfig(choice_rounds=1)
    with pytest.raises(ValueError, match="choice_rounds >= 1"):
        EntityConfig(choice_head=True, choice_regret=True)
    with pytest.raises(ValueError, match="choice_regret"):
        EntityConfig(choice_head=True, choice_rounds=1, choice_regret=1)
    with pytest.raises(ValueError, match="choice_rounds >= 2"):
        EntityConfig(choice_head=True, choice_rounds=1, choice_accumulate=True)
    with pytest.raises(ValueError, match="choice_accumulate"):
        EntityConfig(choice_head=True, choice_rounds=2, choice_accumulate="yes")
    with pytest.raises(ValueError, match="MADDPG-E"):
        _learner("maddpg-e", env, choice_head=True, choice_rounds=1)


def test_intent_policy_round_trips_through_a_policy_file(tmp_path):
    from learners.checkpoint import load_checkpoint, save_checkpoint

    env, obs = _obs("6v6", num_envs=4, steps=3)
    learner = _learner("bicnet-e", env, choice_head=True, choice_rounds=1)
    _stir_intents(learner)
    import dataclasses

    save_checkpoint(tmp_path / "p.safetensors", learner.policy_tensors(),
                    {"kind": "policy", "algo": "bicnet-e", "reward": "ipf",
                     "scenario": "6v6", "num_agents": 6, "num_tasks": 6,
                     "obs_dim": env.obs_dim, "state_dim": env.state_dim,
                     "config": dataclasses.asdict(learner.config)})
    tensors, meta = load_checkpoint(tmp_path / "p.safetensors", kind="policy")
    assert meta["config"]["choice_rounds"] == 1
    again = make_learner("bicnet-e", env.obs_dim, env.state_dim, 6, meta["config"])
    again.load_policy_tensors(tensors)
    torch.testing.assert_close(again.act(obs), learner.act(obs))


# ---------------------------------------------------------------------- the assignment exchange
def test_task_groups_tell_tasks_apart_by_position_across_agvs():
    from learners.entity import _task_groups

    env, obs = _obs("20v20", num_envs=3, steps=5)
    tok = tokens(obs, env.obs_layout)
    B, N, K = tok.task_mask.shape
    ids = _task_groups(tok.pos.unsqueeze(-2) + tok.task[..., 0:2], tok.task_mask)
    assert ids.shape == (B, N, K)
    assert (ids[~tok.task_mask] == N * K).all()
    for b in range(B):
        # the env's index of the task in each visible slot
        at = tok.pos[b].unsqueeze(-2) + tok.task[b, :, :, 0:2]
        true = torch.cdist(at.reshape(-1, 2), env._task_pos[b].to(at.dtype)).argmin(-1)
        seen = tok.task_mask[b].reshape(-1)
        got, want = ids[b].reshape(-1)[seen], true[seen]
        # the same group exactly when the same task
        assert torch.equal(got.unsqueeze(0) == got.unsqueeze(1),
                           want.unsqueeze(0) == want.unsqueeze(1))
        assert len(set(got.tolist())) == len(set(want.tolist())) > 1


def test_task_groups_split_tasks_that_share_a_coordinate():
    from learners.entity import _task_groups

    # four tasks: two share x, two share y, one pair 3e-4 apart; two AGVs see all four
    tasks = torch.tensor([[0.5, 0.0], [0.5, 1.0], [-1.0, 1.0], [-1.0, 1.0003]])
    pos = torch.tensor([[0.0, 0.0], [0.3, -0.2]])
    rel = tasks.unsqueeze(0) - pos.unsqueeze(1)  # (2, 4, 2)
    at = (pos.unsqueeze(1) + rel).unsqueeze(0)
    mask = torch.ones(1, 2, 4, dtype=torch.bool)
    mask[0, 1, 3] = False
    ids = _task_groups(at, mask)[0]
    assert len(set(ids[0].tolist())) == 4
    assert ids[1, :3].tolist() == ids[0, :3].tolist() and ids[1, 3].item() == 8


def test_assignment_exchange_gives_the_nearer_agv_the_contested_task():
    from learners.entity import _Intents, _sinkhorn

    # both AGVs are nearest to the task at x = 0.5; the least total distance sends AGV 1
    # (0.1 away) there and AGV 0 to the task at x = -1 (1.0 away, against 1.4 for AGV 1)
    env, obs = _scene([(0.0, 0.0), (0.4, 0.0)], [(0.5, 0.0), (-1.0, 0.0)])
    tok = tokens(obs, env.obs_layout)
    dist = tok.task[..., 2]
    assert (dist.argmin(-1) == dist.argmin(-1)[0, 0]).all()  # both nearest to one slot
    hears = _Intents(tok).hears
    w = _sinkhorn(-5 * dist, tok, hears, 30)
    at = tok.pos.unsqueeze(-2) + tok.task[..., 0:2]
    goal = torch.gather(at, 2, w.argmax(-1)[..., None, None].expand(1, 2, 1, 2))[0, :, 0]
    torch.testing.assert_close(goal, torch.tensor([[-1.0, 0.0], [0.5, 0.0]], dtype=goal.dtype))
    torch.testing.assert_close(w.sum(-1), torch.ones(1, 2, dtype=w.dtype))
    # no rounds: the softmax of the logits at the last temperature, both on the near task
    w0 = _sinkhorn(-5 * dist, tok, hears, 0)
    assert (w0.argmax(-1) == dist.argmin(-1)).all()
    # a higher last inverse temperature, with more rounds to reach it, ends nearer the hard
    # assignment, on the same tasks
    sharp = _sinkhorn(-5 * dist, tok, hears, 120, beta=300.0)
    assert torch.equal(sharp.argmax(-1), w.argmax(-1))
    assert w.amax(-1).min() < 0.99 < sharp.amax(-1).min()
    # annealed too fast (30 rounds up to 100), the prices cannot follow: both stay near
    hasty = _sinkhorn(-5 * dist, tok, hears, 30, beta=100.0)
    assert (hasty.argmax(-1) == dist.argmin(-1)).all()


def test_assignment_exchange_sums_per_listener_out_of_full_view():
    from learners.entity import _Intents, _sinkhorn

    env, obs = _obs("20v20", num_envs=2, steps=3)
    tok = tokens(obs, env.obs_layout)
    hears = _Intents(tok).hears
    logits = -3 * tok.task[..., 2]
    torch.testing.assert_close(_sinkhorn(logits, tok, hears, 8),
                               _sinkhorn(logits, tok, hears, 8, whole=False))
    # the paper's view: listeners hear different AGVs, and the two sums differ
    scen = sim.get_scenario("20v20")
    env = sim.make_env(scen, num_envs=2, seed=0)
    tok = tokens(env.observe(), env.obs_layout)
    hears = _Intents(tok).hears
    logits = -3 * tok.task[..., 2]
    own = _sinkhorn(logits, tok, hears, 8)
    torch.testing.assert_close(own, _sinkhorn(logits, tok, hears, 8, whole=False))
    assert not torch.allclose(own, _sinkhorn(logits, tok, hears, 8, whole=True))
    assert torch.equal(own[~tok.task_mask], torch.zeros_like(own[~tok.task_mask]))


def test_assignment_exchange_trains_its_scale_and_refuses_bad_settings():
    env, obs = _obs("6v6", num_envs=4, steps=2)
    learner = _learner("bicnet-e", env, choice_head=True, choice_sinkhorn=4)
    _, w = learner.policy_and_choice(obs)
    torch.log(w.amax(-1).clamp_min(1e-9)).sum().backward()
    assert learner.actor.choose.sinkhorn_scale.grad.abs() > 0
    assert learner.actor.encoder.task[0].weight.grad.abs().sum() > 0
    for bad in (-1, 257, 2.5, True):
        with pytest.raises(ValueError, match="choice_sinkhorn"):
            EntityConfig(choice_head=True, choice_sinkhorn=bad)
    with pytest.raises(ValueError, match="needs choice_head=True"):
        EntityConfig(choice_sinkhorn=3)
    with pytest.raises(ValueError, match="MADDPG-E"):
        _learner("maddpg-e", env, choice_head=True, choice_sinkhorn=3)
    sharp = _learner("bicnet-e", env, choice_head=True, choice_sinkhorn=4,
                     choice_sinkhorn_beta=300.0)
    assert sharp.actor.choose.sinkhorn_beta == 300.0
    for bad in (2.9, 1e5, float("nan"), float("inf"), "30"):
        with pytest.raises(ValueError, match="choice_sinkhorn_beta"):
            EntityConfig(choice_head=True, choice_sinkhorn=3, choice_sinkhorn_beta=bad)
    with pytest.raises(ValueError, match="needs choice_sinkhorn >= 1"):
        EntityConfig(choice_head=True, choice_sinkhorn_beta=100.0)
