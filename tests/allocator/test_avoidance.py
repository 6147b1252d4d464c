"""The ORCA velocity QP: the exact 2-D solver and OSQP against the cvxpy reference, the
fallback, and zero overlaps."""

from __future__ import annotations

import numpy as np
import pytest

from allocator.avoidance import (
    FALLBACK_WEIGHT,
    AvoidanceConfig,
    ConstraintRows,
    LeastViolation,
    VelocityAvoidance,
    fallback_weights,
    least_violation_2d,
    solve_qp_2d,
    solve_reference,
)
from allocator.avoidance.rows import take_rows
from sim.world import World
from tests.allocator.conftest import spaced_points


def random_scene(seed: int, n: int = 12, world: World | None = None):
    rng = np.random.default_rng(seed)
    world = world or World(bounds=(-2.0, -2.0, 2.0, 2.0))
    pos = spaced_points(rng, n, world, 0.36)
    vel = rng.normal(0, 0.6, (n, 2))
    pref = rng.normal(0, 1.0, (n, 2))
    return world, pos, vel, pref


@pytest.mark.parametrize("solver", ["exact", "osqp"])
@pytest.mark.parametrize("seed", range(6))
def test_solvers_match_the_cvxpy_reference(seed: int, solver: str) -> None:
    world, pos, vel, pref = random_scene(seed)
    qp = VelocityAvoidance(world, solver=solver)
    static = np.zeros(len(pos), dtype=bool)
    static[:2] = True
    points = np.array([[0.0, 0.0], [1.0, 1.0]])
    rows = qp.constraints(pos, vel, pref, static=static, points=points)
    out = qp.solve(pos, vel, pref, static=static, points=points)
    ref, ref_fell = solve_reference(rows)
    np.testing.assert_array_equal(out.fell_back, ref_fell)
    feasible = ~ref_fell
    assert feasible.sum() >= len(pos) // 2
    atol = 1e-6 if solver == "exact" else 1e-4
    np.testing.assert_allclose(out.velocity[feasible], ref[feasible], atol=atol)
    np.testing.assert_allclose(out.velocity[ref_fell], ref[ref_fell], atol=1e-3)
    assert np.all(out.velocity[static] == 0.0)
    # The second solve of a nearby scene reuses the OSQP solver (warm start, no new setup).
    qp.solve(pos + 1e-3, vel, pref, static=static, points=points)
    assert qp.stats["setup"] == (1 if solver == "osqp" else 0)


@pytest.mark.parametrize("seed", range(20, 40))
def test_exact_solver_equals_osqp_where_feasible(seed: int) -> None:
    world, pos, vel, pref = random_scene(seed, n=16)
    qp = VelocityAvoidance(world)
    exact = qp.solve(pos, vel, pref)
    osqp = VelocityAvoidance(world, solver="osqp").solve(pos, vel, pref)
    both = ~exact.fell_back & ~osqp.fell_back
    assert both.sum() >= 8
    np.testing.assert_allclose(exact.velocity[both], osqp.velocity[both], atol=5e-4)
    # OSQP's infeasibility detection is looser (it may fall back where cvxpy does not).
    _, ref_fell = solve_reference(qp.constraints(pos, vel, pref))
    np.testing.assert_array_equal(exact.fell_back, ref_fell)


def random_rows(rng: np.random.Generator, n: int, k: int, near: float) -> ConstraintRows:
    """Generic random 2-D QPs: k half-planes at distance ~U(-near, 1) from the origin
    (``near`` sets the share of infeasible instances), plus a box with lower bounds, a padded
    row, a parallel and a duplicated line, and rows of non-unit length."""
    ang = rng.uniform(0, 2 * np.pi, (n, k))
    A = np.stack([np.cos(ang), np.sin(ang)], axis=-1) * rng.uniform(0.2, 3.0, (n, k, 1))
    hi = rng.uniform(-near, 1.0, (n, k)) * np.linalg.norm(A, axis=-1)
    A[:, 1] = -A[:, 0]  # a parallel line (opposite side)
    hi[:, 1] = rng.uniform(-0.3, 1.5, n) * np.linalg.norm(A[:, 1], axis=-1)
    A[:, 2], hi[:, 2] = 2 * A[:, 3], 2 * hi[:, 3]  # the same line twice
    A[:, 4], hi[:, 4] = 0.0, np.inf  # padding
    lo = np.full((n, k), -np.inf)
    box = np.broadcast_to(np.eye(2), (n, 2, 2))
    c = rng.normal(0, 0.3, (n, 2))
    A = np.concatenate([A, box], axis=1)
    lo = np.concatenate([lo, c - 1.5], axis=1)
    hi = np.concatenate([hi, c + 1.5], axis=1)
    kind = np.r_[np.full(k, 1), 0, 0]
    pref = rng.normal(0, 2.0, (n, 2))
    return ConstraintRows(A, lo, hi, pref, kind, np.ones(n, dtype=bool))


