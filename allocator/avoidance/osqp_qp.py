"""The velocity QP of every AGV as block-diagonal OSQP problems (:class:`BlockOSQP`)."""

from __future__ import annotations

from typing import Any

import numpy as np
import scipy.sparse as sp

from allocator.avoidance.config import AvoidanceConfig
from allocator.avoidance.osqp_least_violation import LeastViolation
from allocator.avoidance.rows import ConstraintRows, take_rows

__all__ = ["BlockOSQP"]


class BlockOSQP:
    """The OSQP back end of :class:`~allocator.avoidance.VelocityAvoidance` (``solver="osqp"``).

    The problem separates per AGV; it is solved as one sparse block-diagonal OSQP problem per
    ``config.chunk_size`` AGVs, each chunk with its own solver whose sparsity pattern is fixed
    (every AGV has the same number of rows), so consecutive steps only update the data and
    warm start. AGVs whose rows conflict (found from OSQP's infeasibility certificate) get the
    least-violation program of ``fallback``.

    Parameters
    ----------
    config : AvoidanceConfig
        ``eps``, ``max_iter``, ``chunk_size`` and ``fallback_tol`` are used.
    fallback : LeastViolation
        The least-violation program for the AGVs whose rows conflict.
    stats : dict of str to int
        Counters ``"solves"``, ``"fallbacks"`` and ``"setup"``, incremented in place.
    """

    def __init__(
        self, config: AvoidanceConfig, fallback: LeastViolation, stats: dict[str, int]
    ) -> None:
        self.config = config
        self.fallback = fallback
        self.stats = stats
        self._solvers: dict[int, tuple[tuple[int, int], Any]] = {}

    def solve_rows(self, rows: ConstraintRows) -> tuple[np.ndarray, np.ndarray, np.ndarray, str]:
        """``(velocity (n, 2), fell_back (n,), violation (n,), status)`` of built rows.

        ADMM runs until its slowest block converges, and smaller problems stop sooner: hence
        the chunks of ``config.chunk_size`` AGVs.
        """
        n = rows.A.shape[0]
        size = self.config.chunk_size
        if n <= size:
            return self._solve_chunk(rows, 0)
        parts = [
            self._solve_chunk(take_rows(rows, slice(k, min(k + size, n))), k // size)
            for k in range(0, n, size)
        ]
        status = next((p[3] for p in parts if not p[3].startswith("solved")), parts[0][3])
        return (
            np.concatenate([p[0] for p in parts]),
            np.concatenate([p[1] for p in parts]),
            np.concatenate([p[2] for p in parts]),
            status,
        )

    def _solve_chunk(
        self, rows: ConstraintRows, chunk: int
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, str]:
        import osqp

        n, R, _ = rows.A.shape
        self.stats["solves"] += 1
        solver = self._solvers.get(chunk)
        if solver is None or solver[0] != (n, R):
            self._solvers[chunk] = solver = ((n, R), self._setup(n, R))
        solver = solver[1]
        data = rows.A.transpose(0, 2, 1).reshape(-1)  # CSC order: column 2i then 2i+1
        lo = rows.lower.reshape(-1).copy()
        hi = rows.upper.reshape(-1).copy()
        q = -rows.preferred.reshape(-1)
        soft = rows.weight > 0
        suspects = np.zeros(n, dtype=bool)
        # AGVs whose preferred velocity already satisfies their rows keep it: switch their
        # rows off so they cost the solver nothing (the pattern stays fixed).
        at_pref = np.einsum("nrk,nk->nr", rows.A, rows.preferred)
        free = ((at_pref <= rows.upper + 1e-12) & (at_pref >= rows.lower - 1e-12)).all(axis=1)
        if free.all():
            return np.where(rows.active[:, None], rows.preferred, 0.0), suspects, \
                np.zeros(n), "solved"
        lo[np.repeat(free, R)] = -np.inf
        hi[np.repeat(free, R)] = np.inf
        solver.update(q=q, l=lo, u=hi, Ax=data)
        for _ in range(6):
            res = solver.solve(raise_error=False)
            status = res.info.status
            if res.info.status_val in (osqp.SolverStatus.OSQP_SOLVED,
                                       osqp.SolverStatus.OSQP_SOLVED_INACCURATE):
                break
            if res.info.status_val == osqp.SolverStatus.OSQP_PRIMAL_INFEASIBLE:
                new = self._certificate_blocks(res.prim_inf_cert, n, R)
            else:  # stalled: treat every AGV whose rows the iterate violates as a suspect
                new = self._violated(res.x, rows)
            new &= rows.active & ~suspects
            if not new.any():
                new = rows.active & ~suspects
            suspects |= new
            # The suspects get their own least-violation program; the others are re-solved
            # with the suspects' soft rows switched off (warm started).
            relax = (suspects[:, None] & soft[None, :]).reshape(-1)
            solver.update(l=np.where(relax, -np.inf, lo), u=np.where(relax, np.inf, hi))
            if not (rows.active & ~suspects).any():
                break
        x = res.x.reshape(n, 2) if status.startswith("solved") else np.zeros((n, 2))
        velocity = np.where(rows.active[:, None], x, 0.0)
        violation = np.zeros(n)
        fell = np.zeros(n, dtype=bool)
        if suspects.any():
            idx = np.flatnonzero(suspects)
            v, t = self.fallback.solve(take_rows(rows, idx), self.config.eps)
            velocity[idx] = v
            fell[idx] = t > self.config.fallback_tol
            violation[idx] = np.where(fell[idx], t, 0.0)
            self.stats["fallbacks"] += int(fell.sum())
        return velocity, fell, violation, status

    @staticmethod
    def _certificate_blocks(cert: np.ndarray, n: int, R: int) -> np.ndarray:
        """AGVs whose rows carry OSQP's infeasibility certificate (a superset of the culprits:
        a wrongly suspected AGV gets t = 0 and its QP velocity from the fallback program)."""
        y = np.abs(np.asarray(cert, dtype=np.float64).reshape(n, R)).max(axis=1)
        top = y.max() if y.size else 0.0
        return y > 1e-6 * top if top > 0 else np.zeros(n, dtype=bool)

    @staticmethod
    def _violated(x: np.ndarray, rows: ConstraintRows, tol: float = 1e-4) -> np.ndarray:
        n = rows.A.shape[0]
        v = np.asarray(x, dtype=np.float64).reshape(n, 2)
        if not np.all(np.isfinite(v)) or np.abs(v).max() > 1e6:
            return rows.active.copy()
        av = np.einsum("nrk,nk->nr", rows.A, v)
        return ((av > rows.upper + tol) | (av < rows.lower - tol)).any(axis=1)

    def _setup(self, n: int, R: int) -> Any:
        import osqp

        self.stats["setup"] += 1
        c = self.config
        indptr = np.arange(2 * n + 1, dtype=np.int64) * R
        rows_idx = (np.arange(n)[:, None] * R + np.arange(R)[None, :])  # (n, R)
        indices = np.repeat(rows_idx, 2, axis=0).reshape(-1)
        A = sp.csc_matrix((np.ones(2 * n * R), indices, indptr), shape=(n * R, 2 * n))
        P = sp.identity(2 * n, format="csc")
        solver = osqp.OSQP()
        solver.setup(
            P, np.zeros(2 * n), A, np.full(n * R, -np.inf), np.full(n * R, np.inf),
            verbose=False, polishing=False, warm_starting=True, eps_abs=c.eps, eps_rel=c.eps,
            max_iter=c.max_iter, eps_prim_inf=1e-3, adaptive_rho=True,
        )
        return solver

