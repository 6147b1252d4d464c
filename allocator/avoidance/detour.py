"""Paths around standing AGVs modelled as discs (:func:`plan_around_discs`).

The controller's re-routing used to put every parked AGV on the planning map as a square shelf
of half-size ``r``. A square's corners reach ``r sqrt 2`` from its centre, so two parked AGVs
side by side on a diagonal closed a gap that a moving AGV passes easily, and the re-routed
AGV went the long way round (measured: the misses of 6v6, ``docs/safety.md``). Here the
standing AGVs are discs: a grid cell is free when a moving AGV's centre there keeps
``clearance`` from every standing AGV's centre and ``r + margin`` from the walls and shelves;
Dijkstra on the 8-connected grid (``scipy.sparse.csgraph``), then string pulling with exact
segment-to-disc distances.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
import scipy.sparse as sp
from scipy.sparse import csgraph

if TYPE_CHECKING:  # pragma: no cover
    from sim.world import World

__all__ = ["plan_around_discs", "segments_miss_discs"]


def segments_miss_discs(a: np.ndarray, b: np.ndarray, centres: np.ndarray,
                        clearance: float) -> np.ndarray:
    """Whether each segment ``a[k] -> b[k]`` keeps ``clearance`` from every centre.

    Parameters
    ----------
    a, b : np.ndarray, shape (K, 2)
    centres : np.ndarray, shape (C, 2)
    clearance : float

    Returns
    -------
    np.ndarray of bool, shape (K,)
    """
    a = np.asarray(a, dtype=np.float64).reshape(-1, 2)
    b = np.asarray(b, dtype=np.float64).reshape(-1, 2)
    if len(centres) == 0:
        return np.ones(len(a), dtype=bool)
    d = b - a
    L = np.maximum((d ** 2).sum(-1), 1e-18)
    rel = centres[None, :, :] - a[:, None, :]  # (K, C, 2)
    u = np.clip((rel * d[:, None, :]).sum(-1) / L[:, None], 0.0, 1.0)
    gap = np.linalg.norm(d[:, None, :] * u[..., None] - rel, axis=-1)
    return (gap >= clearance - 1e-12).all(axis=1)


def plan_around_discs(world: World, start: np.ndarray, goal: np.ndarray,
                      centres: np.ndarray, clearance: float, margin: float = 0.01,
                      resolution: float = 0.02, max_cells: int = 250_000) -> np.ndarray | None:
    """A short path ``(K, 2)`` from ``start`` to ``goal`` around discs, or None if cut off.

    Parameters
    ----------
    world : World
        Walls at its bounds and its shelves (a disc of radius ``agent_radius + margin`` must
        fit at every point of the path).
    start, goal : np.ndarray, shape (2,)
    centres : np.ndarray, shape (C, 2)
        Standing AGVs; the path's points keep ``clearance`` from each.
    clearance : float
        Centre-to-centre distance kept from the standing AGVs (e.g. ``2 r + 0.02``).
    margin : float
        Extra clearance from the walls and shelves beyond the AGV radius.
    resolution : float
        Grid cell size; coarsened so that the grid has at most ``max_cells`` cells.
    max_cells : int

    Returns
    -------
    np.ndarray of float64, shape (K, 2) or None
        ``start``, the corners, ``goal``; None where the goal cannot be reached.
    """
    from allocator.paths import segment_clear

    start = np.asarray(start, dtype=np.float64)
    goal = np.asarray(goal, dtype=np.float64)
    centres = np.asarray(centres, dtype=np.float64).reshape(-1, 2)
    wall_clear = world.agent_radius + margin

    def clear(p: np.ndarray, q: np.ndarray) -> np.ndarray:
        return segment_clear(p, q, world, wall_clear) & segments_miss_discs(p, q, centres,
                                                                            clearance)

    if clear(start[None], goal[None])[0]:
        return np.stack([start, goal])
    xmin, ymin, xmax, ymax = world.bounds
    res = max(resolution, math.sqrt((xmax - xmin) * (ymax - ymin) / max_cells))
    w = max(int(math.ceil((xmax - xmin) / res)), 1)
    h = max(int(math.ceil((ymax - ymin) / res)), 1)
    xs = xmin + (np.arange(w) + 0.5) * (xmax - xmin) / w
    ys = ymin + (np.arange(h) + 0.5) * (ymax - ymin) / h
    cells = np.stack(np.meshgrid(xs, ys), axis=-1).reshape(-1, 2)
    free = world.is_free(cells, clearance=wall_clear)
    if len(centres):
        from scipy.spatial import cKDTree

        near = cKDTree(centres).query(cells, distance_upper_bound=clearance)[0]
        free &= ~np.isfinite(near)
    free = free.reshape(h, w)
    idx = np.arange(h * w).reshape(h, w)
    dx, dy = (xmax - xmin) / w, (ymax - ymin) / h
    rows, cols, vals = [], [], []
    for di, dj in ((0, 1), (1, 0), (1, 1), (1, -1)):
        i0, i1 = max(0, -di), h - max(0, di)
        j0, j1 = max(0, -dj), w - max(0, dj)
        ok = free[i0:i1, j0:j1] & free[i0 + di:i1 + di, j0 + dj:j1 + dj]
        if di and dj:  # no corner cutting
            ok &= free[i0 + di:i1 + di, j0:j1] & free[i0:i1, j0 + dj:j1 + dj]
        rows.append(idx[i0:i1, j0:j1][ok])
        cols.append(idx[i0 + di:i1 + di, j0 + dj:j1 + dj][ok])
        vals.append(np.full(rows[-1].size, math.hypot(di * dy, dj * dx)))
    graph = sp.coo_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                          shape=(h * w, h * w)).tocsr()
    free_idx = np.flatnonzero(free.ravel())
    if free_idx.size == 0:
        return None

    def snap(p: np.ndarray) -> int:
        d = np.linalg.norm(cells[free_idx] - p, axis=1)
        return int(free_idx[np.argmin(d)])

    s, g = snap(start), snap(goal)
    dist, pred = csgraph.dijkstra(graph, directed=False, indices=s, return_predecessors=True)
    if not np.isfinite(dist[g]):
        return None
    chain = [g]
    while chain[-1] != s:
        chain.append(int(pred[chain[-1]]))
    pts = np.concatenate([start[None], cells[chain[::-1]], goal[None]])
    # string pulling: keep a point only where the line of sight breaks
    out = [pts[0]]
    i, n = 0, len(pts)
    while i < n - 1:
        ok = clear(np.repeat(pts[i][None], n - i - 1, 0), pts[i + 1:])
        vis = np.flatnonzero(ok)
        j = i + 1 + (int(vis[-1]) if vis.size else 0)
        out.append(pts[j])
        i = j
    return np.stack(out)
