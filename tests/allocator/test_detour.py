"""Detours round parked AGVs (allocator/detour.py) and the shield's ``detour=True``."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import allocator
import sim
from allocator.detour import ParkedDetour, blocked_segments
from allocator.shield import SafetyShield, movable_agents
from sim.controllers import NearestTaskController


def test_blocked_segments_geometry() -> None:
    start = np.array([[[0.0, 0.0], [0.0, 0.0]]])
    end = np.array([[[2.0, 0.0], [0.0, 2.0]]])
    centres = np.array([[[1.0, 0.2], [3.0, 0.0]]])
    assert blocked_segments(start, end, centres, 0.3).tolist() == [[True, False]]
    # beyond the end point the segment is not blocked; a masked centre does not count
    assert blocked_segments(start, end, centres, 0.3,
                            np.array([[False, True]])).tolist() == [[False, False]]


def _wall_scene(num_envs: int = 1):
    """AGV 1 parks on task 0 at the origin, right between idle AGV 0 and task 1."""
    env = sim.make_env("2v2", num_envs=num_envs, seed=0)
    env.set_state(np.array([[[-0.8, 0.0], [0.0, 0.0]]] * num_envs),
                  np.array([[[0.0, 0.0], [0.8, 0.0]]] * num_envs))
    env.step(torch.zeros(num_envs, 2, 2))  # AGV 1 claims task 0 and parks
    assert env.agent_task[:, 1].eq(0).all() and env.agent_task[:, 0].eq(-1).all()
    return env


def test_an_intention_through_a_parked_agv_is_turned_round_it() -> None:
    env = _wall_scene()
    detour = ParkedDetour()
    detour.reset(env)
    intended = np.zeros((1, 2, 2))
    intended[0, 0] = [1.0, 0.0]  # straight at task 1, through the parked AGV
    out, turned = detour.redirect(intended, movable_agents(env))
    assert turned.tolist() == [[True, False]]
    assert abs(out[0, 0, 1]) > 0.3  # sideways, round the parked AGV
    assert np.linalg.norm(out[0, 0]) == pytest.approx(1.5)  # the detour's speed
    assert detour.redirected == 1
    # pointing away from every open task: left alone
    intended[0, 0] = [-1.0, 0.0]
    out, turned = detour.redirect(intended, movable_agents(env))
    assert not turned.any() and np.array_equal(out, intended)


def test_a_free_line_or_no_parked_agv_changes_nothing() -> None:
    env = sim.make_env("2v2", num_envs=1, seed=0)
    env.set_state(np.array([[[-0.8, 0.0], [0.0, 0.6]]]), np.array([[[0.0, 0.6], [0.8, 0.0]]]))
    detour = ParkedDetour()
    detour.reset(env)
    intended = np.array([[[1.0, 0.0], [0.0, 0.0]]])
    out, turned = detour.redirect(intended, movable_agents(env))  # nobody parked yet
    assert not turned.any() and np.array_equal(out, intended)
    env.step(torch.zeros(1, 2, 2))  # AGV 1 parks off the line
    out, turned = detour.redirect(intended, movable_agents(env))
    assert not turned.any() and np.array_equal(out, intended)


def test_the_shield_with_detours_reaches_the_task_that_it_is_held_from_without() -> None:
    reached = {}
    for detour in (False, True):
        env = _wall_scene(num_envs=2)
        shield = SafetyShield(NearestTaskController(), detour=detour)
        shield.reset(env)
        obs = env.observe()
        pairs = 0
        for _ in range(30):
            obs, _, _, info = env.step(shield.act(obs))
            pairs += int(info["collision_pairs"].sum())
        assert pairs == 0
        reached[detour] = bool(env.task_claimed[:, 1].all())
        assert (shield.interventions["detour"] > 0) == detour
    assert reached == {False: False, True: True}


def test_bad_settings_and_modes_name_the_problem() -> None:
    for kwargs, word in ((dict(cone=2.0), "cone"), (dict(distance_weight=-1), "distance_weight"),
                         (dict(min_speed=float("nan")), "min_speed"), (dict(lookahead=0),
                                                                        "lookahead"),
                         (dict(speed=0.0), "speed"), (dict(speed=True), "speed")):
        with pytest.raises(ValueError, match=word):
            ParkedDetour(**kwargs)
    with pytest.raises(ValueError, match="reset"):
        ParkedDetour().redirect(np.zeros((1, 2, 2)), np.ones((1, 2), dtype=bool))
    with pytest.raises(ValueError, match="detour"):
        SafetyShield(NearestTaskController(), detour="yes")
    life = sim.make_env("warehouse-20", num_envs=1, seed=0)
    with pytest.raises(ValueError, match="episodic"):
        SafetyShield(NearestTaskController(), detour=True).reset(life)
    with pytest.raises(ValueError, match="shield=True"):
        allocator.make("bicnet-ipf", scenario="6v6", detour=True)
    with pytest.raises(ValueError, match="detour"):
        allocator.make("bicnet-ipf", scenario="6v6", shield=True, detour=1)


def test_learned_allocator_passes_detour_to_its_shield() -> None:
    ctl = allocator.make("bicnet-ipf", scenario="6v6", shield=True, detour=True)
    assert ctl.safety.detour is True
    assert allocator.make("bicnet-ipf", scenario="6v6", shield=True).safety.detour is False
    m = sim.evaluate(ctl, "6v6", episodes=4, seed=0)
    assert m.collisions == 0 and 0.0 < m.response_rate <= 1.0


@pytest.mark.parametrize("value", [None, float("nan"), 1e300, "", 1])
def test_detour_flag_takes_only_a_bool(value) -> None:
    with pytest.raises(ValueError, match="detour must be True or False"):
        SafetyShield(NearestTaskController(), detour=value)


@pytest.mark.parametrize("name,value", [("cone", float("nan")), ("cone", 1e300), ("cone", None),
                                        ("distance_weight", float("inf")), ("speed", "fast"),
                                        ("speed", float("inf")), ("lookahead", 2.5)])
def test_detour_settings_refuse_nan_huge_empty_and_wrong_types(name, value) -> None:
    with pytest.raises(ValueError, match=name):
        ParkedDetour(**{name: value})
