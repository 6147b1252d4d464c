"""What every reward is: the :class:`RewardFn` protocol, and the masking helper they share."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, Protocol

import torch
from torch import Tensor

from sim.state import SimState, StepContext

__all__ = ["RewardFn", "check_reward_terms", "zero_inactive"]


class RewardFn(Protocol):
    """``reward(state, ctx) -> {term: (B, N)}``; terms are summed into the agent's reward.

    A reward whose class sets ``zeroes_inactive = True`` promises that every term is already
    0 in environments that were not running; the step then skips masking the summed reward.
    A reward that needs static facts (the floor, whether the fused kernels run) defines
    ``setup(world, kernels)``, which the environment calls once when it is made.
    """

    def __call__(self, state: SimState, ctx: StepContext) -> dict[str, Tensor]: ...


def zero_inactive(terms: dict[str, Tensor], active: Tensor) -> dict[str, Tensor]:
    """Zero every term in the environments that were not running during the step.

    Parameters
    ----------
    terms : dict of str to Tensor, each shape (B, N)
    active : Tensor of bool, shape (B,)

    Returns
    -------
    dict of str to Tensor, each shape (B, N)
    """
    keep = active.unsqueeze(1)
    return {name: torch.where(keep, value, torch.zeros_like(value))
            for name, value in terms.items()}


def check_reward_terms(terms: Any, shape: tuple[int, int], device: torch.device) -> None:
    """A user reward's output must be ``{name: finite floating (B, N) tensor}`` on ``device``.

    Raises
    ------
    ValueError
        Naming the term that is not a floating tensor, has another shape or device, or holds
        NaN or infinite values (or saying that the output is not a dict).
    """
    if not isinstance(terms, Mapping):
        raise ValueError(f"the reward callable must return a dict {{name: (B, N) tensor}}, "
                         f"got {type(terms).__name__}")
    for name, value in terms.items():
        if not isinstance(value, Tensor) or not value.dtype.is_floating_point:
            raise ValueError(f"reward term {name!r} must be a floating tensor of shape "
                             f"{shape}, got {type(value).__name__} {value!r:.60}")
        if tuple(value.shape) != shape or value.device != device:
            raise ValueError(f"reward term {name!r} must have shape {shape} on "
                             f"{device}, got {tuple(value.shape)} on {value.device}")
        if not bool(torch.isfinite(value).all()):
            raise ValueError(f"reward term {name!r} contains NaN or infinite values")
