"""The textbook MADDPG update: N separate actors and critics, each with its own Adam, updated
one agent at a time in a Python loop.

Not used for training. It is the oracle that ``tests/learners`` compare the batched
:class:`~learners.maddpg.MADDPG` against (same weights in, same weights out), and the baseline of
``benchmarks/learner_speed.py``.
"""

from __future__ import annotations

import torch
from torch import nn

from learners.buffer import Batch
from learners.common import movable_mask
from learners.maddpg import MADDPG
from learners.networks import LoopedMLP

__all__ = ["LoopedMADDPG"]


class LoopedMADDPG:
    """Per-agent networks and optimizers holding copies of a :class:`MADDPG`'s weights.

    Parameters
    ----------
    source : MADDPG
        The batched learner whose weights, targets and hyperparameters are copied (fresh Adam
        states: copy it before its first update to compare updates).
    """

    def __init__(self, source: MADDPG) -> None:
        self.config = cfg = source.config
        self.n = source.num_agents
        self.source = source
        self.actors = LoopedMLP.from_stacked(source.actor).nets
        self.critics = LoopedMLP.from_stacked(source.critic).nets
        self.target_actors = LoopedMLP.from_stacked(source.target_actor).nets
        self.target_critics = LoopedMLP.from_stacked(source.target_critic).nets
        self.actor_optimizers = [torch.optim.Adam(a.parameters(), lr=cfg.actor_lr)
                                 for a in self.actors]
        self.critic_optimizers = [torch.optim.Adam(c.parameters(), lr=cfg.critic_lr)
                                  for c in self.critics]

    def update(self, batch: Batch) -> None:
        """One MADDPG update, agent by agent (critic i, then actor i, for every i; then the
        soft updates), computing what :meth:`MADDPG.update` computes."""
        cfg, n = self.config, self.n
        features = self.source.critic_features(batch.obs, batch.state)
        next_features = self.source.critic_features(batch.next_obs, batch.next_state)
        movable = movable_mask(batch.obs)  # (B, N, 1)
        next_movable = movable_mask(batch.next_obs)
        with torch.no_grad():
            next_action = torch.cat(
                [torch.tanh(self.target_actors[j](batch.next_obs[:, j])) * next_movable[:, j]
                 for j in range(n)], dim=-1)  # (B, 2N)
        taken = batch.action.reshape(batch.action.shape[0], -1)
        for i in range(n):  # critics
            with torch.no_grad():
                q_next = self.target_critics[i](torch.cat([next_features, next_action], -1))
                y = self.source.td_target(batch, q_next.expand(-1, n))[:, i:i + 1]
            q = self.critics[i](torch.cat([features, taken], -1))
            loss = (q - y).pow(2).mean()
            self.critic_optimizers[i].zero_grad()
            loss.backward()
            nn.utils.clip_grad_norm_(self.critics[i].parameters(), cfg.grad_clip)
            self.critic_optimizers[i].step()
        for i in range(n):  # actors, against the updated critics
            pre = self.actors[i](batch.obs[:, i])
            mu = torch.tanh(pre) * movable[:, i]
            joint = taken.clone()
            joint = torch.cat([joint[:, :2 * i], mu, joint[:, 2 * i + 2:]], dim=-1)
            q = self.critics[i](torch.cat([features, joint], -1))
            loss = -(q.squeeze(-1) * movable[:, i, 0]).mean() + cfg.action_l2 * pre.pow(2).mean()
            self.actor_optimizers[i].zero_grad()
            self.critics[i].zero_grad()
            loss.backward()
            nn.utils.clip_grad_norm_(self.actors[i].parameters(), cfg.grad_clip)
            self.actor_optimizers[i].step()
        with torch.no_grad():
            for nets, targets in ((self.actors, self.target_actors),
                                  (self.critics, self.target_critics)):
                for net, target in zip(nets, targets, strict=True):
                    for t, s in zip(target.parameters(), net.parameters(), strict=True):
                        t.lerp_(s, cfg.tau)

    def actor_weights(self) -> list[list[torch.Tensor]]:
        """Per agent, the actor's parameters (for comparisons)."""
        return [[p.detach().clone() for p in a.parameters()] for a in self.actors]
