"""Learned, decentralized allocators: trained MADDPG / BiCNet policies behind the Allocator API.

``allocator.make("bicnet-ipf", scenario="3v3")`` loads the weights shipped in
``allocator/weights/3v3/bicnet-ipf.safetensors`` (or ``checkpoint=`` any policy file written by
``agv train``). There is no central planner: :meth:`LearnedAllocator.assign` places the AGVs
and tasks in the simulator, lets every AGV act on its own observation until the episode ends,
and reports the assignment that emerged (which AGV claimed which task) with the trajectories.
As a controller (``reset`` / ``act``) it runs in :func:`sim.evaluate` like any other allocator.

Names: ``"<algo>-<reward>"`` for algo in {maddpg, bicnet} and reward in {minidist, greedy, ipf},
and ``"bicnet-ipf-time"``: BiCNet trained with the ``ipf-time`` variant of the IPF reward
(issue 16's time terms), whose weights live in ``allocator/weights/<scenario>/time/``.

**Taught, not trained on a reward** (:data:`TAUGHT`): ``"bicnet-dagger"`` is BiCNet-E taught
by imitation (DAgger) of a whole-scene assignment rule, with its choice of task exchanged
among the AGVs (``choice_sinkhorn``). Its weights ship for any N only
(``allocator/weights/any/bicnet-dagger.safetensors``, whatever ``weights=`` says), and it was
taught with the whole scene in view: its :attr:`LearnedAllocator.scenario` shows every task
and every other AGV (``k_tasks = M``, ``k_agents = N - 1``), so run it on that scenario
(``sim.evaluate(solver, solver.scenario, ...)``); :meth:`LearnedAllocator.reset` warns when an
env shows it less. Best served ``shield=True, detour="discs"``. ``"maddpg-dagger"`` is its
lifelong counterpart: MADDPG-E's actor taught by DAgger which open order each AGV should
head for (``benchmarks/lifelong_dagger.py --teacher local``), choosing outright and driving
as the classical dispatchers' driver does (``waypoint_drive``). Its weights ship for lifelong
floors only (``allocator/weights/lifelong/maddpg-dagger.safetensors``), taught with
:data:`TAUGHT_LIFELONG_VIEW` open pickups and other AGVs in view: run it on
``solver.scenario`` (``sim.evaluate_lifelong(solver, solver.scenario, ...)``), shielded.

**Any fleet size.** ``allocator/weights/any/<algo>-<reward>.safetensors`` holds the weights of
the entity-token learner of the same family (``maddpg-e`` for ``maddpg-*``, ``bicnet-e`` for
``bicnet-*``; :mod:`learners.entity`), trained over a curriculum of fleet sizes, when they
have been shipped. ``allocator.make("maddpg-ipf", scenario="50v50", weights="auto")`` uses the
scenario's own weights where they exist (``3v3``, ``6v6``: the paper's table) and the any-N
weights for every other ``NvM`` scenario; ``weights="any"`` asks for the any-N weights on every
scenario; ``weights="scenario"`` (the default, as before) for the scenario's own only.

**Lifelong floors.** An entity learner trained on a lifelong floor (``agv train --algo
maddpg-e --scenario warehouse-20 ...``, :mod:`learners.train`) drives any ``warehouse-N``
floor: ``allocator.make("maddpg-greedy", scenario="warehouse-20", weights=RUN_DIR,
shield=True)`` and then ``sim.evaluate_lifelong(solver, "warehouse-20", ...)``. ``weights``
also takes a policy file or run folder (the same as ``checkpoint=``); the shipped lifelong
weights, when there are any, are ``allocator/weights/<warehouse-N>/<algo>-<reward>`` (the
floor's own) and ``allocator/weights/lifelong/<algo>-<reward>`` (any floor, for
``weights="auto"`` / ``"any"``). Episodic and lifelong weights do not mix (their observations
differ): each refuses the other mode's scenario. There is no one-shot plan on a lifelong floor
(:meth:`LearnedAllocator.assign` is for episodic scenes); the AGVs pick up the open orders
they reach (the simulator's rule for an idle AGV), as decentralized as the episodes' claims.
"""

