"""An incremental linear assignment solver: re-plans re-use the previous optimum and its duals.

A dispatcher re-plans after every event (an AGV becomes free, an order arrives or is picked
up, a breakdown), and each event changes the cost matrix in a few rows or columns only. The
previous optimal matching and its dual potentials then stay valid for every other row, and a
few shortest augmenting paths restore optimality: the dynamic Hungarian algorithm
(Mills-Tettey, Stentz and Dias, 2007). :class:`IncrementalLAP` keeps that state between calls,
keyed by stable row and column identities (AGV indices, order ids), and decides per call what
to keep:

1. Rows and columns are matched to the previous call's by key; for the kept ones the costs are
   compared entry by entry. A row whose entries all moved by the same amount (a loaded AGV
   one step nearer its drop-off: its lag shrank) keeps its match, its potential moved by that
   amount. Of the other changed entries, a column with two or more is a *changed column*,
   every other one makes its row a *changed row*; new rows and columns are changed.
2. The problem is square-padded: n real rows and m - n dummy rows of cost 0 (n <= m; a wider
   than tall problem is solved transposed), a column held by a dummy being a column left free.
   Changed rows, rows whose column changed or left, and dummies whose column changed or left
   are freed; each changed column gets ``v_j = min_i (c_ij - u_i)`` over the rows still
   matched, which keeps every matched row dual feasible.
3. Every free row is matched by one Dijkstra search on the reduced costs (the successive
   shortest path step of Crouse, IEEE TAES 2016, as in :func:`scipy.optimize.
   linear_sum_assignment`), in C (``allocator/_native/lap.c``, compiled on first use like the
   simulator's kernels and cached; a numpy version of the same search where no compiler is).

The result is an optimal assignment whatever was kept (the invariants hold for any kept
state); the warm start only changes how much work it takes. When more than ``max_changed``
of the rows and columns changed, the state is dropped and the problem solved cold.
"""

from __future__ import annotations

import ctypes
import os
import warnings
from pathlib import Path

import numpy as np

__all__ = ["IncrementalLAP", "augment", "native_available", "solve"]

_SOURCE = Path(__file__).parent / "_native" / "lap.c"
_FLAGS = ["-O3", "-std=c99", "-fPIC", "-shared", "-fno-math-errno"]
_lib: ctypes.CDLL | None = None
_tried = False


def _library() -> ctypes.CDLL | None:
    """The compiled kernel (built on first use, cached), or None where it cannot be built."""
    global _lib, _tried
    if _tried:
        return _lib
    _tried = True
    if os.environ.get("AGV_NATIVE", "1").strip().lower() in ("0", "false", "no", "off"):
        return None
    from sim.native import compiler, load_cached  # the simulator's compiler and cache

    if compiler() is None:
        return None
    try:
        lib = load_cached(_SOURCE, _FLAGS, "agv_lap")
    except (OSError, RuntimeError) as err:
        warnings.warn(f"allocator: LAP kernel unavailable ({err}); using numpy", stacklevel=2)
        return None
    fn = lib.agv_lap_augment
    fn.restype = ctypes.c_int64
    fn.argtypes = [ctypes.c_int64, ctypes.c_int64] + [ctypes.c_void_p] * 5 + \
        [ctypes.c_int64, ctypes.c_void_p]
    fn = lib.agv_lap_diff
    fn.restype = ctypes.c_int64
    fn.argtypes = [ctypes.c_int64, ctypes.c_int64, ctypes.c_void_p, ctypes.c_int64] + \
        [ctypes.c_void_p] * 4
    _lib = lib
    return lib


def native_available() -> bool:
    """Whether the C kernel is used in this process."""
    return _library() is not None


