"""The velocity QP and its fallback written in cvxpy (:func:`solve_reference`): readable, slow,
the reference the fast solvers are tested against."""

from __future__ import annotations

import numpy as np

from allocator.avoidance.rows import ConstraintRows

__all__ = ["solve_reference"]


def solve_reference(
    rows: ConstraintRows, fallback_regularization: float = 1e-3
) -> tuple[np.ndarray, np.ndarray]:
    """The same QP (and fallback) written in cvxpy, one small problem per AGV: the readable
    reference the OSQP path is tested against.

    Returns
    -------
    velocity : np.ndarray, shape (n, 2)
    fell_back : np.ndarray of bool, shape (n,)
    """
    import cvxpy as cp

    n = rows.A.shape[0]
    out = np.zeros((n, 2))
    fell = np.zeros(n, dtype=bool)
    weight = rows.weight
    for i in np.flatnonzero(rows.active):
        A, lo, hi, pref = rows.A[i], rows.lower[i], rows.upper[i], rows.preferred[i]
        up, down = np.isfinite(hi), np.isfinite(lo)
        v = cp.Variable(2)
        cons = []
        if up.any():
            cons.append(A[up] @ v <= hi[up])
        if down.any():
            cons.append(A[down] @ v >= lo[down])
        prob = cp.Problem(cp.Minimize(cp.sum_squares(v - pref)), cons)
        prob.solve(solver=cp.CLARABEL)
        if prob.status in (cp.OPTIMAL, cp.OPTIMAL_INACCURATE):
            out[i] = v.value
            continue
        # Least violation: min t s.t. a.v - w t <= u (soft), hard rows kept.
        fell[i] = True
        t = cp.Variable()
        hard = weight == 0.0
        cons = [t >= 0]
        su, hu = up & ~hard, up & hard
        if su.any():
            cons.append(A[su] @ v - weight[su] * t <= hi[su])
        if hu.any():
            cons.append(A[hu] @ v <= hi[hu])
        if down.any():
            cons.append(A[down] @ v >= lo[down])
        obj = t + fallback_regularization / 2 * cp.sum_squares(v - pref)
        cp.Problem(cp.Minimize(obj), cons).solve(solver=cp.CLARABEL)
        out[i] = v.value
    return out, fell
