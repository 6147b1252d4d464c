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
from tests.allocator.test_shield import _run


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
    detour = ParkedDetour(model="squares")  # the discs model keeps the goal: see below
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


@pytest.mark.parametrize("model", ["squares", "discs"])
def test_a_free_line_or_no_parked_agv_changes_nothing(model) -> None:
    env = sim.make_env("2v2", num_envs=1, seed=0)
    env.set_state(np.array([[[-0.8, 0.0], [0.0, 0.6]]]), np.array([[[0.0, 0.6], [0.8, 0.0]]]))
    detour = ParkedDetour(model=model)
    detour.reset(env)
    intended = np.array([[[1.0, 0.0], [0.0, 0.0]]])
    out, turned = detour.redirect(intended, movable_agents(env))  # nobody parked yet
    assert not turned.any() and np.array_equal(out, intended)
    env.step(torch.zeros(1, 2, 2))  # AGV 1 parks off the line
    out, turned = detour.redirect(intended, movable_agents(env))
    assert not turned.any() and np.array_equal(out, intended)


def _drive(env, detour, steps: int) -> SafetyShield:
    """``steps`` steps of the nearest-task controller behind a shield with ``detour``; no
    two AGVs may overlap on the way."""
    shield = SafetyShield(NearestTaskController(), detour=detour)
    assert _run(env, shield, steps) == 0
    return shield


def test_the_shield_with_detours_reaches_the_task_that_it_is_held_from_without() -> None:
    reached = {}
    for detour in (False, "squares", "discs"):
        env = _wall_scene(num_envs=2)
        shield = _drive(env, detour, 30)
        reached[detour] = bool(env.task_claimed[:, 1].all())
        assert (shield.interventions["detour"] > 0) == bool(detour)
    assert reached == {False: False, "squares": True, "discs": True}


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


@pytest.mark.parametrize("value", [None, float("nan"), 1e300, "", 1, "circles", "Discs"])
def test_detour_flag_takes_a_bool_or_a_model_name(value) -> None:
    with pytest.raises(ValueError, match="detour must be True, False or one of 'squares', "
                                         "'discs'"):
        SafetyShield(NearestTaskController(), detour=value)
    with pytest.raises(ValueError, match="detour must be"):
        allocator.make("bicnet-ipf", scenario="6v6", shield=True, detour=value)


def test_detour_models_reach_the_shield() -> None:
    # True is the default model, discs since 2026-12-07 (squares before)
    assert SafetyShield(NearestTaskController(), detour=True).detour_model == "discs"
    assert ParkedDetour().model == "discs" == allocator.detour.DEFAULT_MODEL
    assert SafetyShield(NearestTaskController(), detour="squares").detour_model == "squares"
    assert SafetyShield(NearestTaskController()).detour_model is None
    ctl = allocator.make("bicnet-ipf", scenario="6v6", shield=True, detour="discs")
    assert ctl.safety.detour is True and ctl.safety.detour_model == "discs"
    assert "discs" in repr(ctl.safety)
    m = sim.evaluate(ctl, "6v6", episodes=4, seed=0)
    assert m.collisions == 0 and 0.0 < m.response_rate <= 1.0


def test_discs_model_settings_name_the_problem() -> None:
    for kwargs, word in ((dict(model="circles"), "model"), (dict(model=None), "model"),
                         (dict(model="squares", clearance=0.02), "needs model='discs'"),
                         (dict(model="discs", clearance=-0.01), "clearance"),
                         (dict(model="discs", clearance=float("nan")), "clearance"),
                         (dict(model="discs", clearance="wide"), "clearance"),
                         (dict(model="discs", clearance=1e300), "clearance")):
        with pytest.raises(ValueError, match=word):
            ParkedDetour(**kwargs)
    assert ParkedDetour(model="discs").clearance == pytest.approx(0.011)
    assert ParkedDetour().lookahead == 18 and ParkedDetour(model="squares").lookahead == 6


