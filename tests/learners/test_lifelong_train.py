"""Training the entity learners on a lifelong floor (``train`` with ``warehouse-N``)."""

from __future__ import annotations

import csv
import json

import pytest
import torch

import sim
from learners.cli import add_train_arguments, run_train
from learners.policy import LearnedPolicy
from learners.train import LIFELONG_CSV_COLUMNS, TrainConfig, train

SMALL = {"hidden": 8, "batch_size": 16, "num_envs": 2, "learning_starts": 40,
         "buffer_size": 400}


def _config(run_dir, algo: str = "maddpg-e", episodes: int = 8) -> TrainConfig:
    return TrainConfig(algo=algo, reward="greedy", scenario="warehouse-20", episodes=episodes,
                       seed=1, run_dir=str(run_dir), eval_every=4, log_every=2,
                       checkpoint_every=4, window=15, eval_steps=30, progress=False,
                       tensorboard=False)


def _rows(path) -> list[dict[str, str]]:
    with path.open() as f:
        return list(csv.DictReader(f))


class _Crash(Exception):
    pass


@pytest.mark.parametrize("algo", ["maddpg-e", "bicnet-e"])
def test_lifelong_run_windows_checkpoints_and_resumes_bit_for_bit(tmp_path, algo):
    whole = train(_config(tmp_path / "whole", algo), SMALL)
    # 8 episodes = 4 windows of 15 steps in each of the 2 floors
    assert (whole.episodes, whole.env_steps) == (8, 2 * 4 * 15)
    assert whole.updates == whole.env_steps // 2 - 40 // 2 + 1
    rows = _rows(tmp_path / "whole" / "progress.csv")
    assert list(rows[0])[:len(LIFELONG_CSV_COLUMNS)] == LIFELONG_CSV_COLUMNS
    assert [r["episode"] for r in rows] == ["2", "4", "6", "8"]
    assert rows[1]["eval_throughput"] != "" and float(rows[1]["train_throughput"]) >= 0
    assert whole.best_throughput >= 0 and "throughput" in whole.last_eval
    assert (tmp_path / "whole" / "best.safetensors").is_file()

    def crash(counters):
        raise _Crash  # the process dies right after its first periodic checkpoint

    with pytest.raises(_Crash):
        train(_config(tmp_path / "cut", algo), SMALL, on_checkpoint=crash)
    resumed = train(_config(tmp_path / "cut", algo), resume=True)
    assert (resumed.episodes, resumed.env_steps, resumed.updates) == (
        whole.episodes, whole.env_steps, whole.updates)
    wa, wb = whole.learner.training_tensors(), resumed.learner.training_tensors()
    for k in wa:
        assert torch.equal(wa[k], wb[k]), k
    assert [r["train_throughput"] for r in _rows(tmp_path / "cut" / "progress.csv")] == \
        [r["train_throughput"] for r in rows]

    # the trained policy loads as a lifelong policy and drives sim.evaluate_lifelong
    policy = LearnedPolicy.load(tmp_path / "whole")
    assert policy.any_n and policy.learner.lifelong
    m = sim.evaluate_lifelong(policy, "warehouse-20", steps=20, seed=0)
    assert m.lost == 0 and m.steps == 20


def test_lifelong_refusals(tmp_path):
    with pytest.raises(ValueError, match="'warehouse-20' is lifelong; 'maddpg' trains"):
        TrainConfig(scenario="warehouse-20")
    for field in ("window", "eval_steps", "eval_runs"):
        with pytest.raises(ValueError, match=field):
            TrainConfig(algo="maddpg-e", scenario="warehouse-20", **{field: 0})
    episodic = train(TrainConfig(algo="maddpg-e", scenario="3v3", episodes=2, eval_every=0,
                                 eval_episodes=2, run_dir=str(tmp_path / "epi"),
                                 progress=False, tensorboard=False), SMALL)
    with pytest.raises(ValueError, match="trained on episodic scenes"):
        train(_config(tmp_path / "life"), SMALL,
              init_from=episodic.run_dir / "checkpoint.safetensors")


