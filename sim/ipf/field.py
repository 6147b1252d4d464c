"""One AGV's field for a scene, for plots and checks, and the checks of a scene's
positions (:mod:`sim.ipf`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from sim.ipf.grid import (
    AGENT_VALUE,
    DEFAULT_RESOLUTION,
    TASK_VALUE,
    IPFGrid,
    ipf_grid,
)
from sim.ipf.jacobi import jacobi_field
from sim.world import World

__all__ = ["IPFField", "check_scene", "ipf_field"]


@dataclass(frozen=True)
class IPFField:
    """One AGV's information potential field.

    Attributes
    ----------
    values : np.ndarray, shape (H, W)
        Potentials at the cell centres (row = y, column = x).
    x : np.ndarray, shape (W,)
        Cell-centre x coordinates.
    y : np.ndarray, shape (H,)
        Cell-centre y coordinates.
    agent : int
        Whose field it is.
    value_at_agent : float
        ``r_IPF`` of that AGV: the field at its own cell.
    world : World
    """

    values: np.ndarray
    x: np.ndarray
    y: np.ndarray
    agent: int
    value_at_agent: float
    world: World


def _scene_sources(
    grid: IPFGrid, agents: np.ndarray, tasks: np.ndarray, agent: int, claimed: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Cells and values of AGV ``agent``'s sources, validated (user-facing path)."""
    others = np.delete(np.arange(len(agents)), agent)
    open_tasks = np.flatnonzero(~claimed)
    points = np.concatenate([agents[others], tasks[open_tasks]])
    values = np.concatenate([np.full(len(others), AGENT_VALUE), np.full(len(open_tasks),
                                                                         TASK_VALUE)])
    names = [f"AGV {i}" for i in others] + [f"task {j}" for j in open_tasks]
    cells = grid.cell_of(points).numpy()
    W = grid.shape[1]
    own = int(grid.cell_of(agents[agent]))
    checked = zip([f"AGV {agent} (whose field it is)", *names], [agents[agent], *points],
                  [own, *cells], strict=True)
    for name, point, cell in checked:
        if grid.free_index[cell] < 0:
            what = "a shelf" if grid.obstacle.ravel()[cell] else "the boundary ring"
            raise ValueError(
                f"{name} at ({point[0]:.4g}, {point[1]:.4g}) falls on grid cell "
                f"(row {cell // W}, col {cell % W}), which is {what} and fixed at 0; move it "
                f"into the free floor or use a finer resolution (now {grid.resolution:g})"
            )
    order = np.argsort(cells, kind="stable")
    keep = np.ones(len(cells), dtype=bool)
    for a, b in zip(order[:-1], order[1:], strict=True):
        if cells[a] != cells[b]:
            continue
        if values[a] != values[b]:
            dist = float(np.linalg.norm(points[a] - points[b]))
            raise ValueError(
                f"the grid is too coarse to separate {names[a]} and {names[b]} "
                f"({dist:.3g} apart): both fall on cell (row {cells[a] // W}, col {cells[a] % W}) "
                f"at resolution {grid.resolution:g}; use resolution <= {dist / 1.5:.3g}"
            )
        keep[b] = False  # same value on the same cell: one Dirichlet condition
    return cells[keep], values[keep]


def _as_points(points: object, name: str) -> np.ndarray:
    """``points`` as a float64 array, refusing what is not real numbers (``name`` in errors)."""
    if isinstance(points, Tensor):
        points = points.detach().cpu().numpy()
    try:
        arr = np.asarray(points)
    except ValueError as err:  # ragged nested lists
        raise ValueError(f"{name} must be an array of shape (K, 2), got {points!r}") from err
    if arr.size and arr.dtype.kind not in "iuf":
        raise ValueError(f"{name} must hold real coordinates in world units, got dtype "
                         f"{arr.dtype}")
    return arr.astype(np.float64)


def _as_claimed(claimed: object, num_tasks: int) -> np.ndarray:
    """``claimed`` as a (M,) bool array: booleans, or the numbers 0 and 1."""
    if claimed is None:
        return np.zeros(num_tasks, dtype=bool)
    arr = np.asarray(claimed.detach().cpu() if isinstance(claimed, Tensor) else claimed)
    if arr.dtype.kind in "iuf" and np.isin(arr, (0, 1)).all():
        arr = arr.astype(bool)
    if arr.size and arr.dtype.kind != "b":
        raise ValueError(f"claimed must hold booleans (one per task), got {claimed!r}")
    arr = arr.astype(bool).ravel()
    if arr.shape != (num_tasks,):
        raise ValueError(f"claimed must have shape ({num_tasks},), one flag per task, got "
                         f"{arr.shape}")
    return arr


