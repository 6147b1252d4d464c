"""Scenarios: the paper's ``3v3`` and ``6v6``, any ``NvM``, and a ``warehouse`` with shelves.

A :class:`Scenario` bundles a :class:`~sim.world.World`, the numbers of AGVs and tasks, the
step limit, the observation sizes and a seeded spawner. Spawning is batched: entities are placed
one after another, each drawn for all environments at once from a pool of candidates that
respect the spacing rules of ``DESIGN.md`` (AGVs one diameter apart, tasks
2 x (radius + capture radius) apart, nothing inside a wall or shelf, no AGV on a task).
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import torch
from torch import Tensor

from sim.checks import check_slots
from sim.lifelong import LifelongScenario
from sim.spawn import Sampler, place_entities, uniform_sampler
from sim.world import World

__all__ = ["Scenario", "SCENARIOS", "get_scenario", "warehouse_world", "scenario_names",
           "place_entities", "uniform_sampler"]

@dataclass(frozen=True)
class Scenario:
    """A seeded family of episodes.

    Attributes
    ----------
    name : str
    world : World
    num_agents, num_tasks : int
        N AGVs and M tasks (free, may differ).
    max_steps : int
        Step limit of an episode.
    k_tasks, k_agents : int
        How many nearest tasks / other AGVs an observation holds, each in
        [0, :data:`sim.checks.MAX_SLOTS`].
    sensing_range : float
        Entities farther than this are masked out of observations.
    agent_sampler, task_sampler : callable, optional
        Candidate generators; default uniform over the free floor.
    scene : tuple of Tensor, optional
        ``(agents (N, 2), tasks (M, 2))``: every episode starts from this one scene instead of
        a random draw (see :meth:`given_scene`); the room check is then skipped.
    """

    name: str
    world: World
    num_agents: int
    num_tasks: int
    max_steps: int = 25
    k_tasks: int = 3
    k_agents: int = 2
    sensing_range: float = math.inf
    agent_sampler: Sampler | None = field(default=None, repr=False, compare=False)
    task_sampler: Sampler | None = field(default=None, repr=False, compare=False)
    scene: tuple[Tensor, Tensor] | None = field(default=None, repr=False, compare=False)

    def __post_init__(self) -> None:
        for attr in ("num_agents", "num_tasks", "max_steps"):
            v = getattr(self, attr)
            if not isinstance(v, (int, np.integer)) or v < 1:
                raise ValueError(f"{attr} must be a positive integer, got {v!r}")
        for attr in ("k_tasks", "k_agents"):
            object.__setattr__(self, attr, check_slots(attr, getattr(self, attr)))
        if not (self.sensing_range > 0):
            raise ValueError(f"sensing_range must be positive, got {self.sensing_range!r}")
        if self.scene is None:
            self._check_room()
            return
        agents, tasks = self.scene
        for what, t, n in (("agents", agents, self.num_agents), ("tasks", tasks, self.num_tasks)):
            if not isinstance(t, Tensor) or t.dtype != torch.float32 or tuple(t.shape) != (n, 2):
                raise ValueError(f"scene {what} must be a float32 tensor of shape ({n}, 2), got "
                                 f"{getattr(t, 'dtype', type(t).__name__)} "
                                 f"{tuple(getattr(t, 'shape', ()))}")
            self.world.check_positions(t.double().cpu().numpy(), f"scene {what}")

    @classmethod
    def given_scene(cls, base: Scenario, agents: object, tasks: object,
                    world: World | None = None, **options: Any) -> Scenario:
        """A scenario whose every episode is one given scene, with ``base``'s other fields.

        The random spawner's rules (AGVs one diameter apart, tasks apart, room to place
        N + M of them) are for drawing scenes; a scene given by the caller is run as it is,
        once its positions are checked against the world (inside the walls, off the shelves).

        Parameters
        ----------
        base : Scenario
            Sensing, observation sizes and step limit come from it.
        agents : array-like, shape (N, 2)
        tasks : array-like, shape (M, 2)
        world : World, optional
            Default ``base.world``.
        **options
            Other fields to replace (e.g. ``max_steps``).

        Raises
        ------
        ValueError
            On positions that are not real numbers of shape (K, 2), outside the world or on a
            shelf, or an unknown field.
        """
        world = base.world if world is None else world
        a = torch.as_tensor(world.check_positions(agents, "agents"), dtype=torch.float32)
        t = torch.as_tensor(world.check_positions(tasks, "tasks"), dtype=torch.float32)
        fields = {f: getattr(base, f) for f in base.__dataclass_fields__}
        unknown = set(options) - set(fields)
        if unknown:
            raise ValueError(f"unknown scenario option(s) {sorted(unknown)}; valid: "
                             f"{sorted(fields)}")
        fields.update(world=world, num_agents=len(a), num_tasks=len(t), scene=(a, t), **options)
        return cls(**fields)

    # ------------------------------------------------------------------ spawning
    def _samplers(self) -> tuple[Sampler, Sampler]:
        w = self.world
        agents = self.agent_sampler or uniform_sampler(w, w.agent_radius)
        tasks = self.task_sampler or uniform_sampler(w, w.agent_radius)
        return agents, tasks

    def _check_room(self) -> None:
        """Fail early, with a clear message, when N AGVs and M tasks cannot be placed."""
        w = self.world
        free_w = w.size[0] - 2 * w.agent_radius
        free_h = w.size[1] - 2 * w.agent_radius
        free_area = max(free_w, 0.0) * max(free_h, 0.0)
        if w.has_obstacles:
            o = w.obstacles
            free_area -= float(np.sum((o[:, 2] - o[:, 0]) * (o[:, 3] - o[:, 1])))
        # Packing bound: discs of radius s/2 around each point, hexagonal density ~0.9.
        need = (self.num_agents * (2 * w.agent_radius) ** 2
                + self.num_tasks * w.task_spacing**2) * (math.sqrt(3) / 2) / 0.9
        if free_area <= 0 or need > free_area:
            raise ValueError(
                f"scenario {self.name!r}: the free floor ({free_area:.2f} square units) leaves no "
                f"room to spawn {self.num_agents} AGVs and {self.num_tasks} tasks with the "
                f"required spacing (about {need:.2f} needed); enlarge the bounds or use fewer"
            )
        try:
            self.spawn(4, torch.Generator().manual_seed(12345), torch.device("cpu"))
        except RuntimeError as err:
            raise ValueError(f"scenario {self.name!r}: {err}") from None

    def spawn(self, B: int, gen: torch.Generator, device: torch.device,
              kernels: Any = None) -> tuple[Tensor, Tensor]:
        """Draw B scenes.

        Parameters
        ----------
        B : int
            Number of scenes.
        gen : torch.Generator
            Source of every random draw.
        device : torch.device
            Where the scenes are made.
        kernels : ctypes.CDLL, optional
            The fused kernels of :mod:`sim.native` to check candidates with (CPU only), as the
            caller chose them (the environment passes its own); None for the torch path. The
            same draws give the same scenes either way.

        Returns
        -------
        agents : Tensor, shape (B, N, 2)
        tasks : Tensor, shape (B, M, 2)
        """
        if self.scene is not None:  # every episode is the given scene
            agents, tasks = self.scene
            return (agents.to(device).expand(B, -1, -1).clone(),
                    tasks.to(device).expand(B, -1, -1).clone())
        agent_sampler, task_sampler = self._samplers()
        return place_entities(self.world, self.num_agents, self.num_tasks, agent_sampler,
                              task_sampler, B, gen, device, kernels)

    def with_options(self, **options: Any) -> Scenario:
        """A copy with some fields replaced (e.g. ``max_steps``)."""
        unknown = set(options) - set(self.__dataclass_fields__)
        if unknown:
            raise ValueError(
                f"unknown scenario option(s) {sorted(unknown)}; "
                f"expected some of {sorted(self.__dataclass_fields__)}"
            )
        return replace(self, **options)


# ---------------------------------------------------------------------- the registry
def paper_scenario(n: int, m: int | None = None, **options: Any) -> Scenario:
    """``NvM`` in an open box: ``[-1, 1]^2`` up to 6 entities of a kind, larger beyond."""
    m = n if m is None else m
    half = max(1.0, math.sqrt(max(n, m) / 6.0))
    world = World(bounds=(-half, -half, half, half))
    base = dict(
        name=f"{n}v{m}",
        world=world,
        num_agents=n,
        num_tasks=m,
        max_steps=int(round(25 * half)),
        k_tasks=min(m, 6),
        k_agents=min(n - 1, 5),
    )
    base.update(options)
    return Scenario(**base)


def warehouse_world(
    columns: int = 2,
    rows: int = 2,
    shelf_length: float = 1.2,
    shelf_depth: float = 0.3,
    aisle: float = 0.7,
    depot: float = 0.6,
    agent_radius: float = 0.15,
) -> World:
    """A floor with ``rows x columns`` shelves and a depot strip along the bottom wall.

    Aisles of width ``aisle`` run around every shelf; the depot strip of height ``depot``
    lies below the lowest aisle.
    """
    width = columns * shelf_length + (columns + 1) * aisle
    height = depot + rows * shelf_depth + (rows + 1) * aisle
    xmin, ymin = -width / 2, -height / 2
    shelves = []
    for i in range(rows):
        y0 = ymin + depot + aisle + i * (shelf_depth + aisle)
        for j in range(columns):
            x0 = xmin + aisle + j * (shelf_length + aisle)
            shelves.append((x0, y0, x0 + shelf_length, y0 + shelf_depth))
    return World(
        bounds=(xmin, ymin, -xmin, -ymin), obstacles=np.array(shelves), agent_radius=agent_radius
    )


def _shelf_face_sampler(world: World, offset: float) -> Sampler:
    """Candidates on the long faces of the shelves, ``offset`` out from the face."""
    shelves = torch.tensor(np.array(world.obstacles))

    def sample(B: int, C: int, gen: torch.Generator, device: torch.device) -> Tensor:
        s = shelves.to(device)
        pick = torch.randint(len(s), (B, C), generator=gen, device=device)
        side = torch.randint(2, (B, C), generator=gen, device=device)
        u = torch.rand(B, C, generator=gen, device=device, dtype=torch.float32)
        rect = s[pick]  # (B, C, 4)
        x = rect[..., 0] + u * (rect[..., 2] - rect[..., 0])
        y = torch.where(side == 0, rect[..., 1] - offset, rect[..., 3] + offset)
        return torch.stack([x, y], dim=-1)

    return sample


def _depot_sampler(world: World, depot: float) -> Sampler:
    r = world.agent_radius
    xmin, ymin, xmax, _ = world.bounds
    lo = torch.tensor([xmin + r, ymin + r], dtype=torch.float32)
    span = torch.tensor([xmax - xmin - 2 * r, depot - 2 * r], dtype=torch.float32)

    def sample(B: int, C: int, gen: torch.Generator, device: torch.device) -> Tensor:
        u = torch.rand(B, C, 2, generator=gen, device=device, dtype=torch.float32)
        return lo.to(device) + u * span.to(device)

    return sample


def warehouse_scenario(num_agents: int = 6, num_tasks: int = 6, **options: Any) -> Scenario:
    """Rows of shelves, tasks at shelf faces, AGVs starting from a depot strip."""
    depot = 0.6
    world = options.pop("world", None) or warehouse_world(depot=depot)
    base = dict(
        name="warehouse",
        world=world,
        num_agents=num_agents,
        num_tasks=num_tasks,
        max_steps=80,
        k_tasks=min(num_tasks, 6),
        k_agents=min(num_agents - 1, 5),
        agent_sampler=_depot_sampler(world, depot),
        task_sampler=_shelf_face_sampler(world, world.agent_radius + 0.05),
    )
    base.update(options)
    return Scenario(**base)


def warehouse_lifelong(num_agents: int, **options: Any) -> LifelongScenario:
    """``warehouse-N``: the lifelong warehouse of :func:`sim.floors.warehouse_floor` for N
    AGVs (shelf rows, pickups at the shelf faces, stations along one side, a depot)."""
    from sim.floors import warehouse_floor

    world = options.pop("world", None) or warehouse_floor(num_agents)
    options.setdefault("name", f"warehouse-{num_agents}")
    return LifelongScenario(world=world, num_agents=num_agents, **options)


SCENARIOS: dict[str, Callable[..., Scenario | LifelongScenario]] = {
    "3v3": lambda **o: paper_scenario(3, 3, **o),
    "6v6": lambda **o: paper_scenario(6, 6, **o),
    "warehouse": warehouse_scenario,
    "warehouse-20": lambda **o: warehouse_lifelong(20, **o),
    "warehouse-50": lambda **o: warehouse_lifelong(50, **o),
    "warehouse-100": lambda **o: warehouse_lifelong(100, **o),
}
"""Named scenarios; any ``"NvM"`` (e.g. ``"10v12"``) and any ``"warehouse-N"`` (lifelong) are
built on demand."""

_NVM = re.compile(r"^(\d+)v(\d+)$")
_WAREHOUSE = re.compile(r"^warehouse-(\d+)$")


def scenario_names() -> list[str]:
    """The registered names (``NvM`` works for any N, M besides these)."""
    return sorted(SCENARIOS)


def get_scenario(name: str | Scenario | LifelongScenario | World,
                 **options: Any) -> Scenario | LifelongScenario:
    """Look a scenario up by name, with optional field overrides.

    Parameters
    ----------
    name : str, Scenario, LifelongScenario or World
        A registry name (``"3v3"``, any ``"NvM"``, ``"warehouse"``, any ``"warehouse-N"``), a
        scenario, or a floor with pickup points and stations (e.g. from
        :func:`sim.load_floor`), which needs ``num_agents=`` and gives a lifelong scenario.
    **options
        Fields to replace (``max_steps=50``, ``arrivals=sim.Poisson(0.4)``, ...).

    Raises
    ------
    ValueError
        For an unknown name (the message lists the known ones) or unknown options.
    """
    if isinstance(name, (Scenario, LifelongScenario)):
        return name.with_options(**options) if options else name
    if isinstance(name, World):
        if "num_agents" not in options:
            raise ValueError("a floor (World) needs num_agents=N to make a lifelong scenario, "
                             "e.g. sim.make_env(world, num_agents=20)")
        options.setdefault("name", "floor")
        return _lifelong(options, world=name)
    if not isinstance(name, str):
        raise ValueError(f"scenario must be a name, a Scenario or a floor (World), got "
                         f"{type(name).__name__}")
    warehouse = _WAREHOUSE.match(name)
    if warehouse:
        n = int(warehouse.group(1))
        if n < 1:
            raise ValueError(f"scenario {name!r} needs at least one AGV")
        _check_options(options, LifelongScenario)
        return warehouse_lifelong(n, **options)
    _check_options(options, Scenario)
    if name in SCENARIOS:
        return SCENARIOS[name](**options)
    match = _NVM.match(name)
    if match:
        n, m = int(match.group(1)), int(match.group(2))
        if n < 1 or m < 1:
            raise ValueError(f"scenario {name!r} needs at least one AGV and one task")
        return paper_scenario(n, m, **options)
    raise ValueError(
        f"unknown scenario {name!r}; expected one of {scenario_names()}, 'NvM' "
        "(N AGVs, M tasks, e.g. '10v10') or 'warehouse-N' (lifelong, N AGVs)"
    )


def _check_options(options: dict[str, Any], kind: type) -> None:
    unknown = set(options) - set(kind.__dataclass_fields__)
    if unknown:
        raise ValueError(
            f"unknown scenario option(s) {sorted(unknown)}; "
            f"expected some of {sorted(kind.__dataclass_fields__)}"
        )


def _lifelong(options: dict[str, Any], world: World) -> LifelongScenario:
    _check_options(options, LifelongScenario)
    return LifelongScenario(world=world, **options)
