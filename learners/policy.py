"""A trained, deterministic policy loaded from a checkpoint, usable as a ``sim`` controller."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from learners.algorithms import ALGORITHMS, ENTITY_ALGORITHMS, check_algo, make_config, make_learner
from learners.checkpoint import load_checkpoint, resolve_checkpoint_path
from learners.common import ActorCritic

__all__ = ["LearnedPolicy", "load_policy", "build_learner", "is_lifelong"]


def is_lifelong(scenario: str) -> bool:
    """Whether a scenario name is a lifelong floor (``warehouse-N``).

    Raises
    ------
    ValueError
        For an unknown scenario.
    """
    import sim

    return bool(getattr(sim.get_scenario(scenario), "lifelong", False))


def build_learner(algo: str, obs_dim: int, state_dim: int, num_agents: int,
                  config: Any = None, lifelong: bool = False) -> ActorCritic:
    """:func:`learners.algorithms.make_learner`, and for ``lifelong`` an entity learner whose
    networks read lifelong observations (:class:`learners.entity.EntityLearner`).

    Raises
    ------
    ValueError
        For ``lifelong`` with an algorithm that is not an entity learner (only those read a
        lifelong floor), or what ``make_learner`` refuses.
    """
    check_algo(algo)
    if algo not in ENTITY_ALGORITHMS and not lifelong:
        return make_learner(algo, obs_dim, state_dim, num_agents, config)
    if algo not in ENTITY_ALGORITHMS:
        raise ValueError(f"only the entity learners {list(ENTITY_ALGORITHMS)} run on lifelong "
                         f"floors (warehouse-N); got {algo!r}")
    cls, cfg_cls = ALGORITHMS[algo]
    if config is None or isinstance(config, dict):
        config = make_config(algo, config)
    elif not isinstance(config, cfg_cls):
        raise ValueError(f"{algo} needs a {cfg_cls.__name__}, got {type(config).__name__}")
    return cls(obs_dim, state_dim, num_agents, config, lifelong=bool(lifelong))


class LearnedPolicy:
    """The actor of a trained learner: ``act(obs)`` maps (B, N, O) observations to (B, N, 2)
    deterministic actions (no exploration noise).

    Parameters
    ----------
    learner : ActorCritic
        A MADDPG or BiCNet learner holding trained actor weights.
    metadata : dict
        The checkpoint's metadata (algorithm, reward, scenario, sizes, config, ...).

    Attributes
    ----------
    algo, reward, scenario : str
    num_agents, obs_dim : int
    any_n : bool
        Whether the weights are an entity learner's (``maddpg-e``, ``bicnet-e``), which read
        observations of any size: their layout comes from :meth:`reset`.
    """

    def __init__(self, learner: ActorCritic, metadata: dict[str, Any]) -> None:
        self.learner = learner.eval()
        self.metadata = metadata
        self.algo: str = metadata["algo"]
        self.reward: str = metadata["reward"]
        self.scenario: str = metadata["scenario"]
        self.num_agents: int = int(metadata["num_agents"])
        self.obs_dim: int = int(metadata["obs_dim"])
        self.any_n: bool = self.algo in ENTITY_ALGORITHMS

    def reset(self, env: Any) -> None:
        """Called once per batch of episodes by :func:`sim.evaluate` (and of runs by
        :func:`sim.evaluate_lifelong`): an entity policy takes the env's observation layout
        (its K slots; lifelong: and the floor's waypoints); the others need nothing.

        Raises
        ------
        ValueError
            For an entity policy on an env of the other mode (episodic weights on a lifelong
            floor or the reverse).
        """
        if self.any_n:
            self.learner.reset(env)

    @classmethod
    def load(
        cls, path: str | os.PathLike[str], *, algo: str | None = None,
        reward: str | None = None, scenario: str | None = None, obs_dim: int | None = None,
    ) -> LearnedPolicy:
        """Load a policy (or training) checkpoint, checking what it was trained for.

        Parameters
        ----------
        path : path-like
            ``.safetensors`` file, its ``.json`` sidecar, or a run folder (its latest policy).
        algo, reward, scenario, obs_dim : optional
            Expected values; a mismatch raises a ValueError naming the field.

        Raises
        ------
        FileNotFoundError, ValueError
            See :func:`learners.checkpoint.load_checkpoint`.
        """
        p = Path(path)
        if p.is_dir() or (p.suffix == "" and not p.with_name(p.name + ".safetensors").exists()):
            p = p / "policy.safetensors"
        if algo is not None:
            check_algo(algo)
        tensors, meta = load_checkpoint(p, algo=algo, reward=reward, scenario=scenario,
                                        obs_dim=obs_dim)
        learner = build_learner(meta["algo"], int(meta["obs_dim"]), int(meta["state_dim"]),
                                int(meta["num_agents"]), dict(meta["config"]),
                                lifelong=is_lifelong(meta["scenario"]))
        try:
            learner.load_policy_tensors({k: v for k, v in tensors.items()
                                         if k.startswith("actor.")})
        except RuntimeError as err:
            raise ValueError(f"checkpoint {resolve_checkpoint_path(p)} does not hold the actor "
                             f"its metadata describes: {err}") from None
        return cls(learner, meta)

    @torch.no_grad()
    def act(self, obs: Tensor) -> Tensor:
        """Deterministic actions.

        Parameters
        ----------
        obs : Tensor, shape (B, N, O)

        Returns
        -------
        Tensor, shape (B, N, 2), in [-1, 1]

        Raises
        ------
        ValueError
            If O differs from the training observation size (entity policies: if the
            observations do not fit the layout given by :meth:`reset` or inferred from N, O).

        Notes
        -----
        BiCNet shares its weights across agents and runs at any N. A MADDPG policy trained
        with N actors drives AGV i of a scene with another N by actor ``i mod N``.
        """
        obs = torch.as_tensor(obs, dtype=torch.float32)
        if obs.dim() != 3 or (obs.shape[-1] != self.obs_dim and not self.any_n):
            raise ValueError(f"observations must have shape (B, N, {self.obs_dim}) for this "
                             f"{self.algo} policy (trained on {self.scenario}), got "
                             f"{tuple(obs.shape)}")
        return self.learner.act(obs)

    __call__ = act

    def __repr__(self) -> str:
        return (f"LearnedPolicy(algo={self.algo!r}, reward={self.reward!r}, "
                f"scenario={self.scenario!r}, episodes={self.metadata.get('episodes')})")


def load_policy(path: str | os.PathLike[str], **expected: Any) -> LearnedPolicy:
    """Shorthand for :meth:`LearnedPolicy.load`."""
    return LearnedPolicy.load(path, **expected)