def _slot_scene(num_envs: int = 1):
    """AGVs 1 and 2 park 0.617 apart across the line from idle AGV 0 to task 2: a slot the
    AGV's disc fits through (0.6) but the shield's gaps do not (0.62)."""
    env = sim.make_env("3v3", num_envs=num_envs, seed=0)
    half = 0.3085
    env.set_state(np.array([[[-0.8, 0.0], [0.0, half], [0.0, -half]]] * num_envs),
                  np.array([[[0.0, half], [0.0, -half], [0.8, 0.0]]] * num_envs))
    env.step(torch.zeros(num_envs, 3, 2))  # AGVs 1 and 2 claim tasks 0 and 1 and park
    assert env.agent_task[:, 0].eq(-1).all() and env.agent_task[:, 1:].ge(0).all()
    return env


def test_the_discs_model_goes_round_a_slot_the_shield_does_not_let_through() -> None:
    reached = {}
    for model in ("squares", "discs"):
        env = _slot_scene()
        shield = _drive(env, model, 40)
        reached[model] = bool(env.task_claimed[0, 2])
        # squares: the line 0.3085 from both parked centres counts as free, so no detour
        assert (shield.interventions["detour"] > 0) == (model == "discs")
    assert reached == {"squares": False, "discs": True}


def test_the_discs_model_keeps_the_goal_while_the_intention_points_elsewhere() -> None:
    kept = {}
    for model in ("squares", "discs"):
        env = _wall_scene()
        detour = ParkedDetour(model=model)
        detour.reset(env)
        intended = np.zeros((1, 2, 2))
        intended[0, 0] = [1.0, 0.0]  # at task 1, through the parked AGV: turned
        assert detour.redirect(intended, movable_agents(env))[1][0, 0]
        intended[0, 0] = [0.0, -1.0]  # at no open task (the detour's momentum, say)
        out, turned = detour.redirect(intended, movable_agents(env))
        kept[model] = bool(turned[0, 0])
        if turned[0, 0]:
            assert out[0, 0, 0] > 0 or abs(out[0, 0, 1]) > 0.3  # still round, toward task 1
        # an AGV that means to stop is left alone either way; that drops the goal
        intended[0, 0] = [0.0, 0.0]
        assert not detour.redirect(intended, movable_agents(env))[1].any()
        intended[0, 0] = [0.0, -1.0]
        assert not detour.redirect(intended, movable_agents(env))[1].any()
    assert kept == {"squares": False, "discs": True}


@pytest.mark.parametrize("name,value", [("cone", float("nan")), ("cone", 1e300), ("cone", None),
                                        ("distance_weight", float("inf")), ("speed", "fast"),
                                        ("speed", float("inf")), ("lookahead", 2.5)])
def test_detour_settings_refuse_nan_huge_empty_and_wrong_types(name, value) -> None:
    with pytest.raises(ValueError, match=name):
        ParkedDetour(**{name: value})


def test_a_shielded_assign_rolls_out_with_the_same_detours(monkeypatch) -> None:
    models = []
    original = ParkedDetour.reset

    def spy(self, env):
        models.append(self.model)
        original(self, env)

    monkeypatch.setattr(ParkedDetour, "reset", spy)
    ctl = allocator.make("bicnet-ipf", scenario="6v6", shield=True, detour="discs")
    rng = np.random.default_rng(0)
    plan = ctl.assign(rng.uniform(-1, 1, (6, 2)) * [1, 0.3] + [0, 0.6],
                      rng.uniform(-1, 1, (6, 2)) * [1, 0.3] - [0, 0.6])
    assert models == ["discs"] and plan.task_of_agent.shape == (6,)
    models.clear()
    allocator.make("bicnet-ipf", scenario="6v6", shield=True).assign(
        np.array([[-1.0, 0.0], [1.0, 0.0]]), np.array([[0.0, 1.0], [0.0, -1.0]]))
    assert models == []
