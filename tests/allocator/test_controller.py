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


def test_a_parked_agv_at_a_wall_is_passed_at_once_on_the_side_with_room() -> None:
    # AGV 1 parks on AGV 0's straight line to its task, 0.46 from the left wall: no AGV fits
    # between them, so AGV 0 must go round the right at once (it used to slide into the gap
    # at the wall and wait there for the stall re-routing: a 3v3 miss).
    env = sim.make_env("2v2", num_envs=1, seed=0)
    env.set_state(torch.tensor([[[-0.56, -0.81], [-0.54, 0.0]]]),
                  torch.tensor([[[-0.71, 0.54], [-0.54, 0.05]]]))
    # (the plan untangling would give AGV 0 the near task instead: the detour is tested alone)
    solver = allocator.make("hungarian", avoidance_options={"untangle": False})
    solver.reset(env)
    ctl = solver.controller
    assert ctl.task_of_agent[0].tolist() == [0, 1]
    obs = env.observe()
    sides = []
    for _ in range(25):
        obs, _, done, info = env.step(solver.act(obs))
        assert int(info["collision_pairs"].sum()) == 0
        sides.append(float(ctl._detour_side[0, 0]))
        if bool(done.all()):
            break
    assert bool(env.task_claimed.all())
    assert ctl.detours > 0 and -1.0 in sides and 1.0 not in sides  # the right, never the wall
    assert int(env.steps[0]) <= 20


def test_detour_and_short_horizons_can_be_switched_off() -> None:
    ctl = allocator.make("hungarian", avoidance_options={"detour": False}).controller
    assert ctl.detour is False
    env = sim.make_env("3v3", num_envs=2, seed=0)
    ctl.reset(env)
    assert ctl._avoidance().config.time_horizon == 0.3
    assert ctl._avoidance().config.static_time_horizon == 0.15
    off = allocator.make("hungarian", avoidance_options={"shield": False}).controller
    off.reset(env)
    assert off._avoidance().config.time_horizon == 1.0  # no shield: the conservative QP
    assert off._avoidance().config.static_time_horizon is None
