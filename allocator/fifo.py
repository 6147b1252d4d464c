"""First in, first out: each order in turn (oldest first) goes to its nearest free AGV.

The default dispatch strategy of OpenTCS. In the paper's episodes the tasks have no release
order, so they go in index order; in lifelong operation the dispatcher is
:class:`allocator.dispatch.FifoDispatcher` (release order, higher priority first).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from allocator.base import register
from allocator.greedy import GreedyAllocator
from allocator.hungarian import check_cost_matrix

__all__ = ["FifoAllocator", "fifo_matching"]


def fifo_matching(cost: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Tasks in index order each take their nearest free AGV (``inf``: never taken).

    Parameters
    ----------
    cost : array-like, shape (N, M)

    Returns
    -------
    rows, cols : np.ndarray of int64
        Matched agent and task indices.

    Raises
    ------
    ValueError
        For a cost that is not a 2-D real matrix or holds NaN or ``-inf``.
    """
    work = check_cost_matrix(cost).copy()
    rows, cols = [], []
    for j in range(work.shape[1]):
        i = int(np.argmin(work[:, j])) if work.shape[0] else 0
        if not work.shape[0] or not np.isfinite(work[i, j]):
            continue
        rows.append(i)
        cols.append(j)
        work[i, :] = np.inf
        if len(rows) == work.shape[0]:
            break
    order = np.argsort(rows, kind="stable")
    return (np.array(rows, dtype=np.int64)[order], np.array(cols, dtype=np.int64)[order])


@register("fifo")
class FifoAllocator(GreedyAllocator):
    """Each task in turn (index order; lifelong: oldest order first) takes its nearest free AGV.

    Parameters and errors as :class:`allocator.greedy.GreedyAllocator`.
    """

    name = "fifo"

    @staticmethod
    def matching(cost: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The matching rule on the (N, M) costs: :func:`fifo_matching`."""
        return fifo_matching(cost)

    def lifelong_dispatcher(self) -> Any:
        """:class:`allocator.dispatch.FifoDispatcher`: the oldest order to its nearest free
        AGV, re-planned on events."""
        from allocator.dispatch import FifoDispatcher

        return FifoDispatcher()

    def __repr__(self) -> str:
        return f"FifoAllocator(planner={self.planner!r})"
