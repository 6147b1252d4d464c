"""What MADDPG and BiCNet share: the actor-critic skeleton, target networks, exploration,
parked-AGV masks and the flat tensor form of their state for checkpoints."""

from __future__ import annotations

import copy
import math
import numbers
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
import torch
from torch import Tensor, nn

from learners.buffer import Batch
from learners.networks import torch_ops
from sim.observations import HOLDING

__all__ = [
    "ActorCritic", "OffPolicyConfig", "movable_mask", "soft_update_", "check_bool",
    "check_choice", "check_int", "check_real",
]


def check_int(name: str, value: Any, minimum: int | None = None,
              maximum: int | None = None) -> int:
    """``value`` as an int, or a ValueError naming ``name`` and the valid range.

    Parameters
    ----------
    name : str
        The field, for the message.
    value : object
        An integer (Python or NumPy; not a bool, not a float such as 2.0).
    minimum, maximum : int, optional
        Inclusive bounds.

    Returns
    -------
    int
    """
    lo = "-inf" if minimum is None else minimum
    hi = "inf" if maximum is None else maximum
    where = f"an integer in [{lo}, {hi}]" if maximum is not None else f"an integer >= {lo}"
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise ValueError(f"{name} must be {where}, got {value!r} ({type(value).__name__})")
    value = int(value)
    if (minimum is not None and value < minimum) or (maximum is not None and value > maximum):
        raise ValueError(f"{name} must be {where}, got {value!r}")
    return value


def check_real(name: str, value: Any, low: float = -math.inf, high: float = math.inf,
               low_open: bool = False, high_open: bool = False) -> float:
    """``value`` as a finite float in the given interval, or a ValueError naming ``name``.

    Parameters
    ----------
    name : str
    value : object
        A real number (not a bool, not NaN or infinite).
    low, high : float
        The bounds of the interval.
    low_open, high_open : bool
        Whether the bound is excluded.

    Returns
    -------
    float
    """
    left = "(" if low_open or low == -math.inf else "["
    right = ")" if high_open or high == math.inf else "]"
    where = f"a finite number in {left}{low:g}, {high:g}{right}"
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise ValueError(f"{name} must be {where}, got {value!r} ({type(value).__name__})")
    value = float(value)
    if (not math.isfinite(value) or value < low or value > high
            or (low_open and value == low) or (high_open and value == high)):
        raise ValueError(f"{name} must be {where}, got {value!r}")
    return value


def check_choice(name: str, value: Any, choices: Iterable[str]) -> str:
    """``value`` if it is one of ``choices``, else a ValueError naming ``name`` and them."""
    choices = list(choices)
    if not isinstance(value, str) or value not in choices:
        raise ValueError(f"{name} must be one of {choices}, got {value!r}")
    return value


def check_bool(name: str, value: Any) -> bool:
    """``value`` if it is a bool (Python or NumPy), else a ValueError naming ``name``."""
    if not isinstance(value, (bool, np.bool_)):
        raise ValueError(f"{name} must be True or False, got {value!r}")
    return bool(value)