from __future__ import annotations

import numbers
import os
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from allocator.base import Assignment, check_inputs

if TYPE_CHECKING:  # pragma: no cover
    from torch import Tensor

    from learners.policy import LearnedPolicy
    from sim.world import World

__all__ = [
    "LearnedAllocator", "LEARNED", "MissingWeightsError", "weights_path", "any_n_weights_path",
    "register_all", "ANY_N", "WEIGHT_CHOICES", "TAUGHT", "whole_view", "scenario_to_run",
    "taught_view", "TAUGHT_LIFELONG_VIEW", "LIFELONG_ONLY", "TAUGHT_NAMES",
]

ALGOS = ("maddpg", "bicnet")
REWARDS = ("minidist", "greedy", "ipf")
VARIANTS = {"bicnet": ("ipf-time",)}
"""Registered reward variants (:data:`sim.rewards.REWARD_VARIANTS`) served by a family: only
those with shipped weights, so that every registered name has weights on 3v3 and 6v6."""
TAUGHT = {"bicnet": ("dagger",), "maddpg": ("dagger",)}
"""Families taught by imitation instead of trained on a reward, by algorithm: registered as
``<algo>-<how>``, their weights ship for any N only (``bicnet-dagger``: episodic scenes;
``maddpg-dagger``: lifelong floors) and they see what they were taught with
(:func:`taught_view`)."""
TAUGHT_NAMES = tuple(f"{a}-{how}" for a, hows in TAUGHT.items() for how in hows)
"""The registry names of the :data:`TAUGHT` families."""
TAUGHT_HOW = {
    "bicnet-dagger": "taught by imitation (DAgger) of a whole-scene assignment rule, for "
                     "episodic scenes",
    "maddpg-dagger": "taught by imitation (DAgger) of a local assignment rule (each AGV's "
                     "share of the least-distance assignment among what it sees), for "
                     "lifelong floors",
}
"""How each :data:`TAUGHT` family was taught (its class docstring)."""
LIFELONG_ONLY = ("maddpg-dagger",)
"""Registered names whose weights serve lifelong floors only: on an episodic scene they raise
:class:`MissingWeightsError` (they have no one-shot ``assign``)."""
TAUGHT_LIFELONG_VIEW = 16
"""The open pickups and other AGVs a taught family sees on a lifelong floor (``k_pickups`` and
``k_agents``): the view its lifelong weights were taught with
(``benchmarks/lifelong_dagger.py --view 16``, the view of its teacher, ``LocalTeacher``)."""
VARIANT_FOLDERS = {"ipf-time": "time"}
"""The folder of a scenario's weights that holds a variant's weights."""
WEIGHTS_DIR = Path(__file__).resolve().parent / "weights"
ANY_N = "any"
"""The folder of ``allocator/weights`` with the any-N (entity-token) weights."""
LIFELONG = "lifelong"
"""The folder of ``allocator/weights`` with the any-N weights for lifelong floors."""
WEIGHT_CHOICES = ("scenario", "auto", "any")
"""``weights=``: only the scenario's own (the default); the scenario's own if shipped, else the
any-N ones (``auto``); only the any-N ones."""


def _whole(num_agents: int, num_tasks: int) -> dict[str, int]:
    """The view fields that show every task and every other AGV of a scene."""
    return dict(k_tasks=num_tasks, k_agents=max(num_agents - 1, 0))


def whole_view(scenario: Any) -> Any:
    """``scenario`` (a name or a scenario) with every task and every other AGV in view
    (``k_tasks = M``, ``k_agents = N - 1``): how a :data:`TAUGHT` family sees a scene.

    Raises
    ------
    ValueError
        For a scenario that is not one (:func:`sim.get_scenario`'s message) or a lifelong
        floor, which has no task slots.
    """
    from sim.scenarios import get_scenario

    scenario = get_scenario(scenario)
    if getattr(scenario, "lifelong", False):
        raise ValueError(f"{scenario.name!r} is a lifelong floor: it has pickups, not the "
                         "task slots of an episodic scene")
    return get_scenario(scenario, **_whole(scenario.num_agents, scenario.num_tasks))