def check_scene(
    agents: object,
    tasks: object,
    agent: object = 0,
    world: World | None = None,
    claimed: object = None,
) -> tuple[World, np.ndarray, np.ndarray, int, np.ndarray]:
    """One scene as :func:`ipf_field` takes it, validated (and used by the plots).

    Parameters
    ----------
    agents : array-like, shape (N, 2)
        AGV positions, N >= 1.
    tasks : array-like, shape (M, 2)
        Task positions; an empty sequence means M = 0.
    agent : int
        An index of ``agents``.
    world : World, optional
        Default ``sim.World()``.
    claimed : array-like of bool, shape (M,), optional
        Booleans or the numbers 0 and 1 (default none claimed).

    Returns
    -------
    world : World
    agents : np.ndarray of float64, shape (N, 2)
    tasks : np.ndarray of float64, shape (M, 2)
    agent : int
    claimed : np.ndarray of bool, shape (M,)

    Raises
    ------
    ValueError
        Naming the argument: a world that is not a :class:`sim.World`, positions that are not
        (K, 2) real numbers, NaN, outside the world or inside a shelf, no AGV, an ``agent``
        that is not an index of ``agents``, ``claimed`` not one boolean per task.
    """
    if world is None:
        world = World()
    elif not isinstance(world, World):
        raise ValueError(f"world must be a sim.World or None, got {type(world).__name__}")
    agents = world.check_positions(_as_points(agents, "agents"), "agents")
    tasks = _as_points(tasks, "tasks")
    tasks = np.zeros((0, 2)) if tasks.size == 0 else world.check_positions(tasks, "tasks")
    if len(agents) == 0:
        raise ValueError("agents must hold at least one AGV, got shape (0, 2)")
    if isinstance(agent, (bool, np.bool_)) or not (
            isinstance(agent, (int, np.integer)) and 0 <= agent < len(agents)):
        raise ValueError(f"agent must be an index in [0, {len(agents)}), got {agent!r}")
    return world, agents, tasks, int(agent), _as_claimed(claimed, len(tasks))


def ipf_field(
    agents: np.ndarray,
    tasks: np.ndarray,
    agent: int = 0,
    world: World | None = None,
    resolution: float = DEFAULT_RESOLUTION,
    claimed: np.ndarray | None = None,
    method: str = "fast",
) -> IPFField:
    """AGV ``agent``'s information potential field, for plots and checks.

    Parameters
    ----------
    agents : array-like, shape (N, 2)
        AGV positions in world units, N >= 1.
    tasks : array-like, shape (M, 2)
        Task positions (M may be 0 when there are other AGVs).
    agent : int
        Whose field: that AGV is not a source, every other AGV is (``-3``).
    world : World, optional
        Default ``sim.World()`` (the box ``[-1, 1]^2``).
    resolution : float
        Cell size in world units (default 0.05).
    claimed : array-like of bool, shape (M,), optional
        Claimed tasks, which are not sources (default none claimed).
    method : {"fast", "jacobi"}
        The exact Green's-function solver or the paper's Jacobi iteration (tol 1e-9).

    Returns
    -------
    IPFField
        ``values`` (H, W) at cell centres ``x`` (W,), ``y`` (H,). With no open task the
        field holds only the other AGVs' ``-3`` and is <= 0 everywhere.

    Raises
    ------
    ValueError
        On bad shapes, non-numeric or NaN positions, positions outside the world or inside a
        shelf, an ``agent`` that is not an index of ``agents``, ``claimed`` of the wrong length,
        a resolution that is not a positive finite cell size, an AGV or source on a cell fixed
        at 0, two sources of different value on one cell (grid too coarse), a grid that would
        need too much memory, or a field without any source (one AGV and no open task: the
        field would be zero everywhere); each message says what would work.

    Examples
    --------
    >>> import numpy as np, sim
    >>> f = sim.ipf_field(np.array([[-0.5, 0.0], [0.5, 0.0]]), np.array([[0.0, 0.5]]), agent=0)
    >>> f.values.shape, float(f.values.max()) <= 5.0
    ((40, 40), True)
    """
    world, agents, tasks, agent, claimed = check_scene(agents, tasks, agent, world, claimed)
    if method not in ("fast", "jacobi"):
        raise ValueError(f"method must be 'fast' or 'jacobi', got {method!r}")
    if len(agents) == 1 and claimed.all():
        raise ValueError(
            "no source: with one AGV and no open task the field is zero everywhere; give at "
            "least one unclaimed task (or another AGV)"
        )
    grid = ipf_grid(world, resolution)
    cells, values = _scene_sources(grid, agents, tasks, agent, claimed)
    if method == "fast":
        field = grid.fields(torch.from_numpy(cells)[None], torch.from_numpy(values)[None])
        phi = field[0].numpy()
    else:
        phi = jacobi_field(grid, cells, values)
    own = int(grid.cell_of(agents[agent]))
    return IPFField(phi, grid.x.copy(), grid.y.copy(), agent, float(phi.ravel()[own]), world)
