"""Reward functions, chosen by name in :func:`sim.make_env`; one module each.

A reward is a small callable ``reward(state, ctx) -> {term_name: (B, N) tensor}`` of the
state after the step (:class:`sim.state.SimState`) and the step's context
(:class:`sim.state.StepContext`, the distances and collisions the environment already computed
for the step); the environment sums the terms into the per-agent reward and reports each term
in ``info["reward_terms"]`` so that shaping can be audited.

- ``minidist`` (global, :mod:`sim.rewards.minidist`): every AGV gets the paper's
  R_t = -(sum over tasks of the distance to the nearest AGV) - (number of overlapping AGV
  pairs). Terms ``distance``, ``collision``.
- ``greedy`` (individual, :mod:`sim.rewards.greedy`): each idle AGV gets the distance it closed
  to its nearest unclaimed task during the step, minus the number of AGVs it overlaps. Terms
  ``progress``, ``collision``.
- ``ipf`` (:mod:`sim.rewards.ipf`): r_IPF + r_g + r_c, the paper's information potential field
  reward. Terms ``ipf``, ``goal``, ``collision``.

One variant (:data:`REWARD_VARIANTS`, not one of the paper's rewards, and not in
:data:`REWARDS`) is made by name too:

- ``ipf-time``: the IPF reward with its goal term weighted by :data:`GOAL_WEIGHT` and a
  ``time`` term, ``-TIME_COST`` (:data:`TIME_COST`) for every AGV after each step that leaves
  a task unclaimed, which pays for finishing early (issue 16;
  ``IPFReward(goal_weight=..., time_cost=...)`` sets other values). Episodic scenarios only.

Every term is a (B, N) tensor and is zero in environments that were already done before the
step (the environment zeroes their summed reward too, so the reported terms add up to it).
The protocol is :class:`sim.rewards.base.RewardFn`.
"""

from __future__ import annotations

from collections.abc import Callable

from sim.rewards.base import RewardFn
from sim.rewards.greedy import Greedy
from sim.rewards.ipf import IPFReward
from sim.rewards.lifelong import LifelongGreedy, LifelongIPF, LifelongMiniDist
from sim.rewards.minidist import MiniDist

__all__ = ["RewardFn", "MiniDist", "Greedy", "IPFReward", "REWARDS", "LIFELONG_REWARDS",
           "LifelongMiniDist", "LifelongGreedy", "LifelongIPF", "make_reward", "REWARD_VARIANTS",
           "TIME_COST", "GOAL_WEIGHT"]

REWARDS: dict[str, Callable[[], RewardFn]] = {
    "minidist": MiniDist,
    "greedy": Greedy,
    "ipf": IPFReward,
}
"""Registered rewards by name."""

LIFELONG_REWARDS: dict[str, Callable[[], RewardFn]] = {
    "minidist": LifelongMiniDist,
    "greedy": LifelongGreedy,
    "ipf": LifelongIPF,
}
"""The same names in lifelong mode (:mod:`sim.rewards.lifelong`)."""

TIME_COST = 3.0
"""The per-step team cost of ``ipf-time`` while any task is unclaimed (chosen on the
validation seed 12345 for issue 16, see ``docs/learners.md``)."""

GOAL_WEIGHT = 3.0
"""The factor of ``ipf-time``'s goal term (chosen with :data:`TIME_COST`)."""

REWARD_VARIANTS: dict[str, Callable[[], RewardFn]] = {
    "ipf-time": lambda: IPFReward(goal_weight=GOAL_WEIGHT, time_cost=TIME_COST),
}
"""Registered variants of the paper's rewards by name (episodic scenarios only)."""


def make_reward(reward: str | RewardFn, lifelong: bool = False) -> RewardFn:
    """Return the reward callable for a registered name, or the callable itself.

    Parameters
    ----------
    reward : str or RewardFn
        A name of :data:`REWARDS` or :data:`REWARD_VARIANTS`, or an object called as
        ``reward(state, ctx)``.
    lifelong : bool
        Names give their lifelong forms (:data:`LIFELONG_REWARDS`); a variant has none.

    Returns
    -------
    RewardFn

    Raises
    ------
    ValueError
        For an unknown name, a class instead of an instance, or anything that is neither a
        name nor a callable (a list, a number, None); the message lists the known names. For
        a variant in lifelong mode.
    """
    names = ", ".join(repr(name) for name in sorted(REWARDS))
    if isinstance(reward, str):
        if reward in REWARD_VARIANTS:
            if lifelong:
                raise ValueError(f"reward {reward!r} is a variant for the episodic scenarios "
                                 f"and has no lifelong form; use one of {names}")
            return REWARD_VARIANTS[reward]()
        if reward not in REWARDS:
            variants = ", ".join(repr(name) for name in sorted(REWARD_VARIANTS))
            raise ValueError(f"unknown reward {reward!r}; expected one of {names}, a variant "
                             f"({variants}), or a callable reward(state, ctx) -> "
                             "{term: (B, N) tensor}")
        return (LIFELONG_REWARDS if lifelong else REWARDS)[reward]()
    if isinstance(reward, type):
        raise ValueError(f"reward must be a name or a reward object, got the class "
                         f"{reward.__name__}; pass an instance, {reward.__name__}()")
    if not callable(reward):
        raise ValueError(f"reward must be one of {names} or a callable reward(state, ctx) -> "
                         f"{{term: (B, N) tensor}}, got {type(reward).__name__} {reward!r}")
    return reward
