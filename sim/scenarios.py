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

from sim.native import pointer
from sim.world import World

__all__ = ["Scenario", "SCENARIOS", "get_scenario", "warehouse_world", "scenario_names"]

Sampler = Callable[[int, int, torch.Generator, torch.device], Tensor]
"""``sampler(B, C, generator, device) -> (B, C, 2)`` candidate positions."""

_CANDIDATES = 16
_ROUNDS = 100


def _uniform_sampler(world: World, margin: float) -> Sampler:
    xmin, ymin, xmax, ymax = world.bounds
    lo = torch.tensor([xmin + margin, ymin + margin], dtype=torch.float32)
    span = torch.tensor([xmax - xmin - 2 * margin, ymax - ymin - 2 * margin], dtype=torch.float32)

    def sample(B: int, C: int, gen: torch.Generator, device: torch.device) -> Tensor:
        u = torch.rand(B, C, 2, generator=gen, device=device, dtype=torch.float32)
        return lo.to(device) + u * span.to(device)

    return sample


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
        How many nearest tasks / other AGVs an observation holds.
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
            v = getattr(self, attr)
            if not isinstance(v, (int, np.integer)) or v < 0:
                raise ValueError(f"{attr} must be a non-negative integer, got {v!r}")
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
        agents = self.agent_sampler or _uniform_sampler(w, w.agent_radius)
        tasks = self.task_sampler or _uniform_sampler(w, w.agent_radius)
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
        w = self.world
        agent_sampler, task_sampler = self._samplers()
        obstacles = torch.tensor(np.array(w.obstacles), dtype=torch.float32, device=device)
        r, cap = w.agent_radius, w.capture_radius
        n, m = self.num_agents, self.num_tasks
        lib = kernels if torch.device(device).type == "cpu" else None
        # Entities are placed one at a time (agents, then tasks), each for all B scenes at once.
        # gap[k, j]: minimum distance between entity k and an earlier entity j.
        kinds = torch.tensor([True] * n + [False] * m, device=device)
        same = kinds.unsqueeze(1) == kinds.unsqueeze(0)
        f32 = dict(dtype=torch.float32, device=device)  # whatever torch's default dtype
        own_gap = torch.where(kinds, torch.tensor(2 * r, **f32),
                              torch.tensor(w.task_spacing, **f32)).unsqueeze(1)
        gap = torch.where(same, own_gap, torch.tensor(cap + 1e-3, **f32)) ** 2
        placed = torch.zeros(B, n + m, 2, dtype=torch.float32, device=device)
        rows = torch.arange(B, device=device)
        for k in range(n + m):
            sampler = agent_sampler if k < n else task_sampler
            todo = rows
            gap_k = gap[k, :k].contiguous()
            for _ in range(_ROUNDS):
                cand = sampler(len(todo), _CANDIDATES, gen, device).float()  # (b, C, 2)
                ok = _clear_of_obstacles(cand, obstacles, r)  # (b, C)
                if lib is not None:  # the same rule, one pass in C
                    b = len(todo)
                    cand, ok = cand.contiguous(), ok.contiguous()
                    found = torch.empty(b, dtype=torch.bool)
                    # todo, placed and found are made here with the kernel's dtypes and shapes.
                    lib.agv_spawn_pick(
                        b, _CANDIDATES, n + m, k,
                        pointer(cand, torch.float32, (b, _CANDIDATES, 2), "candidates"),
                        pointer(ok, torch.bool, (b, _CANDIDATES), "candidate mask"),
                        todo.data_ptr(), pointer(gap_k, torch.float32, (k,), "gap"),
                        placed.data_ptr(), found.data_ptr(),
                    )
                else:
                    if k:
                        prev = placed[todo, :k]  # (b, k, 2)
                        d2 = ((cand.unsqueeze(2) - prev.unsqueeze(1)) ** 2).sum(-1)  # (b, C, k)
                        ok &= (d2 >= gap_k).all(dim=2)
                    found = ok.any(dim=1)
                    first = ok.to(torch.uint8).argmax(dim=1)
                    chosen = cand[torch.arange(len(todo), device=device), first]
                    placed[todo[found], k] = chosen[found]
                todo = todo[~found]
                if not len(todo):
                    break
            else:
                raise RuntimeError(
                    f"could not place {n} AGVs and {m} tasks with the required spacing after "
                    "many tries; the floor is too crowded"
                )
        return placed[:, :n].contiguous(), placed[:, n:].contiguous()

    def with_options(self, **options: Any) -> Scenario:
        """A copy with some fields replaced (e.g. ``max_steps``)."""
        unknown = set(options) - set(self.__dataclass_fields__)
        if unknown:
            raise ValueError(
                f"unknown scenario option(s) {sorted(unknown)}; "
                f"expected some of {sorted(self.__dataclass_fields__)}"
            )
        return replace(self, **options)


def _clear_of_obstacles(points: Tensor, obstacles: Tensor, r: float) -> Tensor:
    """True where a disc of radius r at ``points`` (..., 2) clears every rectangle."""
    if obstacles.numel() == 0:
        return torch.ones(points.shape[:-1], dtype=torch.bool, device=points.device)
    p = points.unsqueeze(-2)
    closest = torch.minimum(torch.maximum(p, obstacles[:, :2]), obstacles[:, 2:])
    return (torch.linalg.vector_norm(p - closest, dim=-1) >= r + 1e-6).all(dim=-1)


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


SCENARIOS: dict[str, Callable[..., Scenario]] = {
    "3v3": lambda **o: paper_scenario(3, 3, **o),
    "6v6": lambda **o: paper_scenario(6, 6, **o),
    "warehouse": warehouse_scenario,
}
"""Named scenarios; any ``"NvM"`` (e.g. ``"10v12"``) is built on demand."""

_NVM = re.compile(r"^(\d+)v(\d+)$")


def scenario_names() -> list[str]:
    """The registered names (``NvM`` works for any N, M besides these)."""
    return sorted(SCENARIOS)


def get_scenario(name: str | Scenario, **options: Any) -> Scenario:
    """Look a scenario up by name, with optional field overrides.

    Raises
    ------
    ValueError
        For an unknown name (the message lists the known ones) or unknown options.
    """
    if isinstance(name, Scenario):
        return name.with_options(**options) if options else name
    unknown = set(options) - set(Scenario.__dataclass_fields__)
    if unknown:
        raise ValueError(
            f"unknown scenario option(s) {sorted(unknown)}; "
            f"expected some of {sorted(Scenario.__dataclass_fields__)}"
        )
    if not isinstance(name, str):
        raise ValueError(f"scenario must be a name or a Scenario, got {type(name).__name__}")
    if name in SCENARIOS:
        return SCENARIOS[name](**options)
    match = _NVM.match(name)
    if match:
        n, m = int(match.group(1)), int(match.group(2))
        if n < 1 or m < 1:
            raise ValueError(f"scenario {name!r} needs at least one AGV and one task")
        return paper_scenario(n, m, **options)
    raise ValueError(
        f"unknown scenario {name!r}; expected one of {scenario_names()} or 'NvM' "
        "(N AGVs, M tasks, e.g. '10v10')"
    )
