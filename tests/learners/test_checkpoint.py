"""Checkpoints: round trip, atomic files, and clear errors for every kind of bad file."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from learners.checkpoint import load_checkpoint, read_metadata, save_checkpoint
from learners.maddpg import MADDPG, MADDPGConfig
from learners.policy import LearnedPolicy


def _policy_file(tmp_path: Path, algo: str = "maddpg", scenario: str = "3v3") -> Path:
    import dataclasses

    import sim
    from learners.algorithms import make_learner

    env = sim.make_env(scenario, num_envs=1)
    learner = make_learner(algo, env.obs_dim, env.state_dim, env.num_agents, {"hidden": 8})
    meta = {"kind": "policy", "algo": algo, "reward": "ipf", "scenario": scenario,
            "num_agents": env.num_agents, "num_tasks": env.num_tasks, "obs_dim": env.obs_dim,
            "state_dim": env.state_dim, "config": dataclasses.asdict(learner.config)}
    return save_checkpoint(tmp_path / f"{algo}.safetensors", learner.policy_tensors(), meta)


def _training_meta(learner: MADDPG) -> dict:
    import dataclasses

    from learners.train import TrainConfig

    return {"kind": "training", "algo": "maddpg", "reward": "ipf", "scenario": "3v3",
            "seed": 0, "num_agents": 3, "num_tasks": 3, "obs_dim": 24, "state_dim": 24,
            "config": dataclasses.asdict(learner.config),
            "train_config": dataclasses.asdict(TrainConfig()), "episodes": 0, "env_steps": 0,
            "updates": 0, "seconds": 0.0, "best_response_rate": -1.0, "last_eval": {}}


def test_round_trip_training_state(tmp_path):
    torch.manual_seed(0)
    learner = MADDPG(24, 24, 3, MADDPGConfig(hidden=8))
    path = save_checkpoint(tmp_path / "ckpt", learner.training_tensors(),
                           _training_meta(learner))
    assert path.name == "ckpt.safetensors" and path.with_suffix(".json").is_file()
    tensors, meta = load_checkpoint(path, algo="maddpg")
    other = MADDPG(24, 24, 3, MADDPGConfig(hidden=8))
    other.load_training_tensors(tensors)
    for a, b in zip(learner.state_dict().values(), other.state_dict().values(), strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=0)
    sidecar = json.loads(path.with_suffix(".json").read_text())
    assert sidecar["sha256"] == meta["sha256"] and "package" in sidecar["code_version"]
    assert not list(tmp_path.glob("*.tmp")) and not list(tmp_path.glob(".*")), (
        "temporary files left behind")


def test_policy_loads_and_acts(tmp_path):
    path = _policy_file(tmp_path)
    policy = LearnedPolicy.load(path.with_suffix(".json"), algo="maddpg", scenario="3v3")
    actions = policy.act(torch.zeros(5, 3, 24))
    assert actions.shape == (5, 3, 2) and actions.abs().max() <= 1


@pytest.mark.parametrize("expected, match", [
    ({"scenario": "6v6"}, "scenario='3v3', expected scenario='6v6'"),
    ({"algo": "bicnet"}, "algo='maddpg', expected algo='bicnet'"),
    ({"obs_dim": 48}, "obs_dim=24, expected obs_dim=48"),
])
def test_wrong_scenario_algo_or_obs_size_is_named(tmp_path, expected, match):
    path = _policy_file(tmp_path)
    with pytest.raises(ValueError, match=match):
        LearnedPolicy.load(path, **expected)


def test_wrong_observation_size_at_act_time(tmp_path):
    policy = LearnedPolicy.load(_policy_file(tmp_path))
    with pytest.raises(ValueError, match=r"shape \(B, N, 24\)"):
        policy.act(torch.zeros(2, 3, 48))


def test_truncated_file_is_reported(tmp_path):
    path = _policy_file(tmp_path)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(ValueError, match="truncated or corrupted"):
        LearnedPolicy.load(path)


def test_flipped_byte_is_reported(tmp_path):
    path = _policy_file(tmp_path)
    data = bytearray(path.read_bytes())
    data[-5] ^= 0xFF  # inside the last tensor's bytes
    path.write_bytes(bytes(data))
    with pytest.raises(ValueError, match="corrupted"):
        LearnedPolicy.load(path)


def test_garbage_and_foreign_files_are_reported(tmp_path):
    junk = tmp_path / "junk.safetensors"
    junk.write_bytes(b"\x00\x01not a safetensors file at all")
    with pytest.raises(ValueError, match="truncated or corrupted"):
        read_metadata(junk)
    from safetensors.torch import save_file

    foreign = tmp_path / "foreign.safetensors"
    save_file({"w": torch.zeros(2)}, str(foreign))
    with pytest.raises(ValueError, match="not an agv learner checkpoint"):
        read_metadata(foreign)
    with pytest.raises(FileNotFoundError, match="no checkpoint at"):
        read_metadata(tmp_path / "missing.safetensors")


def test_no_pickle_anywhere():
    """No checkpoint is ever read through pickle: no torch.load / pickle in learners."""
    root = Path(__file__).resolve().parents[2]
    files = list((root / "learners").glob("*.py")) + [root / "allocator" / "learned.py"]
    for f in files:
        text = f.read_text()
        assert "torch.load" not in text and "import pickle" not in text, f
