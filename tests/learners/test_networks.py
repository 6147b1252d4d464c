"""Stacked per-agent networks compute what separate per-agent networks compute."""

from __future__ import annotations

import torch

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
