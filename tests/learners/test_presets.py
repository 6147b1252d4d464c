"""Named learner settings (``learners.algorithms.PRESETS``) and ``agv train --preset``."""

from __future__ import annotations

import argparse
import dataclasses

import pytest

from learners.algorithms import ALGORITHMS, PRESETS, make_config, preset_overrides
from learners.cli import _preset, add_train_arguments
from learners.train import TrainConfig, train
from tests.learners.conftest import TINY


@pytest.mark.parametrize("algo", sorted(ALGORITHMS))
def test_every_preset_is_a_valid_config_and_default_is_the_defaults(algo):
    for preset in PRESETS:
        cfg = make_config(algo, preset_overrides(algo, preset))
        cfg.validate()
    assert preset_overrides(algo, "default") == {}
    fast = make_config(algo, preset_overrides(algo, "fast"))
    default = make_config(algo)
    # the fast preset collects more transitions per gradient update
    assert (fast.num_envs / fast.updates_per_step
            >= 4 * default.num_envs / default.updates_per_step)


def test_preset_overrides_returns_a_copy_and_names_bad_input():
    preset_overrides("maddpg", "fast")["num_envs"] = 1
    assert PRESETS["fast"]["maddpg"]["num_envs"] != 1
    with pytest.raises(ValueError, match="preset"):
        preset_overrides("maddpg", "fastest")
    with pytest.raises(ValueError, match="algorithm"):
        preset_overrides("ppo", "fast")


def test_cli_preset_comes_before_set():
    parser = argparse.ArgumentParser()
    add_train_arguments(parser)
    args = parser.parse_args(["--preset", "fast", "--set", "num_envs=32"])
    assert _preset("maddpg", args) == PRESETS["fast"]["maddpg"]
    args = parser.parse_args([])
    assert _preset("bicnet", args) == {}
    with pytest.raises(SystemExit):
        parser.parse_args(["--preset", "nope"])


@pytest.mark.parametrize(("num_envs", "updates_per_step"), [(8, 2), (32, 1)])
def test_training_keeps_the_configured_updates_per_transition(tmp_path, num_envs,
                                                              updates_per_step):
    """updates = updates_per_step x (vectorized steps once learning has started)."""
    cfg = {**TINY, "num_envs": num_envs, "updates_per_step": updates_per_step}
    result = train(TrainConfig(algo="maddpg", reward="minidist", scenario="3v3", episodes=40,
                               seed=3, run_dir=str(tmp_path / "run"), eval_every=0,
                               eval_episodes=2, checkpoint_every=10**6, progress=False,
                               tensorboard=False), cfg)
    steps = result.env_steps // num_envs
    before = -(-TINY["learning_starts"] // num_envs) - 1  # vectorized steps without updates
    assert result.updates == updates_per_step * (steps - before)
    saved = result.learner.config
    assert dataclasses.asdict(saved)["num_envs"] == num_envs