@pytest.mark.parametrize(("k", "near"), [(5, 0.5), (8, 0.5), (30, 0.1), (30, 0.05)])
def test_exact_2d_solver_matches_cvxpy_on_random_instances(k: int, near: float) -> None:
    rng = np.random.default_rng(k)
    rows = random_rows(rng, 60, k, near)
    v, feasible = solve_qp_2d(rows.A, rows.lower, rows.upper, rows.preferred)
    ref, ref_fell = solve_reference(rows)
    np.testing.assert_array_equal(feasible, ~ref_fell)
    assert 5 <= feasible.sum() <= 55  # both kinds are exercised
    # Clarabel stops at about 1e-6 on ill-conditioned vertices; the exact answer is never
    # worse than its answer (which may violate rows by ~1e-9), and is feasible (below).
    np.testing.assert_allclose(v[feasible], ref[feasible], atol=1e-5)
    cost = np.sum((v - rows.preferred) ** 2, axis=1)
    ref_cost = np.sum((ref - rows.preferred) ** 2, axis=1)
    assert np.all(cost[feasible] <= ref_cost[feasible] + 1e-7)
    # Feasible answers satisfy every row; infeasible AGVs keep their preferred velocity.
    av = np.einsum("nrk,nk->nr", rows.A, v)
    assert np.all(av[feasible] <= rows.upper[feasible] + 1e-8)
    assert np.all(av[feasible] >= rows.lower[feasible] - 1e-8)
    np.testing.assert_array_equal(v[~feasible], rows.preferred[~feasible])


@pytest.mark.parametrize(("k", "near"), [(5, 0.5), (12, 0.8)])
def test_exact_least_violation_matches_cvxpy_and_osqp(k: int, near: float) -> None:
    rows = random_rows(np.random.default_rng(100 + k), 60, k, near)
    _, feasible = solve_qp_2d(rows.A, rows.lower, rows.upper, rows.preferred)
    idx = np.flatnonzero(~feasible)
    assert idx.size >= 5
    sub = ConstraintRows(rows.A[idx], rows.lower[idx], rows.upper[idx], rows.preferred[idx],
                         rows.kind, rows.active[idx])
    weight = np.array([FALLBACK_WEIGHT.get(int(q), 0.0) for q in rows.kind])
    v, t = least_violation_2d(sub.A, sub.lower, sub.upper, sub.preferred, weight)
    ref, ref_fell = solve_reference(sub)
    assert ref_fell.all() and np.all(t > 0) and np.all(np.isfinite(t))

    def objective(vel: np.ndarray) -> np.ndarray:
        av = np.einsum("nrk,nk->nr", sub.A, vel)
        soft = (weight > 0) & np.isfinite(sub.upper)
        viol = np.where(soft, (av - sub.upper) / np.where(weight > 0, weight, 1.0), -np.inf)
        return np.maximum(viol.max(axis=1), 0.0) + 0.5e-3 * np.sum((vel - sub.preferred) ** 2, 1)

    # Exact: never worse than Clarabel (whose answers can be 1e-4 off on these flat optima).
    assert np.all(objective(v) <= objective(ref) + 1e-9)
    np.testing.assert_allclose(objective(v), objective(ref), atol=1e-7)
    np.testing.assert_allclose(t, objective(v) - 0.5e-3 * np.sum((v - sub.preferred) ** 2, 1),
                               atol=1e-12)
    np.testing.assert_allclose(v, ref, atol=1e-3)
    # The hard rows (acceleration box) hold.
    av = np.einsum("nrk,nk->nr", sub.A, v)
    assert np.all(av[:, -2:] <= sub.upper[:, -2:] + 1e-8)
    assert np.all(av[:, -2:] >= sub.lower[:, -2:] - 1e-8)
    # The OSQP program agrees (to its tolerance).
    v_osqp, t_osqp = LeastViolation().solve(sub)
    np.testing.assert_allclose(t_osqp, t, atol=1e-4)


