"""Shortest paths round the shelves of a floor, on a grid, in torch (:class:`FloorWaypoints`).

On a lifelong floor (``docs/lifelong.md``) the straight line from an AGV to its target usually
runs through a shelf. :class:`FloorWaypoints` gives, for batches of points and targets, **the
next waypoint toward the target along a shortest path around the shelves** and the **path's
length**. The entity learners read both (``learners.floor``, ``learners.entity``) and the
lifelong Greedy reward measures progress in path length (:mod:`sim.rewards.lifelong`), so the
planner lives here, beside the floor it plans on (``allocator.distances.FloorDistances`` is
the dispatchers' finer table; ``sim`` and ``learners`` do not import ``allocator``).

Square cells of side ``resolution``, a cell free where an AGV disc centred on it clears every
shelf and wall (:meth:`sim.World.is_free`), 8-neighbour moves (a diagonal only when both side
cells are free), one Dijkstra field per target cell, computed the first time that cell is a
target and kept (a floor's generated orders use its fixed pickups and stations only, so the
table stops growing quickly). The waypoint is the cell centre ``lookahead`` path cells ahead
(the target itself once the rest of the path is shorter), so a policy heads round a shelf's
corner rather than into it. It does not string-pull paths; the waypoint is a heading, not a
plan. :meth:`FloorWaypoints.sight` gives the path's first corner instead (the farthest path
cell the AGV's disc reaches in a straight line), as the classical dispatchers' driver heads
for it (``allocator.distances.FloorDistances.next_waypoint``).
"""

from __future__ import annotations

import math

import numpy as np
import scipy.sparse as sp
import torch
from scipy import ndimage
from scipy.sparse import csgraph
from torch import Tensor

from sim.world import World, segments_clear

__all__ = ["FloorWaypoints", "SIGHT_CELLS"]

_MAX_CELLS = 4_000_000
SIGHT_CELLS = 64
"""Path cells :meth:`FloorWaypoints.sight` looks along for the last one in sight."""


