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


@pytest.mark.parametrize("n", [3, 6])
def test_birnn_agent_major_pass_is_the_batch_major_textbook_pass(n):
    """BiRNNNet runs agent-major (contiguous activations); the textbook form runs the same
    modules batch-major. Values and every parameter gradient agree to float rounding."""
    torch.manual_seed(1)
    net = BiRNNNet(24, 2, hidden=16)
    x = torch.randn(64, n, 24)
    y = net(x)
    h, _ = net.rnn(torch.relu(net.encoder(x)))
    ref = net.decoder(h)
    assert y.shape == ref.shape == (64, n, 2)
    torch.testing.assert_close(y, ref, rtol=1e-6, atol=1e-6)
    w = torch.randn(64, n, 2)
    params = list(net.parameters())
    got = torch.autograd.grad((y * w).sum(), params)
    want = torch.autograd.grad((ref * w).sum(), params)
    for g, r in zip(got, want, strict=True):
        torch.testing.assert_close(g, r, rtol=1e-5, atol=1e-6)


# ---------------------------------------------------------------- private torch ops
@pytest.fixture
def restore_torch_ops():
    """Put the import-time selection back after a test that forces the fallbacks."""
    from learners.networks import select_torch_ops, torch_ops

    before = torch_ops()
    yield
    select_torch_ops(private_ops=bool(before.private), fused_adam=before.adam_fused)


def test_private_torch_ops_and_their_public_fallbacks_give_the_same_numbers(restore_torch_ops):
    """aten._add_relu_, aten.threshold_backward.grad_input and torch._foreach_lerp_ had no
    public fallback; each now has one, chosen once, with the same results."""
    from learners.common import soft_update_
    from learners.networks import add_relu_, relu_backward_, select_torch_ops

    gen = torch.Generator().manual_seed(0)
    z = torch.randn(3, 64, 32, generator=gen)
    bias = torch.randn(3, 1, 32, generator=gen)
    grad = torch.randn(3, 64, 32, generator=gen)
    src, dst = StackedMLP(3, 5, 2, hidden=8), StackedMLP(3, 5, 2, hidden=8)

    def run() -> list[torch.Tensor]:
        target = copy.deepcopy(dst)
        soft_update_(target, src, 0.01)
        return [add_relu_(z.clone(), bias), relu_backward_(grad.clone(), z),
                *target.parameters()]

    chosen = select_torch_ops()
    assert set(chosen.private) == {"aten._add_relu_", "aten.threshold_backward.grad_input",
                                   "torch._foreach_lerp_"}  # all present in torch 2.13
    private = run()
    fallback = select_torch_ops(private_ops=False)
    assert fallback.private == ()
    public = run()
    for a, b in zip(private, public, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-6, atol=1e-7)
    assert torch.equal(private[0], torch.relu(z + bias))
    assert torch.equal(private[1], torch.where(z > 0, grad, torch.zeros_like(grad)))


def test_a_private_op_that_is_missing_or_raises_is_replaced_by_its_fallback():
    from learners.networks import _agrees, _probe_args, _relu_backward_public

    def missing(grad, act):
        return torch.ops.aten.no_such_op_(grad, act)

    def raises(grad, act):
        raise RuntimeError("not implemented for this build")

    def wrong(grad, act):
        return grad.zero_()

    args = _probe_args()["relu_backward_"]
    assert _agrees(_relu_backward_public, _relu_backward_public, args)
    for op in (missing, raises, wrong):
        assert not _agrees(op, _relu_backward_public, args), op.__name__


@pytest.mark.parametrize("algo", ["maddpg", "bicnet"])
def test_training_with_the_public_fallbacks_and_foreach_adam_gives_the_same_weights(
        restore_torch_ops, algo):
    """Five updates with every private op and fused Adam, and with every fallback (public ops,
    Adam(foreach=True), what a torch 2.3 build gets), end at the same weights."""
    from learners.algorithms import make_learner
    from learners.networks import select_torch_ops

    env, batch = make_batch("3v3")

    def five_updates():
        torch.manual_seed(0)
        learner = make_learner(algo, env.obs_dim, env.state_dim, env.num_agents,
                               {"hidden": 32, "batch_size": 64})
        for _ in range(5):
            learner.update(batch)
        return learner

    assert select_torch_ops().adam_fused
    fast = five_updates()
    assert fast.actor_optimizer.defaults["fused"]
    select_torch_ops(private_ops=False, fused_adam=False)
    public = five_updates()
    assert public.actor_optimizer.defaults["foreach"] and not public.actor_optimizer.defaults[
        "fused"]
    fast_t, public_t = fast.training_tensors(), public.training_tensors()
    assert fast_t.keys() == public_t.keys()
    for k in fast_t:
        torch.testing.assert_close(fast_t[k].float(), public_t[k].float(), rtol=1e-5,
                                   atol=1e-6, msg=k)


def test_private_ops_can_be_turned_off_for_a_process():
    import os
    import subprocess
    import sys

    code = ("from learners.networks import torch_ops; o = torch_ops(); "
            "print(len(o.private), o.adam_fused)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=120, env={**os.environ, "AGV_PRIVATE_TORCH_OPS": "0",
                                           "PYTHONPATH": os.pathsep.join(sys.path)})
    assert out.stdout.split() == ["0", "True"], out.stderr