@dataclass
class OffPolicyConfig:
    """Hyperparameters shared by the off-policy actor-critic learners (MADDPG, BiCNet)."""

    hidden: int = 64
    """Width of the hidden layers."""
    actor_lr: float = 1e-3
    """Adam learning rate of the actor(s)."""
    critic_lr: float = 1e-3
    """Adam learning rate of the critic(s)."""
    gamma: float = 0.95
    """Discount factor."""
    tau: float = 0.01
    """Soft target update rate: target <- (1 - tau) target + tau online, after every update."""
    batch_size: int = 1024
    """Transitions per gradient update."""
    buffer_size: int = 200_000
    """Replay buffer capacity in joint transitions."""
    num_envs: int = 16
    """Parallel environments stepped together while collecting."""
    updates_per_step: int = 1
    """Gradient updates after every vectorized step (num_envs transitions)."""
    learning_starts: int = 4096
    """Transitions collected with the untrained policy before the first update."""
    noise_start: float = 0.5
    """Initial standard deviation of the Gaussian exploration noise."""
    noise_end: float = 0.05
    """Final standard deviation of the exploration noise."""
    noise_decay_episodes: int = 3000
    """Episodes over which the noise decays linearly from noise_start to noise_end."""
    grad_clip: float = 0.5
    """Gradient norm limit of every actor and critic (Lowe et al.: 0.5)."""
    action_l2: float = 1e-3
    """Weight of the penalty on the actors' pre-tanh outputs (Lowe et al.'s regularizer)."""
    reward_scale: float = 1.0
    """Factor applied to rewards before they are stored."""
    terminal_value: str = "absorbing"
    """Target at the end where every task is claimed: ``"absorbing"`` bootstraps the final
    reward forever, r / (1 - gamma), as if the parked fleet kept receiving it (consistent with
    bootstrapping at the step limit); ``"zero"`` is the textbook terminal target r. With the
    positive IPF potentials, ``"zero"`` makes ending the episode by claiming the last task look
    worse than hovering next to it until the step limit."""
    mask_parked: bool = True
    """Zero the actions of parked AGVs (their actions are ignored) in acting and in the losses."""

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        """Check every field (type and range); normalise NumPy numbers to Python ones.

        Raises
        ------
        ValueError
            Naming the first bad field and its valid range.
        """
        for name, low in (("hidden", 1), ("batch_size", 1), ("buffer_size", 1),
                          ("num_envs", 1), ("updates_per_step", 1), ("learning_starts", 0),
                          ("noise_decay_episodes", 0)):
            setattr(self, name, check_int(name, getattr(self, name), low))
        for name, low, high, low_open, high_open in (
            ("actor_lr", 0.0, math.inf, True, False), ("critic_lr", 0.0, math.inf, True, False),
            ("gamma", 0.0, 1.0, False, True), ("tau", 0.0, 1.0, True, False),
            ("noise_start", 0.0, math.inf, False, False),
            ("noise_end", 0.0, math.inf, False, False),
            ("grad_clip", 0.0, math.inf, True, False),
            ("action_l2", 0.0, math.inf, False, False),
            ("reward_scale", 0.0, math.inf, True, False),
        ):
            setattr(self, name, check_real(name, getattr(self, name), low, high, low_open,
                                           high_open))
        check_choice("terminal_value", self.terminal_value, ("absorbing", "zero"))
        self.mask_parked = check_bool("mask_parked", self.mask_parked)
        if self.buffer_size < self.num_envs:
            raise ValueError(f"buffer_size ({self.buffer_size}) must be at least num_envs "
                             f"({self.num_envs}): every step stores num_envs transitions")
        if self.learning_starts > self.buffer_size:
            raise ValueError(f"learning_starts ({self.learning_starts}) must be at most "
                             f"buffer_size ({self.buffer_size}), or no update would ever run")


def movable_mask(obs: Tensor) -> Tensor:
    """1.0 for AGVs that still move, 0.0 for parked ones, shape (B, N, 1).

    Reads the "holds a task" bit (:data:`sim.observations.HOLDING`, the last feature of every
    layout); a parked AGV ignores its action, so its action is zeroed and carries no actor loss.
    """
    return 1.0 - obs[..., HOLDING]


@torch.no_grad()
def soft_update_(target: nn.Module, source: nn.Module, tau: float) -> None:
    """Polyak averaging ``target <- (1 - tau) target + tau source``, in place (one fused
    multi-tensor call where available, see :func:`learners.networks.select_torch_ops`)."""
    torch_ops().lerp_(list(target.parameters()), list(source.parameters()), tau)