class FloorWaypoints:
    """Shortest-path waypoints and lengths on one floor, batched, in torch.

    Parameters
    ----------
    world : sim.World
        The floor (shelves as ``world.obstacles``).
    resolution : float, optional
        Cell side, world units (default half the AGV radius, at most 0.1).
    lookahead : int
        Path cells between an AGV's cell and its waypoint (default 6).
    discs : np.ndarray, shape (C, 2), optional
        Centres of round obstacles besides the shelves (parked AGVs, for
        :class:`allocator.detour.ParkedDetour`): a cell is free only if its centre is at least
        ``disc_clearance`` from each.
    disc_clearance : float
        Least distance from a free cell's centre to a disc's centre (>= 0; default 0).

    Raises
    ------
    ValueError
        For a world that is not a ``sim.World``, a resolution that is not positive and finite
        or gives more than four million cells, a lookahead below 1, discs that are not finite
        (C, 2) centres or a negative disc clearance.
    """

    def __init__(self, world: World, resolution: float | None = None,
                 lookahead: int = 6, discs: np.ndarray | None = None,
                 disc_clearance: float = 0.0) -> None:
        if not isinstance(world, World):
            raise ValueError(f"world must be a sim.World, got {type(world).__name__}")
        res = min(world.agent_radius / 2, 0.1) if resolution is None else resolution
        if isinstance(res, bool) or not isinstance(res, (int, float)) or not \
                (math.isfinite(res) and res > 0):
            raise ValueError(f"resolution must be a positive finite number, got {resolution!r}")
        if isinstance(lookahead, bool) or not isinstance(lookahead, int) or lookahead < 1:
            raise ValueError(f"lookahead must be an integer >= 1, got {lookahead!r}")
        if discs is not None:
            discs = np.asarray(discs, dtype=np.float64)
            if discs.ndim != 2 or discs.shape[1] != 2 or not np.all(np.isfinite(discs)):
                raise ValueError(f"discs must be finite centres of shape (C, 2), got shape "
                                 f"{discs.shape}")
        if isinstance(disc_clearance, bool) or not isinstance(disc_clearance, (int, float)) \
                or not (math.isfinite(disc_clearance) and disc_clearance >= 0):
            raise ValueError(f"disc_clearance must be a finite number >= 0, got "
                             f"{disc_clearance!r}")
        self.world, self.resolution, self.lookahead = world, float(res), lookahead
        xmin, ymin, xmax, ymax = world.bounds
        self.origin = (float(xmin), float(ymin))
        self.width = max(1, math.ceil((xmax - xmin) / res))
        self.height = max(1, math.ceil((ymax - ymin) / res))
        cells = self.width * self.height
        if cells > _MAX_CELLS:
            raise ValueError(f"resolution {res} gives {cells} cells on this floor (at most "
                             f"{_MAX_CELLS}); choose a coarser one")
        ix, iy = np.meshgrid(np.arange(self.width), np.arange(self.height))
        self._centres = np.stack([xmin + (ix.ravel() + 0.5) * res,
                                  ymin + (iy.ravel() + 0.5) * res], axis=1)
        free = world.is_free(self._centres)
        if discs is not None and len(discs):
            free &= self._clear_of(discs, float(disc_clearance))
        free = free.reshape(self.height, self.width)
        if not free.any():
            raise ValueError("no cell of this floor holds an AGV")
        # every cell's nearest free cell (points inside a shelf's margin snap out of it)
        _, (ny, nx) = ndimage.distance_transform_edt(~free, return_indices=True)
        self._snap = torch.as_tensor((ny * self.width + nx).ravel(), dtype=torch.int64)
        self._graph = _grid_graph(free, res)
        self._centres_t = torch.as_tensor(self._centres, dtype=torch.float32)
        self._row_of_cell = torch.full((cells,), -1, dtype=torch.int64)
        self._wp_cell = torch.zeros(0, cells, dtype=torch.int64)
        self._pred = torch.zeros(0, cells, dtype=torch.int64)
        self._dist = torch.zeros(0, cells, dtype=torch.float32)

    def _clear_of(self, discs: np.ndarray, clearance: float) -> np.ndarray:
        """Whether each cell's centre is at least ``clearance`` from every disc's centre,
        (cells,) bool: each disc marks the cells of a window round it (its radius in cells
        plus one, so no cell outside it comes nearer), O(C (clearance / resolution)^2)."""
        res, (x0, y0) = self.resolution, self.origin
        reach = math.ceil(clearance / res) + 1
        if 2 * reach + 1 > max(self.width, self.height):  # a window wider than the floor
            clear = np.ones(self.width * self.height, dtype=bool)
            for disc in discs:
                clear &= np.linalg.norm(self._centres - disc, axis=-1) >= clearance
            return clear
        off = np.arange(-reach, reach + 1)
        gx = np.floor((discs[:, 0] - x0) / res).astype(np.int64)[:, None, None] + off[None, None]
        gy = np.floor((discs[:, 1] - y0) / res).astype(np.int64)[:, None, None] + off[None, :, None]
        gx, gy = np.broadcast_arrays(gx, gy)                                        # (C, S, S)
        near = (x0 + (gx + 0.5) * res - discs[:, 0, None, None]) ** 2 \
            + (y0 + (gy + 0.5) * res - discs[:, 1, None, None]) ** 2 < clearance ** 2
        near &= (gx >= 0) & (gx < self.width) & (gy >= 0) & (gy < self.height)
        clear = np.ones(self.width * self.height, dtype=bool)
        clear[(gy * self.width + gx)[near]] = False
        return clear

    @property
    def cached_targets(self) -> int:
        """Target cells whose fields are kept."""
        return int(self._wp_cell.shape[0])

    def cell_of(self, points: Tensor) -> Tensor:
        """The free cell each point snaps to, (...,) int64 for points (..., 2)."""
        x = ((points[..., 0] - self.origin[0]) / self.resolution).floor().long()
        y = ((points[..., 1] - self.origin[1]) / self.resolution).floor().long()
        raw = y.clamp(0, self.height - 1) * self.width + x.clamp(0, self.width - 1)
        return self._snap[raw]

    def _add_targets(self, cells: Tensor) -> None:
        new = torch.unique(cells[self._row_of_cell[cells] < 0])
        if not new.numel():
            return
        dist, pred = csgraph.dijkstra(self._graph, directed=False, indices=new.numpy(),
                                      return_predecessors=True)
        pred = np.where(pred < 0, np.arange(pred.shape[1])[None, :], pred)  # target: itself
        wp = np.broadcast_to(np.arange(pred.shape[1]), pred.shape).copy()
        rows = np.arange(len(new))[:, None]
        for _ in range(self.lookahead):
            wp = pred[rows, wp]
        start = self._wp_cell.shape[0]
        self._wp_cell = torch.cat([self._wp_cell, torch.as_tensor(wp, dtype=torch.int64)])
        self._pred = torch.cat([self._pred, torch.as_tensor(pred, dtype=torch.int64)])
        self._dist = torch.cat([self._dist, torch.as_tensor(dist, dtype=torch.float32)])
        self._row_of_cell[new] = torch.arange(start, start + len(new))

    def query(self, points: Tensor, targets: Tensor,
              mask: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """The waypoint from each point toward its target and the path length.

        Parameters
        ----------
        points, targets : Tensor, shape (..., 2)
            World units; the same shape.
        mask : Tensor of bool, shape (...), optional
            Pairs to plan; elsewhere the waypoint is the target and the length the straight
            line, and no field is computed for the target (so padding, such as a masked
            slot's zero offset, never fills the table with fields of arbitrary cells).

        Returns
        -------
        waypoint : Tensor, shape (..., 2)
            A cell centre ``lookahead`` cells along the shortest grid path, or the target
            itself when the rest of the path is shorter than that (or when the target cannot
            be reached: then the straight line is all there is).
        length : Tensor, shape (...)
            Path length (grid distance between the two cells plus the straight connectors
            from the point and to the target); the straight-line distance where unreachable.

        Raises
        ------
        ValueError
            If the shapes differ or do not end in 2.
        """
        shape, p, t = _pairs(points, targets, mask)
        if mask is not None:
            keep = mask.reshape(-1)
            wp = t.clone()
            length = torch.linalg.vector_norm(t - p, dim=-1)
            if bool(keep.any()):
                wp[keep], length[keep] = self._plan(p[keep], t[keep])
            return wp.reshape(*shape, 2), length.reshape(shape)
        wp, length = self._plan(p, t)
        return wp.reshape(*shape, 2), length.reshape(shape)

    def sight(self, points: Tensor, targets: Tensor, mask: Tensor | None = None,
              reach: int = SIGHT_CELLS) -> Tensor:
        """The first corner of the shortest path from each point toward its target.

        The target itself when the AGV's disc reaches it in a straight line
        (:func:`sim.world.segments_clear`); else the farthest of the next ``reach`` cells
        along the grid path that the disc reaches in a straight line with every cell before
        it, the path's next cell when none is (the point stands too close to a shelf for any
        straight line), or the target when it cannot be reached. What a driver heads for
        (``allocator.distances.FloorDistances.next_waypoint`` on the dispatchers' finer
        table); :meth:`query`'s waypoint is a fixed number of cells ahead instead.

        Parameters
        ----------
        points, targets : Tensor, shape (..., 2)
            World units; the same shape.
        mask : Tensor of bool, shape (...), optional
            Pairs to plan; elsewhere the waypoint is the target (no field is computed).
        reach : int
            Path cells looked along (>= 1).

        Returns
        -------
        Tensor, shape (..., 2), float32

        Raises
        ------
        ValueError
            If the shapes differ or do not end in 2, or for a ``reach`` that is not an
            integer from 1 to the floor's number of cells.
        """
        shape, p, t = _pairs(points, targets, mask)
        if isinstance(reach, bool) or not isinstance(reach, int) or reach < 1:
            raise ValueError(f"reach must be an integer >= 1, got {reach!r}")
        if reach > self.width * self.height:
            raise ValueError(f"reach must be at most the floor's {self.width * self.height} "
                             f"cells (no path is longer), got {reach}")
        out = t.clone()
        todo = torch.ones(len(p), dtype=torch.bool) if mask is None else mask.reshape(-1).clone()
        if bool(todo.any()):
            p64, t64 = p[todo].double().numpy(), t[todo].double().numpy()
            blocked = torch.as_tensor(~segments_clear(p64, t64, self.world))
            todo[todo.clone()] = blocked
        if bool(todo.any()):
            out[todo] = self._corner(p[todo], t[todo], reach)
        return out.reshape(*shape, 2)

    def _corner(self, p: Tensor, t: Tensor, reach: int) -> Tensor:
        """:meth:`sight` for pairs (P, 2) whose target is out of sight."""
        pc, tc = self.cell_of(p), self.cell_of(t)
        self._add_targets(tc)
        row = self._row_of_cell[tc]
        cells = [pc]
        for _ in range(reach):
            cells.append(self._pred[row, cells[-1]])
        chain = torch.stack(cells[1:], dim=1)  # (P, reach), the target cell repeats at the end
        ends = self._centres[chain.numpy()].reshape(-1, 2)
        starts = np.repeat(p.double().numpy(), reach, axis=0)
        seen = torch.as_tensor(segments_clear(starts, ends, self.world)).reshape(-1, reach)
        last = seen.long().cumprod(dim=1).sum(dim=1) - 1  # the last cell of the seen prefix
        cell = chain.gather(1, last.clamp_min(0).unsqueeze(1)).squeeze(1)
        wp = self._centres_t[cell]
        reached = torch.isfinite(self._dist[row, pc])
        return torch.where(reached.unsqueeze(-1), wp, t)

    def _plan(self, p: Tensor, t: Tensor) -> tuple[Tensor, Tensor]:
        """Waypoints (P, 2) and path lengths (P,) for points and targets (P, 2), float32."""
        pc, tc = self.cell_of(p), self.cell_of(t)
        self._add_targets(tc)
        row = self._row_of_cell[tc]
        grid = self._dist[row, pc]
        wp_cell = self._wp_cell[row, pc]
        cen = self._centres_t
        length = grid + torch.linalg.vector_norm(p - cen[pc], dim=-1) \
            + torch.linalg.vector_norm(t - cen[tc], dim=-1)
        straight = torch.linalg.vector_norm(t - p, dim=-1)
        reach = torch.isfinite(grid)
        near = ~reach | (grid <= self.lookahead * self.resolution * 1.5) | (wp_cell == tc)
        wp = torch.where(near.unsqueeze(-1), t, cen[wp_cell])
        length = torch.where(reach, torch.maximum(length, straight), straight)
        return wp, length


def _pairs(points: Tensor, targets: Tensor, mask: Tensor | None
           ) -> tuple[torch.Size, Tensor, Tensor]:
    """The checked batch shape of (point, target) pairs and both flattened to (P, 2) float32
    (:meth:`FloorWaypoints.query` and :meth:`FloorWaypoints.sight`)."""
    if points.shape != targets.shape or points.shape[-1:] != (2,):
        raise ValueError(f"points and targets must have the same shape (..., 2), got "
                         f"{tuple(points.shape)} and {tuple(targets.shape)}")
    shape = points.shape[:-1]
    if mask is not None and mask.shape != shape:
        raise ValueError(f"mask must have shape {tuple(shape)}, got {tuple(mask.shape)}")
    return shape, points.reshape(-1, 2).float(), targets.reshape(-1, 2).float()


def _grid_graph(free: np.ndarray, res: float) -> sp.csr_matrix:
    """8-neighbour graph of the free cells (a diagonal only if both side cells are free)."""
    H, W = free.shape
    idx = np.arange(H * W).reshape(H, W)
    rows, cols, vals = [], [], []
    for dy, dx in ((0, 1), (1, 0), (1, 1), (1, -1)):
        y0, y1 = 0, H - dy
        x0, x1 = max(0, -dx), W - max(0, dx)
        a = free[y0:y1, x0:x1] & free[y0 + dy:y1 + dy, x0 + dx:x1 + dx]
        if dy and dx:
            a &= free[y0 + dy:y1 + dy, x0:x1] & free[y0:y1, x0 + dx:x1 + dx]
        src = idx[y0:y1, x0:x1][a]
        dst = idx[y0 + dy:y1 + dy, x0 + dx:x1 + dx][a]
        rows.append(src)
        cols.append(dst)
        vals.append(np.full(len(src), res * (math.sqrt(2) if dy and dx else 1.0)))
    r, c, v = np.concatenate(rows), np.concatenate(cols), np.concatenate(vals)
    return sp.csr_matrix((v, (r, c)), shape=(H * W, H * W))