def taught_view(scenario: Any) -> Any:
    """``scenario`` as a :data:`TAUGHT` family sees it: an episodic scene whole
    (:func:`whole_view`), a lifelong floor with :data:`TAUGHT_LIFELONG_VIEW` open pickups and
    other AGVs in view.

    Raises
    ------
    ValueError
        For a scenario that is not one (:func:`sim.get_scenario`'s message).
    """
    from sim.scenarios import get_scenario

    scenario = get_scenario(scenario)
    if getattr(scenario, "lifelong", False):
        return get_scenario(scenario, k_pickups=TAUGHT_LIFELONG_VIEW,
                            k_agents=TAUGHT_LIFELONG_VIEW)
    return whole_view(scenario)


def scenario_to_run(solver: Any, scenario: Any) -> Any:
    """The scenario to evaluate ``solver`` on in place of ``scenario``: a :data:`TAUGHT`
    family's own (:func:`taught_view`), any other solver's ``scenario`` as given."""
    return solver.scenario if getattr(solver, "taught", False) else scenario


class MissingWeightsError(FileNotFoundError, ValueError):
    """No trained weights for this allocator and scenario (a FileNotFoundError and a
    ValueError, so callers that catch either see it)."""


def weights_path(algo: str, reward: str, scenario: str) -> Path:
    """Where the package keeps the weights of ``<algo>-<reward>`` for a scenario (a reward
    variant's in the scenario's :data:`VARIANT_FOLDERS` folder)."""
    folder = WEIGHTS_DIR / scenario / VARIANT_FOLDERS.get(reward, "")
    return folder / f"{algo}-{reward}.safetensors"


def any_n_weights_path(algo: str, reward: str, lifelong: bool = False) -> Path:
    """Where the package keeps the any-N weights of ``<algo>-<reward>`` (the entity learner
    ``<algo>-e``'s, trained over a curriculum of fleet sizes; ``lifelong``: trained on a
    lifelong floor, for every ``warehouse-N``)."""
    return WEIGHTS_DIR / (LIFELONG if lifelong else ANY_N) / f"{algo}-{reward}.safetensors"


