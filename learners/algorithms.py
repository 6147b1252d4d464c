"""The registry of learning algorithms: name -> (learner class, config dataclass)."""

from __future__ import annotations

import dataclasses
from typing import Any

from learners.bicnet import BiCNet, BiCNetConfig
from learners.common import ActorCritic
from learners.maddpg import MADDPG, MADDPGConfig

__all__ = ["ALGORITHMS", "REWARD_NAMES", "check_algo", "make_config", "make_learner"]

ALGORITHMS: dict[str, tuple[type[ActorCritic], type]] = {
    "maddpg": (MADDPG, MADDPGConfig),
    "bicnet": (BiCNet, BiCNetConfig),
}
"""Registered algorithms: name -> (learner class, config dataclass)."""

REWARD_NAMES = ("minidist", "greedy", "ipf")
"""The paper's rewards, as named in ``sim.make_env``."""


def check_algo(algo: str) -> None:
    """Raise a ValueError naming the known algorithms if ``algo`` is not one of them."""
    if not isinstance(algo, str) or algo not in ALGORITHMS:
        raise ValueError(f"unknown algorithm {algo!r}; expected one of {sorted(ALGORITHMS)}")


def make_config(algo: str, overrides: dict[str, Any] | None = None) -> Any:
    """The algorithm's config dataclass with some fields replaced.

    Raises
    ------
    ValueError
        For an unknown algorithm or field name.
    """
    check_algo(algo)
    cls = ALGORITHMS[algo][1]
    overrides = dict(overrides or {})
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(overrides) - names)
    if unknown:
        raise ValueError(f"unknown {cls.__name__} field(s) {unknown}; expected some of "
                         f"{sorted(names)}")
    return cls(**overrides)


def make_learner(
    algo: str, obs_dim: int, state_dim: int, num_agents: int, config: Any = None
) -> ActorCritic:
    """Build a learner; ``config`` may be the dataclass, a dict of overrides, or None."""
    check_algo(algo)
    cls, cfg_cls = ALGORITHMS[algo]
    if config is None or isinstance(config, dict):
        config = make_config(algo, config)
    elif not isinstance(config, cfg_cls):
        raise ValueError(f"{algo} needs a {cfg_cls.__name__}, got {type(config).__name__}")
    return cls(obs_dim, state_dim, num_agents, config)
