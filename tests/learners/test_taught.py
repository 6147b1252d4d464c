"""The taught family ``bicnet-dagger`` (``allocator.learned.TAUGHT``): BiCNet-E taught by
DAgger, shipped for any N, served with the whole scene in view."""

from __future__ import annotations

import json
import warnings

import numpy as np
import pytest

import allocator
import sim
from allocator.learned import (
    LEARNED,
    TAUGHT,
    MissingWeightsError,
    any_n_weights_path,
    whole_view,
)
from tests.learners.test_learned_allocator import _require_shipped

SHIPPED = any_n_weights_path("bicnet", "dagger")


@pytest.fixture(scope="module")
def shipped():
    _require_shipped(SHIPPED)
    return SHIPPED


def test_registered_under_its_own_name_not_a_reward():
    assert TAUGHT == {"bicnet": ("dagger",), "maddpg": ("dagger",)}  # maddpg: lifelong
    assert "bicnet-dagger" in LEARNED and "bicnet-dagger" in allocator.ALLOCATORS
    doc = LEARNED["bicnet-dagger"].__doc__
    assert "imitation" in doc and "reward" not in doc
    assert "trained with the ipf reward" in LEARNED["bicnet-ipf"].__doc__


@pytest.mark.parametrize("weights", [None, "scenario", "auto", "any"])
@pytest.mark.parametrize("scenario, view", [("20v20", (20, 19)), ("7v12", (12, 6)),
                                            ("3v3", (3, 2))])
def test_every_weights_choice_loads_the_any_n_file_with_the_whole_view(shipped, weights,
                                                                      scenario, view):
    solver = allocator.make("bicnet-dagger", scenario=scenario,
                            **({} if weights is None else {"weights": weights}))
    assert solver.taught and solver.any_n and solver.checkpoint == shipped
    assert (solver.scenario.k_tasks, solver.scenario.k_agents) == view
    # the same policy as the file served as bicnet-ipf (its RL stage's reward) at that view
    assert json.loads(shipped.with_suffix(".json").read_text())["reward"] == "ipf"


def test_whole_view_shows_every_task_and_agent():
    s = whole_view(sim.get_scenario("9v4"))
    assert (s.k_tasks, s.k_agents, s.num_agents, s.num_tasks) == (4, 8, 9, 4)
    s = whole_view(sim.get_scenario("1v1"))
    assert (s.k_tasks, s.k_agents) == (1, 0)
    assert (whole_view("12v7").k_tasks, whole_view("12v7").k_agents) == (7, 11)  # a name
    for bad in (3, None, float("nan"), "", "nope", "warehouse-20"):
        with pytest.raises(ValueError):
            whole_view(bad)


def test_same_results_as_the_policy_file_at_the_same_view(shipped):
    """The registry name adds no setting of its own: the Sinkhorn rounds and temperature
    come from the file's config."""
    scen = sim.get_scenario("10v10", k_tasks=10, k_agents=9)
    taught = allocator.make("bicnet-dagger", scenario="10v10", shield=True, detour="discs")
    file = allocator.make("bicnet-ipf", scenario="10v10", checkpoint=shipped, shield=True,
                          detour="discs")
    a = sim.evaluate(taught, taught.scenario, episodes=4, seed=3)
    b = sim.evaluate(file, scen, episodes=4, seed=3)
    np.testing.assert_array_equal(a.episode_time, b.episode_time)
    assert a.collisions == 0 and a.response_rate == b.response_rate
    config = taught.policy.learner.config
    assert (config.choice_sinkhorn, config.choice_sinkhorn_beta) == (256, 100.0)


def test_a_narrower_view_warns_once_and_still_runs(shipped):
    solver = allocator.make("bicnet-dagger", scenario="10v10")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        m = sim.evaluate(solver, "10v10", episodes=2, seed=0)
        sim.evaluate(solver, "10v10", episodes=2, seed=1)
    narrow = [w for w in caught if "whole scene in view" in str(w.message)]
    assert len(narrow) == 1 and "6 of 10 tasks" in str(narrow[0].message)
    assert 0.0 <= m.response_rate <= 1.0
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        sim.evaluate(allocator.make("bicnet-dagger", scenario="10v10"),
                     whole_view(sim.get_scenario("10v10")), episodes=2, seed=0)


def test_assign_sees_the_whole_given_scene(shipped):
    solver = allocator.make("bicnet-dagger", scenario="20v20", shield=True, detour="discs")
    rng = np.random.default_rng(4)
    agents, tasks = rng.uniform(-1.5, 1.5, (8, 2)), rng.uniform(-1.5, 1.5, (11, 2))
    seen = solver._scene_scenario(agents, tasks, None)
    assert (seen.k_tasks, seen.k_agents) == (11, 7)
    result = solver.assign(agents, tasks)
    served = result.task_of_agent[result.task_of_agent >= 0]
    assert len(served) == len(set(served.tolist())) > 0


def test_bad_uses_are_clear_errors(shipped, tmp_path):
    with pytest.raises(MissingWeightsError, match="episodic scenes .NvM. only"):
        allocator.make("bicnet-dagger", scenario="warehouse-20")
    paper = allocator.learned.weights_path("bicnet", "ipf", "3v3")
    if paper.is_file():
        with pytest.raises(ValueError, match="taught for any N: it needs an entity learner"):
            allocator.make("bicnet-dagger", scenario="3v3", checkpoint=paper)
    with pytest.raises(ValueError, match="weights must be one of"):
        allocator.make("bicnet-dagger", scenario="20v20", weights="whole")
    with pytest.raises(ValueError, match="detour must be"):
        allocator.make("bicnet-dagger", scenario="20v20", shield=True, detour="circles")


def test_the_demo_and_agv_evaluate_run_it_at_its_view(shipped, tmp_path, capsys):
    from allocator.cli import main
    from allocator.demo import scale_methods

    names = [name for name, _ in scale_methods()]
    assert "bicnet-dagger (any-N, shielded + discs detour)" in names
    assert main(["evaluate", "bicnet-dagger", "--scenario", "6v6", "--episodes", "2",
                 "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["scenario"] == "6v6" and 0.0 <= out["response_rate"] <= 1.0


def test_scale_table_runs_it_at_its_view_whatever_view_says(shipped, tmp_path):
    from tests.benchmarks.benchmark_scripts import load

    load("scale_table").main(["--sizes", "6", "--episodes", "2", "--floors", "--methods",
                              "hungarian", "bicnet-dagger", "--view", "3:2", "--out",
                              str(tmp_path)])
    rows = json.loads((tmp_path / "scale.json").read_text())["rows"]
    assert [(r["method"], r["shield"], r["view"]) for r in rows] == [
        ("hungarian", False, "3:2"), ("bicnet-dagger any-N", False, "6:5"),
        ("bicnet-dagger any-N", True, "6:5")]
    assert rows[2]["overlaps"] == 0


def test_a_missing_checkpoint_is_named(tmp_path):
    missing = tmp_path / "nowhere.safetensors"
    with pytest.raises(FileNotFoundError, match="nowhere"):
        allocator.make("bicnet-dagger", scenario="20v20", checkpoint=missing)


def test_scenario_to_run_is_the_taught_familys_own_and_anyone_elses_as_given(shipped):
    from allocator.learned import scenario_to_run

    taught = allocator.make("bicnet-dagger", scenario="20v20")
    assert scenario_to_run(taught, "20v20") is taught.scenario
    assert scenario_to_run(allocator.make("hungarian"), "20v20") == "20v20"
