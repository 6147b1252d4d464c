"""Serving the entity learners' weights (any N) through the learned allocators
(``allocator/learned.py``: ``weights=``, ``allocator/weights/any``) and the scale table's
any-N rows."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

import allocator
import sim
from allocator.learned import MissingWeightsError, any_n_weights_path, weights_path
from learners.train import TrainConfig, train
from tests.benchmarks.benchmark_scripts import load
from tests.learners.conftest import TINY


@pytest.fixture(scope="module")
def entity_policy(tmp_path_factory) -> Path:
    run = tmp_path_factory.mktemp("entity") / "run"
    train(TrainConfig(algo="maddpg-e", reward="ipf", scenario="3v3", episodes=8, seed=1,
                      run_dir=str(run), eval_every=8, eval_episodes=2, checkpoint_every=8,
                      progress=False, tensorboard=False), TINY)
    return run / "policy.safetensors"


@pytest.mark.parametrize("scenario", ["4v4", "10v10", "20v20", "7v12"])
def test_entity_weights_drive_any_nvm(entity_policy, scenario):
    solver = allocator.make("maddpg-ipf", scenario=scenario, checkpoint=entity_policy)
    assert solver.any_n
    m = sim.evaluate(solver, scenario, episodes=2, seed=0)
    assert 0.0 <= m.response_rate <= 1.0
    shielded = allocator.make("maddpg-ipf", scenario=scenario, checkpoint=entity_policy,
                              shield=True)
    m = sim.evaluate(shielded, scenario, episodes=2, seed=0)
    assert m.collisions == 0 and shielded.safety.agent_steps > 0


def test_entity_weights_assign_a_scene_of_any_size(entity_policy):
    solver = allocator.make("maddpg-ipf", scenario="12v12", checkpoint=entity_policy,
                            max_steps=5)
    rng = np.random.default_rng(0)
    agents, tasks = rng.uniform(-1.2, 1.2, (12, 2)), rng.uniform(-1.2, 1.2, (9, 2))
    result = solver.assign(agents, tasks)
    assert result.task_of_agent.shape == (12,) and result.agent_of_task.shape == (9,)
    assert solver.last_trajectories.shape == (6, 12, 2)


def test_entity_weights_bad_uses_are_clear_errors(entity_policy):
    with pytest.raises(ValueError, match="algo='maddpg-e', expected algo='bicnet-e'"):
        allocator.make("bicnet-ipf", scenario="20v20", checkpoint=entity_policy)
    with pytest.raises(ValueError, match="reward='ipf', expected reward='greedy'"):
        allocator.make("maddpg-greedy", scenario="20v20", checkpoint=entity_policy)
    with pytest.raises(ValueError, match="lifelong floor"):
        allocator.make("maddpg-ipf", scenario="warehouse-20", checkpoint=entity_policy)
    with pytest.raises(ValueError, match="weights must be one of"):
        allocator.make("maddpg-ipf", scenario="20v20", weights="all")


def test_which_shipped_weights_are_chosen():
    """The default (weights="scenario") loads the scenario's own weights, as before; "auto"
    falls back to the any-N weights where a scenario has none; "any" always takes them. A
    missing file is a MissingWeightsError naming what was looked for."""
    for name in ("maddpg-ipf", "bicnet-ipf"):
        algo, reward = name.split("-")
        if weights_path(algo, reward, "6v6").is_file():
            assert not allocator.make(name, scenario="6v6").any_n
            assert not allocator.make(name, scenario="6v6", weights="auto").any_n
        anyn = any_n_weights_path(algo, reward)
        if anyn.is_file():
            solver = allocator.make(name, scenario="50v50", weights="auto")
            assert solver.any_n and solver.checkpoint == anyn
            assert allocator.make(name, scenario="6v6", weights="any").any_n
            with pytest.raises(MissingWeightsError, match="weights='any'"):
                allocator.make(name, scenario="50v50")
        else:
            with pytest.raises(MissingWeightsError) as info:
                allocator.make(name, scenario="50v50", weights="auto")
            msg = str(info.value)
            assert f"50v50/{name}.safetensors" in msg and f"any/{name}.safetensors" in msg
            assert f"--algo {algo}-e" in msg and "--curriculum" in msg
            with pytest.raises(MissingWeightsError, match=f"any/{name}"):
                allocator.make(name, scenario="6v6", weights="any")
    with pytest.raises(MissingWeightsError, match="9v9/maddpg-greedy"):
        allocator.make("maddpg-greedy", scenario="9v9")


def test_scale_table_entity_rows(entity_policy, tmp_path):
    bench = load("scale_table")
    bench.main(["--sizes", "4", "--episodes", "2", "--floors", "--methods", "hungarian",
                "--entity", str(entity_policy), "--out", str(tmp_path)])
    rows = json.loads((tmp_path / "scale.json").read_text())["rows"]
    assert [(r["method"].split(":")[0], r["shield"]) for r in rows] == [
        ("hungarian", False), ("entity", False), ("entity", True)]
    assert rows[2]["overlaps"] == 0


def test_agv_evaluate_runs_an_entity_checkpoint_on_any_scenario(capsys):
    """`agv evaluate CHECKPOINT --scenario S` reads S's observations with S's layout (the
    checkpoint was trained on 20v20, whose observations have another size)."""
    import torch

    from allocator.cli import main
    from learners.policy import LearnedPolicy

    path = Path(allocator.__file__).parent / "weights" / "any" / "maddpg-ipf.safetensors"
    policy = LearnedPolicy.load(path)
    assert policy.any_n and policy.scenario != "8v8"
    assert main(["evaluate", str(path), "--scenario", "8v8", "--episodes", "2", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["scenario"] == "8v8" and 0.0 <= out["response_rate"] <= 1.0
    with pytest.raises(ValueError, match="cannot read observations of size 7"):
        LearnedPolicy.load(path).act(torch.zeros(1, 4, 7))


def test_shipped_lifelong_weights_drive_a_floor_safely() -> None:
    """allocator/weights/lifelong/maddpg-greedy: found by weights="auto" on any warehouse-N,
    shielded it never lets two AGVs overlap, and it delivers far more than the scripted
    nearest-task controller behind the same shield (on seed 3, 300 steps: 107 against 40
    deliveries per 1000 steps)."""
    from allocator import SafetyShield
    from sim.controllers import NearestTaskController

    assert any_n_weights_path("maddpg", "greedy", lifelong=True).is_file()
    solver = allocator.make("maddpg-greedy", scenario="warehouse-20", weights="auto",
                            shield=True)
    assert solver.checkpoint == any_n_weights_path("maddpg", "greedy", lifelong=True)
    assert solver.safety.keep_right == 0.0  # trained without lanes
    learned = sim.evaluate_lifelong(solver, "warehouse-20", steps=300, seed=3)
    scripted = sim.evaluate_lifelong(SafetyShield(NearestTaskController()), "warehouse-20",
                                     steps=300, seed=3)
    assert learned.collisions_per_1000 == 0 and learned.lost == 0
    assert learned.throughput > 1.5 * scripted.throughput
    bigger = allocator.make("maddpg-greedy", scenario="warehouse-50", weights="auto",
                            shield=True, keep_right=0.55)
    assert bigger.checkpoint == solver.checkpoint and bigger.safety.keep_right == 0.55
