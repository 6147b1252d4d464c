"""Bertsekas's epsilon-auction run decentralized over a communication graph.

Every AGV keeps its own copy of the task prices and of the agent it believes holds each task
(the highest bidder it has heard of). A round has two phases, each an array operation over the
whole fleet:

1. **Bid.** Every AGV that holds no task (by its own copy) bids for the task of greatest net
   value ``benefit[i, j] - price_i[j]``: it raises that task's price by the margin over its
   second-best task plus ``eps`` and records itself as the holder.
2. **Talk.** Every AGV whose copy changed (by its bid or by what it heard) sends it to its
   neighbours (the AGVs within ``comm_range``); a receiver keeps, task by task, the higher
   price, and on equal prices the higher agent index (the max-consensus auction of Zavlanos,
   Spesivtsev and Pappas, 2008).
   An AGV that learns it has been outbid bids again in the next round. Max-consensus is
   idempotent, so AGVs whose copy did not change need not send anything; every message sent
   (one copy to one neighbour) is counted.

With more AGVs than tasks or as many, the auction runs in phases of decreasing ``eps``
(Bertsekas's epsilon scaling): the early phases settle the prices coarsely in few rounds, the
last runs at ``eps`` from those prices; between phases every AGV drops its task and keeps its
prices (a phase ends when the fleet is quiet, the same detection as the end of the auction).

The auction stops when a round has no bid and no message. On a connected graph it then solves
the assignment problem within ``N * eps`` of the optimum, and exactly when the benefits
are integers and ``eps < 1 / N`` (Bertsekas's bound: prices in consensus satisfy
eps-complementary slackness). With more AGVs than tasks, ``N - M`` idle slots of benefit 0
are added, so that every AGV ends with a task or an idle slot. On a disconnected graph every
component runs its own auction: the assignment is conflict-free within each component, and
two components may claim one task; the returned arrays resolve such a clash centrally (the
higher price wins, then the higher agent index) and ``claimed`` keeps every AGV's own claim.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

__all__ = ["AuctionResult", "ComponentAuction", "auction",
           "check_comm_range", "communication_graph", "component_auction", "default_eps"]


@dataclass(frozen=True)
class AuctionResult:
    """The outcome of :func:`auction`.

    Use ``task_of_agent`` (or its inverse ``agent_of_task``) as the plan; ``claimed`` is what
    each AGV believes on its own, which differs only on a disconnected graph.
    """

    task_of_agent: np.ndarray
    """(N,) int64: task index of each AGV, -1 idle."""
    agent_of_task: np.ndarray
    """(M,) int64: AGV serving each task, -1 unserved; the inverse of ``task_of_agent``."""
    rounds: int
    """Rounds run (bid, then talk), the last quiet one included."""
    messages: int
    """Messages sent: one AGV's price and holder vectors to one neighbour."""
    converged: bool
    """Whether the auction went quiet within ``max_rounds``."""
    claimed: np.ndarray
    """(N,) int64: the task each AGV holds by its own copy (-1: none or an idle slot)."""
    component: np.ndarray
    """(N,) int64: connected component of each AGV in the communication graph."""
    prices: np.ndarray
    """(M,) float64: the highest price of each task heard anywhere."""


def communication_graph(positions: np.ndarray, comm_range: float) -> tuple[np.ndarray,
                                                                           np.ndarray]:
    """Directed edges ``(src, dst)`` between AGVs at most ``comm_range`` apart, sorted by dst.

    Parameters
    ----------
    positions : np.ndarray, shape (N, 2)
    comm_range : float

    Returns
    -------
    src, dst : np.ndarray of int64, shape (E,)
        Both directions of every pair; no self-loops.
    """
    pairs = cKDTree(positions).query_pairs(comm_range, output_type="ndarray")
    src = np.concatenate([pairs[:, 0], pairs[:, 1]]).astype(np.int64)
    dst = np.concatenate([pairs[:, 1], pairs[:, 0]]).astype(np.int64)
    order = np.lexsort((src, dst))
    return src[order], dst[order]


