"""The IPF solver: the grid and its graph, the Dirichlet Laplacian and its Green's function,
the batched potentials of every AGV and the task factors kept between steps (see
:mod:`sim.ipf` for the mathematics)."""

from __future__ import annotations

import functools
import math
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from torch import Tensor

from sim import native as sim_native
from sim.ipf.hierarchy import SeparatorTree
from sim.world import World

if TYPE_CHECKING:  # pragma: no cover
    import networkx as nx

__all__ = [
    "TASK_VALUE",
    "AGENT_VALUE",
    "DEFAULT_RESOLUTION",
    "MAX_GREEN_BYTES",
    "MAX_TREE_BYTES",
    "MAX_COLUMN_BYTES",
    "IPFGrid",
    "TaskBlockCache",
    "check_resolution",
    "ipf_grid",
]

TASK_VALUE = 5.0
"""Potential of an unclaimed task's cell."""
AGENT_VALUE = -3.0
"""Potential of another AGV's cell."""
DEFAULT_RESOLUTION = 0.05
"""Default cell size in world units (40 x 40 cells on the MPE box, an AGV spans 6 cells)."""
MAX_GREEN_BYTES = 1 << 29
"""Largest dense Green's function (``F^2 * 8`` bytes) a grid builds: 512 MiB, about 8000
free cells (the 4.5 x 3.3 warehouse at 0.05 needs 195 MiB and builds in seconds). Larger
grids use the separator tree of :mod:`sim.ipf.hierarchy` instead (``IPFGrid.method``)."""
MAX_TREE_BYTES = 1 << 30
"""Largest separator-tree tables (:class:`sim.ipf.hierarchy.SeparatorTree`) a grid builds:
1 GiB (the 14.8 x 11.2 warehouse-100 floor at 0.05 needs about 250 MiB)."""
MAX_CELLS = 1 << 20
"""Largest grid (``H * W`` cells) a grid considers at all; beyond it even the separator tree
would exceed :data:`MAX_TREE_BYTES`."""
MAX_COLUMN_BYTES = 1 << 28
"""Memory for whole rows of ``G`` kept for cells that recur (pickups, stations): 256 MiB."""


