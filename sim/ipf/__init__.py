"""The information potential field (IPF) of the paper, exactly, and fast.

The field
---------
The world is covered by a regular grid of ``H x W`` cells (cell size about ``resolution``
world units, default 0.05 so an AGV of radius 0.15 spans six cells across). The grid is a graph:
one node per cell, edges between 4-neighbours (``networkx.grid_2d_graph``). Three kinds of node
have a fixed value:

- *boundary* nodes (the outermost ring of cells) and *obstacle* nodes (cells whose centre lies
  in a shelf, edges included) are fixed at 0;
- for AGV ``i``: the cell of every unclaimed task is fixed at ``+5`` and the cell of every other
  AGV at ``-3`` (the *sources*). AGV ``i``'s own cell is not a source of its own field, and
  claimed tasks are not sources. Parked AGVs are AGVs: they stay sources at ``-3``.

Every other node is harmonic, ``Phi(u) = (1 / d(u)) * sum of Phi over N(u)`` with ``d(u) = 4``
(every free node lies inside the boundary ring, so it has four neighbours in the graph): the
fixed point of the paper's Jacobi iteration. ``r_IPF`` for AGV ``i`` is ``Phi_i`` at AGV ``i``'s
cell (nearest cell, no interpolation).

Cell rule: a point maps to the cell that contains it, which is the cell with the nearest centre
(``floor((x - xmin) / dx)``, clipped to the grid).

Two solvers
-----------
- :func:`jacobi_field`, the reference: the paper's synchronous Jacobi iteration on the graph,
  run until a guaranteed bound on the max-abs error is below ``tol``.
- the exact fast solver (:meth:`IPFGrid.fields` for whole fields, :meth:`IPFGrid.agent_potentials`
  for the reward). Let ``L = 4 I - A`` be the graph Laplacian restricted to the ``F`` free nodes
  (every node not fixed at 0) and ``G = L^{-1}`` its Dirichlet Green's function, computed once per
  world and resolution. With sources ``S`` at values ``v``, the field is ``Phi = G[:, S] w`` with
  ``G[S, S] w = v``: it is zero on fixed nodes, takes the value ``v`` on ``S`` and is harmonic
  elsewhere because ``L Phi = w`` vanishes off ``S``. For the reward every AGV needs its field only
  at its own cell, and AGV ``i``'s sources are the scene's sources ``T`` minus ``i`` itself. With
  ``K = G[T, T]`` and ``P = K^{-1}``, the Schur-complement identity gives
  ``Phi_i(cell_i) = K[i, T'] K[T', T']^{-1} v_T' = -(sum_{j != i} P_ij v_j) / P_ii``, so one small
  inverse per environment serves all N AGVs. The reward computes only its AGV block,
  ``P_AA = S^{-1}`` with the Schur complement ``S = G[A, A] - G[A, T] D^{-1} G[T, A]`` of the
  tasks' block ``D``; ``D``'s factor changes only at resets and claims and is cached
  (:class:`TaskBlockCache`), so a step costs one gather from ``G``, two small batched matrix
  products and one ``N x N`` inverse per environment.

The reward's rules
------------------
The ``"ipf"`` reward (:class:`sim.rewards.ipf.IPFReward`) pays ``r_IPF`` through
:meth:`IPFGrid.reward_potentials`, which adds one rule to the value above: a parked AGV (one
that holds a task) receives that task's value, ``+5``, since it stands on it (otherwise
claiming, which removes the task's ``+5`` from the field, would pay less than hovering just
outside the capture radius). Plots of a field are in :mod:`sim.render`.

Large floors
------------
Where the dense ``G`` would exceed :data:`MAX_GREEN_BYTES` (``F^2 * 8`` bytes; 50v50 at 0.05
needs 1.2 GiB, warehouse-100 24 GiB) the grid uses a separator tree instead
(``IPFGrid.method == "tree"``, :mod:`sim.ipf.hierarchy`): a nested dissection of the free cells
by straight lines through shelves and aisles, each separator's Schur complement factored once,
and per cell a vector per level such that ``G(s, t)`` is a sum of short dot products over the
domains holding both cells plus a dense leaf block. It is exact (direct, float64) and takes
``O(F sqrt(F))`` memory; every formula above runs on it unchanged (the fused C kernel needs the
dense ``G`` and is used only where it exists). Rows of ``G`` at cells that recur (pickups,
stations) are kept after their first use.

Lifelong floors
---------------
:meth:`IPFGrid.lifelong_potentials`: an AGV that is not loaded sees every open pickup at
``+5``, a loaded one only its own drop-off; both see the other AGVs at ``-3``. One Schur
complement per environment serves the unloaded AGVs, one inverse of ``G[agents, agents]`` with
a rank-one border per loaded AGV (its drop-off) serves the loaded ones.

Colliding sources
-----------------
Sources that share a cell with the same value merge exactly (a Dirichlet value is a value, not a
charge). Sources that share a cell with different values mean the grid is too coarse:
:func:`ipf_field` raises :class:`ValueError`; the batched potentials apply a deterministic rule
instead: *the AGV wins*, the cell is fixed at ``-3`` (an AGV standing on a task is serving it).
A source whose cell is fixed at 0 (a boundary ring or shelf cell): :func:`ipf_field` raises; the
batched potentials ignore it (0 wins), and an AGV on such a cell reads 0. Sources on fixed cells
do not happen in the shipped scenarios at the default resolution (AGVs and tasks stay at least
one AGV radius from walls and shelves); two AGVs on one cell do, rarely (a deep overlap, about
one environment in a thousand per step), and the batched potentials handle those environments
on their general path.
"""

from sim.ipf.field import IPFField, check_scene, ipf_field
from sim.ipf.grid import (
    AGENT_VALUE,
    DEFAULT_RESOLUTION,
    MAX_COLUMN_BYTES,
    MAX_GREEN_BYTES,
    MAX_TREE_BYTES,
    TASK_VALUE,
    IPFGrid,
    TaskBlockCache,
    check_resolution,
    ipf_grid,
)
from sim.ipf.hierarchy import SeparatorTree
from sim.ipf.jacobi import jacobi_field

__all__ = [
    "TASK_VALUE",
    "AGENT_VALUE",
    "DEFAULT_RESOLUTION",
    "MAX_GREEN_BYTES",
    "MAX_TREE_BYTES",
    "MAX_COLUMN_BYTES",
    "IPFGrid",
    "SeparatorTree",
    "IPFField",
    "TaskBlockCache",
    "check_resolution",
    "check_scene",
    "ipf_grid",
    "ipf_field",
    "jacobi_field",
]
