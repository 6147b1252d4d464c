"""The paper's synchronous Jacobi iteration, the reference the exact solver is tested
against (:mod:`sim.ipf`)."""

from __future__ import annotations

import math

import numpy as np
import torch

from sim.ipf.grid import IPFGrid, _check_sources

__all__ = ["jacobi_field"]


def jacobi_field(
    grid: IPFGrid,
    source_cells: np.ndarray,
    source_values: np.ndarray,
    tol: float = 1e-9,
    max_iter: int = 1_000_000,
) -> np.ndarray:
    """The paper's Jacobi iteration, run to a guaranteed tolerance (the reference solver).

    Starting from 0 everywhere except the sources, every node that is neither fixed at 0 nor a
    source is replaced, all at once, by the mean of its graph neighbours,
    ``Phi^{k+1}(u) = (1 / d(u)) * sum_{v in N(u)} Phi^k(v)``, until the max-abs distance to the
    converged field is provably below ``tol``.

    The bound: the iteration matrix ``J`` (``A / 4`` on the updated nodes) is symmetric with
    spectral radius ``rho <= (cos(pi / (W - 1)) + cos(pi / (H - 1))) / 2`` (that of the empty
    box; fixing more nodes only lowers it), so the error after a step of size ``delta`` obeys
    ``max|e| <= ||e||_2 <= rho / (1 - rho) * ||delta||_2``. Iteration stops when that is below
    ``tol``.

    Parameters
    ----------
    grid : IPFGrid
    source_cells : np.ndarray of int, shape (S,)
        Flat cell indices of the sources (:meth:`IPFGrid.cell_of`); must be distinct free cells.
    source_values : np.ndarray, shape (S,)
    tol : float
        Guaranteed max-abs error of the result.
    max_iter : int

    Returns
    -------
    np.ndarray of float64, shape (H, W)

    Raises
    ------
    ValueError
        If a source lies on a fixed cell or two sources share a cell.
    RuntimeError
        If ``max_iter`` iterations do not reach ``tol``.
    """
    cells = np.asarray(source_cells, dtype=np.int64).ravel()
    values = np.asarray(source_values, dtype=np.float64).ravel()
    _check_sources(grid, torch.from_numpy(cells)[None], torch.from_numpy(values)[None])
    if np.any(grid.free_index[cells] < 0):
        raise ValueError("a source lies on a cell fixed at 0 (boundary ring or shelf)")
    if len(np.unique(cells)) != len(cells):
        raise ValueError("two sources share a cell")
    H, W = grid.shape
    adjacency = grid.adjacency
    degree = np.asarray(adjacency.sum(axis=1)).ravel()
    update = ~grid.fixed.ravel()
    update[cells] = False
    phi = np.zeros(H * W)
    phi[cells] = values
    rho = 0.5 * (math.cos(math.pi / (W - 1)) + math.cos(math.pi / (H - 1)))
    bound = rho / (1.0 - rho)
    for _ in range(max_iter):
        mean = (adjacency @ phi) / degree
        delta = np.where(update, mean - phi, 0.0)
        phi = phi + delta
        if bound * np.linalg.norm(delta) < tol:
            return phi.reshape(H, W)
    raise RuntimeError(f"Jacobi iteration did not reach tol={tol} in {max_iter} iterations")
