"""The braking shield: its invariant as a property test on random states, geometry, bad input."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from allocator.avoidance.braking import (
    BrakingShield,
    braking_action,
    braking_offset,
    braking_velocity,
    segment_distance,
    segment_rect_distance,
)

DT, C, G, R = 0.1, 0.25, 0.5, 0.15


def sim_step(pos, vel, action):
    """The simulator's update (mpe order), without contacts: pos moves first."""
    return pos + vel * DT, (1 - C) * vel + G * np.clip(action, -1, 1)


def test_braking_offset_matches_simulated_braking() -> None:
    rng = np.random.default_rng(0)
    for _ in range(50):
        v = rng.uniform(-2.5, 2.5, 2)
        p = np.zeros(2)
        p0 = p.copy()
        total = braking_offset(v[None], DT, C, G)[0]
        vv = v.copy()
        for _ in range(20):
            a = braking_action(vv[None], C, G)[0]
            assert np.all(np.abs(a) <= 1 + 1e-12)
            p, vv = sim_step(p, vv, a)
        assert np.allclose(p - p0, total, atol=1e-12)
        assert np.allclose(vv, 0, atol=1e-12)
        assert np.allclose(braking_velocity(v[None], C, G)[0],
                           sim_step(p0, v, braking_action(v[None], C, G)[0])[1])


def test_segment_distance_cases() -> None:
    z = np.zeros(2)
    assert segment_distance(z, np.array([1.0, 0]), np.array([0.5, -1]), np.array([0.5, 1])) == 0
    assert segment_distance(z, np.array([1.0, 0]), np.array([2.0, 1]), np.array([3, 1.0])) \
        == pytest.approx(np.sqrt(2))
    assert segment_distance(z, z, np.array([0, 2.0]), np.array([0, 2.0])) == pytest.approx(2)
    d = segment_rect_distance(np.array([[0, 0.0]]), np.array([[1, 0.0]]),
                              np.array([[2, -1, 3, 1.0], [0.4, -0.1, 0.6, 0.1], [0, 1, 1, 2]]))
    assert np.allclose(d, [[1.0, 0.0, 1.0]])


def test_segment_distance_against_dense_sampling() -> None:
    rng = np.random.default_rng(1)
    a0, a1, b0, b1 = (rng.uniform(-1, 1, (200, 2)) for _ in range(4))
    d = segment_distance(a0, a1, b0, b1)
    t = np.linspace(0, 1, 101)
    pa = a0[:, None] + t[None, :, None] * (a1 - a0)[:, None]
    pb = b0[:, None] + t[None, :, None] * (b1 - b0)[:, None]
    sampled = np.linalg.norm(pa[:, :, None] - pb[:, None, :], axis=-1).min(axis=(1, 2))
    assert np.all(d <= sampled + 1e-12)
    assert np.all(sampled - d < 0.04)


def _random_safe_state(rng, n, half, margin):
    """n AGVs whose braking segments satisfy the invariant (rejection sampling)."""
    shield = BrakingShield(R, DT, C, G, margin=margin, bounds=(-half, -half, half, half))
    pos = []
    vel = []
    while len(pos) < n:
        p = rng.uniform(-half + R + 0.4, half - R - 0.4, 2)
        v = rng.uniform(-2, 2, 2) * rng.integers(0, 2)
        # the state's whole braking segment, the committed move v dt included
        end = p + braking_offset(v[None], DT, C, G)[0]
        ok = all(segment_distance(p, end, p2, p2 + braking_offset(b[None], DT, C, G)[0])
                 >= 2 * R + margin for p2, b in zip(pos, vel, strict=True))
        ok = ok and bool(np.all(np.abs(end) <= half - R - shield.static_margin))
        if ok:
            pos.append(p)
            vel.append(v)
    return shield, np.array(pos)[None], np.array(vel)[None]


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(2, 12), steps=st.integers(1, 6))
def test_no_overlap_from_any_state_satisfying_the_invariant(seed: int, n: int,
                                                            steps: int) -> None:
    """Whatever the candidates (random reachable velocities), no overlap after any step."""
    rng = np.random.default_rng(seed)
    shield, pos, vel = _random_safe_state(rng, n, 2.0, 0.01)
    movable = rng.random((1, n)) < 0.9
    for _ in range(steps):
        actions = rng.uniform(-1, 1, (1, n, 3, 2))
        cands = shield.realised(vel[:, :, None, :], actions)
        out = shield.filter(pos, vel, cands, movable)
        assert np.all(np.abs(out.action) <= 1 + 1e-12)
        new_pos = pos + np.where(movable[..., None], vel * DT, 0.0)
        new_vel = np.where(movable[..., None], (1 - C) * vel + G * out.action, vel)
        d = np.linalg.norm(new_pos[0, :, None] - new_pos[0, None], axis=-1)
        d[np.eye(n, dtype=bool)] = np.inf
        assert d.min() >= 2 * R + 0.01 - 1e-9
        assert np.all(np.abs(new_pos) <= 2.0 - R + 1e-9)
        # the velocities it chose are the ones the simulator reaches
        assert np.allclose(np.where(movable[..., None], out.velocity, vel), new_vel, atol=1e-9)
        pos, vel = new_pos, new_vel


