"""The registry of learning algorithms: name -> (learner class, config dataclass)."""

from __future__ import annotations

import dataclasses
from typing import Any

from learners.bicnet import BiCNet, BiCNetConfig
from learners.common import ActorCritic
from learners.entity import MADDPGE, BiCNetE, BiCNetEConfig, MADDPGEConfig
from learners.maddpg import MADDPG, MADDPGConfig

__all__ = ["ALGORITHMS", "ENTITY_ALGORITHMS", "PRESETS", "REWARD_NAMES", "check_algo",
           "make_config", "make_learner", "preset_overrides"]

ALGORITHMS: dict[str, tuple[type[ActorCritic], type]] = {
    "maddpg": (MADDPG, MADDPGConfig),
    "bicnet": (BiCNet, BiCNetConfig),
    "maddpg-e": (MADDPGE, MADDPGEConfig),
    "bicnet-e": (BiCNetE, BiCNetEConfig),
}
"""Registered algorithms: name -> (learner class, config dataclass). ``maddpg-e`` and
``bicnet-e`` are the entity-token learners of :mod:`learners.entity` (one set of weights for
any fleet size)."""

ENTITY_ALGORITHMS = ("maddpg-e", "bicnet-e")
"""The algorithms whose weights serve any N (:mod:`learners.entity`)."""

REWARD_NAMES = ("minidist", "greedy", "ipf", "ipf-time")
"""The rewards the learners train with, as named in ``sim.make_env``: the paper's three and
the variant ``ipf-time`` (``sim.rewards.REWARD_VARIANTS``: IPF with a heavier goal term and a
per-step team cost while any task is unclaimed, issue 16)."""


PRESETS: dict[str, dict[str, dict[str, Any]]] = {
    "default": {"maddpg": {}, "bicnet": {}, "maddpg-e": {}, "bicnet-e": {}},
    "fast": {
        "maddpg": {"num_envs": 64, "updates_per_step": 2, "batch_size": 512,
                   "actor_lr": 3e-3, "critic_lr": 3e-3, "tau": 0.03},
        "bicnet": {"num_envs": 128, "updates_per_step": 1, "actor_lr": 3e-3, "critic_lr": 3e-3,
                   "tau": 0.05},
        "maddpg-e": {"num_envs": 64, "updates_per_step": 1, "actor_lr": 3e-3,
                     "critic_lr": 3e-3, "tau": 0.03},
        "bicnet-e": {"num_envs": 64, "updates_per_step": 1, "actor_lr": 3e-3,
                     "critic_lr": 3e-3, "tau": 0.03},
    },
}
"""Named learner settings: preset -> algorithm -> config overrides.

``default`` is the config dataclass's defaults (what the shipped weights were trained with).
``fast`` does fewer, cheaper gradient updates per environment step, which is what makes
training about 5x faster in environment steps per second on a CPU (one update is
compute-bound there, see ``docs/learners.md``), and takes larger steps to make up for it:

* MADDPG: 64 environments and 2 updates per vectorized step (32 transitions per update
  instead of 8), batches of 512 instead of 1024 (replay ratio, batch x updates per
  transition, 16 instead of 128), learning rates 3e-3 instead of 1e-3, target rate tau 0.03
  instead of 0.01;
* BiCNet: 128 environments and 1 update per step (128 transitions per update instead of 16),
  replay ratio 4 instead of 32, learning rates 3e-3, tau 0.05.

Both updates are compute-bound on a CPU (their matrix products run near the core's float32
rate), so 5x the env steps per second needs about 5x fewer sample-gradients per transition;
a higher replay ratio at that speed (MADDPG 18, BiCNet 5) was tried and learned no better
(``benchmarks/results/learner_speed_quality.md``).

``benchmarks/learner_speed.py`` measures both presets' speed, and with ``--quality`` their
validation response after the same number of episodes.
"""


def preset_overrides(algo: str, preset: str) -> dict[str, Any]:
    """The config overrides of a named preset for one algorithm (a fresh dict).

    Raises
    ------
    ValueError
        For an unknown algorithm or preset.
    """
    check_algo(algo)
    if not isinstance(preset, str) or preset not in PRESETS:
        raise ValueError(f"unknown preset {preset!r}; expected one of {sorted(PRESETS)}")
    return dict(PRESETS[preset][algo])


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
