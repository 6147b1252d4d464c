"""The batched ORCA velocity QP of all AGVs (:class:`VelocityAvoidance`) and its output
(:class:`AvoidanceResult`)."""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any

import numpy as np

from allocator.avoidance import native
from allocator.avoidance.config import AvoidanceConfig
from allocator.avoidance.exact_qp import solve_qp_2d
from allocator.avoidance.least_violation import least_violation_2d
from allocator.avoidance.orca import build_rows
from allocator.avoidance.osqp_least_violation import LeastViolation
from allocator.avoidance.osqp_qp import BlockOSQP
from allocator.avoidance.rows import ConstraintRows

if TYPE_CHECKING:  # pragma: no cover
    from sim.world import World

__all__ = ["VelocityAvoidance", "AvoidanceResult"]


@dataclass
class AvoidanceResult:
    """Output of one avoidance step.

    Attributes
    ----------
    velocity : np.ndarray, shape (..., N, 2)
        The new velocities (zero for static AGVs, the given ones for committed AGVs).
    fell_back : np.ndarray of bool, shape (..., N)
        AGVs whose constraints conflicted; their velocity minimises the largest violation.
    violation : np.ndarray, shape (..., N)
        That largest (weighted) violation ``t`` (0 where the QP was feasible).
    status : str
        ``"solved"`` (exact solver) or OSQP's status of the main solve.
    """

    velocity: np.ndarray
    fell_back: np.ndarray
    violation: np.ndarray
    status: str

    @property
    def any_fell_back(self) -> bool:
        return bool(self.fell_back.any())



