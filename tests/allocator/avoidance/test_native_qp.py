"""The C twin of the exact solvers (``qp2d.c``) against the numpy solvers, OSQP and cvxpy, and
the k-d tree neighbour search against the dense one."""

from __future__ import annotations

import numpy as np
import pytest

from allocator.avoidance import (
    AvoidanceConfig,
    ConstraintRows,
    VelocityAvoidance,
    least_violation_2d,
    native,
    orca,
    solve_qp_2d,
    solve_reference,
)
from allocator.avoidance.osqp_least_violation import LeastViolation
from allocator.avoidance.osqp_qp import BlockOSQP
from sim.world import World
from tests.allocator.conftest import spaced_points
from tests.allocator.test_avoidance import random_rows

pytestmark = pytest.mark.skipif(not native.available(),
                                reason=f"no native QP solver: {native.disabled_reason()}")

CFG = AvoidanceConfig()


def numpy_solve(rows: ConstraintRows) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    qp = VelocityAvoidance(config=AvoidanceConfig(native=False))
    v, fell, viol, _ = qp.solve_rows(rows)
    return v, fell, viol


def native_solve(rows: ConstraintRows) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return native.solve_rows_native(rows.A, rows.lower, rows.upper, rows.preferred,
                                    rows.active, rows.weight, 1e-3, CFG.feasibility_tol,
                                    CFG.fallback_tol)


def degenerate_rows() -> ConstraintRows:
    """Hand-made corner cases, one AGV each: no rows, all padding, pref feasible, a vertex
    optimum, parallel lines leaving a strip, a single point, opposite parallel lines with no
    gap (infeasible -> fallback), a zero row that can never hold (hard infeasible), duplicated
    lines, a lower bound only, and an inactive AGV."""
    inf = np.inf
    R = 4
    cases = [
        ([[0, 0]] * 4, [inf] * 4, [-inf] * 4, [0.3, 0.2], True),  # padding only
        ([[1, 0], [0, 1], [0, 0], [0, 0]], [1, 1, inf, inf], [-inf] * 4, [0.5, 0.5], True),
        ([[1, 0], [0, 1], [0, 0], [0, 0]], [1, 1, inf, inf], [-inf] * 4, [2, 2], True),
        ([[0, 1], [0, -1], [0, 0], [0, 0]], [1, 1, inf, inf], [-inf] * 4, [0.3, 5], True),
        ([[0, 1], [0, -1], [1, 0], [-1, 0]], [1, -1, 1, -1], [-inf] * 4, [0.3, 5], True),
        ([[0, 1], [0, -1], [0, 0], [0, 0]], [1, -1.1, inf, inf], [-inf] * 4, [0.3, 5], True),
        ([[1, 0], [0, 0], [0, 0], [0, 0]], [1, inf, -1, inf], [-inf] * 4, [0, 0], True),
        ([[1, 0], [0, 0], [0, 0], [0, 0]], [1, -1, inf, inf], [-inf] * 4, [0, 0], True),
        ([[2, 0], [1, 0], [1, 0], [0, 0]], [2, 1, 1, inf], [-inf] * 4, [3, 1], True),
        ([[1, 0], [0, 1], [0, 0], [0, 0]], [inf] * 4, [1, 0.5, -inf, -inf], [0, 0], True),
        ([[1, 0], [0, 1], [0, 0], [0, 0]], [1, 1, inf, inf], [-inf] * 4, [2, 2], False),
        # an infeasible soft pair inside a hard box: the fallback splits the violation
        ([[1, 0], [-1, 0], [1, 0], [0, 1]], [-0.5, -0.5, 1, 1], [-inf, -inf, -1, -1],
         [0, 0], True),
    ]
    A = np.array([c[0] for c in cases], dtype=np.float64).reshape(-1, R, 2)
    hi = np.array([c[1] for c in cases], dtype=np.float64)
    lo = np.array([c[2] for c in cases], dtype=np.float64)
    pref = np.array([c[3] for c in cases], dtype=np.float64)
    active = np.array([c[4] for c in cases])
    kind = np.array([1, 1, 0, 0])  # two soft (AGV) slots, two hard
    return ConstraintRows(A, lo, hi, pref, kind, active)


