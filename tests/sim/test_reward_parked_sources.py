"""``IPFReward(parked_sources=False)`` (issues 16 and 17): parked AGVs leave the other AGVs'
fields, in an environment's step as in the grid's method; bad values."""

from __future__ import annotations

import pytest
import torch

import sim
from sim.ipf import TASK_VALUE, ipf_grid
from sim.rewards import IPFReward


def _stepped(reward: IPFReward) -> tuple[sim.AGVEnv, dict[str, torch.Tensor]]:
    scenario = sim.Scenario(name="hand", world=sim.World(), num_agents=3, num_tasks=3)
    env = sim.AGVEnv(scenario, num_envs=1, reward=reward, seed=0)
    # AGV 0 parks on task 0 in the step, between AGV 1 and its task; AGV 2 is far.
    env.set_state(torch.tensor([[[0.0, 0.0], [0.45, 0.0], [-0.8, 0.8]]]),
                  torch.tensor([[[0.0, 0.0], [-0.6, 0.0], [0.8, -0.8]]]))
    _, _, _, info = env.step(torch.zeros(1, 3, 2))
    assert env.agent_task[0].tolist() == [0, -1, -1]
    return env, info["reward_terms"]


def test_the_ipf_term_leaves_parked_agvs_out_of_the_field() -> None:
    env, dropped = _stepped(IPFReward(parked_sources=False))
    _, kept = _stepped(IPFReward())
    grid = ipf_grid(env.world)
    want = grid.reward_potentials(env.agent_pos, env.task_pos, env.task_claimed,
                                  env.agent_task, parked_sources=False)
    torch.testing.assert_close(dropped["ipf"], want.to(dropped["ipf"].dtype))
    assert float(dropped["ipf"][0, 0]) == TASK_VALUE == float(kept["ipf"][0, 0])
    # AGV 1 stands next to the parked AGV 0: its -3 no longer pulls AGV 1's field down.
    assert float(dropped["ipf"][0, 1]) > float(kept["ipf"][0, 1]) + 0.5
    for term in ("goal", "collision"):
        torch.testing.assert_close(dropped[term], kept[term])


@pytest.mark.parametrize("bad", [0, 1, "no", None])
def test_a_bad_parked_sources_is_refused(bad) -> None:
    with pytest.raises(ValueError, match="parked_sources must be True or False"):
        IPFReward(parked_sources=bad)