class IPFGrid:
    """The grid graph of one world at one resolution, and its Green's function.

    Build it with :func:`ipf_grid` (cached per world and resolution) rather than directly.

    Parameters
    ----------
    world : World
        Bounds and shelves.
    resolution : float
        Requested cell size in world units; the grid has ``W = round(width / resolution)`` and
        ``H = round(height / resolution)`` cells, so the actual sizes ``dx``, ``dy`` tile the
        world exactly.
    max_bytes : int
        Largest dense Green's function (``F^2 * 8`` bytes) to build; larger grids use the
        separator tree (:mod:`sim.ipf.hierarchy`, exact as well), and grids whose tree would
        exceed :data:`MAX_TREE_BYTES` are refused (``ValueError`` naming a resolution).

    Attributes
    ----------
    shape : tuple of int
        ``(H, W)``.
    x : np.ndarray, shape (W,)
        Cell-centre x coordinates.
    y : np.ndarray, shape (H,)
        Cell-centre y coordinates.
    fixed : np.ndarray of bool, shape (H, W)
        Nodes fixed at 0: the boundary ring and the cells whose centre lies in a shelf.
    obstacle : np.ndarray of bool, shape (H, W)
        The shelf cells alone.
    free_index : np.ndarray of int64, shape (H * W,)
        Index of each cell among the F free (not fixed) cells, ``-1`` for fixed cells.
    num_free : int
        F.
    method : str
        ``"dense"`` (the dense ``G`` and the fused episodic kernel) or ``"tree"`` (entries of
        ``G`` from :attr:`tree`).
    tree : SeparatorTree or None
        The separator tree of ``"tree"`` grids (its numerics built on first use).
    """

    def __init__(
        self, world: World, resolution: float = DEFAULT_RESOLUTION, max_bytes: int = MAX_GREEN_BYTES
    ) -> None:
        resolution = check_resolution(resolution)
        max_bytes = _check_max_bytes(max_bytes)
        if not isinstance(world, World):
            raise ValueError(f"world must be a sim.World, got {type(world).__name__}")
        self.world = world
        self.resolution = resolution
        width, height = world.size
        W, H = int(round(width / resolution)), int(round(height / resolution))
        if W < 3 or H < 3:
            raise ValueError(
                f"resolution {resolution} gives a {H} x {W} grid on a {width:g} x {height:g} "
                "world; at least 3 x 3 cells are needed (one free cell inside the boundary "
                f"ring); use resolution <= {min(width, height) / 3:.4g}"
            )
        # Refuse absurd grids before any (H, W) array is made; the exact test on the free
        # cells' tables follows once the shelves are known.
        if H * W > MAX_CELLS:
            raise ValueError(
                f"resolution {resolution} gives a {H} x {W} grid on a {width:g} x {height:g} "
                f"world, more than {MAX_CELLS} cells; its Green's function would not fit in "
                f"memory; use resolution >= {1.05 * math.sqrt(width * height / MAX_CELLS):.3g}"
            )
        self.shape = (H, W)
        xmin, ymin, _, _ = world.bounds
        self.dx, self.dy = width / W, height / H
        self.x = xmin + (np.arange(W) + 0.5) * self.dx
        self.y = ymin + (np.arange(H) + 0.5) * self.dy
        fixed = np.zeros((H, W), dtype=bool)
        fixed[0, :] = fixed[-1, :] = fixed[:, 0] = fixed[:, -1] = True
        obstacle = np.zeros((H, W), dtype=bool)
        cx, cy = np.meshgrid(self.x, self.y)  # (H, W)
        for x0, y0, x1, y1 in world.obstacles:
            obstacle |= (cx >= x0) & (cx <= x1) & (cy >= y0) & (cy <= y1)
        self.obstacle = obstacle
        self.fixed = fixed | obstacle
        free = ~self.fixed.ravel()
        self.num_free = int(free.sum())
        if self.num_free == 0:
            raise ValueError(
                f"the {H} x {W} grid at resolution {resolution} has no free cell; use a finer one"
            )
        need = self.num_free**2 * 8
        self.tree: SeparatorTree | None = None
        self.method = "dense"
        if need > max_bytes:
            # Too large for the dense G: exact entries from a separator tree instead.
            self.method = "tree"
            self.tree = SeparatorTree(self.fixed)
            if self.tree.nbytes > MAX_TREE_BYTES:
                scale = (self.tree.nbytes / MAX_TREE_BYTES) ** (1 / 3) * 1.1
                raise ValueError(
                    f"resolution {resolution} gives {self.num_free} free cells on this "
                    f"{width:g} x {height:g} world; its Green's function would need "
                    f"{need / 2**20:.0f} MiB dense (limit max_bytes={max_bytes / 2**20:.0f} MiB) "
                    f"and its separator tree {self.tree.nbytes / 2**20:.0f} MiB (limit "
                    f"{MAX_TREE_BYTES / 2**20:.0f} MiB); use resolution >= "
                    f"{resolution * scale:.3g}"
                )
        self.free_index = np.full(H * W, -1, dtype=np.int64)
        self.free_index[free] = np.arange(self.num_free)
        self._green: Tensor | None = None
        self._torch: dict[torch.device, tuple[Tensor, Tensor]] = {}
        self._native_tables: tuple[Tensor, Tensor, int, int, int] | None = None
        self._index: dict[torch.device, Tensor] = {}
        self._slot: Tensor | None = None  # free index -> column of _col_store, or -1
        self._col_store: Tensor | None = None
        self._col_count = 0

    # ------------------------------------------------------------------ the graph
    @functools.cached_property
    def graph(self) -> nx.Graph:
        """The grid graph: nodes ``(row, col)`` with attribute ``fixed`` (bool)."""
        import networkx as nx

        H, W = self.shape
        g = nx.grid_2d_graph(H, W)
        nx.set_node_attributes(g, {(r, c): bool(self.fixed[r, c]) for r, c in g.nodes}, "fixed")
        return g

    @functools.cached_property
    def adjacency(self) -> Any:
        """Sparse ``(H W, H W)`` adjacency matrix of :attr:`graph`, nodes in row-major order."""
        import networkx as nx

        H, W = self.shape
        order = [(r, c) for r in range(H) for c in range(W)]
        return nx.to_scipy_sparse_array(self.graph, nodelist=order, format="csr", dtype=float)

    def laplacian(self) -> Any:
        """The Dirichlet Laplacian ``L = D - A`` restricted to the free nodes, sparse (F, F)."""
        import scipy.sparse as sp

        adj = self.adjacency
        degree = np.asarray(adj.sum(axis=1)).ravel()
        lap = sp.diags(degree) - adj
        free = self.free_index >= 0
        return sp.csc_matrix(lap[free][:, free])

    # ------------------------------------------------------------------ Green's function
    @property
    def green(self) -> np.ndarray:
        """The Dirichlet Green's function ``G = L^{-1}``, dense float64 (F, F), built on first use
        (a read-only view).

        Raises
        ------
        ValueError
            On grids too large for it (``method == "tree"``); use :meth:`green_entries`.
        """
        if self.method != "dense":
            raise ValueError(
                f"this grid has {self.num_free} free cells: its dense Green's function "
                f"({self.num_free**2 * 8 / 2**20:.0f} MiB) is not built (method 'tree'); "
                "read entries with IPFGrid.green_entries(rows, cols)")
        view = self._padded_green()[: self.num_free, : self.num_free].numpy()
        view.setflags(write=False)
        return view

    def _padded_green(self) -> Tensor:
        """``G`` with an extra zero row and column (index F stands for any fixed cell), CPU."""
        if self._green is None:
            # Dense Cholesky of the SPD Laplacian, then G = L^{-1} by one multi-RHS solve:
            # BLAS-3 work, much faster here than F sparse triangular solves.
            F = self.num_free
            lap = torch.from_numpy(self.laplacian().toarray())
            chol = torch.linalg.cholesky(lap)
            del lap
            padded = torch.zeros(F + 1, F + 1, dtype=torch.float64)
            padded[:F, :F] = torch.cholesky_solve(torch.eye(F, dtype=torch.float64), chol)
            del chol
            padded[:F, :F] += padded[:F, :F].T.clone()  # symmetric up to rounding; make it exact
            padded[:F, :F] *= 0.5
            self._green = padded
        return self._green

    def _tables(self, device: torch.device) -> tuple[Tensor, Tensor]:
        """The padded ``G`` and the cell -> free-index table (fixed cells -> F) on ``device``
        (dense grids only)."""
        if device not in self._torch:
            self._torch[device] = (self._padded_green().to(device), self._cell_index(device))
        return self._torch[device]

    def _cell_index(self, device: torch.device) -> Tensor:
        """The cell -> free-index table (fixed cells -> F), (H * W,) int64 on ``device``."""
        if device not in self._index:
            F = self.num_free
            index = torch.from_numpy(np.where(self.free_index >= 0, self.free_index, F))
            self._index[device] = index.to(device)
        return self._index[device]

    def green_entries(self, rows: Tensor, cols: Tensor) -> Tensor:
        """Entries ``G[rows[..., j], cols[..., k]]`` of the Green's function, on any grid.

        Parameters
        ----------
        rows : Tensor of int64, shape (..., J)
            Free-cell indices (``free_index`` of a cell) in ``[0, F]``; ``F`` stands for a
            fixed cell and reads 0.
        cols : Tensor of int64, shape (..., K)
            The same, with the batch dimensions of ``rows``.

        Returns
        -------
        Tensor of float64, shape (..., J, K), on the device of ``rows``

        Raises
        ------
        ValueError
            For indices outside ``[0, F]`` or batch dimensions that differ.
        """
        rows, cols = torch.as_tensor(rows), torch.as_tensor(cols)
        if rows.dim() == 0 or cols.dim() == 0 or rows.shape[:-1] != cols.shape[:-1]:
            raise ValueError(f"rows and cols must have shapes (..., J) and (..., K) with the same "
                             f"batch dimensions, got {tuple(rows.shape)} and {tuple(cols.shape)}")
        for name, t in (("rows", rows), ("cols", cols)):
            if t.dtype != torch.int64 or (t.numel() and (int(t.min()) < 0
                                                         or int(t.max()) > self.num_free)):
                raise ValueError(f"{name} must be int64 free-cell indices in [0, {self.num_free}]")
        return self._gather(rows, cols)

    def _green_rows(self, fidx: Tensor) -> Tensor:
        """Whole rows ``G[fidx[k], :]`` as (S, F + 1) float64 on the CPU (column F reads 0)."""
        table, where = self._column_table(fidx)
        return table.index_select(1, where).T.contiguous()

    def _column_table(self, fidx: Tensor) -> tuple[Tensor, Tensor]:
        """Columns of ``G`` for the cells ``fidx`` (any shape, values in [0, F]): a table
        ``T`` (F + 1, U) float64 on the CPU with ``T[a, k] = G[a, cell k]`` and, for each entry
        of ``fidx`` (flat), its column in it.

        On tree grids the columns are kept in one table that grows up to
        :data:`MAX_COLUMN_BYTES` (cells that recur, pickups and stations, then cost one gather
        after their first use, and an AGV's entries with all of them lie in one row); when the
        cells of one call do not fit, the call gets a table of its own."""
        flat = fidx.cpu().reshape(-1)
        if self.method == "dense":
            return self._padded_green(), flat  # symmetric: its rows are its columns
        assert self.tree is not None
        F1 = self.num_free + 1
        if self._slot is None:
            self._slot = torch.full((F1,), -1, dtype=torch.int64)
            self._col_store = torch.zeros(F1, 0, dtype=torch.float64)
            self._col_count = 0
        where = self._slot.index_select(0, flat)
        if bool((where < 0).any()):
            missing = torch.unique(flat[where < 0])
            count, m = self._col_count, len(missing)
            limit = max(1, MAX_COLUMN_BYTES // (8 * F1))
            if count + m > limit:
                wanted, inverse = torch.unique(flat, return_inverse=True)
                return self.tree.rows(wanted).T.contiguous(), inverse  # this call only
            store = self._col_store
            if count + m > store.shape[1]:
                grown = torch.empty(F1, min(limit, max(2 * store.shape[1], count + m, 16)),
                                    dtype=torch.float64)
                grown[:, :count] = store[:, :count]
                self._col_store = store = grown
            store[:, count: count + m] = self.tree.rows(missing).T
            self._slot[missing] = torch.arange(count, count + m)
            self._col_count = count + m
            where = self._slot.index_select(0, flat)
        return self._col_store, where

    def _pair_block(self, fixed: Tensor, other: Tensor) -> Tensor:
        """``G[fixed[b, k], other[b, j]]`` as (B, K, J) float64 on the device of ``other``,
        where ``fixed`` holds cells that recur between calls (pickups, stations): on tree
        grids their columns are kept and this is one gather (read row by row of ``other``;
        the result is the transpose of a contiguous (B, J, K))."""
        table, where = self._column_table(fixed)
        B, K = fixed.shape
        J = other.shape[1]
        width = table.shape[1]
        flat = (other.cpu().reshape(B, J, 1) * width + where.view(B, 1, K)).view(-1)
        block = table.view(-1).index_select(0, flat).view(B, J, K)
        return block.mT.to(other.device)

    # ------------------------------------------------------------------ cells
    def cell_of(self, points: Tensor | np.ndarray) -> Tensor:
        """Flat row-major index of the cell holding each point (the nearest cell centre).

        Parameters
        ----------
        points : Tensor or np.ndarray, shape (..., 2)
            World coordinates; points outside the world go to the nearest border cell.

        Returns
        -------
        Tensor of int64, shape (...)

        Raises
        ------
        ValueError
            For points whose last dimension is not 2, or NaN coordinates (no cell holds them).
        """
        p = torch.as_tensor(points)
        if p.dim() == 0 or p.shape[-1] != 2:
            raise ValueError(f"points must have shape (..., 2), got {tuple(p.shape)}")
        if p.is_floating_point() and bool(torch.isnan(p).any()):
            raise ValueError("points contain NaN coordinates, which no cell holds")
        return self._cells(p)

    def _cells(self, p: Tensor) -> Tensor:
        """:meth:`cell_of` without its checks, for the batched paths (positions the caller
        made)."""
        H, W = self.shape
        xmin, ymin, _, _ = self.world.bounds
        col = torch.floor((p[..., 0].double() - xmin) / self.dx).long().clamp(0, W - 1)
        row = torch.floor((p[..., 1].double() - ymin) / self.dy).long().clamp(0, H - 1)
        return row * W + col

    # ------------------------------------------------------------------ fast solvers
    def fields(self, source_cells: Tensor, source_values: Tensor,
               source_mask: Tensor | None = None) -> Tensor:
        """Exact fields for a batch of source sets (the fast solver, whole grid).

        Parameters
        ----------
        source_cells : Tensor of int64, shape (K, S)
            Flat cell indices (see :meth:`cell_of`).
        source_values : Tensor, shape (K, S)
            Fixed value of each source.
        source_mask : Tensor of bool, shape (K, S), optional
            Which sources take part (default all).

        Returns
        -------
        Tensor of float64, shape (K, H, W)
            The converged field of each source set. Sources on fixed cells are ignored and
            colliding sources follow the module's rule (earlier wins, so list AGVs first).
        """
        cells = torch.as_tensor(source_cells).long()
        device = cells.device
        values = torch.as_tensor(source_values, device=device).double()
        mask = (torch.ones_like(cells, dtype=torch.bool) if source_mask is None
                else torch.as_tensor(source_mask, device=device).bool())
        _check_sources(self, cells, values, mask)
        index = self._cell_index(device)
        F = self.num_free
        fidx = index[cells]  # (K, S)
        kept = _dedupe(cells, mask & (fidx < F))
        eye = torch.eye(cells.shape[1], dtype=torch.float64, device=device)
        gss = self._gather(fidx, fidx)
        both = kept.unsqueeze(-1) & kept.unsqueeze(-2)
        gss = torch.where(both, gss, eye)
        weights = torch.linalg.solve(gss, (values * kept).unsqueeze(-1))  # (K, S, 1)
        rows = self._green_rows(torch.where(kept, fidx, F).flatten()).to(device)  # (K S, F + 1)
        free_field = rows[:, :F].view(*fidx.shape, F)  # (K, S, F)
        free_field = torch.einsum("ksf,ks->kf", free_field, weights.squeeze(-1) * kept)
        H, W = self.shape
        out = torch.zeros(cells.shape[0], H * W, dtype=torch.float64, device=device)
        out[:, torch.from_numpy(self.free_index >= 0).to(device)] = free_field
        return out.view(-1, H, W)

    def agent_potentials(
        self,
        agent_pos: Tensor,
        task_pos: Tensor,
        task_open: Tensor | None = None,
        task_value: float = TASK_VALUE,
        agent_value: float = AGENT_VALUE,
        cache: TaskBlockCache | None = None,
        native: bool | None = None,
        agent_sources: Tensor | None = None,
    ) -> Tensor:
        """``r_IPF`` of every AGV in every environment: its own field at its own cell.

        Exact (the converged Jacobi fixed point up to float64 rounding), batched, no Python loop
        over environments or AGVs. With ``K = G[T, T]`` over all of an environment's sources and
        ``P = K^{-1}``, AGV i's value is ``v_i - (P v)_i / P_ii`` (see the module notes). Two
        paths compute it:

        - the *block path* (no two sources share a cell, the usual case): with the tasks'
          block ``D = G[tasks, tasks]`` factored as ``L_D L_D^T``, ``X = L_D^{-1} G[tasks,
          agents]`` and the Schur complement ``S = G[agents, agents] - X^T X``, ``P_AA = S^{-1}``
          and ``(P v)_A = S^{-1} (v_A - X^T L_D^{-1} v_T)``. Tasks move only at resets and
          claims, so ``L_D`` and ``L_D^{-1} v_T`` can be kept in ``cache`` and refreshed only
          for the environments whose open tasks changed;
        - the *general path*, for the environments where some sources share a cell (two AGVs
          overlapping deeply, say): one Cholesky factor of the whole ``K`` with the colliding
          sources resolved by the module's rule.

        Parameters
        ----------
        agent_pos : Tensor, shape (B, N, 2)
        task_pos : Tensor, shape (B, M, 2)
        task_open : Tensor of bool, shape (B, M), optional
            Unclaimed tasks (default all); claimed ones are not sources.
        task_value, agent_value : float
            The fixed potentials (+5 and -3 in the paper).
        cache : TaskBlockCache, optional
            Reused task factors (see :class:`TaskBlockCache`); updated in place.
        native : bool, optional
            Use the fused CPU kernel of :mod:`sim.native` (the block formula below, one
            environment at a time in C, colliding sources handled in the same pass) for float32
            CPU tensors. Default: when available; ``False`` forces the torch paths below.
        agent_sources : Tensor of bool, shape (B, N), optional
            The AGVs that are sources of the other AGVs' fields (default all). An AGV that is
            not a source reads 0 (callers override it, as the reward does for parked AGVs).
            Torch paths only: with it, the default ``native`` is ``False``.

        Returns
        -------
        Tensor, shape (B, N), dtype of ``agent_pos``
            ``Phi_i(cell of AGV i)``. Where AGV i's cell holds one of its sources the value is
            that source's (AGV wins over task); on a fixed cell it is 0.

        Raises
        ------
        ValueError
            For positions that are not (B, N, 2) and (B, M, 2), a mask that is not (B, M),
            ``agent_sources`` that is not a (B, N) bool tensor, or ``native=True`` where the
            kernel cannot run (or with ``agent_sources``).
        """
        if agent_sources is not None:
            if native:
                raise ValueError("agent_sources needs the torch paths (native=False or None)")
            native = False
        kernels = None
        if native is not False and self.method == "dense" and agent_pos.dtype == torch.float32 \
                and task_pos.dtype == torch.float32 and task_pos.device.type == "cpu":
            kernels = sim_native.library_for(agent_pos.device)
        if kernels is not None:
            _check_batch_shapes(agent_pos, task_pos, task_open)
            phi = self._potentials_native(kernels, agent_pos, task_pos, task_open, False,
                                          task_value, agent_value, cache)
            return phi.to(agent_pos.dtype)
        if native:
            raise ValueError("native=True needs float32 CPU tensors, the fused kernels "
                             "(see sim.native.disabled_reason()) and a grid with a dense "
                             "Green's function (method 'dense')")
        _check_batch_shapes(agent_pos, task_pos, task_open)
        N = agent_pos.shape[1]
        if agent_sources is not None and (
                agent_sources.dtype != torch.bool
                or tuple(agent_sources.shape) != tuple(agent_pos.shape[:2])):
            raise ValueError(f"agent_sources must be a bool tensor of shape (B, N) = "
                             f"{tuple(agent_pos.shape[:2])}, got {agent_sources.dtype} "
                             f"{tuple(agent_sources.shape)}")
        T = N + task_pos.shape[1]
        device = agent_pos.device
        index = self._cell_index(device)
        cells = self._cells(torch.cat([agent_pos, task_pos], dim=1))  # (B, T), AGVs first
        fidx = index[cells]
        candidate = fidx < self.num_free
        if task_open is not None:
            candidate[:, N:] &= task_open
        if agent_sources is not None:
            candidate[:, :N] &= agent_sources.to(device)
        # Colliding sources (two candidates on one cell) are rare; find them cheaply.
        spread = torch.where(candidate, cells, self._negative_arange(T, device))
        ordered = spread.sort(dim=1).values
        collide = (ordered[:, 1:] == ordered[:, :-1]).any(dim=1).nonzero().flatten()
        phi = self._potentials_block(fidx, candidate, N, task_value, agent_value, cache)
        if len(collide):  # those environments only (the block path is wrong for them)
            phi[collide] = self._potentials_general(
                cells[collide], fidx[collide], candidate[collide], N, task_value, agent_value
            )
        return phi.to(agent_pos.dtype)

    def reward_potentials(
        self,
        agent_pos: Tensor,
        task_pos: Tensor,
        task_claimed: Tensor | None = None,
        agent_task: Tensor | None = None,
        active: Tensor | None = None,
        *,
        kernels: Any = None,
        task_value: float = TASK_VALUE,
        agent_value: float = AGENT_VALUE,
        cache: TaskBlockCache | None = None,
        dtype: torch.dtype = torch.float64,
        parked_sources: bool = True,
    ) -> Tensor:
        """``r_IPF`` as the ``"ipf"`` reward pays it, through the kernels the caller chose.

        :meth:`agent_potentials` with the reward's two rules on top: an AGV that holds a task
        (``agent_task >= 0``, parked on it) reads ``task_value``, and environments that were not
        running (``active`` False) read 0.

        Parameters
        ----------
        agent_pos : Tensor, shape (B, N, 2)
        task_pos : Tensor, shape (B, M, 2)
        task_claimed : Tensor of bool, shape (B, M), optional
            Claimed tasks, which are not sources (default none).
        agent_task : Tensor of int64, shape (B, N), optional
            The task each AGV holds, or -1 (default: none held).
        active : Tensor of bool, shape (B,), optional
            Environments that were running (default all).
        kernels : ctypes.CDLL, optional
            The fused kernels of :mod:`sim.native` to run with (they need float32 CPU
            positions), or None for the torch path. Whoever owns the tensors decides (the
            environment does, once); this method does not look the kernels up.
        task_value, agent_value : float
            The fixed potentials (+5 and -3 in the paper).
        cache : TaskBlockCache, optional
            Reused task factors, updated in place; keep one per batch of environments.
        dtype : torch.dtype
            ``torch.float64`` or ``torch.float32``, the dtype of the result.
        parked_sources : bool
            Whether parked AGVs stay sources (at ``agent_value``) of the other AGVs' fields
            (default True, the reward as shipped). False leaves them out of the field, as
            claimed tasks are; that runs the torch paths whatever ``kernels`` says.

        Returns
        -------
        Tensor, shape (B, N), of ``dtype``

        Raises
        ------
        ValueError
            For a tensor of the wrong shape, or (with ``kernels``) of the wrong dtype or device;
            the message names it.
        """
        _check_batch_shapes(agent_pos, task_pos, task_claimed)
        B, N = agent_pos.shape[:2]
        for name, t, shape in (("agent_task", agent_task, (B, N)), ("active", active, (B,))):
            if t is not None and tuple(t.shape) != shape:
                raise ValueError(f"{name} must have shape {shape}, got {tuple(t.shape)}")
        if dtype not in (torch.float64, torch.float32):
            raise ValueError(f"dtype must be torch.float64 or torch.float32, got {dtype}")
        if kernels is not None and self.method == "dense" and parked_sources:
            return self._potentials_native(kernels, agent_pos, task_pos, task_claimed, True,
                                           task_value, agent_value, cache, agent_task, active,
                                           dtype)
        task_open = None if task_claimed is None else ~task_claimed.to(torch.bool)
        sources = None
        if not parked_sources:
            sources = (torch.ones(B, N, dtype=torch.bool, device=agent_pos.device)
                       if agent_task is None else agent_task < 0)
        phi = self.agent_potentials(agent_pos, task_pos, task_open, task_value, agent_value,
                                    cache=cache, native=False, agent_sources=sources).double()
        if agent_task is not None:
            phi = torch.where(agent_task >= 0, task_value, phi)
        if active is not None:
            phi = phi * active.unsqueeze(1)
        return phi.to(dtype)

    def lifelong_potentials(
        self,
        agent_pos: Tensor,
        pickup_pos: Tensor,
        pickup_open: Tensor,
        dropoff_pos: Tensor,
        loaded: Tensor,
        active: Tensor | None = None,
        *,
        task_value: float = TASK_VALUE,
        agent_value: float = AGENT_VALUE,
        cache: TaskBlockCache | None = None,
        dtype: torch.dtype = torch.float32,
        native: bool | None = None,
    ) -> Tensor:
        """``r_IPF`` of every AGV on a lifelong floor: its own field at its own cell.

        AGV i's field depends on what it carries:

        - *not loaded*: every open pickup at ``task_value`` (pickups that share a cell are one
          source) and every other AGV at ``agent_value``;
        - *loaded*: only its own drop-off at ``task_value`` and every other AGV at
          ``agent_value`` (other AGVs' drop-offs and all pickups are not sources).

        Rules for coinciding cells, as in :meth:`reward_potentials` (the AGV wins): a pickup or
        a drop-off on a cell that holds an AGV is not a source (that cell is ``agent_value`` in
        every field but that AGV's own, where it reads the rules below); AGVs that share a cell
        are one source. AGV i reads ``agent_value`` if another AGV shares its cell, else
        ``task_value`` if a ``task_value`` source of its own field (an open pickup when not
        loaded, its own drop-off when loaded) shares its cell; 0 on a boundary or shelf cell
        (sources there are ignored) and in environments that are not ``active``.

        Exact and batched: per environment one ``N x N`` inverse of the Schur complement of the
        open pickups' block (whose factor is kept in ``cache`` while the open pickups stay the
        same) serves every unloaded AGV, and one inverse of ``G[agents, agents]`` with a rank-one
        border per AGV (its drop-off) serves every loaded one:
        ``P_ii = Q_ii + h_i^2 / s``, ``Phi_i = v_i - ((Q v)_i + h_i (h . v - v_d) / s) / P_ii``
        with ``Q = G[A, A]^{-1}``, ``h = Q G[A, d_i]``, ``s = G[d_i, d_i] - G[d_i, A] h``.
        On large grids (``method == "tree"``) the rows of ``G`` at pickup and drop-off cells
        are kept after their first use (they recur: a floor has finitely many), so only the
        AGVs' own block comes from the separator tree at every call.

        Parameters
        ----------
        agent_pos : Tensor, shape (B, N, 2)
            AGV positions (float32 or float64).
        pickup_pos : Tensor, shape (B, Q, 2)
            Pickup points of the orders (or slots) of each environment.
        pickup_open : Tensor of bool, shape (B, Q)
            Which pickups are open (sources for the AGVs that are not loaded).
        dropoff_pos : Tensor, shape (B, N, 2)
            Each AGV's drop-off point (read only where ``loaded``).
        loaded : Tensor of bool, shape (B, N)
            AGVs carrying an order.
        active : Tensor of bool, shape (B,), optional
            Environments that are running (default all); the others read 0.
        task_value, agent_value : float
            The fixed potentials (+5 and -3).
        cache : TaskBlockCache, optional
            The open pickups' factors kept between calls (updated in place; keep one per batch
            of environments, apart from the episodic reward's).
        dtype : torch.dtype
            ``torch.float32`` or ``torch.float64``, the dtype of the result.
        native : bool, optional
            Do the factorizations, the per-AGV formulas and the cell rules in the CPU kernel
            ``agv_ipf_lifelong`` of :mod:`sim.native` (one pass per environment, after the
            entries of ``G`` are gathered; CPU tensors). Default: when the kernels load;
            ``False`` forces the torch code (the reference).

        Returns
        -------
        Tensor, shape (B, N), of ``dtype``

        Raises
        ------
        ValueError
            Naming the argument, for positions that are not ``(B, ., 2)`` real tensors with
            the same B, masks that are not boolean of the right shape, non-finite potentials
            or another dtype; or ``native=True`` where the kernel cannot run.
        """
        for name, t in (("agent_pos", agent_pos), ("pickup_pos", pickup_pos),
                        ("dropoff_pos", dropoff_pos)):
            if not isinstance(t, Tensor) or t.dim() != 3 or t.shape[-1] != 2 \
                    or not t.is_floating_point():
                raise ValueError(f"{name} must be a real tensor of shape (B, K, 2), got "
                                 f"{getattr(t, 'dtype', type(t).__name__)} "
                                 f"{tuple(getattr(t, 'shape', ()))}")
        B, N = agent_pos.shape[:2]
        Q = pickup_pos.shape[1]
        if pickup_pos.shape[0] != B:
            raise ValueError(f"pickup_pos must have shape ({B}, Q, 2), got "
                             f"{tuple(pickup_pos.shape)}")
        if tuple(dropoff_pos.shape) != (B, N, 2):
            raise ValueError(f"dropoff_pos must have shape ({B}, {N}, 2), got "
                             f"{tuple(dropoff_pos.shape)}")
        for name, t, shape in (("pickup_open", pickup_open, (B, Q)), ("loaded", loaded, (B, N)),
                               ("active", active, (B,))):
            if name == "active" and t is None:
                continue
            if not isinstance(t, Tensor) or t.dtype != torch.bool or tuple(t.shape) != shape:
                raise ValueError(f"{name} must be a bool tensor of shape {shape}, got "
                                 f"{getattr(t, 'dtype', type(t).__name__)} "
                                 f"{tuple(getattr(t, 'shape', ()))}")
        for name, value in (("task_value", task_value), ("agent_value", agent_value)):
            if isinstance(value, bool) or not isinstance(value, (int, float)) \
                    or not math.isfinite(value):
                raise ValueError(f"{name} must be a finite number, got {value!r}")
        if dtype not in (torch.float64, torch.float32):
            raise ValueError(f"dtype must be torch.float64 or torch.float32, got {dtype}")
        device = agent_pos.device
        kernels = None
        if native is not False and device.type == "cpu":
            kernels = sim_native.library()
        if native and kernels is None:
            raise ValueError("native=True needs CPU tensors and the fused kernels (see "
                             "sim.native.disabled_reason())")
        F = self.num_free
        index = self._cell_index(device)
        ca, cp, cd = self._cells(agent_pos), self._cells(pickup_pos), self._cells(dropoff_pos)
        fa, fp, fd = index[ca], index[cp], index[cd]
        if kernels is not None:
            return self._lifelong_native(kernels, ca, cp, cd, fa, fp, fd, pickup_open,
                                         loaded, active, task_value, agent_value,
                                         cache).to(dtype)
        a_cand = fa < F
        same_aa = ca.unsqueeze(-1) == ca.unsqueeze(-2)  # (B, N, N)
        same_pa = cp.unsqueeze(-1) == ca.unsqueeze(-2)  # (B, Q, N)
        a_kept = _dedupe(ca, a_cand, same_aa)
        # the AGV wins a shared cell: pickups and drop-offs there are not sources
        on_agent_p = _any(same_pa & a_cand.unsqueeze(-2), -1)
        on_agent_d = _any((cd.unsqueeze(-1) == ca.unsqueeze(-2)) & a_cand.unsqueeze(-2), -1)
        p_open = pickup_open.to(device) & (fp < F)
        p_kept = _dedupe(cp, p_open & ~on_agent_p)
        loaded = loaded.to(device)
        d_src = loaded & (fd < F) & ~on_agent_d
        f_a = torch.where(a_kept, fa, F)
        f_p = torch.where(p_kept, fp, F)
        v_a = a_kept.to(torch.float64) * agent_value
        g_aa = self._gather(f_a, f_a)  # (B, N, N)
        g_aa.diagonal(dim1=-2, dim2=-1).add_(~a_kept)  # non-sources decouple
        phi = torch.zeros(B, N, dtype=torch.float64, device=device)
        if bool((~loaded).any()):
            # the open pickups' block D = L_D L_D^T, X = G[A, P] L_D^{-T}, S = G_AA - X X^T
            if cache is None:
                cache = TaskBlockCache()
            inv_chol_d, u = cache.update(self, f_p, task_value)
            x_t = self._pair_block(f_p, f_a).mT @ inv_chol_d.mT  # (B, N, Q)
            schur = torch.baddbmm(g_aa, x_t, x_t.mT, alpha=-1.0)
            r = v_a - (x_t @ u.unsqueeze(-1)).squeeze(-1)
            p_ii, p_r = _inverse_diagonal_and_product(schur, r)
            phi = v_a - p_r / p_ii
        if bool(loaded.any()):
            f_d = torch.where(d_src, fd, F)
            # Q = G_AA^{-1} = Y^T Y with Y = C^{-1}, G_AA = C C^T; w_i = Y G[A, d_i], e = Y v_A:
            # g^T Q g = |w_i|^2, h_i = (Q g)_i = Y[:, i] . w_i, h . v_A = w_i . e,
            # Q_ii = |Y[:, i]|^2, (Q v_A)_i = Y[:, i] . e
            chol, _ = torch.linalg.cholesky_ex(g_aa)
            eye = self._eye(N, device)
            inv_chol = torch.linalg.solve_triangular(chol, eye.expand_as(chol), upper=False)
            g_ad = self._pair_block(f_d, f_a).mT  # (B, N_j, N_i): column i is G[A, d_i]
            w = inv_chol @ g_ad  # column i: w_i
            e = (inv_chol @ v_a.unsqueeze(-1)).squeeze(-1)  # (B, N)
            gamma = self._pair_block(f_d.reshape(B * N, 1), f_d.reshape(B * N, 1)).view(B, N)
            s = torch.where(d_src, gamma - (w * w).sum(-2), 1.0)
            v_d = d_src.to(torch.float64) * task_value
            h_ii = (inv_chol * w).sum(-2)
            hv = (w * e.unsqueeze(-1)).sum(-2)
            q_ii = (inv_chol * inv_chol).sum(-2)
            qv = (inv_chol * e.unsqueeze(-1)).sum(-2)
            p_ii = q_ii + h_ii * h_ii / s
            phi_l = v_a - (qv + h_ii * (hv - v_d) / s) / p_ii
            phi = torch.where(loaded, phi_l, phi)
        # coinciding cells, then fixed cells and inactive environments
        not_self = ~self._eye(N, device, torch.bool)
        on_other = _any(same_aa & a_cand.unsqueeze(-2) & not_self, -1)
        on_pickup = _any(same_pa & p_open.unsqueeze(-1), -2)
        on_own = torch.where(loaded, (cd == ca) & (fd < F), on_pickup)
        phi = torch.where(on_own, task_value, phi)
        phi = torch.where(on_other, agent_value, phi)
        phi = torch.where(a_cand, phi, 0.0)
        if active is not None:
            phi = phi * active.to(device).unsqueeze(1)
        return phi.to(dtype)

    def _lifelong_native(
        self, kernels: Any, ca: Tensor, cp: Tensor, cd: Tensor, fa: Tensor, fp: Tensor,
        fd: Tensor, pickup_open: Tensor, loaded: Tensor, active: Tensor | None,
        task_value: float, agent_value: float, cache: TaskBlockCache | None,
    ) -> Tensor:
        """:meth:`lifelong_potentials` through the kernels (CPU tensors, checked inputs):
        the sources in ``agv_ipf_lifelong_sources``, the entries of ``G`` and the two block
        products here, the factorizations, per-AGV formulas and cell rules in
        ``agv_ipf_lifelong``; (B, N) float64."""
        B, N = ca.shape
        Q = cp.shape[1]
        F = self.num_free
        ptr = sim_native.pointer
        f64, i64, u8 = torch.float64, torch.int64, torch.bool
        ca, cp, cd = ca.contiguous(), cp.contiguous(), cd.contiguous()
        fa, fp, fd = fa.contiguous(), fp.contiguous(), fd.contiguous()
        pickup_open = pickup_open.to(device="cpu").contiguous()
        loaded = loaded.to(device="cpu").contiguous()
        f_a, f_d = torch.empty(B, N, dtype=i64), torch.empty(B, N, dtype=i64)
        f_p = torch.empty(B, Q, dtype=i64)
        v_a = torch.empty(B, N, dtype=f64)
        a_cand, d_src = torch.empty(B, N, dtype=u8), torch.empty(B, N, dtype=u8)
        p_open = torch.empty(B, Q, dtype=u8)
        kernels.agv_ipf_lifelong_sources(
            B, N, Q, F, ptr(ca, i64, (B, N), "ca"), ptr(cp, i64, (B, Q), "cp"),
            ptr(cd, i64, (B, N), "cd"), ptr(fa, i64, (B, N), "fa"), ptr(fp, i64, (B, Q), "fp"),
            ptr(fd, i64, (B, N), "fd"), ptr(pickup_open, u8, (B, Q), "pickup_open"),
            ptr(loaded, u8, (B, N), "loaded"), float(agent_value), f_a.data_ptr(),
            f_p.data_ptr(), f_d.data_ptr(), v_a.data_ptr(), a_cand.data_ptr(),
            p_open.data_ptr(), d_src.data_ptr())
        g_aa = self._gather(f_a, f_a)  # (B, N, N)
        g_aa.diagonal(dim1=-2, dim2=-1).add_(f_a == F)  # non-sources decouple
        keep: dict[str, Tensor] = {"g_aa": g_aa.contiguous()}
        any_unloaded, any_loaded = bool((~loaded).any()), bool(loaded.any())
        if any_unloaded:
            if cache is None:
                cache = TaskBlockCache()
            f_p, Qs = cache.compact(f_p, F)
        g_ap, g_ad = self._agent_rows(kernels, f_a, f_p if any_unloaded else None,
                                      f_d if any_loaded else None)
        if any_unloaded:
            assert cache is not None
            inv_chol_d, u = cache.update(self, f_p, task_value, recurring=True, kernels=kernels)
            inv_chol_d, u = inv_chol_d.contiguous(), u.contiguous()
            # S = G_AA - X X^T and r = v_A - X u with X = G[A, P] L_D^{-T}, in the kernel
            keep["schur"] = torch.empty(B, N, N, dtype=f64)
            keep["r"] = torch.empty(B, N, dtype=f64)
            if kernels.agv_ipf_lifelong_block(
                    B, N, Qs, ptr(g_ap, f64, (B, N, Qs), "g_ap"),
                    ptr(inv_chol_d, f64, (B, Qs, Qs), "inv_chol"), ptr(u, f64, (B, Qs), "u"),
                    ptr(keep["g_aa"], f64, (B, N, N), "g_aa"), ptr(v_a, f64, (B, N), "v_a"),
                    keep["schur"].data_ptr(), keep["r"].data_ptr()) < 0:
                raise MemoryError(f"IPF lifelong kernel: no memory for the scratch of N = {N}")
        if any_loaded:
            keep["g_ad"] = g_ad  # [j, i] = G[a_j, d_i]
            keep["gamma"] = self._pair_block(f_d.reshape(B * N, 1),
                                             f_d.reshape(B * N, 1)).reshape(B, N).contiguous()
        keep.update(v_a=v_a, loaded=loaded, d_src=d_src, ca=ca, cp=cp, cd=cd, a_cand=a_cand,
                    p_open=p_open, d_free=(fd < F).contiguous())
        if active is not None:
            keep["active"] = active.to(device="cpu", dtype=torch.bool).contiguous()
        out = torch.empty(B, N, dtype=torch.float64)

        def opt(name: str, dt: torch.dtype, shape: tuple[int, ...]) -> int | None:
            t = keep.get(name)
            return None if t is None else ptr(t, dt, shape, name)

        status = kernels.agv_ipf_lifelong(
            B, N, Q, opt("schur", f64, (B, N, N)), opt("r", f64, (B, N)),
            ptr(keep["g_aa"], f64, (B, N, N), "g_aa"), opt("g_ad", f64, (B, N, N)),
            opt("gamma", f64, (B, N)), ptr(keep["v_a"], f64, (B, N), "v_a"),
            ptr(keep["loaded"], u8, (B, N), "loaded"), ptr(keep["d_src"], u8, (B, N), "d_src"),
            ptr(keep["ca"], i64, (B, N), "ca"), ptr(keep["cp"], i64, (B, Q), "cp"),
            ptr(keep["cd"], i64, (B, N), "cd"), ptr(keep["a_cand"], u8, (B, N), "a_cand"),
            ptr(keep["p_open"], u8, (B, Q), "p_open"),
            ptr(keep["d_free"], u8, (B, N), "d_free"), opt("active", u8, (B,)),
            float(agent_value), float(task_value), out.data_ptr(),
        )
        keep.clear()
        if status < 0:
            raise MemoryError(f"IPF lifelong kernel: no memory for the scratch of N = {N}")
        if status:
            raise RuntimeError("IPF lifelong kernel: a block was not positive definite")
        return out

    def _agent_rows(
        self, kernels: Any, f_a: Tensor, f_p: Tensor | None, f_d: Tensor | None,
    ) -> tuple[Tensor | None, Tensor | None]:
        """``G[f_a[b, j], f_p[b, q]]`` (B, N, Q) and ``G[f_a[b, j], f_d[b, i]]`` (B, N, N),
        contiguous float64 (None where the cells are None), from the kept columns of ``G``
        in one pass of ``agv_ipf_gather_rows`` over the AGVs' rows (the torch gathers of
        :meth:`_pair_block` where the two column sets do not share one table)."""
        B, N = f_a.shape
        sets = [f for f in (f_p, f_d) if f is not None]
        if not sets:
            return None, None
        found = [self._column_table(f) for f in sets]
        table = found[-1][0]
        if any(t is not table for t, _ in found):  # a call-only table: the torch gathers
            return (None if f_p is None else self._pair_block(f_p, f_a).mT.contiguous(),
                    None if f_d is None else self._pair_block(f_d, f_a).mT.contiguous())
        width = table.shape[1]
        ptr = sim_native.pointer
        rows = f_a.contiguous()
        outs: list[Tensor | None] = []
        args: list[Any] = []
        for f, (_, where) in zip(sets, found, strict=True):
            K = f.shape[1]
            w = where.view(B, K).contiguous()
            out = torch.empty(B, N, K, dtype=torch.float64)
            outs.append(out)
            args.append((K, w, out))
        while len(args) < 2:
            args.append((0, None, None))
        (k1, w1, o1), (k2, w2, o2) = args
        kernels.agv_ipf_gather_rows(
            B, N, k1, k2, ptr(table, torch.float64, tuple(table.shape), "column table"), width,
            ptr(rows, torch.int64, (B, N), "agent cells"),
            None if w1 is None else ptr(w1, torch.int64, (B, k1), "columns 1"),
            None if w2 is None else ptr(w2, torch.int64, (B, k2), "columns 2"),
            None if o1 is None else o1.data_ptr(), None if o2 is None else o2.data_ptr())
        del w1, w2, rows
        if f_p is None:
            return None, outs[0]
        return outs[0], outs[1] if f_d is not None else None

    def _potentials_native(
        self, kernels: Any, agent_pos: Tensor, task_pos: Tensor, mask: Tensor | None,
        is_claimed: bool, task_value: float, agent_value: float,
        cache: TaskBlockCache | None = None, agent_task: Tensor | None = None,
        active: Tensor | None = None, dtype: torch.dtype = torch.float64,
    ) -> Tensor:
        """The fused kernel ``agv_ipf`` of ``kernels``, (B, N) of ``dtype``; shapes already
        checked. ``mask`` (B, M) marks the claimed tasks if ``is_claimed``, else the open ones.
        Every buffer reaches C through :func:`sim.native.pointer`: the inputs at every call,
        the grid's tables and the cache's buffers once, when they are made."""
        green_ptr, diag_ptr, index_ptr = self._native_pointers()
        B, N = agent_pos.shape[:2]
        M = task_pos.shape[1]
        H, W = self.shape
        # Converted inputs are kept in `keep` so that they outlive the call (a pointer to a
        # temporary would dangle).
        keep = {
            "agent_pos": agent_pos.contiguous(), "task_pos": task_pos.contiguous(),
            "mask": None if mask is None else mask.to(device="cpu", dtype=torch.bool).contiguous(),
            "agent_task": None if agent_task is None
            else agent_task.to(device="cpu", dtype=torch.int64).contiguous(),
            "active": None if active is None
            else active.to(device="cpu", dtype=torch.bool).contiguous(),
        }
        out = torch.empty(B, N, dtype=dtype)  # contiguous, CPU, (B, N) of dtype by construction
        cache = TaskBlockCache() if cache is None else cache  # holds the buffers: keep it
        cells_ptr, factors_ptr = cache.native_buffers(self, B, M, task_value)
        ptr = sim_native.pointer
        wide = dtype == torch.float64
        xmin, ymin, _, _ = self.world.bounds
        status = kernels.agv_ipf(
            B, N, M, ptr(keep["agent_pos"], torch.float32, (B, N, 2), "agent_pos"),
            ptr(keep["task_pos"], torch.float32, (B, M, 2), "task_pos"),
            None if mask is None else ptr(keep["mask"], torch.bool, (B, M), "task mask"),
            int(is_claimed), green_ptr, diag_ptr, self.num_free, index_ptr, H, W,
            float(xmin), float(ymin), float(self.dx), float(self.dy), float(agent_value),
            float(task_value),
            None if agent_task is None
            else ptr(keep["agent_task"], torch.int64, (B, N), "agent_task"),
            None if active is None else ptr(keep["active"], torch.bool, (B,), "active"),
            cells_ptr, factors_ptr, out.data_ptr() if wide else None,
            None if wide else out.data_ptr(),
        )
        del keep
        if status < 0:
            raise MemoryError(f"IPF kernel: no memory for the scratch of {B} environments")
        if status:
            raise RuntimeError("IPF kernel: a source block was not positive definite")
        return out

    def _native_pointers(self) -> tuple[int, int, int]:
        """Checked addresses of the padded ``G`` (F + 1, F + 1), its diagonal (F + 1,) and the
        free-index table (H * W,) for the kernel; the tensors are made and checked once and
        kept with the grid."""
        if self._native_tables is None:
            green, _ = self._tables(torch.device("cpu"))
            diag = green.diagonal().contiguous()
            index = torch.from_numpy(self.free_index)
            F1 = self.num_free + 1
            ptr = sim_native.pointer
            self._native_tables = (
                diag, index, ptr(green, torch.float64, (F1, F1), "Green's function"),
                ptr(diag, torch.float64, (F1,), "Green's diagonal"),
                ptr(index, torch.int64, (self.shape[0] * self.shape[1],), "free_index"),
            )
        return self._native_tables[2], self._native_tables[3], self._native_tables[4]

    def _gather(self, rows: Tensor, cols: Tensor) -> Tensor:
        """``G[rows[b, j], cols[b, k]]`` as (B, J, K) from the padded G (index F reads 0), or
        from the separator tree on large grids."""
        if self.method != "dense":
            assert self.tree is not None
            # the fused kernel where the kernels load (AGV_NATIVE=0 or no compiler: torch)
            kernels = sim_native.library()
            if rows.device.type == "cpu":
                return self.tree.entries(rows, rows if cols is rows else cols, kernels)
            return self.tree.entries(rows.cpu(), cols.cpu(), kernels).to(rows.device)
        green, _ = self._tables(rows.device)
        F1 = self.num_free + 1
        flat = (rows.unsqueeze(-1) * F1 + cols.unsqueeze(-2)).view(-1)
        return green.view(-1).index_select(0, flat).view(*rows.shape, cols.shape[-1])

    def _potentials_block(
        self, fidx: Tensor, candidate: Tensor, N: int, task_value: float, agent_value: float,
        cache: TaskBlockCache | None,
    ) -> Tensor:
        """The block path of :meth:`agent_potentials` (no two candidates share a cell)."""
        F = self.num_free
        f_all = torch.where(candidate, fidx, F)  # F = not a source (reads G's zero row)
        f_agents, f_tasks = f_all[:, :N], f_all[:, N:]
        if cache is None:
            cache = TaskBlockCache()
        inv_chol_d, u_tasks = cache.update(self, f_tasks, task_value)  # L_D^{-1}, L_D^{-1} v_T
        if self.method == "dense":
            rows = self._gather(f_agents, torch.cat([f_tasks, f_agents], dim=1))  # G[A, T ++ A]
        else:  # the tree computes the symmetric G[A, A] once per pair
            rows = torch.cat([self._gather(f_agents, f_tasks), self._gather(f_agents, f_agents)],
                             dim=-1)
        x_t = rows[..., : f_tasks.shape[1]] @ inv_chol_d.mT  # X^T = G[A, T] L_D^{-T}, (B, N, M)
        schur = rows[..., f_tasks.shape[1]:] - x_t @ x_t.mT  # S = G[A, A] - X^T X, (B, N, N)
        dropped = f_agents == F
        schur.diagonal(dim1=-2, dim2=-1).add_(dropped)
        v_agents = (~dropped).to(torch.float64) * agent_value
        r = v_agents - (x_t * u_tasks.unsqueeze(1)).sum(-1)  # v_A - G[A,T] D^{-1} v_T
        if N > 16:  # many AGVs: a Cholesky factor and its triangular inverse are cheaper
            p_ii, p_v = _inverse_diagonal_and_product(schur, r)
            return v_agents - p_v / p_ii
        # P_AA = S^{-1} and (P v)_A = S^{-1} r; N x N LU inverses are the cheapest batched
        # LAPACK call here, and S is well conditioned (a Schur complement of G[T, T]).
        p_aa, _ = torch.linalg.inv_ex(schur)
        p_ii = p_aa.diagonal(dim1=-2, dim2=-1)
        p_v = (p_aa * r.unsqueeze(1)).sum(-1)
        return v_agents - p_v / p_ii

    def _potentials_general(
        self, cells: Tensor, fidx: Tensor, candidate: Tensor, N: int, task_value: float,
        agent_value: float,
    ) -> Tensor:
        """The general path of :meth:`agent_potentials`: any sources, colliding ones resolved."""
        B, T = cells.shape
        M = T - N
        device = cells.device
        F = self.num_free
        same = cells.unsqueeze(-1) == cells.unsqueeze(-2)  # (B, T, T)
        kept = _dedupe(cells, candidate, same)
        # K = G[T, T] over the kept sources; a dropped source reads the zero row and column F
        # of the padded G and gets a 1 on the diagonal, which decouples it (and a dropped AGV
        # gets Phi = 0 - 0 / 1 = 0, right for an AGV on a fixed cell).
        fidx_kept = torch.where(kept, fidx, F)
        gram = self._gather(fidx_kept, fidx_kept)
        gram.diagonal(dim1=-2, dim2=-1).add_(~kept)
        values = self._values(N, M, agent_value, task_value, device) * kept  # (B, T)
        # With K = C C^T and Y = C^{-1} [e_1 .. e_N, v]: P_ii = |Y_i|^2, (P v)_i = Y_i . Y_v, and
        # Phi_i = -(sum_{j != i} P_ij v_j) / P_ii = v_i - (P v)_i / P_ii.
        chol, _ = torch.linalg.cholesky_ex(gram)
        rhs = torch.empty(B, T, N + 1, dtype=torch.float64, device=device)
        rhs[..., :N] = self._eye(T, device)[:, :N]
        rhs[..., N] = values
        y = torch.linalg.solve_triangular(chol, rhs, upper=False)  # (B, T, N + 1)
        y_agents, y_values = y[..., :N], y[..., N:]
        p_ii = (y_agents * y_agents).sum(1)  # (B, N)
        p_v = (y_agents * y_values).sum(1)
        phi = values[:, :N] - p_v / p_ii
        # AGV i's own cell shared with one of its sources: that source's value (AGV wins).
        not_self = ~self._eye(T, device, torch.bool)[:N]
        coincide = same[:, :N] & candidate.unsqueeze(1) & not_self  # (B, N, T)
        phi = torch.where(coincide[..., N:].any(-1), task_value, phi)
        return torch.where(coincide[..., :N].any(-1), agent_value, phi)

    @staticmethod
    @functools.lru_cache(maxsize=16)
    def _negative_arange(n: int, device: torch.device) -> Tensor:
        return -1 - torch.arange(n, device=device)

    @staticmethod
    @functools.lru_cache(maxsize=16)
    def _values(n: int, m: int, agent_value: float, task_value: float,
                device: torch.device) -> Tensor:
        return torch.cat([torch.full((n,), agent_value, dtype=torch.float64, device=device),
                          torch.full((m,), task_value, dtype=torch.float64, device=device)])

    @staticmethod
    @functools.lru_cache(maxsize=16)
    def _eye(n: int, device: torch.device, dtype: torch.dtype = torch.float64) -> Tensor:
        return torch.eye(n, dtype=dtype, device=device)


def _check_sources(grid: IPFGrid, cells: Tensor, values: Tensor,
                   mask: Tensor | None = None) -> None:
    """Refuse source sets that are not (K, S) cells in the grid with finite values."""
    if cells.dim() != 2:
        raise ValueError(f"source_cells must have shape (K, S), got {tuple(cells.shape)}")
    if values.shape != cells.shape or (mask is not None and mask.shape != cells.shape):
        what = "source_values" if values.shape != cells.shape else "source_mask"
        got = values.shape if values.shape != cells.shape else mask.shape
        raise ValueError(f"{what} must have the shape of source_cells {tuple(cells.shape)}, "
                         f"got {tuple(got)}")
    H, W = grid.shape
    if cells.numel() and (int(cells.min()) < 0 or int(cells.max()) >= H * W):
        raise ValueError(f"source_cells must be flat cell indices in [0, {H * W}) (see "
                         f"IPFGrid.cell_of), got values in [{int(cells.min())}, "
                         f"{int(cells.max())}]")
    if not bool(torch.isfinite(values).all()):
        raise ValueError("source_values must be finite")


def _check_batch_shapes(agent_pos: Tensor, task_pos: Tensor, task_mask: Tensor | None) -> None:
    """Refuse positions that are not (B, N, 2) and (B, M, 2), or a task mask not (B, M)."""
    if agent_pos.dim() != 3 or agent_pos.shape[-1] != 2:
        raise ValueError(f"agent_pos must have shape (B, N, 2), got {tuple(agent_pos.shape)}")
    B = agent_pos.shape[0]
    if task_pos.dim() != 3 or task_pos.shape[-1] != 2 or task_pos.shape[0] != B:
        raise ValueError(f"task_pos must have shape ({B}, M, 2), got {tuple(task_pos.shape)}")
    if task_mask is not None and tuple(task_mask.shape) != tuple(task_pos.shape[:2]):
        raise ValueError(f"the task mask must have shape {tuple(task_pos.shape[:2])}, "
                         f"got {tuple(task_mask.shape)}")


class TaskBlockCache:
    """The tasks' factors of :meth:`IPFGrid.agent_potentials`, kept between steps.

    Holds, per environment, the free-cell indices of the open tasks (F for none), the inverse
    ``L_D^{-1}`` of the Cholesky factor of ``G[tasks, tasks]`` and ``L_D^{-1} v_T``;
    :meth:`update` refreshes the environments whose open tasks changed (a reset or a claim) and
    reuses the rest. One cache serves one batch of environments on one grid; any other grid,
    shape or value rebuilds it.
    """

    def __init__(self) -> None:
        self.grid: IPFGrid | None = None
        self.key: tuple[tuple[int, ...], float, torch.device] | None = None
        self.f_tasks: Tensor | None = None  # (B, M) int64
        self.inv_chol: Tensor | None = None  # (B, M, M) float64
        self.u: Tensor | None = None  # (B, M) float64
        self._native: tuple[Any, ...] | None = None  # (grid, key, cells, factors, pointers)
        self.width = 0  # the width of compact(): the most sources seen, a multiple of 4

    def compact(self, f_tasks: Tensor, F: int) -> tuple[Tensor, int]:
        """The source cells of ``f_tasks`` (B, M) first, in increasing order, the no-source
        index ``F`` after them, cut to a width that only grows (the most sources seen, rounded
        up to a multiple of 4): ``(cells (B, W), W)``.

        The potentials do not depend on the order of the sources or on trailing non-sources
        (identity rows of the factor, zero columns of the products, and with W a multiple of
        4 the kernels' four-lane sums have no tail), so the values are the same whatever the
        width, while the work shrinks with the slots that hold no open order.
        """
        need = int((f_tasks < F).sum(1).max()) if f_tasks.numel() else 0
        width = max(self.width, 4 * ((max(need, 1) + 3) // 4))
        self.width = width
        cells = torch.sort(f_tasks, dim=1).values[:, :width]
        if cells.shape[1] < width:
            pad = cells.new_full((cells.shape[0], width - cells.shape[1]), F)
            cells = torch.cat([cells, pad], dim=1)
        return cells.contiguous(), width

    def native_buffers(self, grid: IPFGrid, B: int, M: int, task_value: float) -> tuple[int, int]:
        """Checked addresses of the fused kernel's per-environment task factors (see
        ``agv_ipf`` in ``sim/_native/ipf.c``): cells (B, 1 + M) int64 (count, then free
        indices; count -1 = empty) and factors (B, M * M + M) float64, kept (and checked by
        :func:`sim.native.pointer`) once, while grid, B, M and the task value stay the same.
        The kernel checks the cells and refreshes stale entries itself."""
        key = (B, M, float(task_value))
        if self._native is None or self._native[0] is not grid or self._native[1] != key:
            cells = torch.full((B, 1 + M), -1, dtype=torch.int64)
            factors = torch.zeros(B, M * M + M, dtype=torch.float64)
            pointers = (sim_native.pointer(cells, torch.int64, (B, 1 + M), "task cells cache"),
                        sim_native.pointer(factors, torch.float64, (B, M * M + M),
                                           "task factors cache"))
            self._native = (grid, key, cells, factors, pointers)
        return self._native[4]

    def update(self, grid: IPFGrid, f_tasks: Tensor, task_value: float,
               recurring: bool = False, kernels: Any = None) -> tuple[Tensor, Tensor]:
        """Factors for the open tasks ``f_tasks`` (B, M), recomputed only where they changed.

        ``recurring=True`` says the task cells recur between calls (a floor's pickup points):
        on tree grids ``G[tasks, tasks]`` is then read from the kept columns of ``G`` (see
        :meth:`IPFGrid._pair_block`) instead of the separator tree. ``kernels`` (the fused
        kernels of :mod:`sim.native`, CPU tensors) factor the blocks in
        ``agv_ipf_inverse_factors`` instead of LAPACK.

        Returns
        -------
        inv_chol : Tensor, shape (B, M, M)
            ``L_D^{-1}``, lower triangular, where ``L_D L_D^T = G[tasks, tasks]`` (identity rows
            for tasks that are not sources).
        u : Tensor, shape (B, M)
            ``L_D^{-1} v_T``.
        """
        key = (tuple(f_tasks.shape), float(task_value), f_tasks.device)
        if self.grid is not grid or self.key != key or self.f_tasks is None:
            self.grid, self.key, self.f_tasks = grid, key, f_tasks.clone()
            self.inv_chol, self.u = self._factor(grid, f_tasks, task_value, recurring, kernels)
            return self.inv_chol, self.u
        changed = (f_tasks != self.f_tasks).any(dim=1).nonzero().flatten()
        if len(changed):
            inv_chol, u = self._factor(grid, f_tasks[changed], task_value, recurring, kernels)
            self.inv_chol[changed] = inv_chol
            self.u[changed] = u
            self.f_tasks[changed] = f_tasks[changed]
        return self.inv_chol, self.u

    @staticmethod
    def _factor(grid: IPFGrid, f_tasks: Tensor, task_value: float, recurring: bool = False,
                kernels: Any = None) -> tuple[Tensor, Tensor]:
        dropped = f_tasks == grid.num_free
        if recurring and grid.method != "dense":
            block = grid._pair_block(f_tasks, f_tasks).contiguous()
        else:
            block = grid._gather(f_tasks, f_tasks)
        block.diagonal(dim1=-2, dim2=-1).add_(dropped)
        if kernels is not None and block.shape[0] and block.shape[1]:
            # the kernel: LAPACK's per-matrix overhead dominates at these sizes
            B, M = block.shape[:2]
            block = block.contiguous()
            inv_chol = torch.empty(B, M, M, dtype=torch.float64)
            status = kernels.agv_ipf_inverse_factors(
                B, M, sim_native.pointer(block, torch.float64, (B, M, M), "block"),
                inv_chol.data_ptr())
            if status < 0:
                raise MemoryError(f"IPF kernel: no memory for the scratch of M = {M}")
            if status:
                raise RuntimeError("IPF: the tasks' block of G was not positive definite")
        else:
            chol, _ = torch.linalg.cholesky_ex(block)
            eye = torch.eye(f_tasks.shape[1], dtype=torch.float64, device=f_tasks.device)
            # row-major (LAPACK hands back column-major): the products and kernels read rows
            inv_chol = torch.linalg.solve_triangular(chol, eye.expand_as(chol),
                                                     upper=False).contiguous()
        u = (inv_chol * ((~dropped).to(torch.float64) * task_value).unsqueeze(1)).sum(-1)
        return inv_chol, u


def _inverse_diagonal_and_product(spd: Tensor, r: Tensor) -> tuple[Tensor, Tensor]:
    """``diag(S^{-1})`` and ``S^{-1} r`` for a batch of SPD matrices ``S`` (B, N, N) and vectors
    ``r`` (B, N): with ``S = C C^T`` and ``Y = C^{-1}``, ``(S^{-1})_ii = sum_k Y_ki^2`` and
    ``(S^{-1} r)_i = sum_k Y_ki (Y r)_k`` (a factor and a triangular inverse, about a third
    of an LU inverse's work)."""
    chol, _ = torch.linalg.cholesky_ex(spd)
    eye = torch.eye(spd.shape[-1], dtype=spd.dtype, device=spd.device)
    inv_chol = torch.linalg.solve_triangular(chol, eye.expand_as(chol), upper=False)
    z = (inv_chol @ r.unsqueeze(-1))  # (B, N, 1)
    return (inv_chol * inv_chol).sum(-2), (inv_chol * z).sum(-2)


def _any(flags: Tensor, dim: int) -> Tensor:
    """``flags.any(dim)`` for bool tensors, as a count (several times faster on the CPU)."""
    return flags.sum(dim) > 0


def _dedupe(cells: Tensor, candidate: Tensor, same: Tensor | None = None) -> Tensor:
    """Keep each candidate source unless an earlier candidate shares its cell.

    Parameters
    ----------
    cells : Tensor of int64, shape (K, S)
    candidate : Tensor of bool, shape (K, S)
    same : Tensor of bool, shape (K, S, S), optional
        ``cells[:, j] == cells[:, k]``, if already computed.

    Returns
    -------
    Tensor of bool, shape (K, S)
    """
    if same is None:
        same = cells.unsqueeze(-1) == cells.unsqueeze(-2)
    earlier = _earlier(cells.shape[1], cells.device)  # [k, j]: j < k
    shadowed = _any(same & (earlier & candidate.unsqueeze(-2)), -1)
    return candidate & ~shadowed


@functools.lru_cache(maxsize=16)
def _earlier(n: int, device: torch.device) -> Tensor:
    return torch.ones(n, n, dtype=torch.bool, device=device).tril(-1)


@functools.lru_cache(maxsize=8)
def _cached_grid(
    bounds: tuple[float, ...], obstacles: bytes, num_obstacles: int, resolution: float,
    max_bytes: int,
) -> IPFGrid:
    obs = np.frombuffer(obstacles, dtype=np.float64).reshape(num_obstacles, 4)
    return IPFGrid(World(bounds=bounds, obstacles=obs.copy()), resolution, max_bytes)


def check_resolution(resolution: object) -> float:
    """``resolution`` as a float, if it is a positive, finite cell size.

    Raises
    ------
    ValueError
        For anything else (0, a negative number, NaN, infinity, a bool, a string, None).
    """
    number = isinstance(resolution, (int, float, np.integer, np.floating))
    if isinstance(resolution, (bool, np.bool_)) or not number \
            or not (math.isfinite(resolution) and resolution > 0):
        raise ValueError("resolution must be a positive, finite cell size in world units "
                         f"(default {DEFAULT_RESOLUTION}), got {resolution!r}")
    return float(resolution)


def _check_max_bytes(max_bytes: object) -> int:
    if isinstance(max_bytes, (bool, np.bool_)) or not isinstance(max_bytes, (int, np.integer)) \
            or max_bytes < 8:
        raise ValueError(f"max_bytes must be an integer number of bytes >= 8 (default "
                         f"{MAX_GREEN_BYTES}), got {max_bytes!r}")
    return int(max_bytes)


def ipf_grid(
    world: World | None = None, resolution: float = DEFAULT_RESOLUTION,
    max_bytes: int = MAX_GREEN_BYTES,
) -> IPFGrid:
    """The (cached) grid of a world at a resolution.

    The cache key is the world's bounds and shelves (not the AGV size or physics, which the
    grid does not depend on), the resolution and the memory limit; 8 grids are kept.

    Raises
    ------
    ValueError
        For a world that is not a :class:`sim.World`, a resolution that is not a positive
        finite number or that gives fewer than 3 x 3 cells, or one whose Green's function
        would exceed ``max_bytes`` (the message names a resolution that fits).
    """
    if world is None:
        world = World()
    elif not isinstance(world, World):
        raise ValueError(f"world must be a sim.World or None, got {type(world).__name__}")
    resolution = check_resolution(resolution)
    max_bytes = _check_max_bytes(max_bytes)
    obs = np.ascontiguousarray(world.obstacles, dtype=np.float64)
    return _cached_grid(tuple(world.bounds), obs.tobytes(), len(obs), resolution, max_bytes)