def test_degenerate_instances_match_numpy_and_cvxpy() -> None:
    rows = degenerate_rows()
    v_n, fell_n, viol_n = numpy_solve(rows)
    v_c, fell_c, viol_c = native_solve(rows)
    np.testing.assert_array_equal(fell_c, fell_n)
    np.testing.assert_allclose(v_c, v_n, atol=1e-12)
    np.testing.assert_allclose(viol_c, viol_n, atol=1e-12)
    # the documented behaviour, case by case
    np.testing.assert_allclose(v_c[0], [0.3, 0.2])
    np.testing.assert_allclose(v_c[2], [1.0, 1.0])
    np.testing.assert_allclose(v_c[3], [0.3, 1.0])
    np.testing.assert_allclose(v_c[4], [1.0, 1.0])
    assert fell_c[5] and 0 < viol_c[5] < np.inf  # opposite lines, no gap: least violation
    assert fell_c[6] and viol_c[6] == np.inf and np.all(v_c[6] == 0)  # hard row never holds
    assert fell_c[7] and viol_c[7] == pytest.approx(1.0)  # a soft one: violated by 1
    np.testing.assert_allclose(v_c[8], [1.0, 1.0])
    np.testing.assert_allclose(v_c[9], [1.0, 0.5])
    assert np.all(v_c[10] == 0) and not fell_c[10]  # inactive
    assert fell_c[11]
    np.testing.assert_allclose(v_c[11], [0.0, 0.0], atol=1e-9)
    np.testing.assert_allclose(viol_c[11], 0.5, atol=1e-9)
    ref, ref_fell = solve_reference(rows)
    feasible = rows.active & ~ref_fell
    np.testing.assert_allclose(v_c[feasible], ref[feasible], atol=1e-6)
    np.testing.assert_array_equal(fell_c[rows.active & (viol_c < np.inf)],
                                  ref_fell[rows.active & (viol_c < np.inf)])


@pytest.mark.parametrize(("k", "near", "seed"),
                         [(5, 0.5, 0), (8, 0.5, 1), (12, 0.8, 2), (30, 0.1, 3),
                          pytest.param(30, 0.05, 4, marks=pytest.mark.slow),  # a second k=30
                          (16, 0.3, 5)])
def test_random_instances_match_numpy_osqp_and_cvxpy(k: int, near: float, seed: int) -> None:
    rng = np.random.default_rng(1000 + seed)
    rows = random_rows(rng, 400, k, near)
    v_c, fell_c, viol_c = native_solve(rows)
    # the numpy exact solvers (the same enumeration): to rounding
    v_n, fell_n, viol_n = numpy_solve(rows)
    np.testing.assert_array_equal(fell_c, fell_n)
    np.testing.assert_allclose(v_c, v_n, atol=1e-9)
    np.testing.assert_allclose(viol_c, viol_n, atol=1e-9)
    _, feasible = solve_qp_2d(rows.A, rows.lower, rows.upper, rows.preferred)
    assert 10 <= feasible.sum() <= 390  # both kinds are exercised
    # OSQP, the oracle: where it calls the QP feasible, to its tolerance
    v_o, fell_o, _, _ = BlockOSQP(CFG, LeastViolation(), {"solves": 0, "fallbacks": 0,
                                                          "setup": 0}).solve_rows(rows)
    # (its infeasibility detection is looser: it falls back on some near-infeasible QPs)
    both = feasible & ~fell_o
    assert both.sum() >= feasible.sum() * 0.7
    np.testing.assert_allclose(v_c[both], v_o[both], atol=5e-4)
    # the least-violation program of OSQP agrees on the AGVs that fell back
    idx = np.flatnonzero(fell_c)
    if idx.size:
        sub = ConstraintRows(rows.A[idx], rows.lower[idx], rows.upper[idx], rows.preferred[idx],
                             rows.kind, rows.active[idx])
        _, t_osqp = LeastViolation().solve(sub)
        solved = np.isfinite(t_osqp)  # OSQP stops at max_iter on a few
        assert solved.mean() >= 0.7
        np.testing.assert_allclose(t_osqp[solved], viol_c[idx][solved], atol=1e-4)
    # cvxpy (Clarabel) on a sample: never a better objective than the exact answer
    few = rng.choice(len(v_c), 25, replace=False)
    sub = ConstraintRows(rows.A[few], rows.lower[few], rows.upper[few], rows.preferred[few],
                         rows.kind, rows.active[few])
    ref, ref_fell = solve_reference(sub)
    np.testing.assert_array_equal(fell_c[few], ref_fell)
    ok = ~ref_fell
    np.testing.assert_allclose(v_c[few][ok], ref[ok], atol=1e-5)
    np.testing.assert_allclose(v_c[few][~ok], ref[~ok], atol=1e-3)


def test_least_violation_alone_matches_numpy() -> None:
    rows = random_rows(np.random.default_rng(7), 300, 12, 0.8)
    _, feasible = solve_qp_2d(rows.A, rows.lower, rows.upper, rows.preferred)
    idx = np.flatnonzero(~feasible)
    v_n, t_n = least_violation_2d(rows.A[idx], rows.lower[idx], rows.upper[idx],
                                  rows.preferred[idx], rows.weight)
    v_c, fell_c, viol_c = native_solve(rows)
    np.testing.assert_allclose(v_c[idx], v_n, atol=1e-9)
    np.testing.assert_allclose(np.where(fell_c[idx], viol_c[idx], 0.0),
                               np.where(t_n > CFG.fallback_tol, t_n, 0.0), atol=1e-9)


