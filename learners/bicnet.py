"""BiCNet (Peng et al., 2017): shared bidirectional-recurrent actor and critic over the agents.

The actor maps the agents' observations (B, N, O) to actions (B, N, 2) through shared
per-agent input layers, a bidirectional GRU along the agent axis and shared per-agent output
layers; the critic does the same with each agent's observation and action and gives one Q per
agent. Updates follow the paper's equations:

* critic:  grad L(xi) = E[sum_i (r_i + gamma Q'_i(s', a'(s')) - Q_i(s, a)) grad Q_i(s, a)],
  i.e. the sum over agents of the squared TD errors;
* actor:   grad J(theta) = E[sum_i sum_j grad_theta a_j grad_{a_j} Q_i(s, a_theta(s))],
  i.e. the gradient of sum_i Q_i(s, a_theta(s)): every agent's action is credited with its
  effect on every agent's Q.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from learners.buffer import Batch
from learners.common import ActorCritic, OffPolicyConfig, check_int, movable_mask
from learners.networks import BiRNNNet

__all__ = ["BiCNetConfig", "BiCNet"]


@dataclass
class BiCNetConfig(OffPolicyConfig):
    """Hyperparameters of BiCNet (defaults tuned on ``3v3``; see ``docs/learners.md``)."""

    hidden: int = 64
    """Width of the fully connected layers and of each GRU direction."""
    input_layers: int = 2
    """Shared fully connected layers before the bidirectional GRU (the paper: four)."""
    output_layers: int = 2
    """Shared fully connected layers after the GRU, the last one linear (the paper: four)."""
    batch_size: int = 512
    """Transitions per gradient update."""

    def validate(self) -> None:
        """Check every field (see :meth:`OffPolicyConfig.validate`), the layer counts too."""
        super().validate()
        self.input_layers = check_int("input_layers", self.input_layers, 1)
        self.output_layers = check_int("output_layers", self.output_layers, 1)


class BiCNet(ActorCritic):
    """Shared bidirectional-GRU actor and critic.

    Parameters
    ----------
    obs_dim : int
        Local observation size O.
    state_dim : int
        Global state size S (unused: the critic reads every agent's observation and action
        through its recurrence; kept for a uniform constructor).
    num_agents : int
        N (the weights do not depend on it).
    config : BiCNetConfig
    """

    name = "bicnet"

    def __init__(
        self, obs_dim: int, state_dim: int, num_agents: int, config: BiCNetConfig | None = None
    ) -> None:
        config = config or BiCNetConfig()
        super().__init__(obs_dim, state_dim, num_agents, config)
        h = config.hidden
        self.actor = BiRNNNet(obs_dim, 2, h, config.input_layers, config.output_layers)
        self.critic = BiRNNNet(obs_dim + 2, 1, h, config.input_layers, config.output_layers)
        self._finish_init()

    def policy(self, obs: Tensor, target: bool = False) -> Tensor:
        """Deterministic actions, (B, N, O) -> (B, N, 2), zero for parked AGVs."""
        net = self.target_actor if target else self.actor
        a = torch.tanh(net(obs))
        return a * movable_mask(obs) if self.config.mask_parked else a

    def q_values(self, obs: Tensor, action: Tensor, target: bool = False) -> Tensor:
        """Per-agent Q, (B, N, O), (B, N, 2) -> (B, N)."""
        net = self.target_critic if target else self.critic
        return net(torch.cat([obs, action], dim=-1)).squeeze(-1)

    def update(self, batch: Batch) -> dict[str, float]:
        """One BiCNet update from a sampled batch (see the module docstring).

        Returns
        -------
        dict
            ``critic_loss``, ``actor_loss`` (sums over agents) and ``q`` (mean Q).
        """
        cfg = self.config
        with torch.no_grad():
            next_action = self.policy(batch.next_obs, target=True)
            q_next = self.q_values(batch.next_obs, next_action, target=True)
            y = self.td_target(batch, q_next)
        q = self.q_values(batch.obs, batch.action)
        critic_loss = (q - y).pow(2).mean(0).sum()
        self.critic_optimizer.zero_grad(set_to_none=True)
        critic_loss.backward()
        torch.nn.utils.clip_grad_norm_(self.critic.parameters(), cfg.grad_clip)
        self.critic_optimizer.step()

        pre = self.actor(batch.obs)  # (B, N, 2)
        mu = torch.tanh(pre) * (movable_mask(batch.obs) if cfg.mask_parked else 1.0)
        actor_loss = -self.q_values(batch.obs, mu).sum(1).mean()
        reg = cfg.action_l2 * pre.pow(2).mean()
        actor_params = list(self.actor.parameters())
        grads = torch.autograd.grad(actor_loss + reg, actor_params)
        for p, g in zip(actor_params, grads, strict=True):
            p.grad = g
        torch.nn.utils.clip_grad_norm_(actor_params, cfg.grad_clip)
        self.actor_optimizer.step()

        self._soft_update()
        self.updates += 1
        return {"critic_loss": critic_loss.item(), "actor_loss": actor_loss.item(),
                "q": q.mean().item()}
