"""A replay buffer preallocated in torch and filled from B parallel environments at once."""

from __future__ import annotations

import math
from dataclasses import dataclass

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
    Every field lives in one preallocated ``(capacity, F)`` float32 table ``rows`` (F: the
    fields' sizes summed); ``data[name]`` are views of its column ranges, shaped as the
    field. :meth:`add` writes the B transitions of one vectorized step as one block of rows;
    :meth:`sample` draws indices uniformly with replacement from an explicit
    ``torch.Generator`` (so that training is reproducible) and gathers them with one
    ``index_select`` of whole rows instead of one gather per field (batch 1024: 0.63 ms ->
    0.22 ms on 3v3, 1.33 ms -> 0.69 ms on 6v6, one thread). The sampled fields are views of
    the gathered ``(batch_size, F)`` table.
    """

    def __init__(
        self, capacity: int, num_agents: int, obs_dim: int, state_dim: int,
        device: str | torch.device = "cpu",
    ) -> None:
        if capacity < 1:
            raise ValueError(f"capacity must be positive, got {capacity}")
        C, N = int(capacity), int(num_agents)
        self.capacity = C
        self._shapes: dict[str, tuple[int, ...]] = {
            "obs": (N, obs_dim), "state": (state_dim,), "action": (N, 2), "reward": (N,),
            "next_obs": (N, obs_dim), "next_state": (state_dim,), "terminal": (),
        }
        self._cols: dict[str, tuple[int, int]] = {}
        width = 0
        for name, shape in self._shapes.items():
            size = math.prod(shape)
            self._cols[name] = (width, width + size)
            width += size
        self.rows = torch.zeros(C, width, device=device, dtype=torch.float32)
        """The table of all transitions, (capacity, F); row t holds every field of one."""
        self.data: dict[str, Tensor] = self._views(self.rows)
        self.pos = 0
        self.size = 0

    def _views(self, table: Tensor) -> dict[str, Tensor]:
        """Every field as a view of ``table`` (R, F): (R, *shape of the field)."""
        r = table.shape[0]
        return {name: table[:, lo:hi].view(r, *self._shapes[name])
                for name, (lo, hi) in self._cols.items()}

    def __len__(self) -> int:
        return self.size

    def add(self, batch: Batch) -> None:
        """Store the B transitions of one vectorized step (every field has leading size B)."""
        b = batch.obs.shape[0]
        if b > self.capacity:
            raise ValueError(f"cannot add {b} transitions to a buffer of capacity {self.capacity}")
        block = torch.empty(b, self.rows.shape[1], dtype=self.rows.dtype,
                            device=self.rows.device)
        for name, view in self._views(block).items():
            value = getattr(batch, name)
            if tuple(value.shape) != tuple(view.shape):
                raise ValueError(f"batch field {name!r} has shape {tuple(value.shape)}; "
                                 f"expected {tuple(view.shape)}")
            view.copy_(value)
        end = self.pos + b
        if end <= self.capacity:
            self.rows[self.pos:end] = block
        else:  # wraps around
            first = self.capacity - self.pos
            self.rows[self.pos:] = block[:first]
            self.rows[: b - first] = block[first:]
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
        return Batch(**self._views(torch.index_select(self.rows, 0, idx)))

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
