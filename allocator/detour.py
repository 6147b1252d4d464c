"""Detours round parked AGVs for intentions that drive straight at a task (episodic scenes).

In an episode an AGV that reaches its task parks on it for good, and a parked AGV is an
obstacle that never moves. A policy that steers straight at its task (the paper's actors, the
entity policies, the assignment rule of ``benchmarks/local_information.py``) pushes into a
parked AGV that stands on that line; the safety shield then stops it there, step after step,
and the last tasks of a crowded episode wait until the step limit (issue 17's diagnosis: the
AGVs left idle at the end are wedged against parked ones). :class:`ParkedDetour` turns such an
intention round the obstacle:

1. **The goal is inferred** from the intended velocity: among the scene's open tasks, the one
   within ``cone`` (cosine) of the heading that scores best on ``cos - distance_weight *
   distance`` (the task the policy points at, the nearer one where two line up). An AGV that
   intends to stand still (speed below ``min_speed``) or points at no open task keeps its
   intention.
2. **Blocked?** The straight segment from the AGV to that goal passes within ``2 r`` of a
   parked AGV's centre.
3. **Detour:** the intended velocity turns toward the next waypoint of a shortest path
   round the parked AGVs (:class:`sim.floor_paths.FloorWaypoints` on the scene's world; one
   planner per scene and set of parked AGVs, built when first needed and kept while that set
   stands), at ``speed``.

Two models of the parked AGVs (``model``):

- ``"squares"`` (the first version, the default until 2026-12-07): every parked AGV a square
  shelf of side
  ``2 r`` on the floor's grid (cells of ``r / 2``); blocked means within ``2 r``. Squares
  close diagonal gaps that discs leave open (two parked AGVs 0.72 apart on a diagonal leave
  no path between them, where the shield passes at 0.62), and the shield's margins close
  gaps the squares leave open (a straight line 0.303 from a parked centre counts as free,
  and the shield stops the AGV there). Where the goal cannot be reached on the grid the
  intention is kept, and the AGV wedges.
- ``"discs"`` (the default): every parked AGV a disc that keeps centres ``2 r + clearance`` away
  (``clearance`` 0.011 by default, a hair above the QP's static margin of 0.01, so the
  planner's gaps are the shield's), on a grid of ``r / 6`` cells (0.025 at ``r`` = 0.15) so
  that gaps a few hundredths wider than that are found; blocked means within ``2 r +
  clearance``. The goal is also kept from step to step while the AGV is turned: an
  intention that points at no open task (the detour's own momentum against the policy's
  push back toward the straight line) keeps the last goal instead of dropping the detour,
  which otherwise flips on and off every other step.

The detour changes preferred velocities only; the QP and the braking filter after it certify
whatever it gives (``docs/safety.md``), so safety does not depend on it. It needs the episodic
env's state (task positions, claims, the AGVs' tasks): a shield's view of the scene, which the
policy behind it does not read. Lifelong floors have paths round their shelves already
(:class:`allocator.traffic.SafeDriver`, the lifelong policies' waypoints) and refuse it.
"""

from __future__ import annotations

import dataclasses
import numbers
from typing import Any

import numpy as np
import torch

from sim.floor_paths import FloorWaypoints

__all__ = ["DEFAULT_MODEL", "DETOUR_MODELS", "ParkedDetour", "blocked_segments", "detour_model"]

DETOUR_MODELS = ("squares", "discs")
"""How :class:`ParkedDetour` can see parked AGVs (see ``model``)."""
DEFAULT_MODEL = "discs"
"""The model of ``detour=True`` and of a bare :class:`ParkedDetour` (``"squares"`` before
2026-12-07: every table made then with ``detour=True`` used squares)."""


def blocked_segments(start: np.ndarray, end: np.ndarray, centres: np.ndarray,
                     radius: float, mask: np.ndarray | None = None) -> np.ndarray:
    """Whether each segment passes within ``radius`` of any (unmasked) centre.

    Parameters
    ----------
    start, end : np.ndarray, shape (B, A, 2)
        Segments, batched over scenes.
    centres : np.ndarray, shape (B, C, 2)
        Obstacle centres.
    radius : float
    mask : np.ndarray of bool, shape (B, C), optional
        Which centres count (default all).

    Returns
    -------
    np.ndarray of bool, shape (B, A)
    """
    d = end - start
    length2 = np.maximum((d * d).sum(-1), 1e-12)                               # (B, A)
    t = ((centres[:, None] - start[:, :, None]) * d[:, :, None]).sum(-1) / length2[..., None]
    nearest = start[:, :, None] + np.clip(t, 0.0, 1.0)[..., None] * d[:, :, None]
    near = np.linalg.norm(nearest - centres[:, None], axis=-1) < radius           # (B, A, C)
    if mask is not None:
        near &= mask[:, None, :]
    return near.any(-1)