class LearnedAllocator:
    """A trained decentralized policy used as an allocator and as a controller.

    Parameters
    ----------
    scenario : str
        The scenario the policy was trained for (e.g. ``"3v3"``); selects the shipped weights
        and is checked against the checkpoint.
    checkpoint : path-like, optional
        A policy file (``.safetensors`` or its ``.json``) or a run folder from ``agv train``,
        instead of the shipped weights.
    max_steps : int, optional
        Step limit of :meth:`assign`'s rollout (a positive integer; default: the scenario's).
    shield : bool
        Pass the policy's actions through :class:`allocator.shield.SafetyShield` (the ORCA QP,
        then the braking filter) when it drives an env (default False: the policy as
        trained). :attr:`safety` then holds the shield and its intervention counts.
    keep_right : float, optional
        With ``shield=True``: the shield's lane angle on lifelong floors
        (``SafetyShield(keep_right=...)``, radians in [0, pi/2)). None (default): the angle the
        weights were trained with behind the shield (``shield_keep_right`` of an entity
        learner's config; 0 for the others).
    detour : bool or str
        With ``shield=True`` in episodic scenes: the shield first turns intentions that drive
        at a task through a parked AGV round it (``SafetyShield(detour=True)``,
        :class:`allocator.detour.ParkedDetour`; default False). ``"discs"``: the planner
        that sees parked AGVs as discs with the shield's own gaps (``ParkedDetour``'s
        ``model``; the default of True); ``"squares"``: the first model.
    weights : {"scenario", "auto", "any"} or path-like, optional
        Which shipped weights (when no ``checkpoint`` is given): only the scenario's own
        (``"scenario"``, the default); the scenario's own if they exist, else the any-N ones
        (``"auto"``); only the any-N ones (``allocator/weights/any``, ``"any"``), which serve
        every ``NvM`` scenario (on a lifelong floor: ``allocator/weights/lifelong``). A path
        (a policy file or an ``agv train`` run folder that exists) is the same as
        ``checkpoint=``. A :data:`TAUGHT` family has only any-N weights: every choice (and
        the default, None) is ``"any"`` for it.

    Attributes
    ----------
    scenario : Scenario
        The scenario the allocator serves; for a :data:`TAUGHT` family with the whole scene
        in view (:func:`whole_view`), which is what it should be evaluated on.
    taught : bool
        Whether the family was taught by imitation (:data:`TAUGHT`) rather than trained on a
        reward.

    Raises
    ------
    MissingWeightsError
        If no checkpoint is given and no weights ship for this scenario (the message names the
        files looked for and the ``agv train`` commands that create them).
    ValueError
        For an unknown option (the message lists the valid ones), a ``max_steps`` that is not
        a positive integer, a ``checkpoint`` that is not a path, or a checkpoint trained for
        another algorithm, reward or scenario, or truncated or corrupted.
    """

    name = "learned"
    algo = ""
    reward = ""

    def __init__(
        self, scenario: str = "3v3", checkpoint: str | os.PathLike[str] | None = None,
        max_steps: int | None = None, shield: bool = False, weights: str | None = None,
        keep_right: float | None = None, detour: bool | str = False, **options: Any,
    ) -> None:
        from learners.policy import LearnedPolicy
        from sim.scenarios import get_scenario

        if options:
            listed = ", ".join(repr(k) for k in options)
            raise ValueError(f"unknown option{'s' if len(options) > 1 else ''} {listed} for "
                             f"allocator {self.name!r}; valid options: "
                             f"{', '.join(self.option_names())}")
        if max_steps is not None and (isinstance(max_steps, bool)
                                      or not isinstance(max_steps, numbers.Integral)
                                      or max_steps < 1):
            raise ValueError(f"max_steps must be a positive integer or None (the scenario's "
                             f"limit), got {max_steps!r}")
        if checkpoint is not None and not isinstance(checkpoint, (str, os.PathLike)):
            raise ValueError(f"checkpoint must be a path to a policy .safetensors file (or "
                             f"None for the shipped weights), got {checkpoint!r}")
        if not isinstance(shield, (bool, np.bool_)):
            raise ValueError(f"shield must be True or False, got {shield!r}")
        if keep_right is not None and not shield:
            raise ValueError("keep_right is the shield's lane angle: it needs shield=True")
        from allocator.detour import detour_model

        detour = detour_model(detour)  # None, "squares" or "discs"
        if detour is not None and not shield:
            raise ValueError("detour is a stage of the shield: it needs shield=True")
        self.taught = self.reward in TAUGHT.get(self.algo, ())
        if weights is None:
            weights = "any" if self.taught else "scenario"
        if isinstance(weights, (str, os.PathLike)) and weights not in WEIGHT_CHOICES \
                and Path(weights).exists():
            if checkpoint is not None:
                raise ValueError("give the weights once: weights=<path> or checkpoint=<path>")
            checkpoint, weights = weights, "scenario"
        if not isinstance(weights, str) or weights not in WEIGHT_CHOICES:
            raise ValueError(f"weights must be one of {list(WEIGHT_CHOICES)} or the path of a "
                             f"policy file or run folder, got {weights!r}")
        self.scenario = get_scenario(scenario)
        self.lifelong = bool(getattr(self.scenario, "lifelong", False))
        """Whether the scenario is a lifelong floor (the policy then drives it through
        ``sim.evaluate_lifelong``)."""
        if checkpoint is None:
            checkpoint = self._shipped(weights)
        self.checkpoint = Path(checkpoint)
        from learners.algorithms import ENTITY_ALGORITHMS
        from learners.checkpoint import read_metadata

        entity_algo = f"{self.algo}-e"
        try:
            found = read_metadata(checkpoint).get("algo")
        except FileNotFoundError:
            found = None  # LearnedPolicy.load names the missing file
        self.any_n = found in ENTITY_ALGORITHMS
        """Whether the weights are an entity learner's (one set for any N)."""
        if self.taught and found is not None and not self.any_n:  # (missing: named below)
            raise ValueError(f"{self.name!r} is taught for any N: it needs an entity learner's "
                             f"({entity_algo!r}) policy file, got {found or 'no'} weights in "
                             f"{self.checkpoint}")
        if self.taught:
            self.scenario = taught_view(self.scenario)
        self._narrow_warned = False
        if self.any_n:
            # a taught family's file records the reward its RL stage had, not how it was taught
            self.policy: LearnedPolicy = LearnedPolicy.load(
                checkpoint, algo=entity_algo, reward=None if self.taught else self.reward)
            trained_lifelong = bool(getattr(self.policy.learner, "lifelong", False))
            if self.lifelong and not trained_lifelong:
                raise ValueError(f"the any-N weights {self.checkpoint} of {self.name!r} serve "
                                 f"the episodic scenarios (NvM); {self.scenario.name!r} is a "
                                 "lifelong floor, whose observations they were not trained on "
                                 "(train lifelong weights with `agv train --algo "
                                 f"{entity_algo} --scenario {self.scenario.name}`)")
            if trained_lifelong and not self.lifelong:
                raise ValueError(f"the weights {self.checkpoint} of {self.name!r} were trained "
                                 f"on the lifelong floor {self.policy.scenario!r}; they drive "
                                 f"lifelong floors (warehouse-N), not {self.scenario.name!r}")
        elif self.lifelong:
            raise ValueError(f"{self.checkpoint} holds {found or 'no'} weights: only the entity "
                             f"learner {entity_algo!r} drives a lifelong floor such as "
                             f"{self.scenario.name!r}")
        else:
            self.policy = LearnedPolicy.load(
                checkpoint, algo=self.algo, reward=self.reward, scenario=self.scenario.name)
        self.max_steps = None if max_steps is None else int(max_steps)
        self.last_trajectories: np.ndarray | None = None
        """(T + 1, N, 2) positions of every AGV during the last :meth:`assign` rollout."""
        self.safety: Any = None
        """The :class:`allocator.shield.SafetyShield` of a ``shield=True`` allocator."""
        if shield:
            from allocator.shield import SafetyShield

            if keep_right is None:  # the angle the weights were trained with behind the shield
                keep_right = float(getattr(self.policy.learner.config, "shield_keep_right", 0.0))
            self.safety = SafetyShield(_Unshielded(self), keep_right=keep_right,
                                       detour=detour or False)

    @classmethod
    def option_names(cls) -> tuple[str, ...]:
        """The keyword options the constructor takes."""
        return ("checkpoint", "detour", "keep_right", "max_steps", "scenario", "shield",
                "weights")

    def _shipped(self, weights: str) -> Path:
        """The shipped weights file for ``weights`` (see the class docstring)."""
        own = weights_path(self.algo, self.reward, self.scenario.name)
        anyn = any_n_weights_path(self.algo, self.reward,
                                  bool(getattr(self.scenario, "lifelong", False)))
        candidates = {"auto": [own, anyn], "scenario": [own], "any": [anyn]}[weights]
        if self.taught:
            candidates = [anyn]
        for path in candidates:
            if path.is_file():
                return path
        looked = " nor ".join(str(p) for p in candidates)
        if self.taught:
            modes = ("episodic scenes (NvM)", "lifelong floors (warehouse-N)")
            mode, other_mode = modes[::-1] if self.lifelong else modes
            other = any_n_weights_path(self.algo, self.reward, not self.lifelong)
            known = f" It ships for {other_mode} only ({other})." if other.is_file() else ""
            raise MissingWeightsError(
                f"no weights for {self.name!r} on scenario {self.scenario.name!r}: expected "
                f"{anyn}, its weights for {mode}.{known} It is taught by imitation "
                "(benchmarks/dagger_probe.py, benchmarks/lifelong_dagger.py); pass "
                "checkpoint=<a policy .safetensors file>")
        if weights == "scenario" and anyn.is_file():
            raise MissingWeightsError(
                f"no trained weights for {self.name!r} on scenario {self.scenario.name!r}: "
                f"expected {own}. Weights for any N ship at {anyn}: pass weights='any' (or "
                "'auto'), or checkpoint=<a policy .safetensors file>")
        hints = []
        if own in candidates:
            algo = f"{self.algo}-e" if getattr(self.scenario, "lifelong", False) else self.algo
            hints.append(f"`agv train --algo {algo} --reward {self.reward} --scenario "
                         f"{self.scenario.name} --export {own}`")
        if anyn in candidates and getattr(self.scenario, "lifelong", False):
            hints.append(f"`agv train --algo {self.algo}-e --reward {self.reward} --scenario "
                         f"{self.scenario.name} --export {anyn}` (any floor)")
        elif anyn in candidates:
            hints.append(f"`agv train --algo {self.algo}-e --reward {self.reward} --curriculum "
                         f"6v6:2000,10v10:1000,20v20:500 --export {anyn}` (any N)")
        raise MissingWeightsError(
            f"no trained weights for {self.name!r} on scenario {self.scenario.name!r}: "
            f"expected {looked}. Create them with {' or '.join(hints)}, or pass "
            "checkpoint=<a policy .safetensors file>")

    def _act(self, obs: Tensor) -> Tensor:
        """The policy's deterministic actions (any-N weights: at any observation size)."""
        if self.any_n:
            import torch

            return self.policy.learner.act(torch.as_tensor(obs, dtype=torch.float32))
        return self.policy.act(obs)

    # ------------------------------------------------------------------ controller
    def reset(self, env: Any) -> None:
        """Nothing to plan: every AGV decides from its own observation at every step.

        Raises
        ------
        ValueError
            For an env of the other mode than the weights': episodic weights on a lifelong
            floor (their observations differ; lifelong weights come from lifelong training) or
            lifelong weights on an episodic scene.
        """
        trained_lifelong = self.any_n and bool(getattr(self.policy.learner, "lifelong", False))
        if getattr(env, "lifelong", False) and not trained_lifelong:
            raise ValueError(f"{self.name!r} was trained on the episodic scenario "
                             f"{self.scenario.name!r}; it cannot drive a lifelong floor (its "
                             "observations differ). Lifelong floors are dispatched by "
                             "'hungarian' and 'greedy', or driven by weights trained on one "
                             f"(`agv train --algo {self.algo}-e --scenario warehouse-20`)")
        if trained_lifelong and not getattr(env, "lifelong", False):
            raise ValueError(f"{self.name!r} holds lifelong weights ({self.checkpoint}); they "
                             "drive lifelong floors (sim.evaluate_lifelong), not episodic "
                             "scenes")
        if self.any_n:  # read the env's observations with its layout (its K slots)
            self.policy.learner.reset(env)
        if self.taught and not self._narrow_warned:
            layout = env.obs_layout
            if getattr(env, "lifelong", False):
                want, seen = TAUGHT_LIFELONG_VIEW, (layout.k_pickups, layout.k_agents)
                narrow = seen[0] < want or seen[1] < min(want, env.num_agents - 1)
                what = (f"{want} open pickups and {want} other AGVs in view; this env shows "
                        f"{seen[0]} and {seen[1]}")
                run = "sim.evaluate_lifelong(solver, solver.scenario, ...)"
            else:
                narrow = layout.k_tasks < env.num_tasks or layout.k_agents < env.num_agents - 1
                what = (f"the whole scene in view; this env shows {layout.k_tasks} of "
                        f"{env.num_tasks} tasks and {layout.k_agents} of {env.num_agents - 1} "
                        "other AGVs")
                run = "sim.evaluate(solver, solver.scenario, ...)"
            if narrow:
                import warnings

                self._narrow_warned = True
                warnings.warn(
                    f"{self.name!r} was taught with {what}, and the policy does worse on "
                    f"less. Run it on solver.scenario ({run})", UserWarning, stacklevel=2)
        if self.safety is not None:
            self.safety.reset(env)

    def act(self, obs: Tensor) -> Tensor:
        """Deterministic actions of the trained policy, (B, N, O) -> (B, N, 2); with
        ``shield=True``, after the safety shield (:meth:`reset` first)."""
        if self.safety is not None:
            if self.safety.env is None:
                raise ValueError(f"{self.name!r} with shield=True needs reset(env) before act")
            return self.safety.filter(self._act(obs))
        return self._act(obs)

    # ------------------------------------------------------------------ allocator
    def _scene_scenario(self, agents: np.ndarray, tasks: np.ndarray,
                        world: World | None) -> Any:
        """The trained scenario's sensing and step limit on the given scene, run as given
        (:meth:`sim.scenarios.Scenario.given_scene`)."""
        base = self.scenario
        view = _whole(len(agents), len(tasks)) if self.taught else {}
        return type(base).given_scene(
            base, agents, tasks, world or base.world,
            max_steps=base.max_steps if self.max_steps is None else self.max_steps, **view)

    def assign(
        self, agents: np.ndarray, tasks: np.ndarray, world: World | None = None
    ) -> Assignment:
        """Run the decentralized policy from the given positions and report who claimed what.

        Parameters
        ----------
        agents : array-like, shape (N, 2)
            AGV positions (world units), at rest.
        tasks : array-like, shape (M, 2)
            Task positions.
        world : World, optional
            The floor (default: the trained scenario's); positions must lie inside it.

        Returns
        -------
        Assignment
            ``task_of_agent`` / ``agent_of_task`` from the claims at the end of the episode
            (-1 where an AGV claimed nothing or a task was not reached within the step limit),
            ``cost`` the distance travelled by all AGVs (serving AGVs counted to their task),
            ``paths`` the trajectory of each serving AGV up to its claim followed by the task
            position (None for idle AGVs), ``unserved`` the reason for every unserved task.
            ``last_trajectories`` holds every AGV's full trajectory.

        Raises
        ------
        ValueError
            On bad input (shapes, NaN, positions outside the world or inside a shelf).

        Notes
        -----
        Any scene the floor holds is run as given, whether or not the scenario's random
        spawner could have drawn it (AGVs closer together than the spawn spacing, more AGVs or
        tasks than it could place). Scenes of another size keep the trained scenario's
        sensing (``k_tasks``, ``k_agents``), so the observation size matches; BiCNet runs at
        any N, and MADDPG drives AGV i with actor ``i mod N_trained``. A :data:`TAUGHT` family
        sees the whole given scene.
        """
        import torch

        from sim.env import AGVEnv

        if self.lifelong:
            raise ValueError(f"{self.name!r} on the lifelong floor {self.scenario.name!r} has "
                             "no one-shot plan: run it with sim.evaluate_lifelong(solver, "
                             f"{self.scenario.name!r}, ...) (assign() is for episodic scenes)")
        agents, tasks = check_inputs(agents, tasks, world)
        n, m = len(agents), len(tasks)
        scenario = self._scene_scenario(agents, tasks, world)
        # in float64, before the simulator's float32 turns a huge coordinate into inf
        scenario.world.check_positions(agents, "agents")
        scenario.world.check_positions(tasks, "tasks")
        env = AGVEnv(scenario, num_envs=1, reward="minidist", seed=0)
        env.set_state(agents[None], tasks[None])
        obs = env.observe()
        if self.any_n:
            self.policy.learner.reset(env)
        act = self._act
        if self.safety is not None:  # the rollout shielded too, by a shield of its own
            from allocator.shield import SafetyShield

            rollout = SafetyShield(_Unshielded(self), qp=self.safety.qp,
                                   margin=self.safety.margin,
                                   detour=self.safety.detour_model or False)
            rollout.reset(env)
            act = rollout.act
        frames = [env.agent_pos[0].clone()]
        while not bool(env.done.all()):
            obs, _, _, _ = env.step(act(obs))
            frames.append(env.agent_pos[0].clone())
        traj = torch.stack(frames).double().numpy()  # (T + 1, N, 2)
        self.last_trajectories = traj
        task_of_agent = env.agent_task[0].numpy().astype(np.int64)
        agent_of_task = np.full(m, -1, dtype=np.int64)
        served = np.flatnonzero(task_of_agent >= 0)
        agent_of_task[task_of_agent[served]] = served
        traj[0] = agents
        steps = np.linalg.norm(np.diff(traj, axis=0), axis=-1)  # (T, N)
        paths: list[np.ndarray | None] = []
        for i in range(n):
            if task_of_agent[i] < 0:
                paths.append(None)
                continue
            # up to the claim (the AGV parks there), then the task itself, which lies within
            # the capture radius of the last position
            moving = np.flatnonzero(steps[:, i] > 0)
            end = int(moving[-1]) + 2 if len(moving) else 1
            paths.append(np.concatenate([traj[:end, i], tasks[task_of_agent[i]][None]]))
        idle = task_of_agent < 0
        cost = float(steps[:, idle].sum()) + sum(
            float(np.linalg.norm(np.diff(p, axis=0), axis=-1).sum()) for p in paths
            if p is not None)
        limit = env.max_steps
        reason = ("no AGV left: every AGV serves another task" if len(served) == n
                  else f"not claimed within the step limit ({limit} steps)")
        unserved = {int(j): reason for j in np.flatnonzero(agent_of_task < 0)}
        return Assignment(task_of_agent, agent_of_task, cost, paths=paths,
                          unserved=unserved, method=self.name)

    def __repr__(self) -> str:
        return (f"{type(self).__name__}(scenario={self.scenario.name!r}, "
                f"checkpoint={str(self.checkpoint)!r})")


