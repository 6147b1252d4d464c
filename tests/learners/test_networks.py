"""Stacked per-agent networks compute what separate per-agent networks compute."""

from __future__ import annotations

import copy

import pytest
import torch

from learners.common import movable_mask
from learners.maddpg import MADDPG, MADDPGConfig
from learners.networks import BiRNNNet, LoopedMLP, StackedMLP, clip_grad_norm_per_agent_
from learners.reference import LoopedMADDPG
from tests.learners.conftest import make_batch


def test_stacked_mlp_matches_separate_networks():
    torch.manual_seed(0)
    stacked = StackedMLP(4, 7, 3, hidden=16, layers=3)
    looped = LoopedMLP.from_stacked(stacked)
    x = torch.randn(4, 10, 7)
    torch.testing.assert_close(stacked(x), looped(x))
    shared = torch.randn(10, 7)  # one input for all N networks (the critics' case)
    torch.testing.assert_close(stacked(shared), looped(shared))


def test_per_agent_clipping_equals_clip_grad_norm_of_each_network():
    torch.manual_seed(0)
    stacked = StackedMLP(3, 5, 2, hidden=8)
    looped = LoopedMLP.from_stacked(stacked)
    x = torch.randn(3, 6, 5)
    (stacked(x).pow(2).sum() * 100).backward()
    (looped(x).pow(2).sum() * 100).backward()
    clip_grad_norm_per_agent_(list(stacked.parameters()), 0.5)
    for n, net in enumerate(looped.nets):
        torch.nn.utils.clip_grad_norm_(net.parameters(), 0.5)
        torch.testing.assert_close(stacked.layers[0].weight.grad[n], net[0].weight.grad.T)


def test_batched_maddpg_update_equals_textbook_loop():
    """Three updates of the stacked learner == three per-agent updates with N Adams."""
    torch.manual_seed(0)
    env, batch = make_batch("3v3")
    for critic_input in ("obs", "state"):
        learner = MADDPG(env.obs_dim, env.state_dim, env.num_agents,
                         MADDPGConfig(hidden=32, critic_input=critic_input))
        reference = LoopedMADDPG(learner)
        for _ in range(3):
            learner.update(batch)
            reference.update(batch)
        for i, weights in enumerate(reference.actor_weights()):
            for k, layer in enumerate(learner.actor.layers):
                torch.testing.assert_close(layer.weight[i], weights[2 * k].T, atol=1e-6,
                                           rtol=1e-5)
        for i, critic in enumerate(reference.target_critics):
            torch.testing.assert_close(learner.target_critic.layers[-1].weight[i],
                                       critic[-1].weight.T, atol=1e-6, rtol=1e-5)


@pytest.mark.parametrize(("scenario", "overrides"), [
    ("3v3", {"mask_parked": False, "terminal_value": "zero"}),
    ("3v3", {"layers": 2, "critic_input": "state+obs"}),
    ("3v3", {"layers": 4}),
    ("6v6", {}),
])
def test_hand_written_gradients_match_the_textbook_loop(scenario, overrides):
    """Every weight of every network (online and target) after three updates, other configs."""
    torch.manual_seed(1)
    env, batch = make_batch(scenario)
    learner = MADDPG(env.obs_dim, env.state_dim, env.num_agents,
                     MADDPGConfig(hidden=16, **overrides))
    reference = LoopedMADDPG(learner)
    for _ in range(3):
        learner.update(batch)
        reference.update(batch)
    for nets, stacked in ((reference.actors, learner.actor), (reference.critics, learner.critic),
                          (reference.target_actors, learner.target_actor),
                          (reference.target_critics, learner.target_critic)):
        for i, net in enumerate(nets):
            linears = [m for m in net if isinstance(m, torch.nn.Linear)]
            for lin, layer in zip(linears, stacked.layers, strict=True):
                torch.testing.assert_close(layer.weight[i], lin.weight.T, atol=1e-6, rtol=1e-5)
                torch.testing.assert_close(layer.bias[i, 0], lin.bias, atol=1e-6, rtol=1e-5)


def test_update_reports_the_losses_it_minimises():
    """critic_loss, actor_loss and q as autograd-free formulas on the networks of the update."""
    torch.manual_seed(0)
    env, batch = make_batch("3v3")
    learner = MADDPG(env.obs_dim, env.state_dim, env.num_agents, MADDPGConfig(hidden=16))
    learner.update(batch)
    before = copy.deepcopy(learner)
    out = learner.update(batch)
    with torch.no_grad():
        features = before.critic_features(batch.obs, batch.state)
        next_features = before.critic_features(batch.next_obs, batch.next_state)
        q_next = before.q_values(next_features, before.policy(batch.next_obs, target=True),
                                 target=True)
        q = before.q_values(features, batch.action)
        y = before.td_target(batch, q_next)
        assert out["critic_loss"] == pytest.approx(float((q - y).pow(2).mean(0).sum()), rel=1e-5)
        assert out["q"] == pytest.approx(float(q.mean()), rel=1e-5, abs=1e-6)
        # The actor loss is taken against the critics after their step (learner.critic).
        mu = before.policy(batch.obs)
        movable = movable_mask(batch.obs)[..., 0]
        loss = 0.0
        for i in range(env.num_agents):
            joint = batch.action.clone()
            joint[:, i] = mu[:, i]
            q_i = learner.q_values(features, joint)[:, i]
            loss -= float((q_i * movable[:, i]).mean())
        assert out["actor_loss"] == pytest.approx(loss, rel=1e-5, abs=1e-6)


def test_birnn_couples_agents_and_handles_any_n():
    torch.manual_seed(0)
    net = BiRNNNet(6, 2, hidden=8)
    x = torch.randn(5, 3, 6)
    y = net(x)
    assert y.shape == (5, 3, 2)
    x2 = x.clone()
    x2[:, 2] += 1.0  # changing the last agent's input changes the first agent's output
    assert not torch.allclose(net(x2)[:, 0], y[:, 0])
    assert net(torch.randn(5, 7, 6)).shape == (5, 7, 2)
