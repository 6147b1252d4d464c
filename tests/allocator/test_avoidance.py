"""The ORCA velocity QP: OSQP against the cvxpy reference, the fallback, and zero overlaps."""

from __future__ import annotations

import numpy as np
import pytest

from allocator.avoidance import AvoidanceConfig, VelocityAvoidance, solve_reference
from sim.world import World
from tests.allocator.conftest import spaced_points


def random_scene(seed: int, n: int = 12, world: World | None = None):
    rng = np.random.default_rng(seed)
    world = world or World(bounds=(-2.0, -2.0, 2.0, 2.0))
    pos = spaced_points(rng, n, world, 0.36)
    vel = rng.normal(0, 0.6, (n, 2))
    pref = rng.normal(0, 1.0, (n, 2))
    return world, pos, vel, pref


@pytest.mark.parametrize("seed", range(6))
def test_osqp_matches_the_cvxpy_reference(seed: int) -> None:
    world, pos, vel, pref = random_scene(seed)
    qp = VelocityAvoidance(world)
    static = np.zeros(len(pos), dtype=bool)
    static[:2] = True
    points = np.array([[0.0, 0.0], [1.0, 1.0]])
    rows = qp.constraints(pos, vel, pref, static=static, points=points)
    out = qp.solve(pos, vel, pref, static=static, points=points)
    ref, ref_fell = solve_reference(rows)
    np.testing.assert_array_equal(out.fell_back, ref_fell)
    feasible = ~ref_fell
    assert feasible.sum() >= len(pos) // 2
    np.testing.assert_allclose(out.velocity[feasible], ref[feasible], atol=1e-4)
    np.testing.assert_allclose(out.velocity[ref_fell], ref[ref_fell], atol=1e-3)
    assert np.all(out.velocity[static] == 0.0)
    # The second solve of a nearby scene reuses the solver (warm start, no new setup).
    qp.solve(pos + 1e-3, vel, pref, static=static, points=points)
    assert qp.stats["setup"] == 1


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
    with pytest.raises(ValueError, match="NaN"):
        VelocityAvoidance().solve(np.full((2, 2), np.nan), np.zeros((2, 2)), np.zeros((2, 2)))