class _Unshielded:
    """The policy of a learned allocator as a bare controller (what its shield wraps)."""

    def __init__(self, allocator: LearnedAllocator) -> None:
        self.name = allocator.name
        self._act = allocator._act

    def reset(self, env: Any) -> None:
        pass

    def act(self, obs: Tensor) -> Tensor:
        return self._act(obs)


def _make_class(algo: str, reward: str) -> type[LearnedAllocator]:
    name = f"{algo}-{reward}"
    pretty = {"maddpg": "MADDPG", "bicnet": "BiCNet"}[algo]
    cls_name = f"{pretty}{''.join(part.capitalize() for part in reward.split('-'))}Allocator"
    how = TAUGHT_HOW[name] if reward in TAUGHT.get(algo, ()) \
        else f"trained with the {reward} reward"
    doc = (f"The {pretty} policy {how} (registry name {name!r}); see "
           ":class:`LearnedAllocator`.")
    return type(cls_name, (LearnedAllocator,),
                {"name": name, "algo": algo, "reward": reward, "__doc__": doc,
                 "__module__": __name__})


LEARNED: dict[str, type[LearnedAllocator]] = {
    f"{a}-{r}": _make_class(a, r)
    for a in ALGOS for r in REWARDS + VARIANTS.get(a, ()) + TAUGHT.get(a, ())
}
"""The learned allocator classes by registry name."""
globals().update({cls.__name__: cls for cls in LEARNED.values()})


def register_all(registry: dict[str, type]) -> None:
    """Add every learned allocator to ``registry`` (``allocator.ALLOCATORS``)."""
    registry.update(LEARNED)
