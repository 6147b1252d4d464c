"""Counter-based random streams: the draws of lifelong operation that no controller may change.

The orders that arrive and the breakdowns that happen must be the same for every controller and
whatever the batching (``DESIGN.md``, "Lifelong operation"). A stateful generator cannot
promise that: how many numbers it has handed out depends on how many environments share it and
on what happened before. Here every draw is instead a pure function of a 64-bit key (one per
environment, itself drawn from the environment's ``torch.Generator`` or derived from an
evaluation seed and the run's index) and of counters that say which draw it is (stream, step,
order id, AGV). The mixing function is SplitMix64's finaliser, computed with wrapping int64
arithmetic in torch, batched over every environment and AGV at once.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from sim.native import pointer

__all__ = ["ARRIVALS", "FAULTS", "ORDER_POINTS", "derive_key", "mix", "uniform"]

ARRIVALS = 1
"""Stream of the per-step arrival counts."""
ORDER_POINTS = 2
"""Stream of each order's pickup and drop-off choice."""
FAULTS = 3
"""Stream of the per-AGV-step breakdown draws."""

_GOLDEN = -7046029254386353131  # 0x9E3779B97F4A7C15 as a signed int64
_M1 = -4658895280553007687  # 0xBF58476D1CE4E5B9
_M2 = -7723592293110705685  # 0x94D049BB133111EB


def _shift(z: Tensor, k: int) -> Tensor:
    """Logical right shift of int64 values (torch's ``>>`` is arithmetic)."""
    return (z >> k) & ((1 << (64 - k)) - 1)


def mix(z: Tensor) -> Tensor:
    """SplitMix64's finaliser on int64 values (wrapping arithmetic), elementwise."""
    z = (z ^ _shift(z, 30)) * _M1
    z = (z ^ _shift(z, 27)) * _M2
    return z ^ _shift(z, 31)


def derive_key(key: Tensor | int, *counters: Tensor | int) -> Tensor:
    """A new key from a key and counters: ``mix(... mix(key + golden * (c1 + 1)) ...)``.

    Parameters
    ----------
    key : Tensor of int64 or int
    *counters : Tensor of int64 or int
        Broadcast against ``key``.

    Returns
    -------
    Tensor of int64, the broadcast shape.
    """
    z = torch.as_tensor(key, dtype=torch.int64)
    for c in counters:
        c = torch.as_tensor(c, dtype=torch.int64, device=z.device)
        z = mix(z + (c + 1) * _GOLDEN)
    return mix(z)


def uniform(key: Tensor | int, *counters: Tensor | int, kernels: Any = None) -> Tensor:
    """Uniform draws in [0, 1) (float64, 53 random bits), one per broadcast element.

    Parameters
    ----------
    key : Tensor of int64 or int
        The environment's key, e.g. shape (B, 1) against counters of shape (B, N).
    *counters : Tensor of int64 or int
    kernels : ctypes.CDLL, optional
        The fused kernels (:mod:`sim.native`): the same draws from ``sim/_native/streams.h``
        (one C loop instead of some thirty small int64 tensor operations); CPU tensors only.

    Returns
    -------
    Tensor of float64, the broadcast shape.
    """
    if kernels is not None:
        return _uniform_native(kernels, key, counters)
    bits = _shift(derive_key(key, *counters), 11)
    return bits.to(torch.float64) * (1.0 / (1 << 53))


def _uniform_native(lib: Any, key: Tensor | int, counters: tuple[Tensor | int, ...]) -> Tensor:
    parts = [torch.as_tensor(key, dtype=torch.int64)]
    parts += [torch.as_tensor(c, dtype=torch.int64) for c in counters]
    shape = torch.broadcast_shapes(*(p.shape for p in parts))
    k = parts[0].expand(shape).contiguous()
    cs = (torch.stack([p.expand(shape) for p in parts[1:]]) if counters
          else torch.zeros((0, *shape), dtype=torch.int64)).contiguous()
    out = torch.empty(shape, dtype=torch.float64)
    n = k.numel()
    lib.agv_uniform(n, len(counters), pointer(k, torch.int64, tuple(shape), "key"),
                    pointer(cs, torch.int64, (len(counters), *shape), "counters"),
                    out.data_ptr())
    return out
