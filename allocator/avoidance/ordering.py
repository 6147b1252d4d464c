"""Plans whose AGVs do not park on each other's way (:func:`parking_conflicts`, :func:`untangle`).

In the episodic simulator an AGV that claims a task parks there for the rest of the episode: it
becomes a static obstacle. A plan that minimises the total distance (the Hungarian plan) does
not see that: it happily sends AGV k along a straight leg that passes the task of AGV i, which
i reaches first. k must then go round i's parked disc, and where i parks next to another parked
AGV or a wall the gap left is narrower than an AGV (an AGV needs a centre distance of
``2 (2 r + margin)`` = 0.62 between two parked ones), so k is re-routed round a cluster of parked
AGVs or boxed in for the rest of the episode. These were most of the remaining misses of 6v6
(``docs/safety.md``).

:func:`parking_conflicts` predicts, from straight legs at cruise speed, which AGV's leg passes
which other AGV's parking point after that AGV has parked there (or about when it parks).
:func:`untangle` then exchanges tasks between AGVs, one exchange at a time, while an exchange
removes conflicts at a cost in total distance of at most ``weight`` per conflict removed, the
best such exchange first. It never exchanges for distance alone: a plan without conflicts is
returned unchanged (the Hungarian plan stays the optimum wherever it has no conflict, and a
greedy plan is not improved into something else).
"""

from __future__ import annotations

import numpy as np

__all__ = ["parking_conflicts", "closed_gates", "untangle"]


