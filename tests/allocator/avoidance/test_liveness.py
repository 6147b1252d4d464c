"""DeadlockResolver: who yields in a wait-for cycle, determinism, bad input."""

from __future__ import annotations

import numpy as np
import pytest

from allocator.avoidance.liveness import DeadlockResolver, neighbour_pairs


def stalled_ring(n: int, steps: int = 3, seed: int = 0):
    ang = 2 * np.pi * np.arange(n) / n
    pos = 0.25 * np.stack([np.cos(ang), np.sin(ang)], -1)[None]
    pref = -pos / np.linalg.norm(pos, axis=-1, keepdims=True)  # all towards the centre
    res = DeadlockResolver(1, n, 0.15, seed=seed)
    active = np.ones((1, n), dtype=bool)
    for _ in range(steps):
        out = res.apply(pos, pref, active, np.zeros((1, n), dtype=bool), 1.0)
    return res, pos, pref, out


def test_in_a_wait_for_cycle_the_highest_priority_agv_does_not_yield() -> None:
    res, _, pref, out = stalled_ring(4)
    top = int(np.argmax(res.priority[0]))
    assert res.yield_left[0, top] == 0
    assert (res.yield_left[0] > 0).sum() >= 1
    # the top AGV is not sent backwards; the yielding ones are
    assert (out[0, top] * pref[0, top]).sum() > 0


def test_two_agvs_facing_each_other_exactly_one_yields() -> None:
    pos = np.array([[[-0.2, 0.0], [0.2, 0.0]]])
    pref = np.array([[[1.0, 0.0], [-1.0, 0.0]]])
    res = DeadlockResolver(1, 2, 0.15, seed=3)
    for _ in range(3):
        res.apply(pos, pref, np.ones((1, 2), bool), np.zeros((1, 2), bool), 1.0)
    assert (res.yield_left[0] > 0).sum() == 1


def test_parked_agvs_are_not_yielded_to() -> None:
    pos = np.array([[[-0.2, 0.0], [0.2, 0.0]]])
    pref = np.array([[[1.0, 0.0], [0.0, 0.0]]])
    res = DeadlockResolver(1, 2, 0.15, seed=0)
    res.priority[:] = [[0, 1]]  # the parked one has the higher priority
    active = np.array([[True, False]])
    for _ in range(3):
        out = res.apply(pos, pref, active, np.zeros((1, 2), bool), 1.0)
    assert res.yield_left[0, 0] == 0
    assert out[0, 0, 1] < 0  # it turns right around the parked AGV instead


def test_same_seed_same_output() -> None:
    a = stalled_ring(6, seed=7)[3]
    b = stalled_ring(6, seed=7)[3]
    np.testing.assert_array_equal(a, b)


def test_neighbour_pairs_tree_matches_brute_force() -> None:
    rng = np.random.default_rng(0)
    pts = rng.uniform(0, 5, (2, 80, 2))
    got = {tuple(p) for p in neighbour_pairs(pts, 0.5)}
    want = set()
    for b in range(2):
        for i in range(80):
            for j in range(i + 1, 80):
                if np.linalg.norm(pts[b, i] - pts[b, j]) < 0.5:
                    want.add((b * 80 + i, b * 80 + j))
    assert got == want


@pytest.mark.parametrize("kwargs, name", [
    (dict(num_envs=0), "num_envs"), (dict(num_agents=True), "num_agents"),
    (dict(radius=-1.0), "radius"), (dict(perturbation=-1e-4), "perturbation"),
    (dict(stall_steps=0), "stall_steps"), (dict(reach=float("inf")), "reach"),
])
def test_bad_parameters_name_the_argument(kwargs, name) -> None:
    base = dict(num_envs=1, num_agents=2, radius=0.15)
    base.update(kwargs)
    with pytest.raises(ValueError, match=name):
        DeadlockResolver(**base)


def test_wrong_shapes_are_refused() -> None:
    res = DeadlockResolver(1, 2, 0.15)
    with pytest.raises(ValueError, match="preferred"):
        res.apply(np.zeros((1, 2, 2)), np.zeros((1, 3, 2)), np.ones((1, 2), bool),
                  np.ones((1, 2), bool), 1.0)