def _components(n: int, src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    graph = coo_matrix((np.ones(len(src)), (src, dst)), shape=(n, n))
    return connected_components(graph, directed=False)[1].astype(np.int64)


def check_comm_range(comm_range: object) -> float:
    """``comm_range`` as a float, or a ValueError naming it (not a positive number)."""
    if isinstance(comm_range, (bool, np.bool_)) or not isinstance(
            comm_range, (int, float, np.integer, np.floating)) or not comm_range > 0:
        raise ValueError(f"comm_range must be a positive number (inf: everyone hears "
                         f"everyone), got {comm_range!r}")
    return float(comm_range)


def _check(benefit: object, positions: object, comm_range: object, eps: object,
           max_rounds: object, scaling: object) -> tuple[np.ndarray, np.ndarray, float]:
    raw = np.asarray(benefit)
    if raw.dtype.kind not in "iuf":
        raise ValueError(f"benefit must hold real numbers, got dtype {raw.dtype}")
    if raw.ndim != 2 or raw.shape[0] == 0:
        raise ValueError(f"benefit must have shape (N, M) with N >= 1, got {raw.shape}")
    b = raw.astype(np.float64)
    bad = np.argwhere(~np.isfinite(b))
    if len(bad):
        raise ValueError(f"benefit holds NaN or infinite values, first at {tuple(bad[0])}")
    n = b.shape[0]
    pos = np.asarray(positions)
    if pos.dtype.kind not in "iuf" or pos.shape != (n, 2):
        raise ValueError(f"positions must be an ({n}, 2) array of real numbers (one row per "
                         f"benefit row), got {pos.dtype} of shape {pos.shape}")
    pos = pos.astype(np.float64)
    if not np.isfinite(pos).all():
        raise ValueError("positions hold NaN or infinite values")
    comm_range = check_comm_range(comm_range)
    if eps is not None and (isinstance(eps, bool) or not isinstance(eps, (int, float, np.number))
                            or not (math.isfinite(eps) and eps > 0)):
        raise ValueError(f"eps must be a positive finite number or None, got {eps!r}")
    if scaling is not None and (isinstance(scaling, bool) or not isinstance(
            scaling, (int, float, np.number)) or not (math.isfinite(scaling) and scaling >= 1)):
        raise ValueError(f"scaling must be a number >= 1 or None, got {scaling!r}")
    if isinstance(max_rounds, bool) or not isinstance(max_rounds, (int, np.integer)) \
            or max_rounds < 1:
        raise ValueError(f"max_rounds must be an int >= 1, got {max_rounds!r}")
    return b, pos, float(comm_range)


def _schedule(value: np.ndarray, eps: float, scaling: float | None) -> list[float]:
    """The phases' increments, largest first, ending at ``eps``."""
    phases = [eps]
    if scaling is not None and scaling > 1:
        spread = float(value.max() - value.min()) if value.size else 0.0
        while phases[-1] * scaling < spread / 4 and len(phases) < 30:
            phases.append(phases[-1] * scaling)
    return phases[::-1]


def default_eps(benefit: np.ndarray) -> float:
    """``1 / (N + 1)`` for integer benefits (the exact optimum); otherwise the spread of the
    benefits over ``50 (N + 1)`` (within 2% of the spread of the optimum)."""
    k = benefit.shape[0] + 1
    if np.array_equal(benefit, np.round(benefit)):
        return 1.0 / k
    spread = float(benefit.max() - benefit.min()) if benefit.size else 0.0
    return max(spread, 1e-12) / (50.0 * k)


def auction(
    benefit: np.ndarray,
    positions: np.ndarray,
    comm_range: float,
    eps: float | None = None,
    max_rounds: int = 20_000,
    scaling: float | None = 5.0,
) -> AuctionResult:
    """Assign N AGVs to M tasks by a decentralized epsilon-auction (maximising benefit).

    Parameters
    ----------
    benefit : array-like, shape (N, M)
        ``benefit[i, j]``: what AGV i gains serving task j (e.g. minus its travel distance).
        Finite real numbers.
    positions : array-like, shape (N, 2)
        AGV positions: AGVs at most ``comm_range`` apart talk directly, the others through
        neighbours (one hop a round).
    comm_range : float
        Radio range, > 0 (``inf``: a complete graph).
    eps : float, optional
        Bid increment; default :func:`default_eps`. Smaller is closer to the optimum (within
        ``N * eps`` on a connected graph) and takes more rounds.
    max_rounds : int
        Stop after this many rounds in all even if bids are still going (``converged`` False).
    scaling : float or None
        Epsilon scaling (N >= M only): phases with ``eps`` times ``scaling ** k``, from about a
        quarter of the benefits' spread down to ``eps``, each run until the fleet is quiet, the
        AGVs dropping their tasks but keeping their prices between phases. None or 1: one phase
        at ``eps``. (With N < M one phase always: prices left on tasks that end unassigned
        would void the optimality bound.)

    Returns
    -------
    AuctionResult
        ``task_of_agent[i]`` is AGV i's task (-1: idle); on a connected graph, when
        ``converged``, every AGV (N <= M) or every task (N >= M) is assigned.

    Raises
    ------
    ValueError
        Naming ``benefit`` (wrong shape, not real, NaN or infinite), ``positions``,
        ``comm_range`` (not positive), ``eps`` or ``max_rounds``.
    """
    b, pos, comm_range = _check(benefit, positions, comm_range, eps, max_rounds, scaling)
    n, m = b.shape
    eps = default_eps(b) if eps is None else float(eps)
    # With more AGVs than tasks: idle slots of benefit 0, so every AGV can end assigned.
    cols = max(n, m)
    value = np.zeros((n, cols))
    value[:, :m] = b
    if math.isinf(comm_range):
        src = np.repeat(np.arange(n), n)
        dst = np.tile(np.arange(n), n)
        keep = src != dst
        src, dst = dst[keep], src[keep]  # sorted by dst
    else:
        src, dst = communication_graph(pos, comm_range)
    component = _components(n, src, dst)

    price = np.zeros((n, cols))  # each AGV's copy of the prices
    holder = np.full((n, cols), -1, dtype=np.int64)  # each AGV's copy of the holders
    task = np.full(n, -1, dtype=np.int64)
    agents = np.arange(n)
    rounds = messages = 0
    quiet = False
    updated = np.zeros(n, dtype=bool)  # copies changed by what an AGV heard last round
    for phase_eps in _schedule(value, eps, scaling if n >= m else None):
        # A new phase: every AGV drops its task and holders and keeps its prices.
        holder[:] = -1
        task[:] = -1
        updated[:] = False
        quiet = False
        while rounds < max_rounds:
            rounds += 1
            # 1. Bid: AGVs without a task by their own copy.
            held = task >= 0
            held[held] = holder[agents[held], task[held]] == agents[held]
            bidders = np.flatnonzero(~held)
            changed = updated.copy()
            if bidders.size:
                net = value[bidders] - price[bidders]  # (K, cols)
                best = np.argmax(net, axis=1)
                top = net[np.arange(bidders.size), best]
                if cols > 1:
                    net[np.arange(bidders.size), best] = -np.inf
                    second = net.max(axis=1)
                else:
                    second = top
                price[bidders, best] += top - second + phase_eps
                holder[bidders, best] = bidders
                task[bidders] = best
                changed[bidders] = True
            # 2. Talk: changed AGVs send their copies; receivers keep the (price, holder) maximum.
            sel = np.flatnonzero(changed[src])
            messages += int(sel.size)
            if not bidders.size and not sel.size:
                quiet = True
                break
            updated = np.zeros(n, dtype=bool)
            if sel.size:
                s, d = src[sel], dst[sel]
                starts = np.flatnonzero(np.r_[True, d[1:] != d[:-1]])
                recv = d[starts]
                heard_p = price[s]  # (E', cols)
                heard_h = holder[s]
                top_p = np.maximum.reduceat(heard_p, starts, axis=0)  # (R, cols)
                group = np.repeat(np.arange(len(starts)), np.diff(np.r_[starts, len(s)]))
                top_h = np.maximum.reduceat(np.where(heard_p == top_p[group], heard_h, -1), starts,
                                            axis=0)
                own_p, own_h = price[recv], holder[recv]
                better = (top_p > own_p) | ((top_p == own_p) & (top_h > own_h))
                price[recv] = np.where(better, top_p, own_p)
                holder[recv] = np.where(better, top_h, own_h)
                updated[recv] = better.any(axis=1)
        if not quiet:
            break
    converged = quiet
    # Each AGV's own claim, then clashes between components resolved by (price, index).
    held = task >= 0
    held[held] = holder[agents[held], task[held]] == agents[held]
    claimed = np.where(held & (task < m), task, -1)
    task_of_agent = np.full(n, -1, dtype=np.int64)
    agent_of_task = np.full(m, -1, dtype=np.int64)
    mine = np.flatnonzero(claimed >= 0)
    if mine.size:
        bid = price[mine, claimed[mine]]
        order = np.lexsort((mine, bid))  # ascending: the last write per task wins
        agent_of_task[claimed[mine[order]]] = mine[order]
        winners = agent_of_task[agent_of_task >= 0]
        task_of_agent[winners] = np.flatnonzero(agent_of_task >= 0)
    prices = price[:, :m].max(axis=0) if m else np.zeros(0)
    return AuctionResult(task_of_agent=task_of_agent, agent_of_task=agent_of_task,
                         rounds=rounds, messages=messages, converged=converged,
                         claimed=claimed, component=component, prices=prices)


@dataclass(frozen=True)
class ComponentAuction:
    """The outcome of :func:`component_auction`."""

    task_of_agent: np.ndarray
    """(N,) int64: task of each AGV, -1 idle (conflict-free: each task heard by one component)."""
    home: np.ndarray
    """(M,) int64: the AGV each task was announced to (nearest its position)."""
    component: np.ndarray
    """(N,) int64: connected component of each AGV."""
    messages: int
    """Auction messages sent in all the components (one AGV's copy to one neighbour)."""
    rounds: int
    """Rounds of the longest component's auction."""
    converged: bool
    """Whether every component's auction went quiet."""


def component_auction(
    benefit: np.ndarray,
    positions: np.ndarray,
    task_positions: np.ndarray,
    comm_range: float,
    eps: float | None = None,
    max_rounds: int = 20_000,
) -> ComponentAuction:
    """A decentralized auction where each task is heard by one component of the graph.

    Each task is announced to the AGV nearest its position (straight line, ties to the lower
    index), which floods it through its connected component (AGVs at most ``comm_range``
    apart); the AGVs of each component then run :func:`auction` over the tasks announced to
    them. No two components hold the same task, so the plan is conflict-free without any
    central step.

    Parameters
    ----------
    benefit : array-like, shape (N, M)
        Finite real numbers: AGV i's gain for task j.
    positions : array-like, shape (N, 2)
    task_positions : array-like, shape (M, 2)
    comm_range : float
        > 0 (``inf``: one component).
    eps, max_rounds
        As :func:`auction`.

    Returns
    -------
    ComponentAuction

    Raises
    ------
    ValueError
        As :func:`auction`, and naming ``task_positions`` for a wrong shape or NaN.
    """
    b, pos, comm_range = _check(benefit, positions, comm_range, eps, max_rounds, None)
    n, m = b.shape
    tasks = np.asarray(task_positions)
    if tasks.dtype.kind not in "iuf" or tasks.shape != (m, 2) or \
            not np.isfinite(tasks.astype(np.float64)).all():
        raise ValueError(f"task_positions must be an ({m}, 2) array of finite real numbers "
                         f"(one row per benefit column), got {tasks.dtype} {tasks.shape}")
    tasks = tasks.astype(np.float64)
    if math.isinf(comm_range) or n == 1:
        component = np.zeros(n, dtype=np.int64)
    else:
        component = _components(n, *communication_graph(pos, comm_range))
    home = cKDTree(pos).query(tasks, k=1)[1].astype(np.int64) if m else np.zeros(0, np.int64)
    heard_by = component[home]
    task_of_agent = np.full(n, -1, dtype=np.int64)
    messages = rounds = 0
    converged = True
    for c in np.unique(heard_by):  # one auction per component that heard a task
        members = np.flatnonzero(component == c)
        heard = np.flatnonzero(heard_by == c)
        out = auction(b[np.ix_(members, heard)], pos[members], comm_range, eps=eps,
                      max_rounds=max_rounds)
        won = out.task_of_agent >= 0
        task_of_agent[members[won]] = heard[out.task_of_agent[won]]
        messages += out.messages
        rounds = max(rounds, out.rounds)
        converged &= out.converged
    return ComponentAuction(task_of_agent=task_of_agent, home=home, component=component,
                            messages=messages, rounds=rounds, converged=bool(converged))
