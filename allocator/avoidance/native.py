"""The C twin of the exact solvers (``qp2d.c``), built on first use: :func:`solve_rows_native`.

:func:`~allocator.avoidance.exact_qp.solve_qp_2d` and
:func:`~allocator.avoidance.least_violation.least_violation_2d` enumerate every AGV's
candidates as flat numpy arrays; the least-violation program has a few thousand candidates per
AGV, which at 1,000 AGVs in a crowded warehouse (a few hundred fall back each step) costs a few
hundred milliseconds of temporaries. ``qp2d.c`` runs the same enumeration, with the same KKT
filters and tolerances, one AGV at a time, and stops checking a candidate at its first violated
row. It is compiled with the system's C compiler the first time it is needed and cached in
``$AGV_CACHE_DIR`` (default ``~/.cache/agv-allocation``), keyed by a hash of the source, the
flags and the machine. Without a compiler, or with ``AGV_NATIVE=0`` in the environment, the
numpy solvers run instead (:func:`available` says which).
"""

from __future__ import annotations

import ctypes
import os
from pathlib import Path

import numpy as np

__all__ = ["available", "disabled_reason", "solve_rows_native", "SOURCE"]

SOURCE = Path(__file__).with_name("qp2d.c")
FLAGS = ["-O2", "-std=c99", "-fPIC", "-shared", "-ffp-contract=off", "-fno-math-errno"]

_lib: ctypes.CDLL | None = None
_tried = False
_reason: str | None = None


def _build() -> ctypes.CDLL:
    from sim.native import load_cached  # the simulator's compiler and cache

    lib = load_cached(SOURCE, FLAGS, "qp2d")
    fn = lib.agv_velocity_qp
    fn.restype = ctypes.c_int64
    fn.argtypes = [ctypes.c_int64, ctypes.c_int64] + [ctypes.c_void_p] * 6 \
        + [ctypes.c_double] * 3 + [ctypes.c_void_p] * 3
    return lib


def _library() -> ctypes.CDLL | None:
    global _lib, _tried, _reason
    if _tried:
        return _lib
    _tried = True
    if os.environ.get("AGV_NATIVE", "1").strip().lower() in ("0", "false", "no", "off"):
        _reason = "AGV_NATIVE=0 in the environment"
        return None
    try:
        _lib = _build()
    except (OSError, RuntimeError) as exc:  # no compiler, a failed build, a bad cache
        _reason = str(exc)
        _lib = None
    return _lib


def available() -> bool:
    """Whether the C solver can be used here (it is built on the first call)."""
    return _library() is not None


def disabled_reason() -> str | None:
    """Why :func:`available` is False (None when it is True or was not asked yet)."""
    _library()
    return _reason


def _f64(x: np.ndarray, shape: tuple[int, ...], name: str) -> np.ndarray:
    arr = np.ascontiguousarray(x, dtype=np.float64)
    if arr.shape != shape:
        raise ValueError(f"{name} must have shape {shape}, got {arr.shape}")
    return arr


def solve_rows_native(
    A: np.ndarray, lower: np.ndarray, upper: np.ndarray, preferred: np.ndarray,
    active: np.ndarray, weight: np.ndarray, regularization: float, tol: float,
    fallback_tol: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Every AGV's exact QP, and the exact least-violation velocity where its rows conflict.

    The same result as :func:`~allocator.avoidance.exact_qp.solve_qp_2d` followed by
    :func:`~allocator.avoidance.least_violation.least_violation_2d` on the AGVs that conflict
    (``VelocityAvoidance`` with ``solver="exact"``), up to rounding.

    Parameters
    ----------
    A : np.ndarray, shape (n, R, 2)
    lower, upper : np.ndarray, shape (n, R)
    preferred : np.ndarray, shape (n, 2)
    active : np.ndarray of bool, shape (n,)
        Inactive AGVs get velocity 0.
    weight : np.ndarray, shape (R,)
        Fallback weight per row slot (0: hard).
    regularization, tol, fallback_tol : float
        As in :func:`least_violation_2d` and :class:`AvoidanceConfig`.

    Returns
    -------
    velocity : np.ndarray, shape (n, 2)
    fell_back : np.ndarray of bool, shape (n,)
        Rows conflict and the least violation exceeds ``fallback_tol``.
    violation : np.ndarray, shape (n,)
        That violation (0 elsewhere; ``inf`` where even the hard rows conflict).

    Raises
    ------
    RuntimeError
        When the C solver is not available (see :func:`available`).
    """
    lib = _library()
    if lib is None:
        raise RuntimeError(f"the native QP solver is not available: {_reason}")
    n, R = A.shape[0], A.shape[1]
    A = _f64(A, (n, R, 2), "A")
    lower = _f64(lower, (n, R), "lower")
    upper = _f64(upper, (n, R), "upper")
    preferred = _f64(preferred, (n, 2), "preferred")
    weight = _f64(weight, (R,), "weight")
    act = np.ascontiguousarray(active, dtype=np.uint8)
    if act.shape != (n,):
        raise ValueError(f"active must have shape {(n,)}, got {act.shape}")
    velocity = np.empty((n, 2))
    fell = np.zeros(n, dtype=np.uint8)
    violation = np.zeros(n)
    if n:
        count = lib.agv_velocity_qp(
            n, R, A.ctypes.data, lower.ctypes.data, upper.ctypes.data, preferred.ctypes.data,
            act.ctypes.data, weight.ctypes.data, float(regularization), float(tol),
            float(fallback_tol), velocity.ctypes.data, fell.ctypes.data, violation.ctypes.data,
        )
        if count < 0:
            raise MemoryError("the native QP solver could not allocate its work space")
    return velocity, fell.astype(bool), violation
