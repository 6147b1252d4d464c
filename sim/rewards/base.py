"""What every reward is: the :class:`RewardFn` protocol, and the masking helper they share."""

from __future__ import annotations

from typing import Protocol

import torch
from torch import Tensor

from sim.state import SimState, StepContext

__all__ = ["RewardFn", "zero_inactive"]


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