def test_exact_2d_solver_edge_cases() -> None:
    # Preferred velocity feasible: returned unchanged; no rows at all: likewise.
    A = np.array([[[1.0, 0.0], [0.0, 0.0]]])
    v, ok = solve_qp_2d(A, np.full((1, 2), -np.inf), np.array([[1.0, np.inf]]),
                        np.array([[0.5, 3.0]]))
    assert ok.all() and v.tolist() == [[0.5, 3.0]]
    v, ok = solve_qp_2d(np.zeros((2, 0, 2)), np.zeros((2, 0)), np.zeros((2, 0)), np.ones((2, 2)))
    assert ok.all() and np.all(v == 1.0)
    # Optimum at a vertex: x <= 1, y <= 1 from (2, 2); a zero row that can never hold.
    A = np.array([[[1.0, 0.0], [0.0, 1.0]], [[1.0, 0.0], [0.0, 0.0]]])
    v, ok = solve_qp_2d(A, np.full((2, 2), -np.inf), np.array([[1.0, 1.0], [1.0, -1.0]]),
                        np.array([[2.0, 2.0], [0.0, 0.0]]))
    assert ok.tolist() == [True, False]
    np.testing.assert_allclose(v[0], [1.0, 1.0], atol=1e-12)
    # Two parallel lines leave a strip: project onto the nearer one; a single point (x = 1,
    # y = 1 from both sides) is feasible; opposite parallel lines without a gap are not.
    A = np.array([[[0.0, 1.0], [0.0, -1.0], [1.0, 0.0], [-1.0, 0.0]]] * 3)
    hi = np.array([[1.0, 1.0, np.inf, np.inf], [1.0, -1.0, 1.0, -1.0], [1.0, -1.1, np.inf, np.inf]])
    v, ok = solve_qp_2d(A, np.full((3, 4), -np.inf), hi, np.array([[0.3, 5.0]] * 3))
    assert ok.tolist() == [True, True, False]
    np.testing.assert_allclose(v[:2], [[0.3, 1.0], [1.0, 1.0]], atol=1e-12)


def test_conflicting_constraints_fall_back_and_say_so() -> None:
    # AGV 0 moves fast at two parked AGVs it cannot avoid within its acceleration limit.
    world = World(bounds=(-2.0, -2.0, 2.0, 2.0))
    qp = VelocityAvoidance(world)
    pos = np.array([[0.0, 0.0], [0.38, 0.1], [0.38, -0.1], [-1.5, 1.5]])
    vel = np.array([[2.0, 0.0], [0.0, 0.0], [0.0, 0.0], [0.3, 0.0]])
    pref = np.array([[2.0, 0.0], [0.0, 0.0], [0.0, 0.0], [0.5, 0.0]])
    static = np.array([False, True, True, False])
    out = qp.solve(pos, vel, pref, static=static)
    assert out.fell_back.tolist() == [True, False, False, False]
    assert out.violation[0] > 0 and np.all(np.isfinite(out.velocity))
    ref, fell = solve_reference(qp.constraints(pos, vel, pref, static=static))
    assert fell.tolist() == out.fell_back.tolist()
    np.testing.assert_allclose(out.velocity, ref, atol=1e-3)
    # It still brakes as hard as it can: the acceleration box is hard.
    assert out.velocity[0, 0] == pytest.approx(0.75 * 2.0 - 0.5, abs=1e-3)


