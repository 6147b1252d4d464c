"""A replay buffer preallocated in torch and filled from B parallel environments at once."""

from __future__ import annotations

from dataclasses import dataclass, fields

import torch
from torch import Tensor

__all__ = ["Batch", "ReplayBuffer"]


@dataclass
class Batch:
    """A batch of joint transitions (B = batch size, N agents)."""

    obs: Tensor  # (B, N, O) local observations
    state: Tensor  # (B, S) global state, for centralized critics
    action: Tensor  # (B, N, 2) actions taken (0 for parked AGVs)
    reward: Tensor  # (B, N) per-agent rewards, already scaled
    next_obs: Tensor  # (B, N, O)
    next_state: Tensor  # (B, S)
    terminal: Tensor  # (B,) float, 1 where the episode ended because every task was claimed


class ReplayBuffer:
    """A circular buffer of joint transitions, one row per environment step.

    Parameters
    ----------
    capacity : int
        Number of transitions kept (the oldest are overwritten).
    num_agents, obs_dim, state_dim : int
        N, O and S of the environment.
    device : str or torch.device

    Notes
    -----
    :meth:`add` writes the B transitions of one vectorized step with one indexed copy per
    field; :meth:`sample` draws indices uniformly with replacement from an explicit
    ``torch.Generator`` so that training is reproducible.
    """

    def __init__(
        self, capacity: int, num_agents: int, obs_dim: int, state_dim: int,
        device: str | torch.device = "cpu",
    ) -> None:
        if capacity < 1:
            raise ValueError(f"capacity must be positive, got {capacity}")
        C, N = int(capacity), int(num_agents)
        z = dict(device=device, dtype=torch.float32)
        self.capacity = C
        self.data: dict[str, Tensor] = {
            "obs": torch.zeros(C, N, obs_dim, **z),
            "state": torch.zeros(C, state_dim, **z),
            "action": torch.zeros(C, N, 2, **z),
            "reward": torch.zeros(C, N, **z),
            "next_obs": torch.zeros(C, N, obs_dim, **z),
            "next_state": torch.zeros(C, state_dim, **z),
            "terminal": torch.zeros(C, **z),
        }
        self.pos = 0
        self.size = 0

    def __len__(self) -> int:
        return self.size

    def add(self, batch: Batch) -> None:
        """Store the B transitions of one vectorized step (every field has leading size B)."""
        b = batch.obs.shape[0]
        if b > self.capacity:
            raise ValueError(f"cannot add {b} transitions to a buffer of capacity {self.capacity}")
        idx = (self.pos + torch.arange(b)) % self.capacity
        for f in fields(Batch):
            self.data[f.name][idx] = getattr(batch, f.name).to(self.data[f.name].dtype)
        self.pos = (self.pos + b) % self.capacity
        self.size = min(self.size + b, self.capacity)

    def sample(self, batch_size: int, generator: torch.Generator) -> Batch:
        """Draw ``batch_size`` transitions uniformly with replacement.

        Returns
        -------
        Batch
            Tensors with leading dimension ``batch_size``.
        """
        if self.size == 0:
            raise ValueError("cannot sample from an empty replay buffer")
        idx = torch.randint(self.size, (batch_size,), generator=generator)
        return Batch(**{k: v[idx] for k, v in self.data.items()})

    # ------------------------------------------------------------------ checkpointing
    def state_dict(self) -> dict[str, Tensor]:
        """The filled part of the buffer and its write position, as tensors."""
        out = {f"buffer.{k}": v[: self.size].contiguous() for k, v in self.data.items()}
        out["buffer.pos"] = torch.tensor(self.pos, dtype=torch.int64)
        return out

    def load_state_dict(self, state: dict[str, Tensor]) -> None:
        """Restore what :meth:`state_dict` returned.

        Raises
        ------
        ValueError
            If the saved shapes do not fit this buffer.
        """
        size = state["buffer.obs"].shape[0]
        if size > self.capacity:
            raise ValueError(
                f"saved replay buffer holds {size} transitions; this buffer's capacity is "
                f"{self.capacity}"
            )
        for k, v in self.data.items():
            saved = state[f"buffer.{k}"]
            if tuple(saved.shape[1:]) != tuple(v.shape[1:]):
                raise ValueError(
                    f"saved replay buffer field {k!r} has rows of shape {tuple(saved.shape[1:])}; "
                    f"expected {tuple(v.shape[1:])}"
                )
            v[:size] = saved
        self.size = size
        self.pos = int(state["buffer.pos"])
