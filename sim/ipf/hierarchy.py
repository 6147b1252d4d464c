"""Exact entries of the Dirichlet Green's function of large grids, without the dense ``G``.

The free cells are split recursively by straight separator lines (a row or a column of the
domain, chosen where it crosses the fewest free cells, so through shelves where it can); the
pieces below a size are *leaves*. For a domain ``D`` with separator ``Sigma`` and the rest
``C = D \\ Sigma`` (the children, not connected to each other once ``Sigma`` is removed), block
elimination of ``L_D`` (the Laplacian restricted to ``D``; every cell outside ``D`` is fixed at 0)
gives, with the harmonic measure ``E = -L_CC^{-1} L_{C Sigma}`` and the Schur complement
``S = L_{Sigma Sigma} + L_{Sigma C} E = R R^T``,

``G_D(s, t) = [s, t in one child c] G_c(s, t) + y_s . y_t``,   ``y_s = R^{-1} b_s``,

where ``b_s`` is row ``s`` of ``E`` for ``s`` in ``C`` and ``e_s`` for ``s`` on ``Sigma``.
Unrolled over the tree, ``G(s, t)`` is the sum of ``y_s . y_t`` over the domains that hold both
cells, plus the leaf's dense Green's function when both lie in one leaf. Per level of the tree the
vectors ``y`` sit in one table ``(F + 1, s_max)`` (row ``F``, and the rows of cells outside every
domain of that level, are zero), so a block of entries between two sets of cells is one gather
and one small matrix product per level, masked to the pairs that share the domain.

Memory is ``F * (sum over levels of the widest separator) * 8`` bytes plus the leaves'
``sum m^2 * 8``: on a floor of ``F`` free cells the separators shrink by about ``sqrt(2)`` a
level, so the sum is a few times the first one, ``O(F sqrt(F))`` against ``F^2`` for ``G``.
Everything is float64 and direct (Cholesky factors and sparse LU solves), so the entries are
exact up to rounding.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch
from torch import Tensor

__all__ = ["LEAF_CELLS", "SeparatorTree", "free_laplacian"]

LEAF_CELLS = 1024
"""Domains of at most this many free cells are leaves (a dense Green's function each)."""
_BALANCE = 0.2
"""A separator line must leave at least this fraction of the domain's cells on each side."""


def free_laplacian(fixed: np.ndarray) -> object:
    """The Dirichlet Laplacian ``4 I - A`` over the free (not fixed) cells of a grid, sparse CSC
    (F, F), free cells in row-major order. Built with numpy (no graph), for large grids.

    Parameters
    ----------
    fixed : np.ndarray of bool, shape (H, W)
        Cells fixed at 0; the outer ring must be fixed (every free cell then has 4 neighbours).
    """
    import scipy.sparse as sp

    H, W = fixed.shape
    free = ~fixed.ravel()
    index = np.full(H * W, -1, dtype=np.int64)
    F = int(free.sum())
    index[free] = np.arange(F)
    cells = np.flatnonzero(free)
    rows, cols = [np.arange(F)], [np.arange(F)]
    vals = [np.full(F, 4.0)]
    for step in (1, -1, W, -W):
        nb = index[cells + step]
        ok = nb >= 0
        rows.append(np.flatnonzero(ok))
        cols.append(nb[ok])
        vals.append(np.full(int(ok.sum()), -1.0))
    return sp.csc_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                         shape=(F, F))


@dataclass
class _Node:
    cells: np.ndarray  # free indices of the domain (separator cells included)
    level: int
    sep: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    children: list[_Node] = field(default_factory=list)

    @property
    def leaf(self) -> bool:
        return not self.children and len(self.sep) == 0