def test_fallback_weights_are_built_once_with_the_rows_and_used_by_every_solver() -> None:
    world = World(bounds=(-2.0, -2.0, 2.0, 2.0))
    pos = np.array([[0.0, 0.0], [0.38, 0.1], [0.38, -0.1], [-1.5, 1.5]])
    vel = np.array([[2.0, 0.0], [0.0, 0.0], [0.0, 0.0], [0.3, 0.0]])
    static = np.array([False, True, True, False])
    rows = VelocityAvoidance(world).constraints(pos, vel, vel, static=static)
    expected = [FALLBACK_WEIGHT.get(int(k), 0.0) for k in rows.kind]
    assert rows.weight.tolist() == expected == fallback_weights(rows.kind).tolist()
    assert take_rows(rows, [0, 3]).weight is rows.weight
    # Other weights (AGV 0 may violate its first neighbour row twice as much) reach the exact
    # solver, both OSQP back ends and the cvxpy reference alike, and change the answer.
    weight = rows.weight.copy()
    weight[0] = 2.0
    custom = ConstraintRows(rows.A, rows.lower, rows.upper, rows.preferred, rows.kind,
                            rows.active, weight)
    ref, fell = solve_reference(custom)
    assert fell.tolist() == [True, False, False, False]
    assert abs(ref[0, 1]) > 0.2  # with the default weights it is 0
    for solver in ("exact", "osqp"):
        v, fell_back, _, _ = VelocityAvoidance(world, solver=solver).solve_rows(custom)
        assert fell_back.tolist() == [True, False, False, False]
        np.testing.assert_allclose(v[0], ref[0], atol=1e-5)
    v, _ = least_violation_2d(custom.A[:1], custom.lower[:1], custom.upper[:1],
                              custom.preferred[:1], custom.weight)
    np.testing.assert_allclose(v[0], ref[0], atol=1e-6)
    v, _ = LeastViolation().solve(take_rows(custom, [0]))
    np.testing.assert_allclose(v[0], ref[0], atol=1e-5)
    default, _ = solve_reference(rows)
    assert abs(default[0, 1]) < 1e-6


def simulate(world: World, start: np.ndarray, goal: np.ndarray, steps: int,
             **config) -> tuple[float, np.ndarray]:
    """The simulator's integration (pos += vel dt; vel = (1 - d) vel + gain a) with the QP.

    Returns the smallest distance between two AGVs over the run and the final positions.
    """
    ph = world.physics
    gain = ph.sensitivity * ph.dt / ph.mass
    qp = VelocityAvoidance(world, **config)
    pos, vel = start.copy(), np.zeros_like(start)
    n = len(pos)
    iu = np.triu_indices(n, 1)
    closest = np.inf
    for _ in range(steps):
        ahead = pos + vel * ph.dt
        delta = goal - ahead
        dist = np.linalg.norm(delta, axis=1, keepdims=True)
        speed = np.minimum(np.minimum(1.5, np.sqrt(8.0 * dist)), dist / ph.dt)
        pref = delta / np.maximum(dist, 1e-9) * speed
        v = qp.solve(ahead, vel, pref).velocity
        action = np.clip((v - (1 - ph.damping) * vel) / gain, -1, 1)
        pos = pos + vel * ph.dt
        vel = (1 - ph.damping) * vel + gain * action
        gap = np.linalg.norm(pos[:, None] - pos[None], axis=-1)[iu].min()
        closest = min(closest, gap)
    return closest, pos


def test_circle_of_16_swaps_to_antipodes_without_overlap() -> None:
    world = World(bounds=(-3.0, -3.0, 3.0, 3.0))
    ang = 2 * np.pi * np.arange(16) / 16
    start = 2.2 * np.stack([np.cos(ang), np.sin(ang)], axis=1)
    closest, final = simulate(world, start, -start, steps=120)
    assert closest >= 2 * world.agent_radius
    assert np.linalg.norm(final - (-start), axis=1).max() < 0.1


@pytest.mark.parametrize("seed", range(3))
def test_dense_random_scenes_without_overlap(seed: int) -> None:
    world = World(bounds=(-1.5, -1.5, 1.5, 1.5))
    rng = np.random.default_rng(seed)
    start = spaced_points(rng, 20, world, 0.32)
    goal = spaced_points(rng, 20, world, 0.4)
    closest, final = simulate(world, start, goal, steps=80)
    assert closest >= 2 * world.agent_radius


def test_config_validation() -> None:
    with pytest.raises(ValueError, match="damping"):
        AvoidanceConfig(damping=0.25)
    with pytest.raises(ValueError, match="positions"):
        VelocityAvoidance().solve(np.zeros((3, 3)), np.zeros((3, 3)), np.zeros((3, 3)))
    with pytest.raises(ValueError, match="solver"):
        AvoidanceConfig(solver="cvxpy")
    with pytest.raises(ValueError, match="NaN"):
        VelocityAvoidance().solve(np.full((2, 2), np.nan), np.zeros((2, 2)), np.zeros((2, 2)))