def test_braking_is_chosen_when_nothing_else_is_safe() -> None:
    shield = BrakingShield(R, DT, C, G, margin=0.01)
    pos = np.array([[[-0.5, 0.0], [0.5, 0.0]]])
    vel = np.array([[[1.5, 0.0], [-1.5, 0.0]]])
    faster = shield.realised(vel[:, :, None], np.array([[[[1, 0]], [[-1, 0]]]]))
    out = shield.filter(pos, vel, faster, np.ones((1, 2), dtype=bool))
    # Each faster option clears the other's braking segment but not the other's option: one
    # of the two gives it up and brakes (the invariant then holds between the option kept
    # and that braking segment)
    assert out.braking.sum() == 1
    assert out.min_pair_gap >= 0.01 - 1e-9
    k = int(np.flatnonzero(out.braking[0])[0])
    assert np.allclose(out.action[0, k], [-1, 0] if k == 0 else [1, 0])
    # Both options aimed at the other's braking segment: both brake.
    closer = np.array([[[-0.3, 0.0], [0.3, 0.0]]])
    out = shield.filter(closer, vel, faster, np.ones((1, 2), dtype=bool))
    assert out.braking.all()
    assert np.allclose(out.action[0, 0], [-1, 0])


def test_two_agvs_closer_than_the_margin_can_still_part() -> None:
    # At rest 0.305 apart (below 2 r + margin): the one leaving may leave while the other,
    # heading the same way, waits; before, both braked for ever (a 3v3 miss).
    shield = BrakingShield(R, DT, C, G, margin=0.01)
    pos = np.array([[[0.0, 0.0], [0.305, 0.0]]])
    vel = np.zeros((1, 2, 2))
    want = shield.realised(vel[:, :, None], np.array([[[[1, 0]], [[1, 0]]]]))
    p, v = pos, vel
    for _ in range(5):
        out = shield.filter(p, v, shield.realised(v[:, :, None], np.array([[[[1, 0]], [[1, 0]]]])),
                            np.ones((1, 2), dtype=bool))
        p, v = sim_step(p, v, out.action)
        assert np.linalg.norm(p[0, 1] - p[0, 0]) >= 0.305 - 1e-9
    assert p[0, 1, 0] > 0.305 + 0.1  # the front AGV got away
    assert want.shape == (1, 2, 1, 2)


def test_shelves_and_walls_are_respected() -> None:
    shelf = np.array([[0.3, -0.5, 0.6, 0.5]])
    shield = BrakingShield(R, DT, C, G, bounds=(-1, -1, 1, 1), obstacles=shelf)
    pos = np.array([[[-0.2, 0.0], [0.0, 0.7]]])
    vel = np.array([[[0.5, 0.0], [0.0, 0.5]]])
    toward = shield.realised(vel[:, :, None], np.ones((1, 2, 1, 2)))
    p, v = pos, vel
    for _ in range(30):
        out = shield.filter(p, v, shield.realised(v[:, :, None], np.ones((1, 2, 1, 2))),
                            np.ones((1, 2), dtype=bool))
        p, v = sim_step(p, v, out.action)
        assert p[0, 0, 0] <= 0.3 - R + 1e-9  # never reaches the shelf
        assert np.all(np.abs(p) <= 1 - R + 1e-9)  # never reaches a wall
    assert toward.shape == (1, 2, 1, 2)


def test_unmovable_agvs_are_obstacles() -> None:
    shield = BrakingShield(R, DT, C, G)
    pos = np.array([[[0.0, 0.0], [0.45, 0.0]]])
    vel = np.array([[[1.0, 0.0], [0.0, 0.0]]])
    movable = np.array([[True, False]])
    p, v = pos, vel
    for _ in range(10):
        out = shield.filter(p, v, shield.realised(v[:, :, None], np.ones((1, 2, 1, 2))), movable)
        p = p + np.where(movable[..., None], v * DT, 0)
        v = np.where(movable[..., None], (1 - C) * v + G * out.action, v)
        assert np.linalg.norm(p[0, 0] - p[0, 1]) >= 2 * R + 0.01 - 1e-9


def test_many_envs_and_agents_use_the_tree() -> None:
    rng = np.random.default_rng(3)
    B, N = 3, 60
    grid = np.stack(np.meshgrid(np.arange(10), np.arange(6)), -1).reshape(-1, 2) * 0.7
    pos = np.repeat(grid[None], B, 0).astype(float)
    vel = np.zeros_like(pos)
    shield = BrakingShield(R, DT, C, G)
    cands = shield.realised(vel[:, :, None], rng.uniform(-1, 1, (B, N, 2, 2)))
    out = shield.filter(pos, vel, cands, np.ones((B, N), dtype=bool))
    assert out.min_pair_gap >= 0.01 - 1e-9


@pytest.mark.parametrize("kwargs, name", [
    (dict(radius=0.0), "radius"), (dict(dt=-1.0), "dt"), (dict(damping=1.0), "damping"),
    (dict(gain=float("nan")), "gain"), (dict(margin=-0.1), "margin"),
    (dict(bounds=(1, 0, 0, 1)), "bounds"), (dict(obstacles=np.zeros((2, 3))), "obstacles"),
    (dict(radius=True), "radius"),
])
def test_bad_parameters_name_the_argument(kwargs, name) -> None:
    base = dict(radius=R, dt=DT, damping=C, gain=G)
    base.update(kwargs)
    with pytest.raises(ValueError, match=name):
        BrakingShield(**base)


def test_bad_filter_input_names_the_argument() -> None:
    shield = BrakingShield(R, DT, C, G)
    pos = np.zeros((1, 2, 2))
    pos[0, 1] = 1.0
    ok = dict(pos=pos, vel=np.zeros((1, 2, 2)), candidates=np.zeros((1, 2, 1, 2)),
              movable=np.ones((1, 2), dtype=bool))
    for key, bad in (("pos", np.zeros((2, 2))), ("vel", np.zeros((1, 3, 2))),
                     ("candidates", np.zeros((1, 2, 2))), ("movable", np.ones((2,), bool)),
                     ("vel", np.full((1, 2, 2), np.nan))):
        args = dict(ok)
        args[key] = bad
        with pytest.raises(ValueError, match=key):
            shield.filter(**args)