def _split(rc: np.ndarray) -> tuple[int, int] | None:
    """The separator line of a domain with cell coordinates ``rc`` (n, 2): ``(axis, value)``,
    the row or column with the fewest cells among those leaving ``_BALANCE`` of the cells on
    each side (ties: the most balanced), or None if no line does."""
    n = len(rc)
    best: tuple[float, int, int] | None = None
    for axis in (0, 1):
        coord = rc[:, axis]
        lo = int(coord.min())
        counts = np.bincount(coord - lo)
        below = np.cumsum(counts) - counts
        above = n - below - counts
        ok = np.minimum(below, above) >= _BALANCE * n
        if not ok.any():
            continue
        cand = np.flatnonzero(ok)
        score = counts[cand] + np.abs(below[cand] - above[cand]) / (2.0 * n)
        k = int(np.argmin(score))
        if best is None or score[k] < best[0]:
            best = (float(score[k]), axis, int(cand[k]) + lo)
    return None if best is None else (best[1], best[2])


class SeparatorTree:
    """Nested dissection of a grid's free cells and the tables that give exact entries of
    its Dirichlet Green's function (see the module notes).

    Made in two stages: the tree (cheap, index work only; :attr:`nbytes` is then exact, so a
    caller can refuse a grid before any factorization) and :meth:`build` (the numerics).

    Parameters
    ----------
    fixed : np.ndarray of bool, shape (H, W)
        Cells fixed at 0, the outer ring included.
    leaf_cells : int
        Domains of at most this many free cells are leaves.

    Attributes
    ----------
    num_free : int
        F.
    depth : int
        Number of separator levels.
    separator_widths : list of int
        The widest separator of each level.
    nbytes : int
        Memory the tables will take (float64 vectors, node ids, leaf blocks).
    """

    def __init__(self, fixed: np.ndarray, leaf_cells: int = LEAF_CELLS) -> None:
        fixed = np.asarray(fixed, dtype=bool)
        if fixed.ndim != 2:
            raise ValueError(f"fixed must be a 2-D mask (H, W), got shape {fixed.shape}")
        if not (isinstance(leaf_cells, (int, np.integer)) and leaf_cells >= 1):
            raise ValueError(f"leaf_cells must be a positive integer, got {leaf_cells!r}")
        self.fixed = fixed
        H, W = fixed.shape
        flat = np.flatnonzero(~fixed.ravel())
        self.num_free = F = len(flat)
        self._rc = np.stack([flat // W, flat % W], axis=1).astype(np.int64)  # (F, 2)
        self.root = _Node(np.arange(F, dtype=np.int64), 0)
        self.leaves: list[_Node] = []
        self.levels: list[list[_Node]] = []
        stack = [self.root]
        while stack:
            node = stack.pop()
            rc = self._rc[node.cells]
            line = None if len(node.cells) <= leaf_cells else _split(rc)
            if line is None:
                self.leaves.append(node)
                continue
            axis, value = line
            coord = rc[:, axis]
            node.sep = node.cells[coord == value]
            while len(self.levels) <= node.level:
                self.levels.append([])
            self.levels[node.level].append(node)
            for side in (coord < value, coord > value):
                if side.any():
                    child = _Node(node.cells[side], node.level + 1)
                    node.children.append(child)
                    stack.append(child)
        self.depth = len(self.levels)
        self.separator_widths = [max(len(n.sep) for n in lev) for lev in self.levels]
        leaf_bytes = sum(len(n.cells) ** 2 for n in self.leaves) * 8
        self.nbytes = int((F + 1) * (8 * sum(self.separator_widths) + 8 * self.depth + 24)
                          + leaf_bytes)
        self._built = False
        self._native: tuple[Any, ...] | None = None
        self._rank_ptr: int | None = None

    # ------------------------------------------------------------------ numerics
    def build(self) -> SeparatorTree:
        """Factor every separator's Schur complement and fill the tables (once)."""
        if self._built:
            return self
        import scipy.sparse.linalg as spla

        F = self.num_free
        lap = free_laplacian(self.fixed).tocsr()
        self._y: list[Tensor] = []
        self._node_id: list[Tensor] = []
        widths = self.separator_widths
        self._offsets = np.concatenate([[0], np.cumsum(widths)]).astype(int).tolist()
        ycat = np.zeros((F + 1, self._offsets[-1]))  # every level's vectors side by side
        # path[c, l]: c's domain at level l, or a negative number of c's own where c lies in
        # none (so that two cells share exactly the levels of their common ancestors)
        path = np.empty((F + 1, self.depth), dtype=np.int64)
        path[:] = -2 - np.arange(F + 1)[:, None]
        for lev, nodes in enumerate(self.levels):
            y = ycat[:, self._offsets[lev]: self._offsets[lev + 1]]
            node_id = np.full(F + 1, -1, dtype=np.int64)
            for k, node in enumerate(nodes):
                sep = node.sep
                s = len(sep)
                rest = np.setdiff1d(node.cells, sep, assume_unique=True)
                lap_ss = lap[sep][:, sep].toarray()
                if len(rest):
                    lap_cs = lap[rest][:, sep]
                    lu = spla.splu(lap[rest][:, rest].tocsc(), permc_spec="MMD_AT_PLUS_A")
                    harm = -lu.solve(lap_cs.toarray())  # E = -L_CC^{-1} L_C,Sigma
                    schur = lap_ss + lap_cs.T @ harm
                else:
                    harm = np.zeros((0, s))
                    schur = lap_ss
                # dense work in torch (its thread setting; numpy's BLAS may oversubscribe)
                chol = torch.linalg.cholesky(torch.from_numpy(0.5 * (schur + schur.T)))
                # y_s = R^{-1} b_s for every cell of the domain: rows of [E; I] R^{-T}
                y[rest, :s] = torch.linalg.solve_triangular(
                    chol, torch.from_numpy(np.ascontiguousarray(harm.T)), upper=False).T.numpy()
                y[sep, :s] = torch.linalg.solve_triangular(
                    chol, torch.eye(s, dtype=torch.float64), upper=False).T.numpy()
                node_id[node.cells] = k
            self._node_id.append(torch.from_numpy(node_id))
            path[:F, lev] = np.where(node_id[:F] >= 0, node_id[:F], path[:F, lev])
        self._ycat = torch.from_numpy(ycat)
        self._y = [self._ycat[:, a:b] for a, b in zip(self._offsets[:-1], self._offsets[1:],
                                                       strict=True)]
        self._path = torch.from_numpy(path)
        # leaves: dense inverses, packed; per cell its leaf, its place in it
        leaf_id = np.full(F + 1, -1, dtype=np.int64)
        local = np.zeros(F + 1, dtype=np.int64)
        size = np.zeros(len(self.leaves) + 1, dtype=np.int64)
        offset = np.zeros(len(self.leaves) + 1, dtype=np.int64)
        blocks = []
        total = 0
        for k, leaf in enumerate(self.leaves):
            m = len(leaf.cells)
            lu = spla.splu(lap[leaf.cells][:, leaf.cells].tocsc(), permc_spec="MMD_AT_PLUS_A")
            inv = lu.solve(np.eye(m))  # a sparse factor: far cheaper than a dense inverse
            blocks.append((0.5 * (inv + inv.T)).ravel())
            leaf_id[leaf.cells] = k
            local[leaf.cells] = np.arange(m)
            size[k], offset[k] = m, total
            total += m * m
        self._leaf_values = torch.from_numpy(np.concatenate(blocks + [np.zeros(1)]))
        self._leaf_id = torch.from_numpy(leaf_id)
        self._leaf_local = torch.from_numpy(local)
        self._leaf_size = torch.from_numpy(size)
        self._leaf_offset = torch.from_numpy(offset)
        mmax = max(len(leaf.cells) for leaf in self.leaves)
        cells = np.full((len(self.leaves) + 1, mmax), F, dtype=np.int64)
        for k, leaf in enumerate(self.leaves):
            cells[k, : len(leaf.cells)] = leaf.cells
        self._leaf_cells = torch.from_numpy(cells)
        self._rank = torch.from_numpy(self._dfs_rank())
        self._built = True
        return self

    def _dfs_rank(self) -> np.ndarray:
        """Each cell's place (F + 1,) in a depth-first order of the tree (a domain's separator,
        then its children; a leaf's cells together; the no-cell index F last): every domain of
        every level, and every leaf, is a run of consecutive places."""
        F = self.num_free
        order: list[np.ndarray] = []
        stack = [self.root]
        while stack:
            node = stack.pop()
            if node.leaf:
                order.append(node.cells)
                continue
            order.append(node.sep)
            stack.extend(reversed(node.children))
        order.append(np.array([F], dtype=np.int64))
        flat = np.concatenate(order)
        rank = np.empty(F + 1, dtype=np.int64)
        rank[flat] = np.arange(F + 1)
        return rank

    # ------------------------------------------------------------------ queries
    def entries(self, rows: Tensor, cols: Tensor, kernels: Any = None) -> Tensor:
        """``G[rows[..., j], cols[..., k]]`` as ``(..., J, K)`` float64; index ``F`` reads 0.

        Parameters
        ----------
        rows : Tensor of int64, shape (..., J)
            Free-cell indices in ``[0, F]`` (F: no cell), on the CPU.
        cols : Tensor of int64, shape (..., K)
            The same, batch dimensions equal to ``rows``'. Passing ``rows`` itself (the same
            object) computes only one triangle.
        kernels : ctypes.CDLL, optional
            The fused kernels of :mod:`sim.native`: ``agv_ipf_tree_entries`` computes each
            pair's dot product over only the levels the pair shares (the torch path below
            masks full products), about 2-3 times less work. None: the torch path.
        """
        self.build()
        sym = rows is cols
        batch, J, K = rows.shape[:-1], rows.shape[-1], cols.shape[-1]
        if J == 0 or K == 0 or rows.numel() == 0:  # nothing to read (reshape(-1, 0) fails)
            return torch.zeros(*batch, J, K, dtype=torch.float64)
        r = rows.reshape(-1, J).contiguous()
        c = r if sym else cols.reshape(-1, K).contiguous()
        if kernels is not None:
            return self._entries_native(kernels, r, c, sym).view(*batch, J, K)
        rf, cf = r.view(-1), c.view(-1)

        def take(table: Tensor, flat: Tensor, like: Tensor) -> Tensor:
            return table.index_select(0, flat).view(like.shape + table.shape[1:])

        lr = take(self._leaf_id, rf, r)
        lc = lr if sym else take(self._leaf_id, cf, c)
        loc_r = take(self._leaf_local, rf, r)
        loc_c = loc_r if sym else take(self._leaf_local, cf, c)
        # leaf block: cells outside every leaf have id -1; they are matched by nothing valid
        lr_safe = lr.clamp_min(0)
        base = take(self._leaf_offset, lr_safe.view(-1), r) \
            + loc_r * take(self._leaf_size, lr_safe.view(-1), r)
        same = (lr.unsqueeze(-1) == lc.unsqueeze(-2)) & (lr >= 0).unsqueeze(-1)
        flat = (base.unsqueeze(-1) + loc_c.unsqueeze(-2)).masked_fill_(~same, 0)
        out = self._leaf_values.index_select(0, flat.view(-1)).view(flat.shape)
        out.masked_fill_(~same, 0.0)
        if self.depth:
            yr = take(self._ycat, rf, r)  # (., J, sum of widths)
            yc = yr if sym else take(self._ycat, cf, c)
            pr = take(self._path, rf, r)  # (., J, depth)
            pc = pr if sym else take(self._path, cf, c)
            # levels a pair shares = its common ancestors; G adds y . y over exactly those
            shared = (pr.unsqueeze(-2) == pc.unsqueeze(-3)).sum(-1)  # (., J, K)
            cum = torch.empty((self.depth,) + out.shape, dtype=torch.float64)
            running = torch.zeros_like(out)
            for lev in range(self.depth):
                a, b = self._offsets[lev], self._offsets[lev + 1]
                running = torch.baddbmm(running, yr[..., a:b], yc[..., a:b].mT)
                cum[lev] = running
            pick = (shared - 1).clamp_min_(0).unsqueeze(0)
            out += cum.gather(0, pick).squeeze(0)
        return out.view(*batch, J, K)

    def _entries_native(self, kernels: Any, r: Tensor, c: Tensor, sym: bool) -> Tensor:
        """:meth:`entries` through ``agv_ipf_tree_entries`` (every pointer checked)."""
        from sim.native import pointer

        Bf, J = r.shape
        K = c.shape[1]
        F1 = self.num_free + 1
        if self._native is None:
            W, L, nl = self._ycat.shape[1], self.depth, len(self.leaves) + 1
            self._offsets_t = torch.tensor(self._offsets, dtype=torch.int64)
            self._native = (
                pointer(self._ycat, torch.float64, (F1, W), "tree vectors"), W,
                pointer(self._path, torch.int64, (F1, L), "tree paths"), L,
                pointer(self._offsets_t, torch.int64, (L + 1,), "tree offsets"),
                pointer(self._leaf_id, torch.int64, (F1,), "leaf ids"),
                pointer(self._leaf_local, torch.int64, (F1,), "leaf places"),
                pointer(self._leaf_size, torch.int64, (nl,), "leaf sizes"),
                pointer(self._leaf_offset, torch.int64, (nl,), "leaf offsets"),
                pointer(self._leaf_values, torch.float64, (int(self._leaf_values.shape[0]),),
                        "leaf blocks"),
            )
        for name, t in (("rows", r), ("cols", c)):
            if t.numel() and (int(t.min()) < 0 or int(t.max()) >= F1):
                raise ValueError(f"{name} must be free-cell indices in [0, {F1 - 1}]")
        out = torch.empty(Bf, J, K, dtype=torch.float64)
        if sym and J > 4:  # many pairs: the tiled kernel (the same entries up to rounding)
            if self._rank_ptr is None:
                self._rank_ptr = pointer(self._rank, torch.int64, (F1,), "tree ranks")
            ycat, W, path, L, offsets, leaf_id, leaf_local, leaf_size, leaf_offset, \
                leaf_values = self._native
            status = kernels.agv_ipf_tree_gram(
                Bf, J, pointer(r, torch.int64, (Bf, J), "rows"), ycat, W, path, L, offsets,
                self._rank_ptr, leaf_id, leaf_local, leaf_size, leaf_offset, leaf_values,
                out.data_ptr())
            if status < 0:
                raise MemoryError(f"IPF tree kernel: no memory for the scratch of J = {J}")
            return out
        kernels.agv_ipf_tree_entries(
            Bf, J, K, pointer(r, torch.int64, (Bf, J), "rows"),
            pointer(c, torch.int64, (Bf, K), "cols"), int(sym), *self._native,
            out.data_ptr())
        return out

    def rows(self, cells: Tensor) -> Tensor:
        """Whole rows ``G[cells[k], :]`` as ``(S, F + 1)`` float64 (column ``F`` is 0).

        Parameters
        ----------
        cells : Tensor of int64, shape (S,)
            Free-cell indices in ``[0, F]``.
        """
        self.build()
        F = self.num_free
        S = cells.shape[0]
        out = torch.zeros(S, F + 1, dtype=torch.float64)
        for y, node in zip(self._y, self._node_id, strict=True):
            prod = y[cells] @ y.T  # (S, F + 1)
            nr = node[cells]
            prod.masked_fill_((node.unsqueeze(0) != nr.unsqueeze(1)) | (nr < 0).unsqueeze(1), 0.0)
            out += prod
        leaf = self._leaf_id[cells]
        has = leaf >= 0
        lf = torch.where(has, leaf, len(self.leaves))
        mmax = self._leaf_cells.shape[1]
        span = torch.arange(mmax)
        size = self._leaf_size[lf]
        idx = (self._leaf_offset[lf] + self._leaf_local[cells] * size).unsqueeze(1) + span
        inside = (span < size.unsqueeze(1)) & has.unsqueeze(1)
        vals = torch.where(inside, self._leaf_values[torch.where(inside, idx, 0)], 0.0)
        out.scatter_add_(1, self._leaf_cells[lf], vals)
        out[:, F] = 0.0
        return out

    def describe(self) -> str:
        """One line: levels, separator widths, leaves and memory."""
        return (f"{self.depth} levels, widest separators {self.separator_widths}, "
                f"{len(self.leaves)} leaves (<= {max(len(x.cells) for x in self.leaves)} cells), "
                f"{self.nbytes / 2**20:.0f} MiB")


def estimate_bytes(fixed: np.ndarray, leaf_cells: int = LEAF_CELLS) -> int:
    """:attr:`SeparatorTree.nbytes` of the tree ``fixed`` would get (the tree is made, not
    the numerics)."""
    return SeparatorTree(fixed, leaf_cells).nbytes
