"""Argument checks shared by the simulator's public functions: each returns the value in the
form the simulator uses, or raises a ValueError that names the argument."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from torch import Tensor

__all__ = ["MAX_SLOTS", "as_actions", "check_count", "check_device", "check_env_ids",
           "check_seed", "check_slots", "real_array"]

MAX_SLOTS = 1024
"""The most entity slots of one kind an observation may have (``k_tasks``, ``k_pickups``,
``k_agents``): the nearest 1024 are more than any floor here fills, and far more would only
be padding that fills memory (a billion slots asked for 60 GB before this bound)."""


def check_count(name: str, value: Any) -> int:
    """``value`` as a positive int (bool, float and str refused)."""
    if (isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer))
            or value < 1):
        raise ValueError(f"{name} must be a positive integer, got {value!r}")
    return int(value)


def check_slots(name: str, value: Any) -> int:
    """``value`` as an int in [0, :data:`MAX_SLOTS`] (bool, float and str refused)."""
    if (isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer))
            or not 0 <= value <= MAX_SLOTS):
        raise ValueError(f"{name} must be an integer in [0, {MAX_SLOTS}], got {value!r}")
    return int(value)


def check_seed(seed: Any, name: str = "seed", bits: int = 64) -> int:
    """``seed`` as an int in [0, 2**bits) (64: the range of ``torch.Generator.manual_seed``)."""
    if (isinstance(seed, (bool, np.bool_)) or not isinstance(seed, (int, np.integer))
            or not 0 <= int(seed) < 2**bits):
        raise ValueError(f"{name} must be an integer in [0, 2**{bits}), got {seed!r}")
    return int(seed)


def check_device(device: Any) -> torch.device:
    """``device`` as a torch.device on which tensors can be made here, in the form that tensors
    made there report (``"cpu:0"`` is ``cpu``, ``"cuda"`` is ``cuda:0``)."""
    if not isinstance(device, (str, torch.device)):
        raise ValueError(f"device must be a str or torch.device such as 'cpu', got {device!r}")
    try:
        return torch.empty(0, device=torch.device(device)).device
    except (RuntimeError, AssertionError, ValueError) as err:
        raise ValueError(
            f"device {str(device)!r} is not usable here ({err}); "
            f"CUDA available: {torch.cuda.is_available()}; try 'cpu'"
        ) from None


def real_array(value: Any, name: str) -> Any:
    """``value`` if it holds real numbers (a tensor or anything numpy reads), else ValueError."""
    if isinstance(value, Tensor):
        if value.dtype.is_complex or value.dtype == torch.bool:
            raise ValueError(f"{name} must hold real numbers, got a {value.dtype} tensor")
        return value
    if value is None or isinstance(value, (str, bytes)):
        raise ValueError(f"{name} must be an array of real numbers, got {value!r}")
    try:
        arr = np.asarray(value)
    except (ValueError, TypeError) as err:
        raise ValueError(f"{name} must be an array of real numbers ({err})") from None
    if arr.dtype.kind not in "iuf":
        raise ValueError(f"{name} must hold real numbers, got an array of dtype {arr.dtype}")
    return arr


def check_env_ids(env_ids: Any, num_envs: int, device: torch.device) -> Tensor:
    """Environment indices (K,) int64 from ids or a boolean mask (B,); all when None.

    Raises
    ------
    ValueError
        For strings, floats, ids outside [0, num_envs), repeated ids or a mask of another shape.
    """
    if env_ids is None:
        return torch.arange(num_envs, device=device)
    if isinstance(env_ids, (str, bytes)):
        raise ValueError(f"env_ids must be integers or a boolean mask, got {env_ids!r}")
    try:
        idx = torch.as_tensor(env_ids, device=device)
    except (TypeError, ValueError, RuntimeError) as err:
        raise ValueError(f"env_ids must be integers or a boolean mask ({err})") from None
    if idx.dtype == torch.bool:
        if idx.shape != (num_envs,):
            raise ValueError(
                f"a boolean env mask must have shape ({num_envs},), got {tuple(idx.shape)}"
            )
        return idx.nonzero().flatten()
    if idx.dtype.is_floating_point or idx.dtype.is_complex:
        raise ValueError(f"env_ids must be integers or a boolean mask, got {idx.dtype} "
                         f"values {idx.flatten().tolist()[:8]}")
    idx = idx.long().flatten()
    if idx.numel() and (idx.min() < 0 or idx.max() >= num_envs):
        raise ValueError(f"env ids must lie in [0, {num_envs}), got {idx.tolist()}")
    if idx.numel() > 1 and torch.unique(idx).numel() != idx.numel():
        raise ValueError(f"env_ids must not repeat an environment, got {idx.tolist()}")
    return idx


def as_actions(actions: Any, shape: tuple[int, int, int], dtype: torch.dtype,
               device: torch.device) -> Tensor:
    """``actions`` as a detached tensor of ``dtype`` on ``device`` with exactly ``shape``
    (B, N, 2); finiteness is the caller's check (the episodes do it in their fused kernel).

    Raises
    ------
    ValueError
        For values that are not real numbers or another shape.
    """
    a = actions
    if not (type(a) is Tensor and a.dtype == dtype and a.device == device
            and not a.requires_grad):
        # The simulator is not differentiable: a policy's output is taken as numbers.
        a = torch.as_tensor(real_array(actions, "actions"), device=device, dtype=dtype).detach()
    if tuple(a.shape) != shape:
        raise ValueError(f"actions must have shape (B, N, 2) = {shape}, got {tuple(a.shape)}")
    return a
