"""ORCA-style collision avoidance as one batched velocity QP.

Every AGV i picks its next velocity v_i as close as possible to its preferred velocity,
subject to linear constraints ``l <= a . v_i <= u``:

- the reciprocal ORCA half-planes of its nearest neighbours (RVO2's construction, each AGV
  taking half the responsibility; parked AGVs are static and the mover takes all of it, and so
  are "committed" AGVs, whose next velocity is already decided and is given),
- half-planes keeping it off points it must not touch (e.g. other AGVs' tasks, which it would
  otherwise claim in passing), the walls and the nearest shelves,
- its speed limit, as a regular polygon, and (optionally) the velocities its acceleration
  limit can reach in one step: ``(1 - damping) v + gain [-1, 1]^2``.

All AGVs of all scenes are solved at once. The default solver (``solver="exact"``,
:func:`solve_qp_2d`) is exact and vectorised over the AGVs: the optimum of a 2-D QP is the
preferred velocity, its projection onto one violated line, or a vertex where a violated line
meets another line, so the candidates of all AGVs are enumerated and checked as flat arrays.
``solver="osqp"`` solves one sparse block-diagonal OSQP problem whose sparsity pattern is fixed
(every AGV has the same number of rows, unused ones padded with ``a = 0`` and infinite bounds),
so consecutive steps only update the data and warm start.

When an AGV's constraints conflict, the QP of that AGV is infeasible. It then gets the "3-D"
program of ORCA: the velocity that minimises the largest (weighted) violation ``t`` of the soft
rows (plus a tiny pull towards the preferred velocity) while the speed and acceleration limits
stay hard; exact and vectorised as well (:func:`least_violation_2d`), or with OSQP
(:class:`LeastViolation`, AGVs found from OSQP's infeasibility certificate).
:class:`AvoidanceResult` reports who fell back.

The same QP is written in cvxpy in :func:`solve_reference` (readable, slow); the tests compare
the solvers. Build the rows (:meth:`VelocityAvoidance.constraints`) in one step and solve them
in another (:meth:`VelocityAvoidance.solve_rows`), as Python-RVO2 does.

Modules, one per part:

- :mod:`~allocator.avoidance.config`: :class:`AvoidanceConfig`;
- :mod:`~allocator.avoidance.rows`: :class:`ConstraintRows`, the row kinds and the fallback
  weights (:func:`fallback_weights`, built once with the rows as ``ConstraintRows.weight``);
- :mod:`~allocator.avoidance.orca`: the ORCA half-planes and every AGV's rows;
- :mod:`~allocator.avoidance.exact_qp`: the exact 2-D QP, :func:`solve_qp_2d`;
- :mod:`~allocator.avoidance.least_violation`: the exact least-violation program;
- :mod:`~allocator.avoidance.osqp_qp` and :mod:`~allocator.avoidance.osqp_least_violation`:
  the two OSQP back ends (:class:`BlockOSQP`, :class:`LeastViolation`);
- :mod:`~allocator.avoidance.reference`: the cvxpy reference;
- :mod:`~allocator.avoidance.velocity_avoidance`: :class:`VelocityAvoidance`, which builds
  the rows and dispatches to a solver;
- :mod:`~allocator.avoidance.native`: the C twin of the exact solvers (``qp2d.c``, built on
  first use; the default where a C compiler is found);
- :mod:`~allocator.avoidance.braking`: the braking shield (the safety guarantee);
- :mod:`~allocator.avoidance.liveness`: the deadlock rules; :mod:`~allocator.avoidance.detour`:
  grid paths round standing AGVs as discs.
- :mod:`~allocator.avoidance.ordering`: plans whose AGVs do not park on each other's way
  (the episodic controller's untangling of the allocator's plan).

OSQP and cvxpy are imported on first use only.
"""

from __future__ import annotations

from allocator.avoidance.config import AvoidanceConfig
from allocator.avoidance.exact_qp import solve_qp_2d
from allocator.avoidance.least_violation import least_violation_2d
from allocator.avoidance.orca import orca_halfplanes
from allocator.avoidance.osqp_least_violation import LeastViolation
from allocator.avoidance.osqp_qp import BlockOSQP
from allocator.avoidance.reference import solve_reference
from allocator.avoidance.rows import (
    AGENT,
    FALLBACK_WEIGHT,
    HARD,
    PAD,
    POINT,
    WALL,
    ConstraintRows,
    fallback_weights,
)
from allocator.avoidance.velocity_avoidance import AvoidanceResult, VelocityAvoidance

__all__ = [
    "AvoidanceConfig",
    "AvoidanceResult",
    "ConstraintRows",
    "VelocityAvoidance",
    "BlockOSQP",
    "orca_halfplanes",
    "solve_reference",
    "solve_qp_2d",
    "least_violation_2d",
    "LeastViolation",
    "fallback_weights",
    "FALLBACK_WEIGHT",
    "HARD",
    "AGENT",
    "WALL",
    "POINT",
    "PAD",
]
