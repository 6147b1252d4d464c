"""Every field of every training configuration is checked when the configuration is made."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from learners.algorithms import make_config, make_learner
from learners.bicnet import BiCNetConfig
from learners.maddpg import MADDPGConfig
from learners.train import TrainConfig

NAN, INF = math.nan, math.inf

# field -> (bad values, words the message must hold besides the field name)
SHARED = {
    "hidden": ([0, -4, 2.5, "64", True, None], ">= 1"),
    "actor_lr": ([0.0, -1e-3, NAN, INF, "1e-3", None], "(0, inf)"),
    "critic_lr": ([0.0, -1e-3, NAN, INF, True], "(0, inf)"),
    "gamma": ([NAN, -0.1, 1.0, 1.5, INF, "0.95"], "[0, 1)"),
    "tau": ([0.0, 5, -0.01, NAN, INF], "(0, 1]"),
    "batch_size": ([0, -1, 32.0, "32"], ">= 1"),
    "buffer_size": ([0, -5, 1e5, None], ">= 1"),
    "num_envs": ([0, -2, 1.5], ">= 1"),
    "updates_per_step": ([0, -1, 0.5], ">= 1"),
    "learning_starts": ([-1, 1.5, None], ">= 0"),
    "noise_start": ([-0.1, NAN, INF, "0.5"], "[0, inf)"),
    "noise_end": ([-0.1, NAN, INF], "[0, inf)"),
    "noise_decay_episodes": ([-1, 2.5, NAN], ">= 0"),
    "grad_clip": ([0.0, -0.5, NAN, INF], "(0, inf)"),
    "action_l2": ([-1e-3, NAN, INF], "[0, inf)"),
    "reward_scale": ([INF, NAN, 0.0, -1.0, "2"], "(0, inf)"),
    "terminal_value": (["bogus", "", None, 0], "['absorbing', 'zero']"),
    "mask_parked": (["yes", 1, None], "True or False"),
}
MADDPG_ONLY = {
    "layers": ([0, -1, 2.5], ">= 1"),
    "critic_input": (["global", None, 3], "['obs', 'state', 'state+obs']"),
}
BICNET_ONLY = {
    "input_layers": ([0, -1, 1.5], ">= 1"),
    "output_layers": ([0, -2, "2"], ">= 1"),
}
TRAIN = {
    "algo": (["ppo", None, 3], "maddpg"),
    "reward": (["dense", None, 1], "ipf"),
    "scenario": (["bogus", None, 3], "scenario"),
    "episodes": ([0, -5, 2.5, "100", True], ">= 1"),
    "seed": ([-1, 1.5, "0", None, 2**63], "[0, "),
    "run_dir": ([3, ""], "folder path"),
    "eval_every": ([-1, 2.5], ">= 0"),
    "eval_episodes": ([0, -3, 1.5], ">= 1"),
    "eval_seed": ([-1, 0.5, None], "[0, "),
    "log_every": ([0, -1, 1.5], ">= 1"),
    "checkpoint_every": ([0, -1, 1.5], ">= 1"),
    "stop_response": ([NAN, -0.1, 1.5, INF, "0.9"], "[0, 1]"),
    "fastest_min_response": ([NAN, -0.1, 1.5, INF, "0.9", None], "[0, 1]"),
    "critic_warmup": ([-1, 2.5, "10", None, True], ">= 0"),
    "threads": ([0, -1, 1.5], ">= 1"),
    "progress": (["no", None], "True or False"),
    "tensorboard": (["no", 0], "True or False"),
    "window": ([0, -1, 1.5, "100"], ">= 1"),
    "eval_steps": ([0, -2, 2.5, None], ">= 1"),
    "eval_runs": ([0, -1, 1.5, "2", None, True], ">= 1"),
}


def _cases(fields: dict[str, tuple[list, str]]) -> list:
    return [pytest.param(name, bad, words, id=f"{name}={bad!r}")
            for name, (values, words) in fields.items() for bad in values]


def _check(make, name: str, bad, words: str) -> None:
    with pytest.raises(ValueError) as info:
        make(**{name: bad})
    msg = str(info.value)
    assert name in msg or (name == "reward" and "reward" in msg), msg
    assert words in msg, msg


@pytest.mark.parametrize("cls", [MADDPGConfig, BiCNetConfig], ids=lambda c: c.__name__)
@pytest.mark.parametrize("name, bad, words", _cases(SHARED))
def test_learner_config_rejects_a_bad_field_when_made(cls, name, bad, words):
    """hidden=0 gave a ZeroDivisionError, hidden=-4 and batch_size=0 RuntimeErrors, gamma=nan,
    tau=5 and reward_scale=inf NaN weights, terminal_value=bogus a late error,
    updates_per_step=0 no updates at all: all only once training had started."""
    _check(cls, name, bad, words)


@pytest.mark.parametrize("name, bad, words", _cases(MADDPG_ONLY))
def test_maddpg_config_rejects_a_bad_field_when_made(name, bad, words):
    _check(MADDPGConfig, name, bad, words)


@pytest.mark.parametrize("name, bad, words", _cases(BICNET_ONLY))
def test_bicnet_config_rejects_a_bad_field_when_made(name, bad, words):
    _check(BiCNetConfig, name, bad, words)


@pytest.mark.parametrize("name, bad, words", _cases(TRAIN))
def test_train_config_rejects_a_bad_field_when_made(tmp_path, name, bad, words):
    _check(lambda **kw: TrainConfig(**{"run_dir": str(tmp_path), **kw}), name, bad, words)


def test_config_fields_that_do_not_fit_together_are_refused():
    with pytest.raises(ValueError, match=r"buffer_size \(4\) must be at least num_envs \(16\)"):
        MADDPGConfig(buffer_size=4, num_envs=16, learning_starts=0)
    with pytest.raises(ValueError, match=r"learning_starts \(5000\) must be at most buffer_size"):
        BiCNetConfig(buffer_size=1000, learning_starts=5000)


def test_every_config_field_has_a_bad_value_tested():
    for cls, extra in ((MADDPGConfig, MADDPG_ONLY), (BiCNetConfig, BICNET_ONLY),
                       (TrainConfig, TRAIN)):
        names = {f.name for f in dataclasses.fields(cls)}
        tested = set(extra) | (set() if cls is TrainConfig else set(SHARED))
        assert names == tested, (cls.__name__, names ^ tested)


def test_edge_values_and_numpy_numbers_are_accepted():
    cfg = MADDPGConfig(gamma=0.0, tau=1.0, learning_starts=0, noise_end=0.0, action_l2=0.0,
                       hidden=np.int64(8), batch_size=np.int32(16), actor_lr=np.float32(1e-3),
                       mask_parked=np.bool_(False))
    assert type(cfg.hidden) is int and type(cfg.batch_size) is int
    assert type(cfg.actor_lr) is float and cfg.mask_parked is False
    tc = TrainConfig(seed=np.int64(3), episodes=np.int64(10), stop_response=1)
    assert type(tc.seed) is int and tc.stop_response == 1.0


def test_config_changed_after_it_was_made_is_checked_again(tmp_path):
    """make_learner and train() re-check a config whose fields were set after it was made."""
    cfg = MADDPGConfig()
    cfg.hidden = 0
    with pytest.raises(ValueError, match="hidden must be an integer >= 1, got 0"):
        make_learner("maddpg", 24, 24, 3, cfg)
    from learners.train import train

    tc = TrainConfig(run_dir=str(tmp_path / "run"))
    tc.episodes = 0
    with pytest.raises(ValueError, match="episodes must be an integer >= 1, got 0"):
        train(tc)
    with pytest.raises(ValueError, match="tau must be a finite number in"):
        make_config("bicnet", {"tau": 5})


def test_train_config_refuses_a_lifelong_scenario() -> None:
    with pytest.raises(ValueError, match="'warehouse-20' is lifelong"):
        TrainConfig(scenario="warehouse-20")
