"""The simulator's step rules in plain numpy, one environment at a time, in float64.

Written from the rules of ``DESIGN.md`` and ``docs/simulator.md`` (not from the torch code),
as an independent reference for the batched step:

1. force = clip(action, -1, 1) x sensitivity + MPE's soft contact force from every other disc;
2. MPE's integration, idle AGVs only: ``p += v dt``, then ``v = v (1 - damping) + f / m dt``;
3. shelves push an overlapping disc out along the shortest way and cancel its velocity into
   them; walls clamp the centre to ``[lo + r, hi - r]`` and zero the velocity into them;
4. claims, one round: each open task within the capture radius of an idle AGV goes to its
   nearest such AGV, an AGV that wins several takes its nearest, and parks (velocity zero);
5. the step counter, ``done`` (every task claimed or the step limit);
6. overlapping discs, R_t, the MiniDist and Greedy terms;
7. observations: own velocity and position, the K nearest open tasks and K nearest other AGVs
   within the sensing range (sorted, ties to the lower index, zero-padded with a mask bit),
   whether the AGV holds a task;
8. the IPF reward (``docs/ipf.md``): each AGV's own field, solved as the discrete Dirichlet
   problem it is (a sparse linear solve per AGV), at its own cell.

A finished environment is frozen: nothing moves and every reward is zero.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sparse
from scipy.sparse.linalg import spsolve


@dataclass
class Rules:
    """The constants one environment's step reads."""

    dt: float
    damping: float
    mass: float
    sensitivity: float
    contact_force: float
    contact_margin: float
    radius: float
    capture: float
    bounds: tuple[float, float, float, float]
    shelves: np.ndarray  # (K, 4) xmin, ymin, xmax, ymax
    walls: bool
    sensing_range: float
    k_tasks: int
    k_agents: int
    max_steps: int
    floor_shelves: np.ndarray  # (K, 4) the same shelves in float64, as the IPF grid reads them

    @classmethod
    def of(cls, scenario) -> Rules:
        w, ph = scenario.world, scenario.world.physics
        return cls(ph.dt, ph.damping, ph.mass, ph.sensitivity, ph.contact_force,
                   ph.contact_margin, w.agent_radius, w.capture_radius, tuple(w.bounds),
                   _float32(np.asarray(w.obstacles, dtype=np.float64).reshape(-1, 4)), w.walls,
                   float(scenario.sensing_range), scenario.k_tasks, scenario.k_agents,
                   scenario.max_steps, np.asarray(w.obstacles, dtype=np.float64).reshape(-1, 4))


def _float32(x: np.ndarray | float) -> np.ndarray:
    """Geometry as the simulator stores it: the nearest float32 numbers, in float64.

    An AGV at rest against a wall or shelf sits exactly on the float32 limit; compared with
    the float64 limit, it would count as inside and have its velocity cancelled.
    """
    return np.asarray(x, dtype=np.float32).astype(np.float64)


def contact_forces(rules: Rules, pos: np.ndarray) -> np.ndarray:
    """MPE's soft contact: ``c * k * log(1 + exp((2r - d) / k)) * (p_i - p_j) / d``, (N, 2)."""
    n = len(pos)
    force = np.zeros((n, 2))
    k = rules.contact_margin
    for i in range(n):
        for j in range(n):
            if i == j:
                continue
            delta = pos[i] - pos[j]
            dist = float(np.hypot(*delta))
            penetration = k * np.logaddexp(0.0, (2 * rules.radius - dist) / k)
            force[i] += rules.contact_force * penetration * delta / max(dist, 1e-3)
    return force


