"""Decentralized epsilon-auction: optimality against scipy, bounds, components, validation."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import linear_sum_assignment

from allocator.auction import auction, communication_graph


def _total(benefit: np.ndarray, task_of_agent: np.ndarray) -> float:
    rows = np.flatnonzero(task_of_agent >= 0)
    return float(benefit[rows, task_of_agent[rows]].sum())


def _optimum(benefit: np.ndarray) -> float:
    return float(benefit[linear_sum_assignment(benefit, maximize=True)].sum())


def _valid(result, n: int, m: int) -> None:  # noqa: ANN001
    t, a = result.task_of_agent, result.agent_of_task
    assert t.shape == (n,) and a.shape == (m,)
    served = t[t >= 0]
    assert len(np.unique(served)) == len(served)
    assert np.all(a[served] == np.flatnonzero(t >= 0))
    assert np.sum(a >= 0) == len(served)


@pytest.mark.parametrize("shape", [(6, 6), (8, 13), (13, 8), (20, 20), (1, 5), (5, 1)])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_integer_benefits_optimal_on_connected_graph(shape: tuple[int, int], seed: int) -> None:
    rng = np.random.default_rng(seed)
    n, m = shape
    benefit = rng.integers(-20, 40, size=shape).astype(float)
    # Positions on a line 1 apart, range 1.5: a path graph, the slowest to spread prices.
    positions = np.stack([np.arange(n, dtype=float), np.zeros(n)], axis=1)
    result = auction(benefit, positions, comm_range=1.5, eps=1.0 / (n + 1))
    assert result.converged
    assert np.all(result.component == 0)
    _valid(result, n, m)
    assert np.sum(result.task_of_agent >= 0) == min(n, m)
    assert _total(benefit, result.task_of_agent) == _optimum(benefit)
    assert result.rounds > 1 and (result.messages > 0) == (n > 1)


@pytest.mark.parametrize("seed", range(4))
def test_real_benefits_within_n_eps(seed: int) -> None:
    rng = np.random.default_rng(seed)
    n, m = 15, 18
    benefit = -rng.uniform(0, 10, size=(n, m))
    positions = rng.uniform(0, 5, size=(n, 2))
    eps = 0.05
    result = auction(benefit, positions, comm_range=np.inf, eps=eps)
    assert result.converged
    _valid(result, n, m)
    gap = _optimum(benefit) - _total(benefit, result.task_of_agent)
    assert -1e-9 <= gap <= n * eps


@pytest.mark.parametrize("scaling", [None, 3.0, 10.0])
def test_epsilon_scaling_keeps_the_optimum(scaling: float | None) -> None:
    rng = np.random.default_rng(11)
    benefit = rng.integers(0, 1000, size=(25, 20)).astype(float)
    positions = rng.uniform(0, 5, size=(25, 2))
    result = auction(benefit, positions, comm_range=2.5, scaling=scaling)
    assert result.converged and np.all(result.component == 0)
    assert _total(benefit, result.task_of_agent) == _optimum(benefit)


def test_disconnected_graph_conflict_free_within_components() -> None:
    rng = np.random.default_rng(3)
    # Two clusters far apart, each connected inside; both like the same few tasks.
    positions = np.concatenate([rng.uniform(0, 1, (6, 2)), rng.uniform(50, 51, (5, 2))])
    benefit = rng.integers(0, 30, size=(11, 7)).astype(float)
    result = auction(benefit, positions, comm_range=2.0)
    assert result.converged
    assert len(np.unique(result.component)) == 2
    for c in np.unique(result.component):
        claims = result.claimed[(result.component == c) & (result.claimed >= 0)]
        assert len(np.unique(claims)) == len(claims)  # no clash inside a component
        members = np.flatnonzero(result.component == c)
        assert np.sum(result.claimed[members] >= 0) == min(len(members), 7)
    _valid(result, 11, 7)  # the returned plan has no clash across components either


def test_isolated_agents_each_take_their_best() -> None:
    benefit = np.array([[5.0, 1.0], [4.0, 2.0]])
    result = auction(benefit, [[0.0, 0.0], [100.0, 0.0]], comm_range=1.0)
    np.testing.assert_array_equal(result.claimed, [0, 0])  # both claim task 0, unaware
    assert result.messages == 0
    np.testing.assert_array_equal(result.task_of_agent, [0, -1])


def test_permuting_agents_keeps_the_optimum() -> None:
    rng = np.random.default_rng(5)
    benefit = rng.integers(0, 50, size=(12, 12)).astype(float)
    positions = rng.uniform(0, 4, size=(12, 2))
    perm = rng.permutation(12)
    a = auction(benefit, positions, comm_range=2.0)
    b = auction(benefit[perm], positions[perm], comm_range=2.0)
    assert _total(benefit, a.task_of_agent) == _total(benefit[perm], b.task_of_agent)


def test_max_rounds_reports_not_converged() -> None:
    rng = np.random.default_rng(6)
    benefit = rng.integers(0, 50, size=(20, 20)).astype(float)
    result = auction(benefit, rng.uniform(0, 5, (20, 2)), comm_range=1.0, max_rounds=2)
    assert not result.converged and result.rounds == 2
    _valid(result, 20, 20)


def test_communication_graph_edges() -> None:
    src, dst = communication_graph(np.array([[0.0, 0.0], [1.0, 0.0], [3.0, 0.0]]), 1.5)
    assert sorted(zip(src.tolist(), dst.tolist(), strict=True)) == [(0, 1), (1, 0)]


@pytest.mark.parametrize("comm_range", [0.0, -1.0, float("nan"), "far", True])
def test_comm_range_not_positive(comm_range: object) -> None:
    with pytest.raises(ValueError, match="comm_range"):
        auction(np.ones((2, 2)), np.zeros((2, 2)), comm_range=comm_range)  # type: ignore[arg-type]


@pytest.mark.parametrize(
    "benefit",
    [np.array([[1.0, np.nan], [0.0, 1.0]]), np.ones(3), np.ones((3, 2)), np.zeros((0, 2)),
     np.array([["a", "b"], ["c", "d"]]), np.array([[1.0, np.inf], [0.0, 1.0]])],
)
def test_bad_benefit(benefit: np.ndarray) -> None:
    with pytest.raises(ValueError, match="benefit|positions"):
        auction(benefit, np.zeros((2, 2)), comm_range=1.0)


def test_benefit_nan_names_benefit() -> None:
    with pytest.raises(ValueError, match="^benefit"):
        auction(np.array([[np.nan]]), np.zeros((1, 2)), comm_range=1.0)


def test_positions_and_eps_validated() -> None:
    with pytest.raises(ValueError, match="^positions"):
        auction(np.ones((2, 2)), np.zeros((3, 2)), comm_range=1.0)
    with pytest.raises(ValueError, match="^eps"):
        auction(np.ones((2, 2)), np.zeros((2, 2)), comm_range=1.0, eps=0.0)
    with pytest.raises(ValueError, match="^scaling"):
        auction(np.ones((2, 2)), np.zeros((2, 2)), comm_range=1.0, scaling=0.5)
    with pytest.raises(ValueError, match="^max_rounds"):
        auction(np.ones((2, 2)), np.zeros((2, 2)), comm_range=1.0, max_rounds=0)
