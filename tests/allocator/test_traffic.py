"""SafeDriver: the lifelong driver with a safety shield (issue 14)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import sim
from allocator.dispatch import HungarianDispatcher
from allocator.traffic import SafeDriver


def test_safe_driver_drives_a_lifelong_floor_without_collisions() -> None:
    driver = SafeDriver()
    m = sim.evaluate_lifelong(HungarianDispatcher(driver=driver), "warehouse-20", steps=100,
                              seed=0, faults=sim.Breakdowns(rate=2e-3, repair_steps=30))
    assert m.collisions_per_1000 == 0.0
    assert m.lost == 0
    assert np.isfinite(m.wait_mean)  # orders were picked up (deliveries take longer)
    assert driver.steps == 100


def test_safe_driver_actions_have_the_interface_of_waypoint_driver() -> None:
    env = sim.make_env("warehouse-20", num_envs=2, seed=1)
    env.reset()
    disp = HungarianDispatcher(driver=SafeDriver())
    disp.reset(env)
    a = disp.act(None)
    assert a.shape == (2, env.num_agents, 2) and a.dtype == torch.float32
    assert bool((a.abs() <= 1).all())
    assert disp.distances is disp.driver.distances


def test_act_before_reset_is_refused() -> None:
    with pytest.raises(ValueError, match="reset"):
        SafeDriver().act(None)


@pytest.mark.parametrize("kwargs, name", [
    (dict(gain=0), "gain"), (dict(max_speed=-1.0), "max_speed"), (dict(margin=-0.1), "margin"),
    (dict(perturbation=float("nan")), "perturbation"), (dict(seed=-1), "seed"),
    (dict(avoidance="yes"), "avoidance"), (dict(avoidance_options=3), "avoidance_options"),
    (dict(keep_right=-0.1), "keep_right"),
])
def test_bad_parameters_name_the_argument(kwargs, name) -> None:
    with pytest.raises(ValueError, match=name):
        SafeDriver(**kwargs)


def test_seeded_runs_are_identical() -> None:
    outs = []
    for _ in range(2):
        env = sim.make_env("warehouse-20", num_envs=1, seed=3)
        env.reset()
        disp = HungarianDispatcher(driver=SafeDriver(seed=5))
        disp.reset(env)
        for _ in range(10):
            env.step(disp.act(None))
        outs.append(env.agent_pos.clone())
    assert torch.equal(outs[0], outs[1])
    assert np.isfinite(outs[0].numpy()).all()
