"""The QP of n AGVs as rows (:class:`ConstraintRows`), the row kinds and the fallback weights."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

__all__ = [
    "ConstraintRows",
    "FALLBACK_WEIGHT",
    "fallback_weights",
    "take_rows",
    "HARD",
    "AGENT",
    "WALL",
    "POINT",
    "PAD",
]

# Row kinds. Soft rows may be violated by the fallback, ``weight * t`` at most.
HARD, AGENT, WALL, POINT, PAD = 0, 1, 2, 3, 4
FALLBACK_WEIGHT = {AGENT: 1.0, WALL: 2.0, POINT: 4.0}
"""How much each soft kind may be violated relative to AGV-AGV rows in the fallback."""


def fallback_weights(kind: np.ndarray) -> np.ndarray:
    """The fallback weight of each row slot from its kind (0: hard), shape (R,).

    Parameters
    ----------
    kind : np.ndarray of int, shape (R,)
        ``HARD``, ``AGENT``, ``WALL``, ``POINT`` or ``PAD`` per row slot.

    Returns
    -------
    np.ndarray, shape (R,)
        :data:`FALLBACK_WEIGHT` of the soft kinds, 0 for ``HARD`` and ``PAD``.
    """
    return np.array([FALLBACK_WEIGHT.get(int(k), 0.0) for k in kind])



@dataclass
class ConstraintRows:
    """The QP of n AGVs: ``min ||v_i - pref_i||^2  s.t.  lower_i <= A_i v_i <= upper_i``.

    Attributes
    ----------
    A : np.ndarray, shape (n, R, 2)
    lower, upper : np.ndarray, shape (n, R)
        ``-inf`` / ``inf`` where unbounded; padded rows have ``A = 0`` and infinite bounds.
    preferred : np.ndarray, shape (n, 2)
    kind : np.ndarray of int, shape (R,)
        ``HARD``, ``AGENT``, ``WALL``, ``POINT`` or ``PAD`` per row slot.
    active : np.ndarray of bool, shape (n,)
        AGVs that move (static ones get velocity 0 and no rows).
    weight : np.ndarray, shape (R,)
        How much each row slot may be violated in the fallback (0: hard); by default
        :func:`fallback_weights` of ``kind``, built here once and used by every solver.
    """

    A: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    preferred: np.ndarray
    kind: np.ndarray
    active: np.ndarray
    weight: np.ndarray | None = None

    def __post_init__(self) -> None:
        if self.weight is None:
            self.weight = fallback_weights(self.kind)


def take_rows(rows: ConstraintRows, idx: Any) -> ConstraintRows:
    """The rows of some AGVs (``idx``: indices, a slice or a mask over the n AGVs)."""
    return ConstraintRows(rows.A[idx], rows.lower[idx], rows.upper[idx], rows.preferred[idx],
                          rows.kind, rows.active[idx], rows.weight)