def shelf_collision(rules: Rules, p: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Push one disc (centre ``p``, velocity ``v``) out of every shelf it overlaps."""
    push, cancel = np.zeros(2), np.zeros(2)
    faces = np.array([[-1.0, 0.0], [0.0, -1.0], [1.0, 0.0], [0.0, 1.0]])
    for xmin, ymin, xmax, ymax in rules.shelves:
        closest = np.array([min(max(p[0], xmin), xmax), min(max(p[1], ymin), ymax)])
        gap = p - closest
        dist = float(np.hypot(*gap))
        if dist <= 1e-9:  # centre inside: leave through the nearest face
            to_face = [p[0] - xmin, p[1] - ymin, xmax - p[0], ymax - p[1]]
            face = int(np.argmin(to_face))
            normal, depth = faces[face], to_face[face] + rules.radius
        else:
            normal, depth = gap / dist, rules.radius - dist
        if depth > 0:
            push += normal * depth
            cancel += normal * min(float(v @ normal), 0.0)
    return p + push, v - cancel


def wall_collision(rules: Rules, p: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    xmin, ymin, xmax, ymax = rules.bounds
    lo = _float32(np.array([xmin, ymin]) + rules.radius)
    hi = _float32(np.array([xmax, ymax]) - rules.radius)
    v = v.copy()
    for c in range(2):
        if (p[c] < lo[c] and v[c] < 0) or (p[c] > hi[c] and v[c] > 0):
            v[c] = 0.0
    return np.clip(p, lo, hi), v


def nearest_slots(rows: list[np.ndarray], dist: np.ndarray, k: int) -> np.ndarray:
    """The k nearest visible entries (finite ``dist``), sorted, ties to the lower index, each
    ``row + [1]``; missing slots are zeros."""
    width = (len(rows[0]) if rows else 0) + 1
    out = np.zeros((k, width))
    order = sorted((d, j) for j, d in enumerate(dist) if np.isfinite(d))
    for slot, (_, j) in enumerate(order[:k]):
        out[slot, :-1] = rows[j]
        out[slot, -1] = 1.0
    return out.reshape(-1)


def observe(rules: Rules, s: dict[str, np.ndarray]) -> np.ndarray:
    """(N, O) observations of one environment's state ``s``."""
    pos, vel, tasks = s["agent_pos"], s["agent_vel"], s["task_pos"]
    n = len(pos)
    obs = []
    for i in range(n):
        parts = [vel[i], pos[i]]
        if rules.k_tasks:
            rel = [tasks[j] - pos[i] for j in range(len(tasks))]
            d = np.array([np.hypot(*r) for r in rel])
            d[s["task_claimed"] | (d > rules.sensing_range)] = np.inf
            parts.append(nearest_slots(rel, d, rules.k_tasks))
        if rules.k_agents:
            rows = [np.concatenate([pos[j] - pos[i], vel[j]]) for j in range(n)]
            d = np.array([np.hypot(*(pos[j] - pos[i])) for j in range(n)])
            d[i] = np.inf
            d[d > rules.sensing_range] = np.inf
            parts.append(nearest_slots(rows, d, rules.k_agents))
        parts.append([1.0 if s["agent_task"][i] >= 0 else 0.0])
        obs.append(np.concatenate(parts))
    return np.array(obs)


def step(rules: Rules, s: dict[str, np.ndarray], action: np.ndarray) -> dict:
    """One step of one environment from state ``s`` (float64 arrays) with actions (N, 2).

    Returns
    -------
    dict
        The new state (``agent_pos``, ``agent_vel``, ``task_claimed``, ``agent_task``,
        ``steps``, ``done``), ``obs`` (N, O), ``claimed_now`` (M,), ``collision_pairs``,
        ``collisions_per_agent`` (N,), ``team_reward`` and the reward terms
        ``minidist`` {distance, collision} and ``greedy`` {progress, collision}, each (N,).
    """
    pos, vel = s["agent_pos"].copy(), s["agent_vel"].copy()
    tasks, claimed, held = s["task_pos"], s["task_claimed"].copy(), s["agent_task"].copy()
    n, m = len(pos), len(tasks)
    active = not bool(s["done"])
    claimed_now = np.zeros(m, dtype=bool)
    if active:
        force = np.clip(action, -1.0, 1.0) * rules.sensitivity
        if rules.contact_force > 0 and n > 1:
            force = force + contact_forces(rules, pos)
        for i in range(n):
            if held[i] >= 0:
                continue  # parked: neither moved nor pushed
            p = pos[i] + vel[i] * rules.dt
            v = vel[i] * (1.0 - rules.damping) + force[i] / rules.mass * rules.dt
            if len(rules.shelves):
                p, v = shelf_collision(rules, p, v)
            if rules.walls:
                p, v = wall_collision(rules, p, v)
            pos[i], vel[i] = p, v
        dist = np.linalg.norm(pos[:, None] - tasks[None], axis=-1)  # (N, M)
        eligible = (dist <= rules.capture) & (held < 0)[:, None] & ~claimed[None]
        winner = {}
        for j in range(m):
            candidates = [i for i in range(n) if eligible[i, j]]
            if candidates:
                winner[j] = min(candidates, key=lambda i: (dist[i, j], i))
        for i in range(n):
            won = [j for j, w in winner.items() if w == i]
            if won:
                j = min(won, key=lambda j: (dist[i, j], j))
                held[i], claimed[j], claimed_now[j] = j, True, True
                vel[i] = 0.0
    steps = s["steps"] + int(active)
    done = bool(s["done"]) or bool(claimed.all()) or steps >= rules.max_steps
    new = {"agent_pos": pos, "agent_vel": vel, "task_pos": tasks, "task_claimed": claimed,
           "agent_task": held, "steps": steps, "done": done}

    dist = np.linalg.norm(pos[:, None] - tasks[None], axis=-1)
    gaps = np.linalg.norm(pos[:, None] - pos[None], axis=-1)
    overlap = (gaps < 2 * rules.radius) & ~np.eye(n, dtype=bool) & active
    pairs = float(np.triu(overlap, 1).sum())
    per_agent = overlap.sum(axis=1).astype(np.float64)
    team = -(dist.min(axis=0).sum() + pairs) if active else 0.0
    zeros = np.zeros(n)
    minidist = {"distance": np.full(n, team + pairs) if active else zeros,
                "collision": np.full(n, -pairs)}
    progress = zeros.copy()
    if active and not s["task_claimed"].all():
        before = np.linalg.norm(s["agent_pos"][:, None] - tasks[None], axis=-1)
        before[:, s["task_claimed"]] = np.inf
        for i in range(n):
            if s["agent_task"][i] < 0:
                target = int(np.argmin(before[i]))
                progress[i] = before[i, target] - dist[i, target]
    greedy = {"progress": progress, "collision": -per_agent}
    return {**new, "obs": observe(rules, new), "claimed_now": claimed_now,
            "collision_pairs": pairs, "collisions_per_agent": per_agent, "team_reward": team,
            "minidist": minidist, "greedy": greedy}


IPF_RESOLUTION, IPF_TASK, IPF_AGENT = 0.05, 5.0, -3.0
"""The paper's grid cell size and source values."""


def _grid(rules: Rules) -> tuple[int, int, float, float, np.ndarray]:
    """``H, W, dx, dy`` and the fixed cells (H, W): the boundary ring and every cell whose
    centre lies in a shelf, edges included."""
    xmin, ymin, xmax, ymax = rules.bounds
    W = int(round((xmax - xmin) / IPF_RESOLUTION))
    H = int(round((ymax - ymin) / IPF_RESOLUTION))
    dx, dy = (xmax - xmin) / W, (ymax - ymin) / H
    fixed = np.zeros((H, W), dtype=bool)
    fixed[[0, -1], :] = True
    fixed[:, [0, -1]] = True
    cy = (ymin + (np.arange(H) + 0.5) * dy)[:, None]  # cell centres
    cx = (xmin + (np.arange(W) + 0.5) * dx)[None, :]
    for x0, y0, x1, y1 in rules.floor_shelves:
        fixed |= (x0 <= cx) & (cx <= x1) & (y0 <= cy) & (cy <= y1)
    return H, W, dx, dy, fixed


def _cell(rules: Rules, point: np.ndarray, grid: tuple) -> tuple[int, int]:
    H, W, dx, dy, _ = grid
    col = min(max(int(np.floor((point[0] - rules.bounds[0]) / dx)), 0), W - 1)
    row = min(max(int(np.floor((point[1] - rules.bounds[1]) / dy)), 0), H - 1)
    return row, col


@functools.cache
def _adjacency(H: int, W: int) -> sparse.csr_matrix:
    """The 4-neighbour adjacency of an H x W grid of cells (row-major), (H W, H W)."""
    def path(n: int) -> sparse.spmatrix:
        return sparse.diags([np.ones(n - 1), np.ones(n - 1)], [-1, 1])

    return (sparse.kron(sparse.identity(H), path(W)) + sparse.kron(path(H), sparse.identity(W))
            ).tocsr()


def harmonic_field(fixed: np.ndarray, values: np.ndarray) -> np.ndarray:
    """The field equal to ``values`` on the ``fixed`` cells (H, W) and, on every other cell,
    the mean of its four neighbours: the discrete Dirichlet problem, one sparse solve
    ``(4 I - A_FF) phi_F = A_FX values_X``."""
    H, W = fixed.shape
    adjacency = _adjacency(H, W)
    free = np.flatnonzero(~fixed.ravel())
    held = np.flatnonzero(fixed.ravel())
    a_ff = adjacency[free][:, free]
    system = (4.0 * sparse.identity(len(free)) - a_ff).tocsc()
    rhs = adjacency[free][:, held] @ values.ravel()[held]
    field = values.astype(np.float64).copy()
    field.ravel()[free] = spsolve(system, rhs)
    return field


def ipf_terms(rules: Rules, new: dict[str, np.ndarray], active: bool) -> dict[str, np.ndarray]:
    """The IPF reward's terms (N,) of one environment, from its state ``new`` after the step
    (``docs/ipf.md``); ``active``: whether it was running during the step.

    ``ipf``: AGV i's own field at its own cell (sources: open tasks +5, the other AGVs -3,
    an AGV winning a cell it shares with a task, sources on fixed cells ignored; AGV i reading
    the value of a source on its own cell); a parked AGV gets its task's +5. ``goal``:
    -(sum over tasks of the distance to the nearest AGV). ``collision``: -1 for an AGV whose
    disc overlaps another's.
    """
    n = len(new["agent_pos"])
    zeros = np.zeros(n)
    if not active:
        return {"ipf": zeros, "goal": zeros, "collision": zeros.copy()}
    grid = _grid(rules)
    fixed = grid[4]
    agent_cells = [_cell(rules, p, grid) for p in new["agent_pos"]]
    task_cells = [_cell(rules, t, grid) for j, t in enumerate(new["task_pos"])
                  if not new["task_claimed"][j]]
    ipf = np.zeros(n)
    for i in range(n):
        if new["agent_task"][i] >= 0:
            ipf[i] = IPF_TASK
            continue
        sources: dict[tuple[int, int], float] = {}
        for cell in task_cells:
            sources[cell] = IPF_TASK
        for k, cell in enumerate(agent_cells):
            if k != i:
                sources[cell] = IPF_AGENT  # an AGV wins a cell it shares with a task
        own = agent_cells[i]
        if fixed[own]:
            continue  # a fixed cell reads 0
        if own in sources:
            ipf[i] = sources[own]
            continue
        values = np.zeros(fixed.shape)
        is_fixed = fixed.copy()
        for cell, value in sources.items():
            if not fixed[cell]:  # a source on a fixed cell is ignored: 0 wins
                values[cell] = value
                is_fixed[cell] = True
        ipf[i] = harmonic_field(is_fixed, values)[own]
    pos, tasks = new["agent_pos"], new["task_pos"]
    goal = -np.linalg.norm(pos[:, None] - tasks[None], axis=-1).min(axis=0).sum()
    gaps = np.linalg.norm(pos[:, None] - pos[None], axis=-1)
    gaps[np.eye(n, dtype=bool)] = np.inf
    overlaps = (gaps < 2 * rules.radius).any(axis=1)
    return {"ipf": ipf, "goal": np.full(n, goal), "collision": -overlaps.astype(np.float64)}
