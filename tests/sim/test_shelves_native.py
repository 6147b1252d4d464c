"""The fused shelf-collision kernel (sim/_native/shelves.h) against its torch reference."""

from __future__ import annotations

import pytest
import torch

import sim
from sim import native, physics

pytestmark = pytest.mark.skipif(not native.available(), reason="no C compiler here")


@pytest.mark.parametrize("seed", range(6))
def test_shelf_kernel_is_the_torch_reference_bit_for_bit(seed: int) -> None:
    world = sim.warehouse_floor(50)
    shelves = torch.tensor(world.obstacles, dtype=torch.float32)
    g = torch.Generator().manual_seed(seed)
    # Points all over the floor: clear, touching a face or a corner, inside a shelf.
    pos = torch.rand(16, 50, 2, generator=g) * torch.tensor(world.size, dtype=torch.float32)
    vel = torch.randn(16, 50, 2, generator=g)
    want = physics.collide_obstacles(pos, vel, shelves, world.agent_radius)
    got = physics.shelf_kernel(native.library(), shelves, world.agent_radius)(pos.clone(),
                                                                               vel.clone())
    assert torch.equal(got[0], want[0]) and torch.equal(got[1], want[1])
    assert bool((want[0] != pos).any())  # some discs were pushed


@pytest.mark.parametrize("scenario", ["warehouse", "warehouse-20"])
def test_steps_with_and_without_the_kernel_agree(scenario: str) -> None:
    runs = []
    for use in (True, False):
        env = sim.make_env(scenario, num_envs=4, seed=1, native=use)
        g = torch.Generator().manual_seed(0)
        for _ in range(30):
            env.step(torch.rand(4, env.num_agents, 2, generator=g) * 2 - 1)
        runs.append((env.agent_pos.clone(), env.agent_vel.clone()))
    assert torch.equal(runs[0][0], runs[1][0]) and torch.equal(runs[0][1], runs[1][1])


def test_kernel_checks_its_tensors() -> None:
    collide = physics.shelf_kernel(native.library(), torch.zeros(1, 4) + torch.tensor(
        [0.0, 0.0, 1.0, 1.0]), 0.15)
    with pytest.raises(ValueError, match="vel"):
        collide(torch.zeros(2, 3, 2), torch.zeros(2, 3, 2, dtype=torch.float64))