class VelocityAvoidance:
    """Batched ORCA velocity QP for all AGVs (exact vectorised solver, or OSQP).

    Parameters
    ----------
    world : World, optional
        Walls at its bounds and its shelves become constraints.
    config : AvoidanceConfig, optional
        Default :meth:`AvoidanceConfig.for_world` with a world, else ``AvoidanceConfig()``.
    **overrides
        Fields of :class:`AvoidanceConfig` to change.

    Examples
    --------
    Two AGVs heading at each other swerve instead of colliding:

    >>> import numpy as np
    >>> from allocator.avoidance import VelocityAvoidance
    >>> qp = VelocityAvoidance(radius=0.15)
    >>> pos = np.array([[-0.5, 0.0], [0.5, 0.0]])
    >>> vel = np.array([[1.0, 0.0], [-1.0, 0.0]])
    >>> out = qp.solve(pos, vel, preferred=vel)
    >>> bool(abs(out.velocity[0, 1]) > 0.1), out.fell_back.tolist()
    (True, [False, False])
    """

    def __init__(
        self, world: World | None = None, config: AvoidanceConfig | None = None,
        **overrides: Any,
    ) -> None:
        if config is None:
            config = AvoidanceConfig.for_world(world, **overrides) if world is not None \
                else AvoidanceConfig(**overrides)
        elif overrides:
            config = replace(config, **overrides)
        self.config = config
        self.world = world
        ang = 2 * np.pi * (np.arange(config.polygon_sides) + 0.5) / config.polygon_sides
        self._poly = np.stack([np.cos(ang), np.sin(ang)], axis=1)  # (P, 2)
        self._poly_cos = float(np.cos(np.pi / config.polygon_sides))
        self._fallback = LeastViolation()
        self.stats = {"solves": 0, "fallbacks": 0, "setup": 0}
        self._osqp = BlockOSQP(config, self._fallback, self.stats)

    # ------------------------------------------------------------------ rows
    def constraints(
        self,
        positions: np.ndarray,
        velocities: np.ndarray,
        preferred: np.ndarray,
        static: np.ndarray | None = None,
        points: np.ndarray | None = None,
        point_mask: np.ndarray | None = None,
        point_radius: float = 0.1,
        committed: np.ndarray | None = None,
        static_reference: np.ndarray | None = None,
    ) -> ConstraintRows:
        """Build every AGV's rows (:func:`~allocator.avoidance.orca.build_rows`); arguments as
        in :meth:`solve`.

        Returns
        -------
        ConstraintRows
            ``n = B * N`` AGVs (``B = 1`` for an ``(N, 2)`` scene).
        """
        pos, vel, pref, static, points, point_mask = self._check(
            positions, velocities, preferred, static, points, point_mask
        )
        fixed = self._mask(committed, pos.shape[:2], positions, "committed") & ~static
        ref = None
        if static_reference is not None:
            ref = np.asarray(static_reference, dtype=np.float64)
            ref = ref[None] if np.ndim(positions) == 2 and ref.ndim == 2 else ref
            if ref.shape != pos.shape:
                raise ValueError(f"static_reference must have the shape of positions "
                                 f"{np.shape(positions)}, got {np.shape(static_reference)}")
            if np.isinf(ref).any():
                raise ValueError("static_reference contains infinite values (NaN: unused)")
        return build_rows(self.config, self.world, pos, vel, pref, static, points, point_mask,
                          point_radius, fixed, ref)

    @staticmethod
    def _mask(mask: Any, shape: tuple[int, int], positions: Any, name: str) -> np.ndarray:
        """A (B, N) boolean mask from ``None`` (all False) or an (N,) / (B, N) array."""
        if mask is None:
            return np.zeros(shape, dtype=bool)
        m = np.asarray(mask, dtype=bool)
        single = np.ndim(positions) == 2
        m = m[None] if single and m.ndim == 1 else m
        if m.shape != shape:
            raise ValueError(f"{name} must have shape {shape[single:]}, got {m.shape[single:]}")
        return m

    def _check(
        self, positions: Any, velocities: Any, preferred: Any, static: Any, points: Any,
        point_mask: Any,
    ) -> tuple[np.ndarray, ...]:
        pos = np.asarray(positions, dtype=np.float64)
        single = pos.ndim == 2
        if single:
            pos = pos[None]
        if pos.ndim != 3 or pos.shape[-1] != 2:
            raise ValueError(f"positions must have shape (N, 2) or (B, N, 2), got {pos.shape}")
        B, N, _ = pos.shape
        out = [pos]
        for name, x in (("velocities", velocities), ("preferred", preferred)):
            arr = np.asarray(x, dtype=np.float64)
            arr = arr[None] if single else arr
            if arr.shape != pos.shape:
                raise ValueError(f"{name} must have the shape of positions {pos.shape[single:]}"
                                 f", got {arr.shape[single:]}")
            out.append(arr)
        for name, arr in zip(("positions", "velocities", "preferred"), out, strict=True):
            if not np.all(np.isfinite(arr)):
                raise ValueError(f"{name} contain NaN or infinite values")
        st = np.zeros((B, N), dtype=bool) if static is None else np.asarray(static, dtype=bool)
        st = st[None] if single and st.ndim == 1 else st
        if st.shape != (B, N):
            raise ValueError(f"static must have shape {(B, N)[single:]}, got {st.shape}")
        out.append(st)
        if points is None:
            out += [None, None]
        else:
            pts = np.asarray(points, dtype=np.float64)
            pts = pts[None] if single and pts.ndim == 2 else pts
            if pts.ndim != 3 or pts.shape[0] != B or pts.shape[2] != 2:
                raise ValueError(f"points must have shape (P, 2) or (B, P, 2), got {pts.shape}")
            m = np.ones((B, N, pts.shape[1]), dtype=bool) if point_mask is None else \
                np.asarray(point_mask, dtype=bool)
            m = m[None] if single and m.ndim == 2 else m
            if m.shape != (B, N, pts.shape[1]):
                raise ValueError(
                    f"point_mask must have shape {(B, N, pts.shape[1])[single:]}, got {m.shape}"
                )
            out += [pts, m]
        return tuple(out)

    # ------------------------------------------------------------------ solve
    def solve(
        self,
        positions: np.ndarray,
        velocities: np.ndarray,
        preferred: np.ndarray,
        static: np.ndarray | None = None,
        points: np.ndarray | None = None,
        point_mask: np.ndarray | None = None,
        point_radius: float = 0.1,
        committed: np.ndarray | None = None,
        static_reference: np.ndarray | None = None,
    ) -> AvoidanceResult:
        """New velocities for every AGV, as close to ``preferred`` as the constraints allow.

        Parameters
        ----------
        positions, velocities, preferred : np.ndarray, shape (N, 2) or (B, N, 2)
            B independent scenes of N AGVs (AGVs of different scenes never interact).
            ``positions`` are where the AGVs are when the new velocity takes effect.
        static : np.ndarray of bool, shape (N,) or (B, N), optional
            Parked AGVs: obstacles for the others, velocity 0 themselves.
        points : np.ndarray, shape (P, 2) or (B, P, 2), optional
            Points to keep ``point_radius + margin`` away from (e.g. other AGVs' tasks).
        point_mask : np.ndarray of bool, shape (N, P) or (B, N, P), optional
            Which AGV must avoid which point (default all).
        point_radius : float
            Radius of the forbidden points.
        committed : np.ndarray of bool, shape (N,) or (B, N), optional
            AGVs whose next velocity is already decided, given in ``velocities`` (e.g. ones
            that could not honour their reciprocal rows): they get no rows and keep that
            velocity, and their neighbours take the full responsibility against them (with
            the moving margin). Ignored where ``static``.
        static_reference : np.ndarray, shape (N, 2) or (B, N, 2), optional
            Per AGV, the velocity its rows against *static* neighbours are built from instead
            of its current velocity (NaN rows: the current velocity). ORCA linearises a
            neighbour's velocity obstacle at the boundary point nearest that velocity, so the
            half-plane keeps the AGV on that velocity's side of the obstacle; a controller
            that has chosen to pass a parked AGV on one side gives a velocity on that side
            (its preferred one), else an AGV still heading for the other leg is held on it.

        Returns
        -------
        AvoidanceResult
            ``velocity`` with the shape of ``positions``; ``fell_back`` marks AGVs whose
            constraints conflicted (their velocity least violates them).
        """
        rows = self.constraints(positions, velocities, preferred, static, points, point_mask,
                                point_radius, committed, static_reference)
        vel, fell, viol, status = self.solve_rows(rows)
        shape = np.shape(positions)
        if committed is not None:  # committed AGVs keep their given velocity
            keep = np.asarray(committed, dtype=bool) & (
                True if static is None else ~np.asarray(static, dtype=bool))
            vel = np.where(np.broadcast_to(keep, shape[:-1]).reshape(-1, 1),
                           np.asarray(velocities, dtype=np.float64).reshape(-1, 2), vel)
        return AvoidanceResult(
            vel.reshape(shape), fell.reshape(shape[:-1]), viol.reshape(shape[:-1]), status
        )

    def solve_rows(self, rows: ConstraintRows) -> tuple[np.ndarray, np.ndarray, np.ndarray, str]:
        """Solve built rows: ``(velocity (n, 2), fell_back (n,), violation (n,), status)``.

        With ``config.solver == "exact"`` (default) every AGV's QP is solved exactly by
        :func:`solve_qp_2d`; the AGVs whose rows conflict get the exact least-violation
        velocity of :func:`least_violation_2d` (both vectorised over the AGVs), or both by
        their C twin (:func:`~allocator.avoidance.native.solve_rows_native`, ``config.native``;
        the default wherever it builds).

        With ``"osqp"`` the problem (it separates per AGV) is solved as one block-diagonal OSQP
        problem, or several of ``config.chunk_size`` AGVs (each with its own warm-started
        solver): ADMM runs until its slowest block converges, and smaller problems stop sooner
        (:class:`~allocator.avoidance.osqp_qp.BlockOSQP`).
        """
        if self.config.solver == "exact":
            return self._solve_exact(rows)
        return self._osqp.solve_rows(rows)

    def _solve_exact(
        self, rows: ConstraintRows
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, str]:
        n = rows.A.shape[0]
        self.stats["solves"] += 1
        if self.config.native is not False and (self.config.native or native.available()):
            velocity, fell, violation = native.solve_rows_native(
                rows.A, rows.lower, rows.upper, rows.preferred, rows.active, rows.weight,
                self._fallback.regularization, self.config.feasibility_tol,
                self.config.fallback_tol,
            )
            self.stats["fallbacks"] += int(fell.sum())
            return velocity, fell, violation, "solved"
        v, ok = solve_qp_2d(rows.A, rows.lower, rows.upper, rows.preferred,
                            self.config.feasibility_tol)
        velocity = np.where(rows.active[:, None], v, 0.0)
        fell = np.zeros(n, dtype=bool)
        violation = np.zeros(n)
        bad = ~ok & rows.active
        if bad.any():
            idx = np.flatnonzero(bad)
            v, t = least_violation_2d(
                rows.A[idx], rows.lower[idx], rows.upper[idx], rows.preferred[idx],
                rows.weight, self._fallback.regularization,
                self.config.feasibility_tol,
            )
            velocity[idx] = v
            fell[idx] = t > self.config.fallback_tol
            violation[idx] = np.where(fell[idx], t, 0.0)
            self.stats["fallbacks"] += int(fell.sum())
        return velocity, fell, violation, "solved"