class ActorCritic(nn.Module):
    """Base of the deterministic actor-critic learners.

    Subclasses build ``self.actor`` and ``self.critic`` (targets are deep copies), the two Adam
    optimizers, and implement :meth:`policy` and :meth:`update`.
    """

    name: ClassVar[str] = ""
    actor: nn.Module
    critic: nn.Module

    def __init__(self, obs_dim: int, state_dim: int, num_agents: int, config: Any) -> None:
        super().__init__()
        config.validate()
        self.obs_dim = check_int("obs_dim", obs_dim, 1)
        self.state_dim = check_int("state_dim", state_dim, 1)
        self.num_agents = check_int("num_agents", num_agents, 1)
        self.config = config
        self.updates = 0

    def _finish_init(self) -> None:
        """Create the target networks and the optimizers (call at the end of ``__init__``)."""
        cfg = self.config
        self.target_actor = copy.deepcopy(self.actor).requires_grad_(False)
        self.target_critic = copy.deepcopy(self.critic).requires_grad_(False)
        # fused: one kernel for all parameters (the stacked layout has few, large tensors),
        # where this torch has a fused CPU Adam (>= 2.4); multi-tensor foreach otherwise
        kernel = {"fused": True} if torch_ops().adam_fused else {"foreach": True}
        self.actor_optimizer = torch.optim.Adam(self.actor.parameters(), lr=cfg.actor_lr,
                                                **kernel)
        self.critic_optimizer = torch.optim.Adam(self.critic.parameters(), lr=cfg.critic_lr,
                                                 **kernel)

    # ------------------------------------------------------------------ acting
    def policy(self, obs: Tensor, target: bool = False) -> Tensor:
        """Deterministic actions in [-1, 1], (B, N, O) -> (B, N, 2)."""
        raise NotImplementedError

    @torch.no_grad()
    def act(self, obs: Tensor) -> Tensor:
        """Deterministic actions for evaluation, (B, N, O) -> (B, N, 2)."""
        return self.policy(obs)

    @torch.no_grad()
    def explore(self, obs: Tensor, noise_std: float, generator: torch.Generator) -> Tensor:
        """Actions with Gaussian exploration noise, clipped to [-1, 1], zero for parked AGVs
        (with ``mask_parked``).

        Parameters
        ----------
        obs : Tensor, shape (B, N, O)
        noise_std : float
            Standard deviation of the noise added to each action component.
        generator : torch.Generator
            Source of the noise.

        Returns
        -------
        Tensor, shape (B, N, 2)
        """
        a = self.policy(obs)
        noise = torch.randn(a.shape, generator=generator, dtype=a.dtype, device=a.device)
        a = (a + noise_std * noise).clamp(-1.0, 1.0)
        return a * movable_mask(obs) if self.config.mask_parked else a

    def td_target(self, batch: Batch, q_next: Tensor) -> Tensor:
        """y = r + gamma Q'(s', mu'(s')); at a terminal (every task claimed) Q' is replaced by
        the absorbing value r / (1 - gamma) or by 0 (``config.terminal_value``). (B, N)."""
        cfg = self.config
        terminal = batch.terminal.unsqueeze(1).bool()
        if cfg.terminal_value == "absorbing":
            after = torch.where(terminal, batch.reward / (1.0 - cfg.gamma), q_next)
        elif cfg.terminal_value == "zero":
            after = torch.where(terminal, torch.zeros_like(q_next), q_next)
        else:  # the config was changed after it was checked
            raise ValueError(f"terminal_value must be 'absorbing' or 'zero', got "
                             f"{cfg.terminal_value!r}")
        return batch.reward + cfg.gamma * after

    def update(self, batch: Batch) -> dict[str, float]:
        """One gradient step of the critic(s), then of the actor(s), then the soft update."""
        raise NotImplementedError

    def _soft_update(self) -> None:
        soft_update_(self.target_actor, self.actor, self.config.tau)
        soft_update_(self.target_critic, self.critic, self.config.tau)

    # ------------------------------------------------------------------ state as flat tensors
    def policy_tensors(self) -> dict[str, Tensor]:
        """The actor's weights only: what a deployed policy needs."""
        return {f"actor.{k}": v.detach().contiguous() for k, v in self.actor.state_dict().items()}

    def adapt_init_tensors(self, tensors: dict[str, Tensor]) -> dict[str, Tensor]:
        """Tensors of another run (``train(init_from=...)``) made to fit these networks where
        a setting that widens an input layer differs (the entity learners' ``parked_token``);
        here: unchanged."""
        return tensors

    def load_policy_tensors(self, tensors: dict[str, Tensor]) -> None:
        """Load :meth:`policy_tensors` output (strict: every key must match)."""
        sd = {k[len("actor."):]: v for k, v in tensors.items() if k.startswith("actor.")}
        self.actor.load_state_dict(sd, strict=True)
        self.target_actor.load_state_dict(sd, strict=True)

    def training_tensors(self) -> dict[str, Tensor]:
        """Networks, target networks and Adam moments, flat, for a safetensors checkpoint."""
        out: dict[str, Tensor] = {}
        for prefix, module in (("actor", self.actor), ("critic", self.critic),
                               ("target_actor", self.target_actor),
                               ("target_critic", self.target_critic)):
            for k, v in module.state_dict().items():
                out[f"{prefix}.{k}"] = v.detach().clone().contiguous()
        for prefix, opt in (("actor_optimizer", self.actor_optimizer),
                            ("critic_optimizer", self.critic_optimizer)):
            for i, st in opt.state_dict()["state"].items():
                for k, v in st.items():
                    out[f"{prefix}.{i}.{k}"] = torch.as_tensor(v).detach().clone().contiguous()
        out["updates"] = torch.tensor(self.updates, dtype=torch.int64)
        return out

    def load_training_tensors(self, tensors: dict[str, Tensor]) -> None:
        """Restore :meth:`training_tensors` output exactly."""
        for prefix, module in (("actor", self.actor), ("critic", self.critic),
                               ("target_actor", self.target_actor),
                               ("target_critic", self.target_critic)):
            sd = {k[len(prefix) + 1:]: v for k, v in tensors.items()
                  if k.startswith(prefix + ".") }
            module.load_state_dict(sd, strict=True)
        for prefix, opt in (("actor_optimizer", self.actor_optimizer),
                            ("critic_optimizer", self.critic_optimizer)):
            state: dict[int, dict[str, Tensor]] = {}
            for k, v in tensors.items():
                if k.startswith(prefix + "."):
                    _, i, name = k.split(".", 2)
                    state.setdefault(int(i), {})[name] = v.clone()
            opt.load_state_dict({"state": state,
                                 "param_groups": opt.state_dict()["param_groups"]})
        self.updates = int(tensors["updates"])
