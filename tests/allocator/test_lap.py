"""The incremental assignment solver: optimal on every event sequence, cross-checked by scipy."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import linear_sum_assignment

import allocator.lap as lap_module
from allocator.lap import IncrementalLAP, solve

BIG = 1e9  # the dispatcher's forbidden pair


def _total(cost: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> float:
    return float(cost[rows, cols].sum())


def _check(cost: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> None:
    r, c = linear_sum_assignment(cost)
    assert len(rows) == len(r) == min(cost.shape)
    assert np.all(np.diff(rows) > 0), "rows ascending, each once"
    assert len(np.unique(cols)) == len(cols)
    want = _total(cost, r, c)
    assert abs(_total(cost, rows, cols) - want) <= 1e-9 * max(1.0, abs(want))


def _event(rng: np.random.Generator, cost: np.ndarray, rk: np.ndarray, ck: np.ndarray,
           fresh: int, forbid: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """One dispatcher-like event: an AGV or an order comes or goes, a row or column changes."""
    kind = int(rng.integers(0, 7))
    a, o = cost.shape

    def draw(shape):
        out = rng.integers(0, 6, shape).astype(float)
        out[rng.random(shape) < forbid] = BIG
        return out

    if kind == 0 and a > 1:  # an AGV leaves the plan (breakdown, loaded without drop-off)
        d = int(rng.integers(a))
        cost, rk = np.delete(cost, d, 0), np.delete(rk, d)
    elif kind == 1:  # an AGV joins (repair, delivery)
        cost, rk = np.vstack([cost, draw((1, o))]), np.append(rk, fresh)
        fresh += 1
    elif kind == 2 and o > 1:  # an order is picked up
        d = int(rng.integers(o))
        cost, ck = np.delete(cost, d, 1), np.delete(ck, d)
    elif kind == 3:  # an order arrives
        cost, ck = np.hstack([cost, draw((a, 1))]), np.append(ck, fresh)
        fresh += 1
    elif kind == 4:  # an AGV's costs change (it moved, it became loaded)
        cost = cost.copy()
        cost[int(rng.integers(a))] = draw(o)
    elif kind == 5:  # an order's column term changes (priority, deadline, returned)
        cost = cost.copy()
        cost[:, int(rng.integers(o))] += rng.normal()
    else:  # a few scattered entries
        cost = cost.copy()
        k = int(rng.integers(1, 4))
        cost[rng.integers(0, a, k), rng.integers(0, o, k)] = draw(k)
    return cost, rk, ck, fresh


@pytest.mark.parametrize("forbid", [0.0, 0.2])
def test_event_sequences_match_scipy(forbid):
    rng = np.random.default_rng(7)
    warm = 0
    for _ in range(60):
        solver = IncrementalLAP()
        a, o = (int(v) for v in rng.integers(1, 25, 2))
        cost = rng.integers(0, 6, (a, o)).astype(float)  # many ties
        rk, ck = np.arange(a), np.arange(o)
        fresh = 1000
        for _ in range(25):
            rows, cols = solver.solve(cost, rk, ck)
            _check(cost, rows, cols)
            warm += solver.last_mode == "warm"
            cost, rk, ck, fresh = _event(rng, cost, rk, ck, fresh, forbid)
    assert warm > 500  # the warm path is what was tested


def test_inf_forbidden_and_infeasible():
    cost = np.array([[1.0, np.inf, 3.0], [np.inf, 2.0, np.inf]])
    rows, cols = solve(cost)
    assert cols.tolist() == [0, 1] or cols.tolist() == [2, 1]
    assert _total(cost, rows, cols) == 3.0
    with pytest.raises(ValueError, match="infeasible"):
        solve(np.array([[np.inf, np.inf], [1.0, 2.0]]))


def test_continuous_costs_rectangular_both_ways():
    rng = np.random.default_rng(3)
    for shape in [(40, 60), (60, 40), (50, 50)]:
        solver = IncrementalLAP()
        cost = rng.random(shape)
        for _ in range(10):
            _check(cost, *solver.solve(cost))
            cost = cost.copy()
            cost[int(rng.integers(shape[0]))] = rng.random(shape[1])


def test_caller_mutating_its_matrix_is_seen():
    solver = IncrementalLAP()
    cost = np.array([[1.0, 2.0], [2.0, 1.0]])
    solver.solve(cost)
    cost[0, 0] = 9.0  # in place: the solver kept its own copy
    rows, cols = solver.solve(cost)
    assert cols.tolist() == [1, 0] or _total(cost, rows, cols) == 3.0
    _check(cost, rows, cols)


def test_numpy_fallback_agrees(monkeypatch):
    rng = np.random.default_rng(11)
    cost = rng.integers(0, 4, (12, 17)).astype(float)
    native = IncrementalLAP()
    want = native.solve(cost)
    monkeypatch.setattr(lap_module, "_library", lambda: None)
    solver = IncrementalLAP()
    rows, cols = solver.solve(cost)
    _check(cost, rows, cols)
    assert _total(cost, rows, cols) == _total(cost, *want)
    cost[3] = rng.integers(0, 4, 17)
    _check(cost, *solver.solve(cost))
    assert solver.last_mode == "warm"


def test_unchanged_matrix_needs_no_search():
    solver = IncrementalLAP()
    cost = np.random.default_rng(0).random((30, 45))
    solver.solve(cost)
    solver.solve(cost)
    assert solver.last_mode == "warm" and solver.last_free == 0 and solver.last_scans == 0


def test_too_many_changes_solve_cold():
    solver = IncrementalLAP(max_changed=0.1)
    rng = np.random.default_rng(0)
    solver.solve(rng.random((20, 20)))
    solver.solve(rng.random((20, 20)))
    assert solver.last_mode == "cold"


@pytest.mark.parametrize("bad, match", [
    (np.zeros(3), "2-D"),
    (np.array([[np.nan, 1.0]]), "NaN"),
    (np.array([[-np.inf, 1.0]]), "NaN or -inf"),
])
def test_bad_cost(bad, match):
    with pytest.raises(ValueError, match=match):
        IncrementalLAP().solve(bad)


def test_bad_keys_and_options():
    with pytest.raises(ValueError, match="row_keys"):
        IncrementalLAP().solve(np.zeros((2, 2)), row_keys=[1, 1])
    with pytest.raises(ValueError, match="col_keys"):
        IncrementalLAP().solve(np.zeros((2, 2)), col_keys=[1])
    with pytest.raises(ValueError, match="max_changed"):
        IncrementalLAP(max_changed=2.0)


def test_empty():
    rows, cols = IncrementalLAP().solve(np.zeros((0, 3)))
    assert rows.shape == cols.shape == (0,)
