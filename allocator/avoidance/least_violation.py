"""ORCA's "3-D" least-violation program for AGVs whose rows conflict, exact and vectorised
(:func:`least_violation_2d`)."""

from __future__ import annotations

from functools import lru_cache
from itertools import combinations

import numpy as np

from allocator.avoidance.exact_qp import one_sided

__all__ = ["least_violation_2d"]


def _intersect(
    n1x: np.ndarray, n1y: np.ndarray, d1: np.ndarray,
    n2x: np.ndarray, n2y: np.ndarray, d2: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Intersections of the lines ``n1 . v = d1`` and ``n2 . v = d2`` (any equal shapes):
    ``(x, y, valid)``, valid where the lines are not (nearly) parallel and ``d`` finite."""
    det = n1x * n2y - n1y * n2x
    scale = np.sqrt((n1x * n1x + n1y * n1y) * (n2x * n2x + n2y * n2y))
    valid = (np.abs(det) > 1e-10 * scale) & np.isfinite(d1) & np.isfinite(d2) & (scale > 0)
    inv = np.where(valid, 1.0 / np.where(valid, det, 1.0), 0.0)
    d1 = np.where(valid, d1, 0.0)
    d2 = np.where(valid, d2, 0.0)
    return (d1 * n2y - d2 * n1y) * inv, (n1x * d2 - n2x * d1) * inv, valid


def _solve2(
    ax: np.ndarray, ay: np.ndarray, bx: np.ndarray, by: np.ndarray, rx: np.ndarray,
    ry: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(alpha, beta, valid)`` with ``alpha a + beta b = r`` (2-vectors, any equal shapes)."""
    det = ax * by - ay * bx
    valid = np.abs(det) > 1e-14
    inv = np.where(valid, 1.0 / np.where(valid, det, 1.0), 0.0)
    return (rx * by - ry * bx) * inv, (ax * ry - ay * rx) * inv, valid


def _project(
    qx: np.ndarray, qy: np.ndarray, nx: np.ndarray, ny: np.ndarray, d: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Projections of the points ``q`` onto the lines ``n . v = d``: ``(x, y, valid)``."""
    nn = nx * nx + ny * ny
    valid = (nn > 1e-20) & np.isfinite(d) & np.isfinite(qx) & np.isfinite(qy)
    f = np.where(valid, (nx * qx + ny * qy - np.where(valid, d, 0.0)) / np.where(valid, nn, 1.0),
                 0.0)
    return qx - f * nx, qy - f * ny, valid


@lru_cache(maxsize=64)
def _combinations(k: int, r: int) -> np.ndarray:
    """All r-subsets of range(k), shape (C(k, r), r)."""
    return np.array(list(combinations(range(k), r)), dtype=np.intp).reshape(-1, r)


def least_violation_2d(
    A: np.ndarray,
    lower: np.ndarray,
    upper: np.ndarray,
    preferred: np.ndarray,
    weight: np.ndarray,
    regularization: float = 1e-3,
    tol: float = 1e-9,
) -> tuple[np.ndarray, np.ndarray]:
    """Exact ORCA "3-D" program for many AGVs whose rows conflict, vectorised.

    Per AGV: ``min t + (r / 2) ||v - pref||^2`` s.t. ``a . v - w t <= upper`` on soft rows
    (``w > 0``), ``a . v <= upper`` on hard rows (``w = 0``), ``a . v >= lower`` (hard),
    ``t >= 0`` (the program of :class:`LeastViolation` and :func:`solve_reference`).

    With ``t(v) = max(0, max_soft (a . v - upper) / w)`` this is ``min t(v) + (r / 2)
    ||v - pref||^2`` over the hard polygon. Where the rows conflict, ``t > 0`` at the optimum
    and its KKT multipliers can be carried by at most three independent active constraints,
    one of them soft, so the optimum is one of: ``q_k = pref - (a_k / w_k) / r`` (one soft row),
    ``q_k`` projected onto a hard line, a hard vertex, ``q_j`` projected onto the "tie line"
    of two soft rows (where their scaled violations are equal), a tie line meeting a hard line,
    or two tie lines meeting. All these candidates are enumerated for all AGVs at once; the
    one with the least objective inside the hard polygon is the optimum.

    Parameters
    ----------
    A : np.ndarray, shape (n, R, 2)
    lower, upper : np.ndarray, shape (n, R)
    preferred : np.ndarray, shape (n, 2)
    weight : np.ndarray, shape (R,)
        ``w`` per row slot (0: hard).
    regularization : float
        ``r`` (> 0).
    tol : float
        Slack allowed on the hard rows.

    Returns
    -------
    velocity : np.ndarray, shape (n, 2)
        Zero where even the hard rows conflict.
    violation : np.ndarray, shape (n,)
        ``t`` at the optimum (``inf`` where the hard rows conflict).

    Notes
    -----
    Meant for infeasible QPs (call :func:`solve_qp_2d` first): where the rows are compatible,
    the optimum can have ``t = 0`` with no soft row active, which is not enumerated.
    """
    pref = np.asarray(preferred, dtype=np.float64)
    n = pref.shape[0]
    velocity = np.zeros((n, 2))
    violation = np.full(n, np.inf)
    if n == 0:
        return velocity, violation
    r = float(regularization)
    G, h, w = one_sided(A, lower, upper, weight)
    present = np.isfinite(h).any(axis=0)
    S = np.flatnonzero((w > 0).any(axis=0) & present)
    H = np.flatnonzero(~(w > 0).any(axis=0) & present)
    gx, gy = G[..., 0], G[..., 1]
    px, py = pref[:, 0:1], pref[:, 1:2]
    ws = w[:, S]
    ux, uy, c = gx[:, S] / ws, gy[:, S] / ws, h[:, S] / ws  # scaled soft rows: u . v - c
    qx, qy = px - ux / r, py - uy / r
    hx, hy, hh = gx[:, H], gy[:, H], h[:, H]
    Ks, Kh = S.size, H.size
    parts: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
    # Each candidate is kept only where its KKT multipliers have the right signs:
    # r (pref - v) = sum_soft mu_i u_i + sum_hard nu_l g_l, mu >= 0, sum mu = 1, nu >= 0.
    neg = -1e-7  # loose: an extra candidate costs nothing, a missing one the optimum
    with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
        parts.append((qx, qy, np.isfinite(c)))  # one soft row: mu = 1
        if Kh:
            # q_k projected onto a hard line: nu = (r (p - v) - u_k) . g_l.
            x, y, ok = _project(qx[:, :, None], qy[:, :, None], hx[:, None], hy[:, None],
                                hh[:, None])
            nu = (r * (px[:, :, None] - x) - ux[:, :, None]) * hx[:, None] \
                + (r * (py[:, :, None] - y) - uy[:, :, None]) * hy[:, None]
            parts.append((x, y, ok & np.isfinite(c)[:, :, None] & (nu >= neg)))
            i1, i2 = _combinations(Kh, 2).T
            parts.append(_intersect(hx[:, i1], hy[:, i1], hh[:, i1],
                                    hx[:, i2], hy[:, i2], hh[:, i2]))  # hard vertex
        if Ks >= 2:
            j, k = _combinations(Ks, 2).T
            tx, ty, td = ux[:, j] - ux[:, k], uy[:, j] - uy[:, k], c[:, j] - c[:, k]
            # Two soft rows tie: r (p - v) - u_k = mu (u_j - u_k), 0 <= mu <= 1.
            x, y, ok = _project(qx[:, j], qy[:, j], tx, ty, td)
            mu = ((r * (px - x) - ux[:, k]) * tx + (r * (py - y) - uy[:, k]) * ty) \
                / (tx * tx + ty * ty)
            parts.append((x, y, ok & (mu >= neg) & (mu <= 1 - neg)))
            if Kh:
                # ... and a hard line: r (p - v) - u_k = mu (u_j - u_k) + nu g_l.
                x, y, ok = _intersect(tx[:, :, None], ty[:, :, None], td[:, :, None],
                                      hx[:, None], hy[:, None], hh[:, None])
                rx = r * (px[:, :, None] - x) - ux[:, k, None]
                ry = r * (py[:, :, None] - y) - uy[:, k, None]
                mu, nu, ok2 = _solve2(tx[:, :, None], ty[:, :, None], hx[:, None], hy[:, None],
                                      rx, ry)
                parts.append((x, y, ok & ok2 & (mu >= neg) & (mu <= 1 - neg) & (nu >= neg)))
        if Ks >= 3:
            j, k, l = _combinations(Ks, 3).T
            # Three soft rows tie: r (p - v) - u_j = mu_k (u_k - u_j) + mu_l (u_l - u_j).
            x, y, ok = _intersect(
                ux[:, j] - ux[:, k], uy[:, j] - uy[:, k], c[:, j] - c[:, k],
                ux[:, j] - ux[:, l], uy[:, j] - uy[:, l], c[:, j] - c[:, l],
            )
            mk, ml, ok2 = _solve2(ux[:, k] - ux[:, j], uy[:, k] - uy[:, j],
                                  ux[:, l] - ux[:, j], uy[:, l] - uy[:, j],
                                  r * (px - x) - ux[:, j], r * (py - y) - uy[:, j])
            parts.append((x, y, ok & ok2 & (mk >= neg) & (ml >= neg) & (mk + ml <= 1 - neg)))
    X = np.concatenate([p[0].reshape(n, -1) for p in parts], axis=1)
    Y = np.concatenate([p[1].reshape(n, -1) for p in parts], axis=1)
    ok = np.concatenate([p[2].reshape(n, -1) for p in parts], axis=1)
    ai, ci = np.nonzero(ok)
    x, y = X[ai, ci], Y[ai, ci]
    inside = (hx[ai] * x[:, None] + hy[ai] * y[:, None] - hh[ai] <= tol).all(axis=1)
    ai, x, y = ai[inside], x[inside], y[inside]
    t = np.maximum((ux[ai] * x[:, None] + uy[ai] * y[:, None] - c[ai]).max(axis=1, initial=0.0),
                   0.0)
    f = t + 0.5 * r * ((x - pref[ai, 0]) ** 2 + (y - pref[ai, 1]) ** 2)
    if ai.size:
        order = np.lexsort((f, ai))
        agents, first = np.unique(ai[order], return_index=True)
        sel = order[first]
        velocity[agents, 0] = x[sel]
        velocity[agents, 1] = y[sel]
        violation[agents] = t[sel]
    return velocity, violation