def test_an_evaluation_averages_eval_runs_runs(tmp_path):
    """``eval_runs`` runs per lifelong evaluation, batched on ``eval_seed``: the logged
    throughput is the one ``sim.evaluate_lifelong`` gives the final policy over that many."""
    config = _config(tmp_path / "runs")
    config.episodes, config.eval_every, config.eval_runs = 4, 0, 3
    result = train(config, SMALL)
    assert result.last_eval["runs"] == 3
    policy = LearnedPolicy.load(tmp_path / "runs" / "policy.safetensors")
    m = sim.evaluate_lifelong(policy, "warehouse-20", steps=config.eval_steps,
                              seed=config.eval_seed, runs=3)
    assert result.last_eval["throughput"] == pytest.approx(m.throughput, abs=1e-9)
    rows = _rows(tmp_path / "runs" / "progress.csv")
    assert float(rows[-1]["eval_throughput"]) == pytest.approx(m.throughput, abs=1e-6)


def test_agv_train_cli_on_a_lifelong_floor(tmp_path, capsys):
    run_dir = tmp_path / "cli"
    args = ["--algo", "maddpg-e", "--reward", "greedy", "--scenario", "warehouse-20",
            "--episodes", "2", "--eval-every", "0", "--run-dir", str(run_dir),
            "--no-progress", *[f"--set={k}={v}" for k, v in SMALL.items()]]
    import argparse

    parser = argparse.ArgumentParser()
    add_train_arguments(parser)
    assert run_train(parser.parse_args(args)) == 0
    rows = _rows(run_dir / "progress.csv")
    # the default window is 100 steps: 2 episodes = 1 window in each of 2 floors
    assert int(rows[-1]["episode"]) == 2 and int(rows[-1]["env_steps"]) == 2 * 100
    assert rows[-1]["eval_throughput"] != ""
    out = capsys.readouterr().out
    assert "throughput" in out and "deliveries / 1000 steps" in out and "nan" not in out
    # --window and --eval-steps reach the run
    run_dir = tmp_path / "cli-window"
    args[args.index("--run-dir") + 1] = str(run_dir)
    assert run_train(parser.parse_args([*args, "--window", "30", "--eval-steps", "40",
                                        "--eval-runs", "2"])) == 0
    rows = _rows(run_dir / "progress.csv")
    assert int(rows[-1]["env_steps"]) == 2 * 30
    config = json.loads((run_dir / "config.json").read_text())
    assert config["train"]["window"] == 30 and config["train"]["eval_steps"] == 40
    assert config["train"]["eval_runs"] == 2
    with pytest.raises(SystemExit):
        parser.parse_args([*args, "--window", "0"])


def test_shielded_training_stores_the_intended_actions(tmp_path):
    """With the shield in the loop on a lifelong floor (the fleet starts packed in the depot,
    so the shield changes most first actions) the buffer holds the policy's intended actions:
    the first step's equal those of the same run without the shield (same weights,
    observations and noise), while the executed ones differed."""
    from allocator import SafetyShield
    from learners.checkpoint import load_checkpoint

    stored = {}
    for shield in (False, True):
        config = _config(tmp_path / f"s{shield}", episodes=2)
        config.window = 10
        result = train(config, {**SMALL, "shield": shield}, make_shield=SafetyShield)
        tensors, _ = load_checkpoint(result.run_dir / "checkpoint.safetensors")
        stored[shield] = tensors["buffer.action"][:SMALL["num_envs"]]
    assert torch.equal(stored[False], stored[True])
    env = sim.make_env("warehouse-20", num_envs=SMALL["num_envs"], seed=config.seed)
    safety = SafetyShield(_Still())
    safety.reset(env)
    assert not torch.equal(safety.filter(stored[True]), stored[True])


class _Still:
    def reset(self, env):
        pass

    def act(self, obs):
        return torch.zeros(*obs.shape[:2], 2)
