"""The exact 2-D QP of every AGV, vectorised over the AGVs (:func:`solve_qp_2d`)."""

from __future__ import annotations

import numpy as np

__all__ = ["solve_qp_2d", "one_sided"]


def one_sided(
    A: np.ndarray, lower: np.ndarray, upper: np.ndarray, weight: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rewrite ``lower <= A v <= upper`` as ``G v <= h`` with unit rows.

    Parameters
    ----------
    A : np.ndarray, shape (n, R, 2)
    lower, upper : np.ndarray, shape (n, R)
    weight : np.ndarray, shape (R,), optional
        Fallback weight of each row slot (0: hard).

    Returns
    -------
    G : np.ndarray, shape (n, K, 2)
        Unit normals (row slots whose bound is infinite for every AGV are dropped; a lower
        bound becomes the row ``-a . v <= -lower``). Zero rows get ``G = 0``.
    h : np.ndarray, shape (n, K)
        ``+inf`` where a row is absent (padding, or a zero row that holds anyway); negative
        where a zero row can never hold (the AGV is then infeasible).
    w : np.ndarray, shape (n, K)
        ``weight`` divided by the row's length (lower-bound rows are hard, as in
        :func:`solve_reference`); zeros without ``weight``.
    """
    up = np.isfinite(upper).any(axis=0)
    down = np.isfinite(lower).any(axis=0)
    wt = np.zeros(A.shape[1]) if weight is None else np.asarray(weight, dtype=np.float64)
    if down.any():
        G = np.concatenate([A[:, up], -A[:, down]], axis=1)
        h = np.concatenate([upper[:, up], -lower[:, down]], axis=1)
        wt = np.concatenate([wt[up], np.zeros(int(down.sum()))])
    else:
        G, h, wt = A[:, up], upper[:, up], wt[up]
    norm = np.sqrt(G[..., 0] ** 2 + G[..., 1] ** 2)
    zero = norm < 1e-12
    if zero.any():
        h = np.where(zero & (h >= 0.0), np.inf, h)
        norm = np.where(zero, 1.0, norm)
    inv = 1.0 / norm
    return G * inv[..., None], h * inv, wt * inv


def solve_qp_2d(
    A: np.ndarray,
    lower: np.ndarray,
    upper: np.ndarray,
    preferred: np.ndarray,
    tol: float = 1e-9,
) -> tuple[np.ndarray, np.ndarray]:
    """Exact ``min ||v_i - pref_i||^2 s.t. lower_i <= A_i v_i <= upper_i`` for many 2-D QPs.

    The minimiser is the Euclidean projection of ``pref_i`` onto the feasible polygon, so it
    is ``pref_i`` itself, the projection of ``pref_i`` onto one violated line, or a vertex
    where a violated line meets another line (KKT: at least one active line is violated by
    ``pref_i``). The candidates of all AGVs are enumerated as flat arrays and checked at
    once (no loop over AGVs): first the projections onto the violated lines, ``E`` (AGV,
    line) pairs checked against all ``K`` rows, ``(E, K)``; then, only for AGVs none of whose
    projections is feasible, the vertices of each violated line with every other line whose
    KKT multipliers are non-negative, again ``(E', K)``. Any feasible point is at least as far
    from ``pref_i`` as the optimum, and the optimum is a candidate, so the feasible candidate
    nearest ``pref_i`` is the optimum (up to ``tol``).

    Parameters
    ----------
    A : np.ndarray, shape (n, R, 2)
    lower, upper : np.ndarray, shape (n, R)
        ``-inf`` / ``inf`` where unbounded (padded rows: ``A = 0``, infinite bounds).
    preferred : np.ndarray, shape (n, 2)
    tol : float
        A row holds when ``a . v <= b + tol`` (rows normalised to unit normals).

    Returns
    -------
    velocity : np.ndarray, shape (n, 2)
        The optimum; ``preferred`` where the rows conflict.
    feasible : np.ndarray of bool, shape (n,)
        False where no point satisfies every row (within ``tol``).
    """
    pref = np.asarray(preferred, dtype=np.float64)
    n = pref.shape[0]
    velocity = pref.copy()
    feasible = np.ones(n, dtype=bool)
    if n == 0 or A.shape[1] == 0:
        return velocity, feasible
    G, h, _ = one_sided(A, lower, upper)
    gx, gy = G[..., 0], G[..., 1]
    s = gx * pref[:, None, 0] + gy * pref[:, None, 1] - h  # (n, K): violation at pref
    violated = s > tol
    need = violated.any(axis=1)
    if not need.any():
        return velocity, feasible
    K = h.shape[1]

    # 1. Projections onto the violated lines, one candidate per (AGV i, line k) pair:
    #    c = p - s_k g_k, where row j has slack g_j . c - h_j = s_j - s_k (g_j . g_k).
    ai, ki = np.nonzero(violated)  # (E,)
    sk = s[ai, ki]
    gram = gx[ai] * gx[ai, ki, None] + gy[ai] * gy[ai, ki, None]  # (E, K)
    ok = (s[ai] - sk[:, None] * gram <= tol).all(axis=1)
    done = np.zeros(n, dtype=bool)
    if ok.any():
        # The nearest feasible projection of each AGV (candidates sorted by AGV, then s_k).
        ai_ok, ki_ok, sk_ok = ai[ok], ki[ok], sk[ok]
        order = np.lexsort((sk_ok, ai_ok))
        first = np.unique(ai_ok[order], return_index=True)[1]
        sel = order[first]
        i, k = ai_ok[sel], ki_ok[sel]
        velocity[i] = pref[i] - sk_ok[sel, None] * G[i, k]
        done[i] = True
    rest = need & ~done
    if not rest.any():
        return velocity, feasible

    # 2. Vertices where a violated line j meets another line k, one candidate per (i, j, k);
    #    kept when the KKT multipliers of p - c = l_j g_j + l_k g_k are both >= 0 (that
    #    vertex is then the optimum if it is feasible).
    ai, ji = np.nonzero(violated & rest[:, None])
    E = ai.size
    ai = np.repeat(ai, K)
    ji = np.repeat(ji, K)
    ki = np.tile(np.arange(K), E)
    gjx, gjy, hj = gx[ai, ji], gy[ai, ji], h[ai, ji]
    gkx, gky, hk = gx[ai, ki], gy[ai, ki], h[ai, ki]
    det = gjx * gky - gjy * gkx
    pair = (np.abs(det) > 1e-12) & np.isfinite(hk)
    ai, ji, ki = ai[pair], ji[pair], ki[pair]
    gjx, gjy, hj, gkx, gky, hk = (x[pair] for x in (gjx, gjy, hj, gkx, gky, hk))
    inv = 1.0 / det[pair]
    cx = (hj * gky - hk * gjy) * inv
    cy = (gjx * hk - gkx * hj) * inv
    dx, dy = pref[ai, 0] - cx, pref[ai, 1] - cy
    lam_j = (dx * gky - dy * gkx) * inv
    lam_k = (gjx * dy - gjy * dx) * inv
    kkt = (lam_j >= -1e-6) & (lam_k >= -1e-6)  # loose: extra candidates cost nothing
    ai, cx, cy, dx, dy = ai[kkt], cx[kkt], cy[kkt], dx[kkt], dy[kkt]
    ok = (gx[ai] * cx[:, None] + gy[ai] * cy[:, None] - h[ai] <= tol).all(axis=1)
    if ok.any():
        ai, cx, cy = ai[ok], cx[ok], cy[ok]
        order = np.lexsort((dx[ok] ** 2 + dy[ok] ** 2, ai))
        first = np.unique(ai[order], return_index=True)[1]
        sel = order[first]
        velocity[ai[sel], 0] = cx[sel]
        velocity[ai[sel], 1] = cy[sel]
        rest[ai[sel]] = False
    feasible[rest] = False
    return velocity, feasible