def _augment_numpy(n: int, cost: np.ndarray, u: np.ndarray, v: np.ndarray,
                   col4row: np.ndarray, row4col: np.ndarray, free_rows: np.ndarray) -> int:
    """The C kernel's search in numpy (one vectorised scan per expanded row)."""
    m = len(v)
    zero = np.zeros(m)
    scans = 0
    for cur in free_rows:
        if col4row[cur] >= 0:
            continue
        spc = np.full(m, np.inf)
        path = np.full(m, -1, dtype=np.int64)
        done = np.zeros(m, dtype=bool)
        rows, cols = [], []
        i, min_val, sink = int(cur), 0.0, -1
        while sink < 0:
            rows.append(i)
            scans += 1
            row = cost[i] if i < n else zero
            r = min_val + row - u[i] - v
            better = (r < spc) & ~done
            spc[better] = r[better]
            path[better] = i
            cand = np.where(done, np.inf, spc)
            lowest = cand.min()
            if not np.isfinite(lowest):
                return -1
            ties = np.flatnonzero(cand == lowest)
            free = ties[row4col[ties] < 0]
            j = int(free[0] if len(free) else ties[0])
            min_val = float(lowest)
            done[j] = True
            cols.append(j)
            if row4col[j] < 0:
                sink = j
            else:
                i = int(row4col[j])
        u[cur] += min_val
        for r in rows[1:]:
            u[r] += min_val - spc[col4row[r]]
        cols_a = np.asarray(cols)
        v[cols_a] -= min_val - spc[cols_a]
        j = sink
        while True:
            r = int(path[j])
            row4col[j] = r
            col4row[r], j = j, int(col4row[r])
            if r == cur:
                break
    return scans


def augment(n: int, cost: np.ndarray, u: np.ndarray, v: np.ndarray, col4row: np.ndarray,
            row4col: np.ndarray, free_rows: np.ndarray) -> int:
    """Match every row of ``free_rows`` by a shortest augmenting path, in place.

    Parameters
    ----------
    n : int
        Real rows; rows ``n .. m-1`` are dummies of cost 0.
    cost : np.ndarray of float64, shape (n, m), C-contiguous
        ``inf`` marks a forbidden pair.
    u, v : np.ndarray of float64, shape (m,)
        Row and column potentials (dual feasible on the matched rows, tight on matched pairs).
    col4row, row4col : np.ndarray of int64, shape (m,)
        The matching, -1 for free.
    free_rows : np.ndarray of int64, shape (F,)

    Returns
    -------
    int
        Rows expanded by the searches (the work done).

    Raises
    ------
    ValueError
        If a free row has no finite augmenting path (the problem is infeasible).
    """
    lib = _library()
    free_rows = np.ascontiguousarray(free_rows, dtype=np.int64)
    if lib is None:
        scans = _augment_numpy(n, cost, u, v, col4row, row4col, free_rows)
    else:
        scans = lib.agv_lap_augment(n, len(v), cost.ctypes.data, u.ctypes.data,
                                    v.ctypes.data, col4row.ctypes.data, row4col.ctypes.data,
                                    len(free_rows), free_rows.ctypes.data)
        if scans == -2:
            raise MemoryError("allocator: the LAP kernel ran out of memory")
    if scans < 0:
        raise ValueError("cost matrix is infeasible")
    return int(scans)


def _check_cost(cost: object) -> np.ndarray:
    c = np.asarray(cost, dtype=np.float64)
    if c.ndim != 2:
        raise ValueError(f"cost must be a 2-D matrix, got shape {c.shape}")
    if c.size and not c.min() > -np.inf:  # NaN propagates through min
        raise ValueError("cost contains NaN or -inf entries")
    return c