def test_zero_agents_and_bad_shapes() -> None:
    v, fell, viol = native.solve_rows_native(np.zeros((0, 3, 2)), np.zeros((0, 3)),
                                             np.zeros((0, 3)), np.zeros((0, 2)),
                                             np.zeros(0, bool), np.zeros(3), 1e-3, 1e-9, 1e-4)
    assert v.shape == (0, 2) and fell.shape == (0,) and viol.shape == (0,)
    with pytest.raises(ValueError, match="preferred"):
        native.solve_rows_native(np.zeros((2, 3, 2)), np.zeros((2, 3)), np.zeros((2, 3)),
                                 np.zeros((3, 2)), np.ones(2, bool), np.zeros(3), 1e-3, 1e-9,
                                 1e-4)
    with pytest.raises(ValueError, match="native"):
        AvoidanceConfig(native="yes")  # type: ignore[arg-type]


def crowd(seed: int, n: int) -> tuple[World, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    world = World(bounds=(-4.0, -4.0, 4.0, 4.0))
    pos = spaced_points(rng, n, world, 0.33)
    vel = rng.normal(0, 0.6, (n, 2))
    pref = rng.normal(0, 1.0, (n, 2))
    static = rng.random(n) < 0.2
    return world, pos, vel, pref, static


@pytest.mark.parametrize("seed", range(3))
def test_kd_tree_neighbours_equal_the_dense_ones(seed: int, monkeypatch) -> None:
    world, pos, vel, pref, static = crowd(seed, 120)
    B = np.stack([pos, pos[::-1] * 0.9])
    for k in (1, 8):
        monkeypatch.setattr(orca, "DENSE_MAX", 10_000)
        nb_d, ok_d = orca.neighbours(B, k, 1.2)
        monkeypatch.setattr(orca, "DENSE_MAX", 0)
        nb_t, ok_t = orca.neighbours(B, k, 1.2)
        np.testing.assert_array_equal(ok_t, ok_d)
        np.testing.assert_array_equal(np.where(ok_t, nb_t, -1), np.where(ok_d, nb_d, -1))
    # the whole avoidance step is the same either way, and the same in numpy and C
    outs = []
    for dense in (10_000, 0):
        monkeypatch.setattr(orca, "DENSE_MAX", dense)
        for nat in (True, False):
            qp = VelocityAvoidance(world, native=nat)
            outs.append(qp.solve(pos, vel, pref, static=static))
    for out in outs[1:]:
        np.testing.assert_array_equal(out.fell_back, outs[0].fell_back)
        np.testing.assert_allclose(out.velocity, outs[0].velocity, atol=1e-9)


def test_an_agv_exactly_on_another_is_not_its_own_neighbour(monkeypatch) -> None:
    monkeypatch.setattr(orca, "DENSE_MAX", 0)
    pos = np.array([[[0.0, 0.0], [0.0, 0.0], [0.5, 0.0], [5.0, 5.0]]])
    nb, ok = orca.neighbours(pos, 2, 1.0)
    assert ok[0, 0].all() and set(nb[0, 0].tolist()) == {1, 2}
    assert ok[0, 1].all() and set(nb[0, 1].tolist()) == {0, 2}
    assert not ok[0, 3].any()


def test_static_reference_and_static_horizon() -> None:
    # An AGV heading for the left leg of a parked AGV's cone: its row is built at its current
    # velocity and keeps it on that side; built at a reference on the right side it lets it go
    # right.
    pos = np.array([[0.0, 0.0], [0.6, 0.0]])
    vel = np.array([[1.0, 0.3], [0.0, 0.0]])
    static = np.array([False, True])
    right = np.array([[1.0, -0.6], [0.0, 0.0]])
    qp = VelocityAvoidance(radius=0.15)
    plain = qp.solve(pos, vel, right, static=static)
    same = qp.solve(pos, vel, right, static=static, static_reference=np.full((2, 2), np.nan))
    np.testing.assert_array_equal(plain.velocity, same.velocity)
    turned = qp.solve(pos, vel, right, static=static, static_reference=right)
    assert turned.velocity[0, 1] < plain.velocity[0, 1] - 0.1  # further to the right
    np.testing.assert_allclose(turned.velocity[0], right[0], atol=0.01)
    with pytest.raises(ValueError, match="static_reference"):
        qp.solve(pos, vel, right, static=static, static_reference=np.zeros((3, 2)))
    with pytest.raises(ValueError, match="static_reference"):
        qp.solve(pos, vel, right, static=static, static_reference=np.full((2, 2), np.inf))
    # a shorter horizon against parked AGVs lets an AGV close in faster
    slow = VelocityAvoidance(radius=0.15).solve(pos, vel, np.array([[2.0, 0.0], [0, 0]]),
                                                static=static)
    fast = VelocityAvoidance(radius=0.15, static_time_horizon=0.2).solve(
        pos, vel, np.array([[2.0, 0.0], [0, 0]]), static=static)
    assert fast.velocity[0, 0] > slow.velocity[0, 0] + 0.1
    with pytest.raises(ValueError, match="static_time_horizon"):
        AvoidanceConfig(static_time_horizon=0.0)
