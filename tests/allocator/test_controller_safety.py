"""The episodic controller's safety shield and liveness rules (issue 14)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import allocator
import sim
from allocator.controller import AllocatorController
from tests.benchmarks.benchmark_scripts import load

_antipodal = load("antipodal")
AntipodalAllocator = _antipodal.AntipodalAllocator
circle_scenario, circle_scene = _antipodal.circle_scenario, _antipodal.circle_scene


def run_circle(n: int, radius: float, kind: str, steps: int = 200, **opts):
    from sim.env import AGVEnv

    scn = circle_scenario(n, radius, kind, steps)
    env = AGVEnv(scn, num_envs=1, reward="minidist", seed=0)
    a, t = circle_scene(n, radius, kind)
    env.set_state(torch.as_tensor(a[None], dtype=torch.float32),
                  torch.as_tensor(t[None], dtype=torch.float32))
    ctl = AllocatorController(AntipodalAllocator(), avoidance_options=opts or None)
    ctl.reset(env)
    overlaps = 0
    while not bool(env.done.all()):
        _, _, _, info = env.step(ctl.act(None))
        overlaps += int(info["collision_pairs"].sum())
    return int(env.task_claimed.sum()), overlaps, ctl


@pytest.mark.parametrize("kind", ["opposite", "on-path"])
def test_small_antipodal_circle_is_served_without_overlap(kind: str) -> None:
    served, overlaps, ctl = run_circle(8, 0.8, kind)
    assert overlaps == 0
    assert served == 8


def test_symmetric_circle_deadlocks_without_the_liveness_rules_and_not_with_them() -> None:
    # 12 AGVs exactly symmetric: the ORCA QP alone freezes them around the centre.
    served_off, _, _ = run_circle(12, 1.0, "opposite", steps=120, liveness=False)
    served_on, overlaps, ctl = run_circle(12, 1.0, "opposite", steps=120)
    assert served_on == 12 and overlaps == 0
    assert served_off < served_on


def test_shield_keeps_the_gap_in_every_step() -> None:
    _, overlaps, ctl = run_circle(10, 0.9, "opposite", steps=150)
    assert overlaps == 0
    assert ctl.last_shield.min_pair_gap >= -1e-6  # segments never closer than 2 r


def test_dense_random_scenes_do_not_overlap() -> None:
    m = sim.evaluate(allocator.make("hungarian"), "20v20", episodes=4, seed=0)
    assert m.collisions == 0.0


def test_warehouse_shelves_are_respected() -> None:
    solver = allocator.make("hungarian")
    env = sim.make_env("warehouse", num_envs=4, seed=0)
    env.reset()
    solver.reset(env)
    shelves = np.asarray(env.world.obstacles)
    r = env.world.agent_radius
    while not bool(env.done.all()):
        _, _, _, info = env.step(solver.act(None))
        assert float(info["collision_pairs"].sum()) == 0.0
        p = env.agent_pos.double().numpy().reshape(-1, 2)
        closest = np.clip(p[:, None, :], shelves[None, :, :2], shelves[None, :, 2:])
        assert np.linalg.norm(p[:, None] - closest, axis=-1).min() >= r - 1e-5


@pytest.mark.parametrize("key, value", [("shield_margin", -1.0),
                                        ("perturbation", float("nan"))])
def test_bad_shield_options_name_the_option(key: str, value: float) -> None:
    with pytest.raises(ValueError, match=key):
        AllocatorController(AntipodalAllocator(), avoidance_options={key: value})
