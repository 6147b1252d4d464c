"""MADDPG (Lowe et al., 2017) with continuous actions, agents' networks stacked.

Each AGV i has an actor mu_i(o_i) on its local observation and a centralized critic
Q_i(x, a_1, ..., a_N) on the global state and every action. The N actors are one
:class:`~learners.networks.StackedMLP` (weights (N, in, out)) and so are the N critics, so a
forward pass of all of them is one batched matmul per layer. Updates follow the paper's
equations:

* critic:  y_i = r_i + gamma (1 - terminal) Q'_i(x', mu'_1(o'_1), ..., mu'_N(o'_N)),
  L_i = E[(Q_i(x, a) - y_i)^2];
* actor:   grad J(mu_i) = E[grad mu_i(o_i) grad_{a_i} Q_i(x, a_1, ..., a_i = mu_i(o_i), ..., a_N)],
  the other agents' actions taken from the replay buffer as in Lowe et al.;
* targets: soft updates with rate tau; gradients clipped per agent.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from learners.buffer import Batch
from learners.common import ActorCritic, OffPolicyConfig, movable_mask
from learners.networks import StackedMLP, clip_grad_norm_per_agent_

__all__ = ["MADDPGConfig", "MADDPG"]


@dataclass
class MADDPGConfig(OffPolicyConfig):
    """Hyperparameters of MADDPG (defaults tuned on ``3v3``; see ``docs/learners.md``)."""

    hidden: int = 64
    """Width of the two hidden layers of every actor and critic (three FC layers)."""
    layers: int = 3
    """Fully connected layers per actor and per critic (the paper: three)."""
    updates_per_step: int = 2
    """Gradient updates after every vectorized step (num_envs transitions)."""
    critic_input: str = "obs"
    """What the centralized critics see besides all actions: ``"obs"`` (every agent's local
    observation, the paper's x = [o_1, ..., o_N]), ``"state"`` (the simulator's global state)
    or ``"state+obs"`` (both)."""


class MADDPG(ActorCritic):
    """N actors and N centralized critics, trained together with batched matmuls.

    Parameters
    ----------
    obs_dim : int
        Local observation size O.
    state_dim : int
        Global state size S.
    num_agents : int
        N.
    config : MADDPGConfig
    """

    name = "maddpg"

    def __init__(
        self, obs_dim: int, state_dim: int, num_agents: int, config: MADDPGConfig | None = None
    ) -> None:
        config = config or MADDPGConfig()
        super().__init__(obs_dim, state_dim, num_agents, config)
        n, h = num_agents, config.hidden
        sizes = {"obs": n * obs_dim, "state": state_dim, "state+obs": state_dim + n * obs_dim}
        if config.critic_input not in sizes:
            raise ValueError(f"critic_input must be one of {sorted(sizes)}, got "
                             f"{config.critic_input!r}")
        self.actor = StackedMLP(n, obs_dim, 2, h, config.layers)
        self.critic = StackedMLP(n, sizes[config.critic_input] + 2 * n, 1, h, config.layers)
        self._finish_init()
        self.register_buffer("_agents", torch.arange(n), persistent=False)

    def _actor_out(self, obs: Tensor, target: bool = False) -> Tensor:
        """Pre-tanh actor outputs, (B, N, O) -> (N, B, 2).

        On a scene with N' != N AGVs (deployment only), AGV i runs actor ``i mod N``: each
        actor reads only its own AGV's local observation, so any actor can drive any AGV.
        """
        net = self.target_actor if target else self.actor
        n = obs.shape[1]
        index = None if n == self.num_agents else torch.arange(n) % self.num_agents
        return net(obs.transpose(0, 1), index)

    def policy(self, obs: Tensor, target: bool = False) -> Tensor:
        """Deterministic actions, (B, N, O) -> (B, N, 2), zero for parked AGVs."""
        a = torch.tanh(self._actor_out(obs, target)).transpose(0, 1)
        return a * movable_mask(obs) if self.config.mask_parked else a

    def critic_features(self, obs: Tensor, state: Tensor) -> Tensor:
        """What the critics see besides the actions, (B, N, O), (B, S) -> (B, C)."""
        parts = {"obs": [obs.flatten(1)], "state": [state],
                 "state+obs": [state, obs.flatten(1)]}[self.config.critic_input]
        return parts[0] if len(parts) == 1 else torch.cat(parts, dim=-1)

    def q_values(self, features: Tensor, action: Tensor, target: bool = False) -> Tensor:
        """Every critic on the same joint action: (B, C), (B, N, 2) -> (B, N)."""
        net = self.target_critic if target else self.critic
        x = torch.cat([features, action.reshape(action.shape[0], -1)], dim=-1)
        return self._critic_tail(net, self._critic_head(net, x)).transpose(0, 1)

    @staticmethod
    def _critic_head(net: StackedMLP, x: Tensor) -> Tensor:
        """First critic layer on an input shared by all N critics, as one GEMM:
        (B, D) @ (D, N H) -> (N, B, H), pre-activation."""
        layer = net.layers[0]
        n, d, h = layer.weight.shape
        out = x @ layer.weight.permute(1, 0, 2).reshape(d, n * h)
        return out.view(-1, n, h).transpose(0, 1) + layer.bias

    @staticmethod
    def _critic_tail(net: StackedMLP, h: Tensor) -> Tensor:
        """The critic layers after the first, (N, B, H) pre-activation -> (N, B)."""
        for layer in net.layers[1:]:
            h = layer(torch.relu(h))
        return h.squeeze(-1)

    def update(self, batch: Batch) -> dict[str, float]:
        """One MADDPG update of all agents from a sampled batch.

        Parameters
        ----------
        batch : Batch
            obs (B, N, O), state (B, S), action (B, N, 2), reward (B, N), next_obs,
            next_state, terminal (B,).

        Returns
        -------
        dict
            ``critic_loss``, ``actor_loss`` (sums over agents) and ``q`` (mean Q).
        """
        cfg = self.config
        n, bsz = self.num_agents, batch.obs.shape[0]
        # Critics: one TD step each, all N in one batched forward.
        with torch.no_grad():
            next_action = self.policy(batch.next_obs, target=True)
            next_features = self.critic_features(batch.next_obs, batch.next_state)
            q_next = self.q_values(next_features, next_action, target=True)
            y = self.td_target(batch, q_next)
        features = self.critic_features(batch.obs, batch.state)
        q = self.q_values(features, batch.action)
        critic_loss = (q - y).pow(2).mean(0).sum()
        self.critic_optimizer.zero_grad(set_to_none=True)
        critic_loss.backward()
        clip_grad_norm_per_agent_(list(self.critic.parameters()), cfg.grad_clip)
        self.critic_optimizer.step()

        # Actors: critic i sees mu_i(o_i) in slot i and the buffer's actions elsewhere. Its
        # first layer is linear, so [x, a with a_i = mu_i] W_i = [x, a] W_i + (mu_i - a_i) W_i,a_i:
        # the shared part is one GEMM without gradient, the own-action part one small bmm.
        pre = self._actor_out(batch.obs)  # (N, B, 2)
        movable = movable_mask(batch.obs).transpose(0, 1)  # (N, B, 1)
        mu = torch.tanh(pre) * (movable if cfg.mask_parked else 1.0)
        taken = batch.action.transpose(0, 1)  # (N, B, 2)
        first = self.critic.layers[0].weight.detach()  # (N, C + 2N, H)
        c = features.shape[1]
        own = first[:, c:].reshape(n, n, 2, -1)[self._agents, self._agents]  # (N, 2, H)
        with torch.no_grad():
            base = self._critic_head(self.critic, torch.cat(
                [features, batch.action.reshape(bsz, -1)], dim=-1))
        q_pi = self._critic_tail(self.critic, base + torch.bmm(mu - taken, own))  # (N, B)
        weight = movable.squeeze(-1) if cfg.mask_parked else torch.ones_like(q_pi)
        actor_loss = -(q_pi * weight).mean(1).sum()
        reg = cfg.action_l2 * (pre.pow(2).mean(dim=(1, 2))).sum()
        actor_params = list(self.actor.parameters())
        grads = torch.autograd.grad(actor_loss + reg, actor_params)
        for p, g in zip(actor_params, grads, strict=True):
            p.grad = g
        clip_grad_norm_per_agent_(actor_params, cfg.grad_clip)
        self.actor_optimizer.step()

        self._soft_update()
        self.updates += 1
        return {"critic_loss": critic_loss.item(), "actor_loss": actor_loss.item(),
                "q": q.mean().item()}