def _check(agents: np.ndarray, tasks: np.ndarray, task_of_agent: np.ndarray,
           ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    a = np.asarray(agents, dtype=np.float64)
    t = np.asarray(tasks, dtype=np.float64)
    plan = np.asarray(task_of_agent)
    if a.ndim != 2 or a.shape[1] != 2 or not np.isfinite(a).all():
        raise ValueError(f"agents must be finite real numbers of shape (N, 2), got shape "
                         f"{a.shape}")
    if t.ndim != 2 or t.shape[1] != 2 or not np.isfinite(t).all():
        raise ValueError(f"tasks must be finite real numbers of shape (M, 2), got shape "
                         f"{t.shape}")
    if plan.shape != (len(a),) or not np.issubdtype(plan.dtype, np.integer):
        raise ValueError(f"task_of_agent must be integers of shape ({len(a)},), got "
                         f"{plan.dtype} {plan.shape}")
    if ((plan < -1) | (plan >= len(t))).any():
        raise ValueError(f"task_of_agent must hold task indices in [0, {len(t)}) or -1, got "
                         f"{plan.tolist()}")
    served = plan[plan >= 0]
    if len(np.unique(served)) != len(served):
        raise ValueError(f"task_of_agent gives a task to two AGVs: {plan.tolist()}")
    return a, t, plan.astype(np.int64)


def _positive(name: str, value: float) -> float:
    value = float(value)
    if not (np.isfinite(value) and value > 0):
        raise ValueError(f"{name} must be a positive number, got {value!r}")
    return value


def parking_conflicts(agents: np.ndarray, tasks: np.ndarray, task_of_agent: np.ndarray,
                      clearance: float, capture: float, step: float, lead: float = 2.0,
                      slack: float = 2.0) -> np.ndarray:
    """Which AGV's leg passes which AGV's parking point after it parked (a straight-line model).

    AGV i, sent along the straight leg from ``agents[i]`` to its task, parks where the leg
    enters the task's capture disc, ``p_i = task + min(capture, L_i) u_i`` (``u_i`` the unit
    vector from the task to the AGV, ``L_i`` the leg's length), after
    ``T_i = lead + max(L_i - capture, 0) / step`` steps. AGV k's leg *conflicts* with i's
    parking when it passes closer than ``clearance`` to ``p_i`` and k reaches the leg's point
    nearest ``p_i`` (``lead + s L_k / step`` steps, ``s`` the fraction of the leg) no earlier
    than ``T_i - slack``.

    Parameters
    ----------
    agents : np.ndarray, shape (N, 2)
    tasks : np.ndarray, shape (M, 2)
    task_of_agent : np.ndarray of int, shape (N,)
        Task of each AGV, -1 for none (such an AGV neither parks nor drives).
    clearance : float
        Centre distance below which the leg is blocked (``2 r`` plus a margin).
    capture : float
        The simulator's capture radius.
    step : float
        Distance an AGV covers per step at cruise speed.
    lead : float
        Steps to reach cruise speed (added to every time).
    slack : float
        Steps by which k may pass before i parks and still count (the model's error).

    Returns
    -------
    np.ndarray of bool, shape (N, N)
        ``[k, i]``: k's leg conflicts with i's parking (False on the diagonal and for AGVs
        without a task).

    Raises
    ------
    ValueError
        On positions that are not finite (K, 2) arrays, a plan that is not a partial
        one-to-one map into the tasks, or a parameter that is not a positive number (``lead``
        and ``slack``: not a number >= 0).
    """
    a, t, plan = _check(agents, tasks, task_of_agent)
    clearance = _positive("clearance", clearance)
    capture = _positive("capture", capture)
    step = _positive("step", step)
    for name, value in (("lead", lead), ("slack", slack)):
        if not (np.isfinite(value) and value >= 0):
            raise ValueError(f"{name} must be a number >= 0, got {value!r}")
    return _conflicts(a, t, plan, clearance, capture, step, lead, slack)


def _legs(a: np.ndarray, t: np.ndarray, plan: np.ndarray, capture: float, step: float,
          lead: float) -> tuple[np.ndarray, ...]:
    idx = np.flatnonzero(plan >= 0)
    start = a[idx]
    seg = t[plan[idx]] - start
    length = np.linalg.norm(seg, axis=1)
    unit = -seg / np.maximum(length, 1e-12)[:, None]
    park = start + seg + np.minimum(capture, length)[:, None] * unit
    parked_at = lead + np.maximum(length - capture, 0.0) / step
    return idx, start, seg, length, park, parked_at


def _conflicts(a: np.ndarray, t: np.ndarray, plan: np.ndarray, clearance: float,
               capture: float, step: float, lead: float, slack: float) -> np.ndarray:
    n = len(a)
    out = np.zeros((n, n), dtype=bool)
    idx, start, seg, length, park, parked_at = _legs(a, t, plan, capture, step, lead)
    if len(idx) < 2:
        return out
    rel = park[None, :, :] - start[:, None, :]  # [k, i]: p_i - a_k
    s = np.clip((rel * seg[:, None, :]).sum(-1) / np.maximum(length ** 2, 1e-24)[:, None],
                0.0, 1.0)
    gap = np.linalg.norm(seg[:, None, :] * s[..., None] - rel, axis=-1)
    passes_at = lead + s * length[:, None] / step
    hit = (gap < clearance) & (parked_at[None, :] <= passes_at + slack)
    np.fill_diagonal(hit, False)
    out[np.ix_(idx, idx)] = hit
    return out


def _cross(p: np.ndarray, q: np.ndarray, r: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Whether segments ``p -> q`` and ``r -> s`` cross (broadcast over leading axes)."""
    def orient(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
        return (b[..., 0] - a[..., 0]) * (c[..., 1] - a[..., 1]) \
            - (b[..., 1] - a[..., 1]) * (c[..., 0] - a[..., 0])

    return (orient(p, q, r) * orient(p, q, s) < 0) & (orient(r, s, p) * orient(r, s, q) < 0)


def closed_gates(agents: np.ndarray, tasks: np.ndarray, task_of_agent: np.ndarray,
                 clearance: float, capture: float, step: float, radius: float,
                 bounds: tuple[float, float, float, float] | None = None, lead: float = 2.0,
                 slack: float = 2.0) -> np.ndarray:
    """How many closed gates each AGV's leg crosses (a straight-line model).

    A *gate* is the segment between two parking points (as in :func:`parking_conflicts`)
    closer than ``2 clearance``, or between a parking point closer than ``radius + clearance``
    to a wall and the nearest point of that wall: an AGV does not fit through it. AGV k's leg
    crosses a *closed* gate when it crosses the segment and both AGVs (the one AGV, for a wall
    gate) parked ``slack`` steps before k gets there or earlier.

    Parameters
    ----------
    agents, tasks, task_of_agent, clearance, capture, step, lead, slack
        As in :func:`parking_conflicts`.
    radius : float
        The AGVs' radius.
    bounds : tuple of 4 floats, optional
        ``(xmin, ymin, xmax, ymax)`` of the walls; None: no walls.

    Returns
    -------
    np.ndarray of int64, shape (N,)

    Raises
    ------
    ValueError
        As :func:`parking_conflicts`, and for bounds that are not 4 increasing numbers.
    """
    a, t, plan = _check(agents, tasks, task_of_agent)
    clearance = _positive("clearance", clearance)
    capture = _positive("capture", capture)
    step = _positive("step", step)
    radius = _positive("radius", radius)
    box = None
    if bounds is not None:
        box = np.asarray(bounds, dtype=np.float64)
        if box.shape != (4,) or not np.isfinite(box).all() or box[2] <= box[0] \
                or box[3] <= box[1]:
            raise ValueError(f"bounds must be (xmin, ymin, xmax, ymax), got {bounds!r}")
    return _gates(a, t, plan, clearance, capture, step, radius, box, lead, slack)


def _gates(a: np.ndarray, t: np.ndarray, plan: np.ndarray, clearance: float, capture: float,
           step: float, radius: float, box: np.ndarray | None, lead: float,
           slack: float) -> np.ndarray:
    n = len(a)
    out = np.zeros(n, dtype=np.int64)
    idx, start, seg, length, park, parked_at = _legs(a, t, plan, capture, step, lead)
    if len(idx) < 2:
        return out
    ends, closes, owners = [], [], []
    d = np.linalg.norm(park[:, None] - park[None], axis=-1)
    i, j = np.nonzero(np.triu(d < 2 * clearance, 1))
    if len(i):
        ends.append(np.stack([park[i], park[j]], 1))
        closes.append(np.maximum(parked_at[i], parked_at[j]))
        owners.append(np.stack([i, j], 1))
    if box is not None:
        for axis, side, wall in ((0, -1, box[0]), (1, -1, box[1]), (0, 1, box[2]),
                                 (1, 1, box[3])):
            near = np.flatnonzero(side * (wall - park[:, axis]) < radius + clearance)
            if len(near):
                foot = park[near].copy()
                foot[:, axis] = wall
                ends.append(np.stack([park[near], foot], 1))
                closes.append(parked_at[near])
                owners.append(np.stack([near, near], 1))
    if not ends:
        return out
    gate = np.concatenate(ends)  # (G, 2, 2)
    close = np.concatenate(closes)
    own = np.concatenate(owners)
    end = start + seg
    crosses = _cross(start[:, None], end[:, None], gate[None, :, 0], gate[None, :, 1])  # (K, G)
    # where the leg crosses the gate: the fraction of the leg, from the two orientations
    g0, g1 = gate[None, :, 0], gate[None, :, 1]
    den = (seg[:, None, 0] * (g1[..., 1] - g0[..., 1])
           - seg[:, None, 1] * (g1[..., 0] - g0[..., 0]))
    num = ((g0[..., 0] - start[:, None, 0]) * (g1[..., 1] - g0[..., 1])
           - (g0[..., 1] - start[:, None, 1]) * (g1[..., 0] - g0[..., 0]))
    frac = np.clip(num / np.where(np.abs(den) > 1e-12, den, 1e-12), 0.0, 1.0)
    passes_at = lead + frac * length[:, None] / step
    mine = (own[None, :, 0] == np.arange(len(idx))[:, None]) \
        | (own[None, :, 1] == np.arange(len(idx))[:, None])
    hit = crosses & ~mine & (close[None, :] <= passes_at + slack)
    out[idx] = hit.sum(1)
    return out


def _scores(a: np.ndarray, t: np.ndarray, plans: np.ndarray, clearance: float,
            capture: float, step: float, radius: float | None, box: np.ndarray | None,
            gate_weight: float, lead: float, slack: float) -> tuple[np.ndarray, np.ndarray]:
    """Scores (P,) and involved AGVs (P, N) of P plans (P, N) at once: the same counts as
    :func:`_conflicts` and :func:`_gates` (the tests compare them), vectorised over plans."""
    P, n = plans.shape
    valid = plans >= 0  # (P, N)
    goal = t[np.maximum(plans, 0)]  # (P, N, 2)
    seg = goal - a[None]
    length = np.linalg.norm(seg, axis=-1)
    unit = -seg / np.maximum(length, 1e-12)[..., None]
    park = goal + np.minimum(capture, length)[..., None] * unit
    parked_at = lead + np.maximum(length - capture, 0.0) / step
    len_sq = np.maximum(length ** 2, 1e-24)
    # conflicts [p, k, i]: k's leg passes i's parking point
    rel = park[:, None, :, :] - a[None, :, None, :]
    s = np.clip((rel * seg[:, :, None, :]).sum(-1) / len_sq[:, :, None], 0.0, 1.0)
    gap = np.linalg.norm(seg[:, :, None, :] * s[..., None] - rel, axis=-1)
    passes_at = lead + s * length[:, :, None] / step
    pair = valid[:, :, None] & valid[:, None, :] & ~np.eye(n, dtype=bool)[None]
    hit = pair & (gap < clearance) & (parked_at[:, None, :] <= passes_at + slack)
    total = hit.sum((1, 2)).astype(np.float64)
    involved = hit.any(1) | hit.any(2)
    if radius is None or gate_weight == 0 or n < 2:
        return total, involved
    both = valid.sum(1) >= 2
    gates = np.zeros((P, n), dtype=np.int64)
    # gates between two parking points: sparse (p, i, j)
    d = np.linalg.norm(park[:, :, None, :] - park[:, None, :, :], axis=-1)
    close = np.triu(np.ones((n, n), dtype=bool), 1)[None] & (d < 2 * clearance) \
        & valid[:, :, None] & valid[:, None, :] & both[:, None, None]
    gp, gi, gj = np.nonzero(close)
    ends = [(gp, park[gp, gi], park[gp, gj], np.maximum(parked_at[gp, gi], parked_at[gp, gj]),
             gi, gj)]
    if box is not None:
        for axis, side, wall in ((0, -1, box[0]), (1, -1, box[1]), (0, 1, box[2]),
                                 (1, 1, box[3])):
            wp, wi = np.nonzero(valid & both[:, None]
                                & (side * (wall - park[..., axis]) < radius + clearance))
            foot = park[wp, wi].copy()
            foot[:, axis] = wall
            ends.append((wp, park[wp, wi], foot, parked_at[wp, wi], wi, wi))
    for gp, g0, g1, closes, oi, oj in ends:
        if not len(gp):
            continue
        start = np.broadcast_to(a[None], (len(gp), n, 2))  # (G, K, 2)
        sg = seg[gp]
        end = start + sg
        crosses = _cross(start, end, g0[:, None], g1[:, None])  # (G, K)
        den = sg[..., 0] * (g1[:, None, 1] - g0[:, None, 1]) \
            - sg[..., 1] * (g1[:, None, 0] - g0[:, None, 0])
        num = (g0[:, None, 0] - start[..., 0]) * (g1[:, None, 1] - g0[:, None, 1]) \
            - (g0[:, None, 1] - start[..., 1]) * (g1[:, None, 0] - g0[:, None, 0])
        frac = np.clip(num / np.where(np.abs(den) > 1e-12, den, 1e-12), 0.0, 1.0)
        at = lead + frac * length[gp] / step
        k = np.arange(n)[None]
        mine = (k == oi[:, None]) | (k == oj[:, None])
        hit = crosses & ~mine & valid[gp] & (closes[:, None] <= at + slack)
        np.add.at(gates, (np.repeat(gp, n), np.tile(np.arange(n), len(gp))), hit.ravel())
    total += gate_weight * gates.sum(1)
    involved |= gates > 0
    return total, involved


def untangle(agents: np.ndarray, tasks: np.ndarray, task_of_agent: np.ndarray,
             clearance: float, capture: float, step: float, weight: float = 0.2,
             radius: float | None = None, bounds: tuple[float, float, float, float] | None = None,
             gate_weight: float = 3.0, lead: float = 2.0, slack: float = 2.0,
             max_exchanges: int | None = None) -> np.ndarray:
    """The plan with tasks exchanged between AGVs so that fewer legs pass parked AGVs.

    The plan's *score* counts its conflicts (:func:`parking_conflicts`) and, with ``radius``
    given, ``gate_weight`` times the closed gates its legs cross (:func:`closed_gates`). Each
    round tries every exchange of the tasks of two AGVs of which at least one takes part in a
    conflict or a closed gate (an AGV without a task may take the other's task). An exchange
    is *worth it* when it lowers the score by ``d > 0`` and lengthens the total straight-line
    distance by at most ``weight * d``; the one with the largest ``weight * d - (added
    distance)`` is made, until none is worth it (or ``max_exchanges``, default ``2 N``, were
    made). Every exchange lowers the score, so this stops.

    Parameters
    ----------
    agents : np.ndarray, shape (N, 2)
    tasks : np.ndarray, shape (M, 2)
    task_of_agent : np.ndarray of int, shape (N,)
        The plan (-1: no task); not modified.
    clearance, capture, step, lead, slack : float
        As in :func:`parking_conflicts`.
    weight : float
        Distance (world units) worth paying to lower the score by one; 0 returns the plan.
    radius : float, optional
        The AGVs' radius: count closed gates too (None: conflicts only).
    bounds : tuple of 4 floats, optional
        The walls, for the gates between a parking point and a wall.
    gate_weight : float
        Score of one closed gate crossed.
    max_exchanges : int, optional

    Returns
    -------
    np.ndarray of int64, shape (N,)
        The new plan: the same set of served tasks, possibly held by other AGVs.

    Raises
    ------
    ValueError
        As :func:`parking_conflicts` and :func:`closed_gates`, and for a negative ``weight``,
        ``gate_weight`` or ``max_exchanges``.
    """
    a, t, plan = _check(agents, tasks, task_of_agent)
    clearance = _positive("clearance", clearance)
    capture = _positive("capture", capture)
    step = _positive("step", step)
    for name, value in (("weight", weight), ("gate_weight", gate_weight), ("lead", lead),
                        ("slack", slack)):
        if not (np.isfinite(value) and value >= 0):
            raise ValueError(f"{name} must be a number >= 0, got {value!r}")
    box = None
    if radius is not None:
        radius = _positive("radius", radius)
        if bounds is not None:
            box = np.asarray(bounds, dtype=np.float64)
            if box.shape != (4,) or not np.isfinite(box).all() or box[2] <= box[0] \
                    or box[3] <= box[1]:
                raise ValueError(f"bounds must be (xmin, ymin, xmax, ymax), got {bounds!r}")
    n = len(a)
    limit = 2 * n if max_exchanges is None else int(max_exchanges)
    if limit < 0:
        raise ValueError(f"max_exchanges must be >= 0, got {max_exchanges!r}")
    plan = plan.copy()
    if weight == 0 or n < 2:
        return plan

    def length(p: np.ndarray) -> np.ndarray:
        out = np.zeros(n)
        m = p >= 0
        out[m] = np.linalg.norm(t[p[m]] - a[m], axis=1)
        return out

    def score(plans: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        out_t, out_i = [], []
        for lo in range(0, len(plans), 256):  # bounded memory: (256, N, N, 2) arrays
            tt, ii = _scores(a, t, plans[lo:lo + 256], clearance, capture, step, radius, box,
                             gate_weight, lead, slack)
            out_t.append(tt)
            out_i.append(ii)
        return np.concatenate(out_t), np.concatenate(out_i)

    totals, inv = score(plan[None])
    total, involved = float(totals[0]), inv[0]
    for _ in range(limit):
        if total == 0:
            break
        pairs = [(i, j) for i in np.flatnonzero(involved) for j in range(n)
                 if j != i and not (plan[i] < 0 and plan[j] < 0)]
        if not pairs:
            break
        ij = np.array(pairs)
        trials = np.repeat(plan[None], len(ij), axis=0)
        rows = np.arange(len(ij))
        trials[rows, ij[:, 0]] = plan[ij[:, 1]]
        trials[rows, ij[:, 1]] = plan[ij[:, 0]]
        new_totals, new_inv = score(trials)
        removed = total - new_totals
        legs = length(plan)
        after = np.zeros((len(ij), 2))
        for c in range(2):
            task = trials[rows, ij[:, c]]
            ok = task >= 0
            after[ok, c] = np.linalg.norm(t[task[ok]] - a[ij[ok, c]], axis=1)
        added = after.sum(1) - legs[ij].sum(1)
        gain = weight * removed - added
        worth = (removed > 0) & (added <= weight * removed) & (gain > 1e-12)
        if not worth.any():
            break
        b = int(np.argmax(np.where(worth, gain, -np.inf)))
        plan, total, involved = trials[b], float(new_totals[b]), new_inv[b]
    return plan
