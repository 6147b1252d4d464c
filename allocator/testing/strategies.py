"""Hypothesis strategies for allocation scenes and for floors with shelves.

Needs `hypothesis <https://hypothesis.readthedocs.io>`_ (``pip install hypothesis``, or the
project's ``test`` extra); the rest of :mod:`allocator.testing` works without it.

>>> import allocator
>>> from hypothesis import given, settings
>>> from allocator.testing import assert_consistent_plan, scenes
>>> @settings(max_examples=10, deadline=None)
... @given(scenes(max_agents=4, max_tasks=4))
... def test_hungarian_plans_are_consistent(scene):
...     agents, tasks = scene
...     plan = allocator.make("hungarian").assign(agents, tasks)
...     assert_consistent_plan(plan, agents, tasks, complete=True)
>>> test_hungarian_plans_are_consistent()
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

try:
    from hypothesis import reject
    from hypothesis import strategies as st
except ImportError as err:  # pragma: no cover - exercised in a subprocess without hypothesis
    raise ImportError(
        "allocator.testing.scenes and allocator.testing.worlds need hypothesis: "
        "pip install hypothesis (or the 'test' extra of agv-allocation); the other helpers of "
        "allocator.testing work without it"
    ) from err

from sim.world import World

__all__ = ["scenes", "worlds"]

_TRIES = 30
"""Draws per point before a crowded example is rejected."""


def _count(value: object, what: str) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        raise ValueError(f"{what} must be a positive integer, got {value!r}")
    return int(value)


def _room(world: World, gap: float) -> int:
    """How many points ``gap`` apart a hexagonal lattice puts on the free floor."""
    xmin, ymin, xmax, ymax = world.bounds
    r = world.agent_radius
    ys = np.arange(ymin + r, ymax - r + 1e-12, gap * math.sqrt(3) / 2)
    rows = []
    for k, y in enumerate(ys):
        xs = np.arange(xmin + r + (gap / 2 if k % 2 else 0.0), xmax - r + 1e-12, gap)
        rows.append(np.stack([xs, np.full_like(xs, y)], axis=1))
    lattice = np.concatenate(rows) if rows else np.zeros((0, 2))
    return int(world.is_free(lattice).sum())


def scenes(
    min_agents: int = 1,
    max_agents: int = 4,
    min_tasks: int = 1,
    max_tasks: int = 4,
    world: World | None = None,
    min_gap: float | None = None,
) -> Any:
    """A strategy for scenes ``(agents, tasks)`` on the free floor of ``world``.

    Every point (AGV or task) lies where an AGV disc fits (:meth:`sim.World.is_free`), and any
    two points are at least ``min_gap`` apart, so no AGV overlaps another and none starts on a
    task. On a floor too small for ``max_agents + max_tasks`` such points (more than half of
    what a hexagonal packing holds), the counts stop at what fits: at least ``min_agents`` and
    ``min_tasks`` always.

    Parameters
    ----------
    min_agents, max_agents : int
        Range of N.
    min_tasks, max_tasks : int
        Range of M.
    world : World, optional
        The floor (default: the open MPE box ``[-1, 1]^2``). To draw the floor too, chain
        the strategies: ``worlds().flatmap(lambda w: scenes(world=w).map(lambda s: (w, *s)))``.
    min_gap : float, optional
        Least distance between two points (default: an AGV diameter).

    Returns
    -------
    SearchStrategy of (np.ndarray, np.ndarray)
        ``agents`` (N, 2) and ``tasks`` (M, 2), float64.

    Raises
    ------
    ValueError
        For bad bounds, or when even ``min_agents + min_tasks`` points do not fit.

    Examples
    --------
    >>> from allocator.testing import scenes
    >>> agents, tasks = scenes(min_agents=3, max_agents=3, max_tasks=2).example()
    >>> agents.shape, tasks.shape[1]
    ((3, 2), 2)
    """
    lo_n, hi_n = _count(min_agents, "min_agents"), _count(max_agents, "max_agents")
    lo_m, hi_m = _count(min_tasks, "min_tasks"), _count(max_tasks, "max_tasks")
    if lo_n > hi_n:
        raise ValueError(f"min_agents ({lo_n}) must not exceed max_agents ({hi_n})")
    if lo_m > hi_m:
        raise ValueError(f"min_tasks ({lo_m}) must not exceed max_tasks ({hi_m})")
    if world is None:
        world = World()
    if not isinstance(world, World):
        raise ValueError(f"world must be a sim.World or None, got {type(world).__name__}")
    gap = 2 * world.agent_radius if min_gap is None else float(min_gap)
    if not (math.isfinite(gap) and gap >= 0):
        raise ValueError(f"min_gap must be a non-negative number, got {min_gap!r}")
    capacity = _room(world, max(gap, 1e-3)) // 2
    if lo_n + lo_m > capacity:
        raise ValueError(
            f"min_agents + min_tasks = {lo_n + lo_m} points {gap} apart are too many for "
            f"random placement on this floor (at most {capacity}); lower them or min_gap, "
            "or use a larger world"
        )
    xmin, ymin, xmax, ymax = world.bounds
    r = world.agent_radius
    xs = st.floats(xmin + r, xmax - r, allow_nan=False, allow_infinity=False)
    ys = st.floats(ymin + r, ymax - r, allow_nan=False, allow_infinity=False)

    @st.composite
    def draw_scene(draw: Any) -> tuple[np.ndarray, np.ndarray]:
        n = draw(st.integers(lo_n, min(hi_n, capacity - lo_m)), label="num_agents")
        m = draw(st.integers(lo_m, min(hi_m, capacity - n)), label="num_tasks")
        points: list[np.ndarray] = []
        for _ in range(n + m):
            for _ in range(_TRIES):
                p = np.array([draw(xs), draw(ys)])
                if world.is_free(p[None])[0] and all(
                    np.hypot(*(p - q)) >= gap for q in points
                ):
                    points.append(p)
                    break
            else:
                reject()
        pts = np.array(points, dtype=np.float64)
        return pts[:n].copy(), pts[n:].copy()

    return draw_scene()


def worlds(
    min_shelves: int = 0,
    max_shelves: int = 6,
    agent_radius: float = 0.15,
) -> Any:
    """A strategy for warehouse floors: :class:`sim.World` objects with rectangular shelves.

    Shelves stand in a grid of 1 to 4 columns and rows, each in its own slot, with aisles at
    least ``2 * agent_radius + 0.2`` wide around every slot, so every free point can reach every
    other. Slot sizes, shelf sizes within their slot, aisle widths and the floor's position
    vary; with no shelf the floor is open.

    Parameters
    ----------
    min_shelves, max_shelves : int
        Range of the number of shelves (0 to 16).
    agent_radius : float
        AGV radius of the worlds.

    Returns
    -------
    SearchStrategy of World

    Raises
    ------
    ValueError
        For a bad range or radius.

    Examples
    --------
    >>> from allocator.testing import worlds
    >>> world = worlds(min_shelves=2, max_shelves=2).example()
    >>> world.obstacles.shape
    (2, 4)
    """
    for name, value in (("min_shelves", min_shelves), ("max_shelves", max_shelves)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or not (
            0 <= value <= 16
        ):
            raise ValueError(f"{name} must be an integer in [0, 16], got {value!r}")
    if min_shelves > max_shelves:
        raise ValueError(f"min_shelves ({min_shelves}) must not exceed max_shelves ({max_shelves})")
    if not (isinstance(agent_radius, (int, float)) and 0 < agent_radius <= 1):
        raise ValueError(f"agent_radius must be a number in (0, 1], got {agent_radius!r}")
    r = float(agent_radius)
    sizes = st.floats(0.2, 1.5, allow_nan=False)
    fractions = st.floats(0.5, 1.0, allow_nan=False)

    @st.composite
    def draw_world(draw: Any) -> World:
        count = draw(st.integers(min_shelves, max_shelves), label="num_shelves")
        cols = draw(st.integers(max(1, math.ceil(count / 4)), 4), label="columns")
        rows = draw(st.integers(max(1, math.ceil(count / cols)), 4), label="rows")
        slot_w, slot_h = draw(sizes), draw(sizes)
        aisle = draw(st.floats(2 * r + 0.2, 2 * r + 0.8, allow_nan=False), label="aisle")
        x0 = draw(st.floats(-2.0, 2.0, allow_nan=False), label="x offset")
        y0 = draw(st.floats(-2.0, 2.0, allow_nan=False), label="y offset")
        slots = draw(
            st.lists(st.integers(0, cols * rows - 1), min_size=count, max_size=count,
                     unique=True),
            label="slots",
        )
        shelves = []
        for s in sorted(slots):
            c, k = divmod(s, rows)
            left = x0 + aisle + c * (slot_w + aisle)
            bottom = y0 + aisle + k * (slot_h + aisle)
            shelves.append((left, bottom, left + slot_w * draw(fractions),
                            bottom + slot_h * draw(fractions)))
        width = cols * slot_w + (cols + 1) * aisle
        height = rows * slot_h + (rows + 1) * aisle
        return World(
            bounds=(x0, y0, x0 + width, y0 + height),
            obstacles=np.array(shelves, dtype=np.float64).reshape(-1, 4),
            agent_radius=r,
        )

    return draw_world()