def solve(cost: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A cold optimal assignment, as :func:`scipy.optimize.linear_sum_assignment`.

    Parameters
    ----------
    cost : array_like, shape (A, O)
        ``inf`` marks a forbidden pair.

    Returns
    -------
    rows, cols : np.ndarray of int64, shape (min(A, O),)
        Row ``rows[k]`` is matched to column ``cols[k]``, rows ascending.
    """
    return IncrementalLAP(max_changed=0.0).solve(cost)


class IncrementalLAP:
    """A min-sum assignment solver that re-uses its previous optimum (see the module).

    Parameters
    ----------
    max_changed : float
        Fraction of the rows plus columns that may change for a warm start (default 0.9);
        beyond it the previous state is dropped and the problem solved cold.

    Attributes
    ----------
    last_mode : str
        ``"cold"`` or ``"warm"``: how the last call solved.
    last_free : int
        Rows the last call matched by a search.
    last_scans : int
        Rows the searches of the last call expanded.
    """

    def __init__(self, max_changed: float = 0.9) -> None:
        if isinstance(max_changed, bool) or not isinstance(max_changed, (int, float)) \
                or not 0.0 <= max_changed <= 1.0:
            raise ValueError(f"max_changed must be a number in [0, 1], got {max_changed!r}")
        self.max_changed = float(max_changed)
        self.last_mode = "cold"
        self.last_free = 0
        self.last_scans = 0
        self._state: dict | None = None

    def reset(self) -> None:
        """Forget the previous solution (the next call solves cold)."""
        self._state = None

    def solve(self, cost: np.ndarray, row_keys: np.ndarray | None = None,
              col_keys: np.ndarray | None = None, *,
              copy: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """An optimal assignment of ``cost``, warm-started from the previous call.

        Parameters
        ----------
        cost : array_like, shape (A, O)
            ``inf`` marks a forbidden pair.
        row_keys : np.ndarray of int, shape (A,), optional
            Stable identities of the rows (e.g. AGV indices), unique; default ``arange(A)``.
        col_keys : np.ndarray of int, shape (O,), optional
            Stable identities of the columns (e.g. order ids), unique; default ``arange(O)``.
        copy : bool
            Keep a copy of ``cost`` for the next call (default). False keeps ``cost`` itself
            (C-contiguous float64, wider than tall): the caller then must not write to it.

        Returns
        -------
        rows, cols : np.ndarray of int64, shape (min(A, O),)
            Row ``rows[k]`` is matched to column ``cols[k]``, rows ascending (the layout of
            :func:`scipy.optimize.linear_sum_assignment`).

        Raises
        ------
        ValueError
            For a cost that is not a 2-D matrix, has NaN or -inf, or is infeasible; for keys
            of the wrong length or not unique.
        """
        c = _check_cost(cost)
        a, o = c.shape
        rk = np.arange(a, dtype=np.int64) if row_keys is None else \
            np.asarray(row_keys, dtype=np.int64)
        ck = np.arange(o, dtype=np.int64) if col_keys is None else \
            np.asarray(col_keys, dtype=np.int64)
        for name, keys, size in (("row_keys", rk, a), ("col_keys", ck, o)):
            if keys.shape != (size,):
                raise ValueError(f"{name} must have shape ({size},), got {keys.shape}")
            if len(np.unique(keys)) != size:
                raise ValueError(f"{name} must be unique")
        if a == 0 or o == 0:
            self._state = None
            self.last_mode, self.last_free, self.last_scans = "cold", 0, 0
            return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
        flip = a > o
        if flip:
            c, rk, ck = c.T, ck, rk
        # Kept for the next call: a copy unless the caller hands the matrix over.
        c = np.array(c, dtype=np.float64, order="C") if copy else np.ascontiguousarray(c)
        n, m = c.shape
        st = self._warm(c, rk, ck, flip)
        if st is None:
            u, v = np.zeros(m), np.zeros(m)
            col4row = np.full(m, -1, dtype=np.int64)
            row4col = np.full(m, -1, dtype=np.int64)
            free = np.arange(m, dtype=np.int64)
            self.last_mode = "cold"
        else:
            u, v, col4row, row4col, free = st
            self.last_mode = "warm"
        try:
            self.last_scans = augment(n, c, u, v, col4row, row4col, free)
        except ValueError:
            self._state = None
            raise
        self.last_free = len(free)
        self._state = dict(cost=c, rk=rk, ck=ck, flip=flip, u=u, v=v, col4row=col4row)
        rows = np.arange(n, dtype=np.int64)
        cols = col4row[:n].copy()
        if flip:
            order = np.argsort(cols)
            return cols[order], rows[order]
        return rows, cols

    def _warm(self, c: np.ndarray, rk: np.ndarray, ck: np.ndarray, flip: bool):
        """The kept state for the new problem ``(u, v, col4row, row4col, free rows)``, or
        None for a cold solve."""
        s = self._state
        if s is None or s["flip"] != flip or self.max_changed <= 0:
            return None
        n, m = c.shape
        old_c, old_n = s["cost"], s["cost"].shape[0]
        old_m = old_c.shape[1]
        ri = _lookup(s["rk"], rk)  # old index of each new row, -1 new
        cj = _lookup(s["ck"], ck)
        krow, kcol = np.flatnonzero(ri >= 0), np.flatnonzero(cj >= 0)
        changed_col = cj < 0
        changed_row = ri < 0
        new_of_col = np.full(old_m, -1, dtype=np.int64)  # old column -> new column
        new_of_col[cj[kcol]] = kcol
        moved = np.zeros(0, dtype=np.int64)  # kept rows with a changed entry elsewhere
        if len(krow) and len(kcol):
            diff = _diff(c, old_c, ri, cj)  # (n, m) bool, False off the kept rows / columns
            per_row = np.count_nonzero(diff, axis=1)
            # A row with many changed entries changed itself (an AGV moved); the columns are
            # blamed on the other rows: two or more changed entries make a changed column.
            few = per_row <= max(1, len(kcol) // 2)
            per_col = np.count_nonzero(diff if few.all() else diff[few], axis=0)
            blamed = per_col >= 2
            changed_col |= blamed
            if blamed.any():
                outside = diff[:, ~blamed].any(axis=1)
            else:
                outside = per_row > 0
            moved = np.flatnonzero(outside)
        if changed_row.sum() + len(moved) + changed_col.sum() > self.max_changed * (n + m):
            return None
        u = np.zeros(m)
        v = np.zeros(m)
        v[kcol] = s["v"][cj[kcol]]
        col4row = np.full(m, -1, dtype=np.int64)
        # Real rows: keep the match of kept rows whose column stays and is unchanged.
        keep = krow[~changed_row[krow]]
        held = s["col4row"][ri[keep]]
        held = new_of_col[held]
        ok = held >= 0
        ok[ok] = ~changed_col[held[ok]]
        keep, held = keep[ok], held[ok]
        u[keep] = s["u"][ri[keep]]
        # A moved row keeps its match if that column is still its cheapest in reduced cost
        # (against the kept columns' potentials): u_i = c_ij - v_j, exactly tight. Changed
        # columns get their potentials below, from every matched row.
        if len(moved):
            mv = np.isin(keep, moved)
            rows_m, cols_m = keep[mv], held[mv]
            u_m = c[rows_m, cols_m] - v[cols_m]
            steady = np.flatnonzero(~changed_col)
            red = c[np.ix_(rows_m, steady)] - v[steady] - u_m[:, None]
            tol = 1e-12 + 1e-15 * np.abs(c[np.ix_(rows_m, steady)])
            with np.errstate(invalid="ignore"):
                fine = (red >= -tol).all(axis=1) & np.isfinite(u_m)
            u[rows_m[fine]] = u_m[fine]
            drop = np.zeros(len(keep), dtype=bool)
            drop[np.flatnonzero(mv)[~fine]] = True
            keep, held = keep[~drop], held[~drop]
            changed_row[rows_m[~fine]] = True
        col4row[keep] = held
        # Dummy rows n .. m-1: re-use old dummies (their potentials and columns) in order.
        old_dummy = np.arange(old_n, old_m)
        dummies = min(m - n, len(old_dummy))
        if dummies:
            od = old_dummy[:dummies]
            dcol = new_of_col[s["col4row"][od]]
            dok = dcol >= 0
            dok[dok] = ~changed_col[dcol[dok]]
            drow = n + np.arange(dummies)
            col4row[drow[dok]] = dcol[dok]
            u[drow[dok]] = s["u"][od[dok]]
        # A column matched twice (cannot happen: kept matches are a subset of a matching).
        matched = col4row >= 0
        row4col = np.full(m, -1, dtype=np.int64)
        row4col[col4row[matched]] = np.flatnonzero(matched)
        # Changed columns: v_j = min over matched rows of c_ij - u_i (dummies: -u_i).
        ch = np.flatnonzero(changed_col)
        if len(ch):
            real = np.flatnonzero(matched[:n])
            vals = np.full(len(ch), np.inf)
            if len(real):
                vals = (c[np.ix_(real, ch)] - u[real, None]).min(axis=0)
            dm = np.flatnonzero(matched[n:]) + n
            if len(dm):
                vals = np.minimum(vals, -u[dm].max())
            v[ch] = np.where(np.isfinite(vals), vals, 0.0)
        free = np.flatnonzero(~matched).astype(np.int64)
        return u, v, col4row, row4col, free


def _diff(c: np.ndarray, old: np.ndarray, ri: np.ndarray, cj: np.ndarray) -> np.ndarray:
    """``c[i, j] != old[ri[i], cj[j]]`` where both are >= 0, else False; (n, m) bool."""
    lib = _library()
    if lib is None:
        out = np.zeros(c.shape, dtype=bool)
        kr, kc = np.flatnonzero(ri >= 0), np.flatnonzero(cj >= 0)
        out[np.ix_(kr, kc)] = _sub(c, kr, kc) != _sub(old, ri[kr], cj[kc])
        return out
    out = np.empty(c.shape, dtype=np.uint8)
    ri = np.ascontiguousarray(ri, dtype=np.int64)
    cj = np.ascontiguousarray(cj, dtype=np.int64)
    lib.agv_lap_diff(c.shape[0], c.shape[1], c.ctypes.data, old.shape[1], old.ctypes.data,
                     ri.ctypes.data, cj.ctypes.data, out.ctypes.data)
    return out.view(bool)


def _sub(a: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """``a[np.ix_(rows, cols)]``: no copy along an axis taken whole and in order, block
    copies where the indices run in a few consecutive stretches (an order came or went),
    a gather otherwise."""
    if len(rows) != a.shape[0] or (rows != np.arange(a.shape[0])).any():
        a = _take(a, rows, 0)
    if len(cols) != a.shape[1] or (cols != np.arange(a.shape[1])).any():
        a = _take(a, cols, 1)
    return a


def _take(a: np.ndarray, idx: np.ndarray, axis: int) -> np.ndarray:
    """``np.take(a, idx, axis)`` of a 2-D array, by block copies when ``idx`` has few runs."""
    if len(idx) == 0:
        return np.take(a, idx, axis=axis)
    breaks = np.flatnonzero(np.diff(idx) != 1) + 1
    if len(breaks) > 32:
        return np.take(a, idx, axis=axis)
    starts = np.concatenate([[0], breaks])
    ends = np.concatenate([breaks, [len(idx)]])
    shape = (len(idx), a.shape[1]) if axis == 0 else (a.shape[0], len(idx))
    out = np.empty(shape, dtype=a.dtype)
    for s, e in zip(starts, ends, strict=True):  # a few runs, each one block copy
        src = int(idx[s])
        if axis == 0:
            out[s:e] = a[src: src + e - s]
        else:
            out[:, s:e] = a[:, src: src + e - s]
    return out


def _lookup(old: np.ndarray, new: np.ndarray) -> np.ndarray:
    """Index in ``old`` of each key of ``new`` (-1 where absent)."""
    if len(old) == 0:
        return np.full(len(new), -1, dtype=np.int64)
    order = np.argsort(old, kind="stable")
    pos = np.searchsorted(old, new, sorter=order)
    pos = np.minimum(pos, len(old) - 1)
    idx = order[pos]
    return np.where(old[idx] == new, idx, -1).astype(np.int64)
