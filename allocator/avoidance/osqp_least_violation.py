"""ORCA's "3-D" least-violation program batched in one OSQP problem (:class:`LeastViolation`)."""

from __future__ import annotations

from typing import Any

import numpy as np
import scipy.sparse as sp

from allocator.avoidance.rows import ConstraintRows, take_rows

__all__ = ["LeastViolation"]


class LeastViolation:
    """ORCA's "3-D" program for AGVs whose rows conflict, batched in one OSQP problem.

    Per AGV: ``min t + (regularization / 2) ||v - pref||^2`` s.t. ``a . v - w t <= u`` on
    soft rows (``w``: :attr:`ConstraintRows.weight`), the hard rows (speed polygon, acceleration
    box) unchanged, ``t >= 0``. Where the rows are compatible the optimum has ``t = 0`` and
    ``v`` equals the QP solution (the penalty on ``t`` is exact), so one solve serves all AGVs.
    The sparsity pattern is fixed per (n, R), so repeated calls update and warm start.
    """

    def __init__(self, regularization: float = 1e-3) -> None:
        self.regularization = regularization
        self._solver: Any = None
        self._key: tuple[int, int] | None = None

    def problem(
        self, rows: ConstraintRows
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``(dense (n, R + 1, 3), lower (n, R + 1), upper (n, R + 1), q (3 n,))``."""
        n, R, _ = rows.A.shape
        weight = rows.weight
        t_col = np.broadcast_to(-weight, (n, R))[..., None]
        dense = np.concatenate([rows.A, t_col], axis=2)
        t_row = np.zeros((n, 1, 3))
        t_row[..., 2] = 1.0
        dense = np.concatenate([dense, t_row], axis=1)
        lo = np.concatenate([rows.lower, np.zeros((n, 1))], axis=1)
        hi = np.concatenate([rows.upper, np.full((n, 1), np.inf)], axis=1)
        q = np.concatenate(
            [-self.regularization * rows.preferred, rows.active[:, None].astype(float)], axis=1
        ).reshape(-1)
        return dense, lo, hi, q

    def solve(self, rows: ConstraintRows, eps: float = 1e-6) -> tuple[np.ndarray, np.ndarray]:
        """Velocities (n, 2) and violations t (n,) (``inf`` where even the hard rows conflict).

        When the joint solve does not converge, each AGV is solved on its own (a stalled block
        must not cost the others their answer)."""
        import osqp

        n, R, _ = rows.A.shape
        dense, lo, hi, q = self.problem(rows)
        if self._solver is None or self._key != (n, R):
            R1 = R + 1
            indptr = np.arange(3 * n + 1, dtype=np.int64) * R1
            rows_idx = np.arange(n)[:, None] * R1 + np.arange(R1)[None, :]
            indices = np.repeat(rows_idx, 3, axis=0).reshape(-1)
            A = sp.csc_matrix((np.ones(3 * n * R1), indices, indptr), shape=(n * R1, 3 * n))
            P = sp.diags(np.tile([self.regularization, self.regularization, 0.0], n),
                         format="csc")
            self._solver = osqp.OSQP()
            self._solver.setup(
                P, q, A, lo.reshape(-1), hi.reshape(-1), verbose=False, polishing=False,
                eps_abs=eps * 0.1, eps_rel=eps * 0.1, max_iter=50000, warm_starting=True,
            )
            self._key = (n, R)
        self._solver.update(q=q, l=lo.reshape(-1), u=hi.reshape(-1),
                            Ax=dense.transpose(0, 2, 1).reshape(-1))
        res = self._solver.solve(raise_error=False)
        if not res.info.status.startswith("solved"):
            if n > 1:  # one slow block stalls ADMM for all: solve them one by one
                parts = [LeastViolation(self.regularization).solve(take_rows(rows, [i]), eps)
                         for i in range(n)]
                return np.concatenate([q[0] for q in parts]), np.concatenate([q[1] for q in parts])
            return np.zeros((n, 2)), np.where(rows.active, np.inf, 0.0)
        z = res.x.reshape(n, 3)
        velocity = np.where(rows.active[:, None], z[:, :2], 0.0)
        return velocity, np.maximum(z[:, 2], 0.0) * rows.active