def detour_model(detour: Any) -> str | None:
    """The model a ``detour`` argument asks for: None (False: no detours), ``"discs"``
    (True: the default model) or the model named (one of :data:`DETOUR_MODELS`).

    Raises
    ------
    ValueError
        For anything else (the message names the valid values).
    """
    if isinstance(detour, (bool, np.bool_)):
        return DEFAULT_MODEL if detour else None
    if isinstance(detour, str) and detour in DETOUR_MODELS:
        return detour
    raise ValueError(f"detour must be True, False or one of "
                     f"{', '.join(map(repr, DETOUR_MODELS))}, got {detour!r}")


def _fraction(name: str, value: Any, low: float, high: float) -> float:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Real) \
            or not np.isfinite(value) or not low <= value <= high:
        raise ValueError(f"{name} must be a number in [{low:g}, {high:g}], got {value!r}")
    return float(value)


class ParkedDetour:
    """Turn idle AGVs' intended velocities round the parked AGVs that block their task.

    Parameters
    ----------
    cone : float
        Least cosine between the intended velocity and the direction of a task for that task
        to count as the goal (in [-1, 1]; default 0.7, about 45 degrees).
    distance_weight : float
        Per unit of distance, what a task loses against one that lines up better (>= 0;
        default 0.05).
    min_speed : float
        Intended speeds below this (units/s) are left alone: the AGV means to stop (>= 0;
        default 0.05).
    lookahead : int, optional
        Path cells from an AGV to its waypoint (>= 1; default 6 for ``"squares"``,
        :class:`FloorWaypoints`'s, and 18 for ``"discs"``, the same 0.45 units on its finer
        grid).
    speed : float or None
        Speed of a detour (> 0; default 1.5 units/s, three quarters of the terminal speed of
        a unit action: a policy that crawls toward a blocked task is sped up, one that rushes
        it slowed down). None: the intended speed. Either way no faster than reaches the
        waypoint in one step. (On 50 episodes of 50v50, seed 0, a taught entity policy behind
        the shield: 99.6% response in 51.6 steps at 1.5 against 99.3% in 56.4 at the intended
        speed capped at 1.5.)
    model : str
        ``"discs"`` (default, :data:`DEFAULT_MODEL`) or ``"squares"``: how the planner sees
        parked AGVs (above).
    clearance : float, optional
        ``"discs"`` only: the gap kept beyond ``2 r`` between an AGV's centre and a parked
        one's (in [0, 1]; default 0.011).

    Attributes
    ----------
    redirected : int
        AGV-steps whose intention was turned since :meth:`reset`.

    Raises
    ------
    ValueError
        For a parameter outside its range (the message names it).
    """

    def __init__(self, cone: float = 0.7, distance_weight: float = 0.05,
                 min_speed: float = 0.05, lookahead: int | None = None,
                 speed: float | None = 1.5, model: str = DEFAULT_MODEL,
                 clearance: float | None = None) -> None:
        if model not in DETOUR_MODELS:
            raise ValueError(f"model must be one of {', '.join(map(repr, DETOUR_MODELS))}, "
                             f"got {model!r}")
        self.model = model
        if clearance is not None and model != "discs":
            raise ValueError("clearance is the discs model's gap: it needs model='discs'")
        self.clearance = 0.0 if model == "squares" else _fraction(
            "clearance", 0.011 if clearance is None else clearance, 0.0, 1.0)
        if lookahead is None:
            lookahead = 6 if model == "squares" else 18
        self.cone = _fraction("cone", cone, -1.0, 1.0)
        self.distance_weight = _fraction("distance_weight", distance_weight, 0.0, np.inf)
        self.min_speed = _fraction("min_speed", min_speed, 0.0, np.inf)
        if isinstance(lookahead, (bool, np.bool_)) or not isinstance(lookahead, numbers.Integral) \
                or lookahead < 1:
            raise ValueError(f"lookahead must be an integer >= 1, got {lookahead!r}")
        self.lookahead = int(lookahead)
        self.speed = None if speed is None else _fraction("speed", speed, 0.0, np.inf)
        if self.speed == 0.0:
            raise ValueError("speed must be > 0 (or None: the intended speed)")
        self.env: Any = None
        self.redirected = 0
        self._planners: dict[int, tuple[bytes, FloorWaypoints]] = {}
        self._goal = np.zeros((0, 0), dtype=np.int64)

    def reset(self, env: Any) -> None:
        """Bind to an episodic env.

        Raises
        ------
        ValueError
            For a lifelong env (its floor has paths round the shelves already) or an env
            without task positions, claims and the AGVs' tasks.
        """
        if getattr(env, "lifelong", False) or getattr(env, "fleet", None) is not None:
            raise ValueError("detours round parked AGVs are for episodic scenes; a lifelong "
                             "floor's AGVs never park (its drivers plan round the shelves)")
        for attr in ("task_pos", "task_claimed", "agent_task", "agent_pos", "world"):
            if not hasattr(env, attr):
                raise ValueError(f"ParkedDetour needs an episodic env with {attr!r}")
        self.env = env
        self.dt = float(env.world.physics.dt)
        self.redirected = 0
        self._planners = {}
        self._goal = np.full((env.num_envs, env.num_agents), -1, dtype=np.int64)

    def _planner(self, b: int, parked_pos: np.ndarray) -> FloorWaypoints:
        """The shortest-path planner of scene ``b`` round its parked AGVs (kept per set)."""
        key = np.ascontiguousarray(parked_pos).tobytes()
        kept = self._planners.get(b)
        if kept is not None and kept[0] == key:
            return kept[1]
        world = self.env.world
        r = world.agent_radius
        bare = dict(pickups=np.zeros((0, 2)), stations=np.zeros((0, 2)), depot=np.zeros((0, 4)))
        if self.model == "discs":
            planner = FloorWaypoints(dataclasses.replace(world, **bare), resolution=r / 6,
                                     lookahead=self.lookahead, discs=parked_pos,
                                     disc_clearance=2 * r + self.clearance)
        else:
            squares = np.concatenate([parked_pos - r, parked_pos + r], axis=1)
            floor = dataclasses.replace(
                world, obstacles=np.concatenate([np.asarray(world.obstacles).reshape(-1, 4),
                                                 squares]), **bare)
            planner = FloorWaypoints(floor, lookahead=self.lookahead)
        self._planners[b] = (key, planner)
        return planner

    def redirect(self, intended: np.ndarray, movable: np.ndarray) -> tuple[np.ndarray,
                                                                           np.ndarray]:
        """The intended velocities with detours round parked AGVs.

        Parameters
        ----------
        intended : np.ndarray, shape (B, N, 2)
            Velocities the AGVs intend for the next step.
        movable : np.ndarray of bool, shape (B, N)
            The AGVs the simulator moves next (idle, in running scenes).

        Returns
        -------
        velocity : np.ndarray, shape (B, N, 2)
            ``intended`` where nothing is in the way; elsewhere toward the waypoint round the
            parked AGVs at ``speed`` (capped at the speed that reaches the waypoint in one
            step).
        turned : np.ndarray of bool, shape (B, N)
            The AGVs turned.

        Raises
        ------
        ValueError
            Before :meth:`reset`.
        """
        env = self.env
        if env is None:
            raise ValueError("ParkedDetour.redirect needs reset(env) first")
        out = np.array(intended, dtype=np.float64, copy=True)
        turned = np.zeros(movable.shape, dtype=bool)
        pos = env.agent_pos.detach().cpu().double().numpy()
        parked = env.agent_task.detach().cpu().numpy() >= 0
        open_ = ~env.task_claimed.detach().cpu().numpy()
        speed = np.linalg.norm(out, axis=-1)
        ask = movable & (speed > self.min_speed) & parked.any(1, keepdims=True) \
            & open_.any(1, keepdims=True)
        if not ask.any():
            self._goal[:] = -1
            return out, turned
        tasks = env.task_pos.detach().cpu().double().numpy()
        rel = tasks[:, None] - pos[:, :, None]                                    # (B, N, M, 2)
        dist = np.linalg.norm(rel, axis=-1)
        cos = (rel * out[:, :, None]).sum(-1) / np.maximum(dist * speed[..., None], 1e-12)
        score = np.where((cos >= self.cone) & open_[:, None], cos - self.distance_weight * dist,
                         -np.inf)
        pick = score.argmax(-1)
        found = np.isfinite(np.take_along_axis(score, pick[..., None], -1)[..., 0])
        if self.model == "discs":  # an AGV turned last step keeps its goal while still open
            kept = self._goal >= 0
            kept &= ~found & np.take_along_axis(open_, np.maximum(self._goal, 0), 1)
            pick, found = np.where(kept, self._goal, pick), found | kept
        ask &= found
        goal = np.take_along_axis(tasks, pick[..., None].repeat(2, -1), 1)         # (B, N, 2)
        ask &= blocked_segments(pos, goal, pos, 2.0 * env.world.agent_radius + self.clearance,
                                parked)
        for b in np.flatnonzero(ask.any(1)):
            agents = np.flatnonzero(ask[b])
            planner = self._planner(int(b), pos[b, parked[b]])
            waypoint, _ = planner.query(torch.as_tensor(pos[b, agents]),
                                        torch.as_tensor(goal[b, agents]))
            heading = waypoint.double().numpy() - pos[b, agents]
            norm = np.linalg.norm(heading, axis=-1, keepdims=True)
            ok = norm[:, 0] > 1e-9
            go = speed[b, agents[ok], None] if self.speed is None \
                else np.full((len(agents[ok]), 1), self.speed)
            go = np.minimum(go, norm[ok] / self.dt)  # arrive at the waypoint, not past it
            out[b, agents[ok]] = heading[ok] / norm[ok] * go
            turned[b, agents[ok]] = True
        self.redirected += int(turned.sum())
        self._goal = np.where(turned, pick, -1)
        return out, turned
