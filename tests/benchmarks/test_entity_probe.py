"""``benchmarks/entity_probe.py`` (issue 17's fine-tune probes): a tiny run from a tiny
checkpoint with the changed reward, and bad values as clear errors before any run."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from benchmark_scripts import load

import sim.rewards
from learners.checkpoint import read_metadata
from learners.train import TrainConfig, train

entity_probe = load("entity_probe")
TINY = {"hidden": 8, "batch_size": 16, "num_envs": 2, "learning_starts": 16,
        "buffer_size": 512}


def _start(tmp_path: Path) -> Path:
    config = TrainConfig(algo="bicnet-e", reward="ipf", scenario="3v3", episodes=4, seed=1,
                         run_dir=str(tmp_path / "start"), eval_every=0, progress=False,
                         tensorboard=False)
    return train(config, TINY).run_dir / "checkpoint.safetensors"


def test_a_tiny_probe_starts_from_an_ipf_run_with_the_changed_reward(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # The script registers its reward under 'ipf-time' for its process; restore it after.
    monkeypatch.setitem(sim.rewards.REWARD_VARIANTS, "ipf-time",
                        sim.rewards.REWARD_VARIANTS["ipf-time"])
    start = _start(tmp_path)
    settings = tmp_path / "config.json"
    settings.write_text(json.dumps({"bicnet-e": TINY}))
    name = str(tmp_path / "probes" / "p")  # absolute: runs/entity-probes/NAME is this folder
    entity_probe.main([name, "--start", str(start), "--scenario", "4v4", "--episodes", "4",
                       "--drop-parked-sources", "--assign-weight", "2",
                       "--settings", str(settings)])
    record = json.loads((tmp_path / "probes" / "p.probe.json").read_text())
    assert record["options"] == {"assign_weight": 2.0, "parked_sources": False}
    meta = read_metadata(tmp_path / "probes" / "p" / "checkpoint.safetensors")
    assert meta["reward"] == "ipf-time" and meta["scenario"] == "4v4"
    assert sim.rewards.REWARD_VARIANTS["ipf-time"]().parked_sources is False


def test_the_variant_is_restored_after_the_probe_test() -> None:
    # (runs after the test above in file order: the registry is the shipped one again)
    assert sim.rewards.make_reward("ipf-time").time_cost == sim.rewards.TIME_COST > 0


@pytest.mark.parametrize(("flags", "match"), [
    (["--assign-weight", "-1"], "assign_weight must be a finite number >= 0"),
    (["--settings", "/nonexistent/config.json"], "no such file"),
])
def test_bad_values_are_clear_errors_before_any_run(tmp_path: Path, flags, match) -> None:
    run = tmp_path / "probe"
    with pytest.raises(ValueError, match=match):
        entity_probe.main([str(run), "--start", str(tmp_path / "none"), *flags])
    assert not run.exists()
