"""The taught lifelong family ``maddpg-dagger`` (``allocator.learned.TAUGHT``): MADDPG-E's
actor taught by DAgger which open order each AGV heads for, driving as ``WaypointDriver``
(``waypoint_drive``), shipped for lifelong floors, served with 16 pickups and AGVs in view."""

from __future__ import annotations

import json
import warnings

import pytest

import allocator
import sim
from allocator.learned import (
    LEARNED,
    LIFELONG_ONLY,
    TAUGHT,
    TAUGHT_LIFELONG_VIEW,
    MissingWeightsError,
    any_n_weights_path,
    scenario_to_run,
    taught_view,
)
from tests.benchmarks.benchmark_scripts import ROOT
from tests.learners.test_learned_allocator import _require_shipped

SHIPPED = any_n_weights_path("maddpg", "dagger", lifelong=True)


@pytest.fixture(scope="module")
def shipped():
    _require_shipped(SHIPPED)
    return SHIPPED


def test_registered_with_how_it_was_taught():
    assert TAUGHT["maddpg"] == ("dagger",) and "maddpg-dagger" in allocator.ALLOCATORS
    for name in LIFELONG_ONLY:  # what the episodic registry tests leave out: lifelong only
        algo, how = name.split("-")
        assert any_n_weights_path(algo, how, lifelong=True).is_file()
        assert not any_n_weights_path(algo, how).is_file()
    doc = LEARNED["maddpg-dagger"].__doc__
    assert "imitation" in doc and "lifelong floors" in doc and "reward" not in doc


@pytest.mark.parametrize("weights", [None, "scenario", "auto", "any"])
@pytest.mark.parametrize("floor", ["warehouse-20", "warehouse-50"])
def test_every_weights_choice_loads_the_lifelong_file_at_its_view(shipped, weights, floor):
    solver = allocator.make("maddpg-dagger", scenario=floor,
                            **({} if weights is None else {"weights": weights}))
    assert solver.taught and solver.any_n and solver.lifelong and solver.checkpoint == shipped
    view = (solver.scenario.k_pickups, solver.scenario.k_agents)
    assert view == (TAUGHT_LIFELONG_VIEW, TAUGHT_LIFELONG_VIEW) == (16, 16)
    assert solver.policy.learner.config.waypoint_drive is True
    # the view it was taught with, as recorded beside the weights
    record = json.loads((ROOT / "benchmarks/results/scale/lifelong/taught/seed2/dagger.probe.json")
                        .read_text())
    assert record["view"] == TAUGHT_LIFELONG_VIEW and record["waypoint_drive"] is True


def test_taught_view_of_a_floor_and_of_a_scene():
    s = taught_view("warehouse-50")
    assert (s.k_pickups, s.k_agents, s.num_agents) == (16, 16, 50)
    assert (taught_view("9v4").k_tasks, taught_view("9v4").k_agents) == (4, 8)
    with pytest.raises(ValueError):
        taught_view("nope")


def test_shielded_on_its_view_it_delivers_without_overlaps_as_the_file_does(shipped):
    solver = allocator.make("maddpg-dagger", scenario="warehouse-20", shield=True)
    assert solver.safety.keep_right == 0.5  # the lanes it was taught behind
    m = sim.evaluate_lifelong(solver, solver.scenario, steps=150, seed=2)
    assert m.delivered > 0 and m.collisions_per_1000 == 0
    same = allocator.make("maddpg-greedy", scenario="warehouse-20", weights=shipped,
                          shield=True)
    again = sim.evaluate_lifelong(same, solver.scenario, steps=150, seed=2)
    assert again.delivered == m.delivered


def test_a_narrower_view_warns_once_and_still_runs(shipped):
    solver = allocator.make("maddpg-dagger", scenario="warehouse-20", shield=True)
    with pytest.warns(UserWarning, match="16 open pickups and 16 other AGVs in view; this "
                                         "env shows 4 and 4"):
        m = sim.evaluate_lifelong(solver, "warehouse-20", steps=20, seed=0)
    assert m.collisions_per_1000 == 0
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        sim.evaluate_lifelong(solver, "warehouse-20", steps=5, seed=1)  # once only
        sim.evaluate_lifelong(allocator.make("maddpg-dagger", scenario="warehouse-20"),
                              taught_view("warehouse-20"), steps=5, seed=1)


def test_bad_uses_are_clear_errors(shipped):
    with pytest.raises(MissingWeightsError, match="lifelong floors .warehouse-N. only"):
        allocator.make("maddpg-dagger", scenario="20v20")
    with pytest.raises(ValueError, match="lifelong floors .warehouse-N., not"):
        allocator.make("maddpg-dagger", scenario="20v20", checkpoint=shipped)
    with pytest.raises(ValueError, match="weights must be one of"):
        allocator.make("maddpg-dagger", scenario="warehouse-20", weights="sixteen")
    with pytest.raises(ValueError, match="keep_right is the shield's lane angle"):
        allocator.make("maddpg-dagger", scenario="warehouse-20", keep_right=0.5)


def test_the_tables_run_it_at_its_view(shipped, tmp_path):
    from allocator.demo import lifelong_methods
    from tests.benchmarks.benchmark_scripts import load

    assert "maddpg-dagger (shielded)" in [name for name, _ in lifelong_methods()]
    solver = allocator.make("maddpg-dagger", scenario="warehouse-20")
    assert scenario_to_run(solver, "warehouse-20") is solver.scenario
    rows = load("shield_lifelong").main([
        "--floor", "warehouse-20", "--steps", "30", "--weights", "maddpg-dagger",
        "--variants", "lanes", "--keep-right", "0.5", "--baselines",
        "--out", str(tmp_path / "s.md")])
    assert [r["method"] for r in rows] == ["learned (maddpg-dagger)"] and rows[0]["overlaps"] == 0
    load("scale_table").main(["--sizes", "--floors", "warehouse-20", "--lifelong-steps", "30",
                              "--dispatchers", "fifo", "--out", str(tmp_path)])
    table = json.loads((tmp_path / "scale.json").read_text())["rows"]
    taught = [r for r in table if r["method"] == "maddpg-dagger (shipped)"]
    assert [r["view"] for r in taught] == ["16:16", "16:16"]
    assert [r["view"] for r in table if r["method"] == "fifo"] == ["4:4"]
