"""The allocator controller in the simulator: Hungarian + ORCA serve every task safely."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import allocator
import sim


def test_hungarian_with_avoidance_serves_3v3_without_collisions() -> None:
    solver = allocator.make("hungarian")
    m = sim.evaluate(solver, "3v3", episodes=24, seed=1)
    assert m.collisions == 0.0
    assert m.response_rate == 1.0
    assert m.avg_time < 15


def test_greedy_is_a_controller_too() -> None:
    m = sim.evaluate(allocator.make("greedy"), "3v3", episodes=8, seed=2)
    assert m.response_rate > 0.9


def test_velocity_to_action_conversion_reaches_the_command() -> None:
    # Without avoidance the AGV follows its preferred velocity: after one step the simulator's
    # velocity equals (1 - damping) v + gain * action, the command when it is reachable.
    env = sim.make_env("1v1", num_envs=1, seed=0)
    env.set_state(torch.tensor([[[-0.5, 0.0]]]), torch.tensor([[[0.5, 0.0]]]))
    ctl = allocator.make("hungarian", avoidance=False).controller
    ctl.reset(env)
    action = ctl.act(env.observe())
    assert action[0, 0, 0] == pytest.approx(1.0)  # full throttle towards the task
    env.step(action)
    assert float(env.agent_vel[0, 0, 0]) == pytest.approx(0.5, abs=1e-6)


def test_reassigns_when_a_task_is_taken_by_another_agv() -> None:
    env = sim.make_env("2v2", num_envs=1, seed=0)
    env.set_state(torch.tensor([[[-0.5, 0.0], [0.5, 0.5]]]),
                  torch.tensor([[[-0.5, 0.5], [0.5, -0.5]]]))
    solver = allocator.make("hungarian")
    solver.reset(env)
    plan = solver.controller.task_of_agent.copy()
    solver.controller.task_of_agent[:] = plan[:, ::-1]  # a stale plan against the claims
    env.agent_task[0, 1] = int(plan[0, 1])
    env.task_claimed[0, int(plan[0, 1])] = True
    solver.act(env.observe())
    assert solver.controller.reassignments == 1
    assert solver.controller.task_of_agent[0, 0] == plan[0, 0]


@pytest.mark.slow
def test_warehouse_with_ompl_paths() -> None:
    solver = allocator.make("hungarian", planner="ompl")
    m = sim.evaluate(solver, "warehouse", episodes=8, seed=0)
    assert m.collisions == 0.0
    assert m.response_rate > 0.9
    assert np.isfinite(m.avg_time)
