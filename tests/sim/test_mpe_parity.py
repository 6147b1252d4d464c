"""One step of this simulator equals one step of mpe2's simple_spread_v3 (continuous actions)
from the same state and action, with walls, claiming and obstacles switched off."""

import numpy as np
import pytest
import torch

import sim
from sim.scenarios import Scenario
from sim.world import World

simple_spread_v3 = pytest.importorskip("mpe2.simple_spread_v3")


def _mpe_action(a: np.ndarray) -> np.ndarray:
    """Our (ax, ay) in [-1, 1] as mpe2's 5-dim continuous action [noop, -x, +x, -y, +y]."""
    return np.array([0.0, max(-a[0], 0), max(a[0], 0), max(-a[1], 0), max(a[1], 0)], np.float32)


@pytest.mark.parametrize("n", [3, 6])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_one_step_equals_mpe2(n: int, seed: int) -> None:
    rng = np.random.default_rng(seed)
    mpe = simple_spread_v3.parallel_env(N=n, continuous_actions=True, max_cycles=25)
    mpe.reset(seed=seed)
    world = mpe.unwrapped.world
    # A crowded state so the soft contact forces are exercised.
    pos = rng.uniform(-0.4, 0.4, size=(n, 2))
    pos[1] = pos[0] + rng.uniform(-0.15, 0.15, size=2)  # at least one overlapping pair
    vel = rng.uniform(-1.0, 1.0, size=(n, 2))
    act = rng.uniform(-1.0, 1.0, size=(n, 2))
    for i, agent in enumerate(world.agents):
        agent.state.p_pos = pos[i].copy()
        agent.state.p_vel = vel[i].copy()
    mpe.step({f"agent_{i}": _mpe_action(act[i]) for i in range(n)})
    mpe_pos = np.array([a.state.p_pos for a in world.agents])
    mpe_vel = np.array([a.state.p_vel for a in world.agents])

    # Open MPE world: no walls, no capture (radius tiny, tasks far outside the agents' reach).
    open_world = World(bounds=(-10, -10, 10, 10), walls=False, capture_radius=1e-6)
    scenario = Scenario("parity", open_world, num_agents=n, num_tasks=1, k_tasks=1,
                        k_agents=n - 1)
    env = sim.AGVEnv(scenario, num_envs=1, seed=0)
    env.set_state(torch.tensor(pos[None]), torch.tensor([[[9.0, 9.0]]]), torch.tensor(vel[None]))
    env.step(torch.tensor(act[None], dtype=torch.float32))
    np.testing.assert_allclose(env.agent_pos[0].numpy(), mpe_pos, atol=1e-5)
    np.testing.assert_allclose(env.agent_vel[0].numpy(), mpe_vel, atol=1e-5)
    # The check is not vacuous: contacts really acted in this scene.
    d = np.linalg.norm(pos[:, None] - pos[None], axis=-1) + np.eye(n) * 9
    assert d.min() < 0.3
