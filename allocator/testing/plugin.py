"""pytest plugin: fixtures for allocation tests (registered as the ``agv_allocation`` entry point).

Installed with the package, so any test suite in the same environment gets the fixtures:

``agv_world``
    A :class:`sim.World`; by default every test using it runs twice, on the open MPE box
    (``"open"``) and on the shelf warehouse of :func:`sim.scenarios.warehouse_world`
    (``"warehouse"``). Choose with indirect parametrization.
``agv_scenario``
    An :class:`AGVScenario`: a named :class:`sim.Scenario` (default ``"3v3"``) with one seeded
    scene of it, ready for ``assign``. Parametrize indirectly with any scenario name
    (``"3v3"``, ``"6v6"``, ``"warehouse"``, ``"NvM"``).

Examples
--------
A user's test file::

    import pytest
    from allocator.testing import assert_consistent_plan

    from my_fleet import MyAllocator

    def test_plans_on_every_floor(agv_world):
        agents, tasks = [[0.0, 0.0], [0.5, 0.0]], [[0.0, 0.5], [0.5, 0.5]]
        plan = MyAllocator().assign(agents, tasks, agv_world)
        assert_consistent_plan(plan, agents, tasks, agv_world)

    def test_a_spawned_scene(agv_scenario):
        s = agv_scenario
        plan = MyAllocator().assign(s.agents, s.tasks, s.world)
        assert_consistent_plan(plan, s.agents, s.tasks, s.world)

    @pytest.mark.parametrize("agv_scenario", ["3v3", "6v6"], indirect=True)
    def test_both_sizes(agv_scenario):
        ...

    @pytest.mark.parametrize("agv_world", ["warehouse"], indirect=True)
    def test_shelves_only(agv_world):
        ...
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import pytest

if TYPE_CHECKING:  # pragma: no cover
    from sim.scenarios import Scenario
    from sim.world import World

__all__ = ["AGVScenario", "make_world", "make_scenario", "WORLDS"]

WORLDS = ("open", "warehouse")
"""The names ``agv_world`` takes, in its default order."""


@dataclass(frozen=True)
class AGVScenario:
    """A named scenario and one seeded scene of it.

    Attributes
    ----------
    name : str
        The scenario's name (``"3v3"``, ``"warehouse"``, ...).
    scenario : sim.Scenario
        The scenario itself (``spawn`` draws more scenes).
    world : sim.World
        Its floor.
    agents : np.ndarray, shape (N, 2)
        AGV positions of the scene, float64.
    tasks : np.ndarray, shape (M, 2)
        Task positions of the scene, float64.
    seed : int
        Seed the scene was drawn with.
    """

    name: str
    scenario: Scenario
    world: World
    agents: np.ndarray
    tasks: np.ndarray
    seed: int


def make_world(name: object) -> World:
    """The world called ``name`` (one of :data:`WORLDS`), or ``name`` itself if a World.

    Raises
    ------
    ValueError
        For another name.
    """
    from sim.scenarios import warehouse_world
    from sim.world import World

    if isinstance(name, World):
        return name
    if name == "open":
        return World()
    if name == "warehouse":
        return warehouse_world()
    raise ValueError(f"agv_world must be one of {list(WORLDS)} or a sim.World, got {name!r}")


def make_scenario(name: object, seed: int = 0) -> AGVScenario:
    """The scenario ``name`` with the scene that its spawner draws first with ``seed``.

    Raises
    ------
    ValueError
        For an unknown scenario (the message lists the known ones).
    """
    import torch

    import sim

    scenario = sim.get_scenario(name)
    agents, tasks = scenario.spawn(1, torch.Generator().manual_seed(seed), torch.device("cpu"))
    return AGVScenario(
        name=scenario.name,
        scenario=scenario,
        world=scenario.world,
        agents=agents[0].double().numpy(),
        tasks=tasks[0].double().numpy(),
        seed=seed,
    )


@pytest.fixture(params=WORLDS)
def agv_world(request: pytest.FixtureRequest) -> World:
    """A floor: the open MPE box and the shelf warehouse (see the module docstring)."""
    return make_world(request.param)


@pytest.fixture
def agv_scenario(request: pytest.FixtureRequest) -> AGVScenario:
    """A scenario with one seeded scene, ``"3v3"`` unless parametrized indirectly."""
    return make_scenario(getattr(request, "param", "3v3"))

