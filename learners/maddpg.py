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
from learners.common import ActorCritic, OffPolicyConfig, check_choice, check_int, movable_mask
from learners.networks import (
    StackedMLP,
    Workspace,
    add_relu_,
    clip_grad_norm_per_agent_,
    grad_buffer,
    stacked_backward_,
    stacked_forward_,
)

__all__ = ["MADDPGConfig", "MADDPG", "CRITIC_INPUTS"]

CRITIC_INPUTS = ("obs", "state", "state+obs")
"""What the centralized critics may see besides the actions (``MADDPGConfig.critic_input``)."""


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

    def validate(self) -> None:
        """Check every field (see :meth:`OffPolicyConfig.validate`), ``layers`` and
        ``critic_input`` too."""
        super().validate()
        self.layers = check_int("layers", self.layers, 1)
        check_choice("critic_input", self.critic_input, CRITIC_INPUTS)


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
        self.actor = StackedMLP(n, obs_dim, 2, h, config.layers)
        self.critic = StackedMLP(n, sizes[config.critic_input] + 2 * n, 1, h, config.layers)
        self._finish_init()
        self.register_buffer("_agents", torch.arange(n), persistent=False)
        self._ws = Workspace()  # scratch tensors of :meth:`update`, reused between updates

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

    # ------------------------------------------------------------------ the update
    def _critic_pass(self, net: StackedMLP, x: Tensor, tag: str, own: tuple[Tensor, Tensor]
                     | None = None) -> list[Tensor]:
        """All N critics on one shared input, into workspace tensors.

        The first layer is one GEMM (B, D) @ (D, N H) written to a (B, N, H) tensor that is
        read as (N, B, H) (no transposing copy); bias and ReLU are one in-place pass. With
        ``own = (delta, w_own)`` the term ``delta @ w_own`` (N, B, 2) x (N, 2, H) is added to
        the first pre-activation before its ReLU (the actor pass, see :meth:`update`).

        Returns ``[x, h_1, ..., h_{L-1}, q]`` as :func:`stacked_forward_` does, q (N, B, 1).
        """
        first = net.layers[0]
        n, d, h = first.weight.shape
        bsz = x.shape[0]
        z = self._ws.get(tag + "head", (bsz, n, h), x)
        torch.mm(x, first.weight.transpose(0, 1).reshape(d, n * h), out=z.view(bsz, n * h))
        z = z.transpose(0, 1)  # (N, B, H) view
        if own is not None:
            z.baddbmm_(*own)
        if len(net.layers) == 1:
            return [x, z.add_(first.bias)]
        add_relu_(z, first.bias)
        return [x, *stacked_forward_(net.layers[1:], z, self._ws, tag)]

    def _joint_input(self, name: str, features: Tensor, action: Tensor | None) -> Tensor:
        """The critics' input [features, a_1, ..., a_N] (B, C + 2N) in a workspace tensor
        (with ``action`` None the action part is left to the caller)."""
        bsz, c = features.shape
        x = self._ws.get(name, (bsz, c + 2 * self.num_agents), features)
        x[:, :c].copy_(features)
        if action is not None:
            x[:, c:].copy_(action.reshape(bsz, -1))
        return x

    def update(self, batch: Batch) -> dict[str, float]:
        """One MADDPG update of all agents from a sampled batch.

        The N critics, then the N actors, take one clipped Adam step each, then the targets
        move by tau; the same computation as the textbook loop of N networks
        (:class:`learners.reference.LoopedMADDPG`, tested equal to 1e-6). How it is fast:

        * every layer of all N networks is one batched matmul followed by one in-place
          bias + ReLU pass; the critics' first layer (one input shared by all N) is one GEMM;
        * the gradients are written by hand (the networks are plain ReLU MLPs): no autograd
          graph, and every temporary and gradient lives in a :class:`Workspace` reused from
          one update to the next (``out=`` and in-place ops), which on CPU saves more than
          the graph does;
        * in the actor pass, critic i needs [x, a_1, ..., mu_i(o_i), ..., a_N]; its first
          layer is linear, so its pre-activation is the critic pass's shared GEMM on the
          buffer's joint action plus (mu_i - a_i) W_i[a_i rows], a (N, B, 2) x (N, 2, H)
          product: no per-agent copy of the joint action, and the gradient flows only through
          that small product;
        * per-agent clipping of stacked gradients is vectorised; Adam is fused; the soft update
          is one multi-tensor lerp per network.

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
        cfg, ws = self.config, self._ws
        n, bsz = self.num_agents, batch.obs.shape[0]
        # Workspace names: "a" actor passes (target, then online), "c" critic passes (target,
        # online, then the actor pass), "g" gradients. Phases that do not overlap share
        # tensors, which keeps the update's memory footprint (and its cache misses) small.
        mask = cfg.mask_parked
        with torch.no_grad():
            # ---- TD targets: target actors, then target critics on the next joint action.
            x_next = self._joint_input(
                "x_next", self.critic_features(batch.next_obs, batch.next_state), None)
            # Actor outputs are written as (B, N, 2), the joint action's layout, so that the
            # elementwise work is on contiguous memory.
            next_action = ws.get("next_action", batch.action.shape, batch.action)
            stacked_forward_(self.target_actor.layers, batch.next_obs.transpose(0, 1), ws, "a",
                             out=next_action.transpose(0, 1))
            next_action.tanh_()
            if mask:
                next_action.mul_(movable_mask(batch.next_obs))
            x_next[:, x_next.shape[1] - 2 * n:].copy_(next_action.view(bsz, 2 * n))
            q_next = self._critic_pass(self.target_critic, x_next, "c")[-1]  # (N, B, 1)
            y = self.td_target(batch, q_next.squeeze(-1).transpose(0, 1))  # (B, N)

            # ---- Critics: L = sum_i mean_b (Q_i - y_i)^2, dL/dQ_i = 2 (Q_i - y_i) / B.
            x = self._joint_input("x", self.critic_features(batch.obs, batch.state),
                                  batch.action)
            acts = self._critic_pass(self.critic, x, "c")
            q = acts[-1]  # (N, B, 1)
            diff = torch.sub(q, y.transpose(0, 1).unsqueeze(-1), out=ws.get("diff", q.shape, q))
            critic_loss = diff.pow(2).sum() / bsz
            q_mean = q.mean()
            self._critic_backward(acts, diff.mul_(2.0 / bsz))
            clip_grad_norm_per_agent_(list(self.critic.parameters()), cfg.grad_clip)
        self.critic_optimizer.step()

        with torch.no_grad():
            # ---- Actors, against the updated critics.
            pre = ws.get("pre", batch.action.shape, batch.action)  # (B, N, 2)
            actor_acts = stacked_forward_(self.actor.layers, batch.obs.transpose(0, 1), ws, "a",
                                          out=pre.transpose(0, 1))
            t = torch.tanh(pre, out=ws.get("tanh", pre.shape, pre))
            movable = movable_mask(batch.obs)  # (B, N, 1)
            # Critic i with mu_i in slot i: the shared GEMM on x plus (mu_i - a_i) W_i[a_i rows].
            first = self.critic.layers[0].weight  # (N, C + 2N, H)
            c = x.shape[1] - 2 * n
            own = first[:, c:].view(n, n, 2, -1)[self._agents, self._agents]  # (N, 2, H)
            delta = ws.get("delta", pre.shape, pre)
            if mask:
                torch.mul(t, movable, out=delta)
            else:
                delta.copy_(t)
            delta.sub_(batch.action)  # mu_i - a_i, (B, N, 2)
            pass_acts = self._critic_pass(self.critic, x, "c", own=(delta.transpose(0, 1), own))
            weight = movable.transpose(0, 1) if mask else torch.ones_like(pass_acts[-1])
            actor_loss = -(pass_acts[-1] * weight).sum() / bsz
            # d(-sum_i mean_b w Q_i)/dQ_i = -w / B, back to the first pre-activation, to mu_i.
            dz = self._pass_backward(pass_acts, weight.mul(-1.0 / bsz))
            dmu = ws.get("dmu", pre.shape, pre)
            torch.bmm(dz, own.transpose(1, 2), out=dmu.transpose(0, 1))
            # Through mu = tanh(pre) * movable, plus the regulariser action_l2 * mean(pre^2).
            dpre = t.pow_(2).neg_().add_(1.0).mul_(dmu)
            if mask:
                dpre.mul_(movable)
            dpre.add_(pre, alpha=cfg.action_l2 / bsz)
            stacked_backward_(self.actor.layers, actor_acts, dpre.transpose(0, 1), ws, "g")
            clip_grad_norm_per_agent_(list(self.actor.parameters()), cfg.grad_clip)
        self.actor_optimizer.step()

        self._soft_update()
        self.updates += 1
        return {"critic_loss": critic_loss.item(), "actor_loss": actor_loss.item(),
                "q": q_mean.item()}

    def _critic_backward(self, acts: list[Tensor], dq: Tensor) -> None:
        """Gradients of every critic parameter from dL/dQ (N, B, 1), into their ``.grad``."""
        layers = self.critic.layers
        first = layers[0]
        n, d, h = first.weight.shape
        bsz = dq.shape[1]
        if len(layers) == 1:
            dz = dq
        else:
            dz = self._ws.get("ghead", (bsz, n, h), dq).transpose(0, 1)
            stacked_backward_(layers, acts, dq, self._ws, "g", stop=1, grad_in_out=dz)
        # First layer, shared input x (B, D): one GEMM x^T @ dz (B, N H) -> (D, N H).
        dz_flat = dz.transpose(0, 1).reshape(bsz, n * h)
        gw = torch.mm(acts[0].t(), dz_flat, out=self._ws.get("gw", (d, n * h), dq))
        grad_buffer(first.weight).copy_(gw.view(d, n, h).transpose(0, 1))
        torch.sum(dz_flat, dim=0, out=grad_buffer(first.bias).view(n * h))

    def _pass_backward(self, acts: list[Tensor], dq: Tensor) -> Tensor:
        """d loss / d (first pre-activation) of the actor pass, (N, B, H); no critic grads."""
        if len(self.critic.layers) == 1:
            return dq
        return stacked_backward_(self.critic.layers, acts, dq, self._ws, "g", stop=1,
                                 param_grads=False)
