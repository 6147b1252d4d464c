"""Training over a curriculum of fleet sizes (``learners/curriculum.py``, ``agv train
--curriculum``), the shield in the training loop, and ``train(init_from=...)``."""

from __future__ import annotations

import csv
import json

import pytest
import torch

from learners.checkpoint import read_metadata
from learners.cli import add_train_arguments, run_train
from learners.curriculum import Stage, load_curriculum, parse_curriculum, train_curriculum
from learners.train import TrainConfig, train
from tests.learners.conftest import TINY

STAGES = "3v3:16,5v5:16"


def _config(run_dir, algo: str = "maddpg-e", seed: int = 2) -> TrainConfig:
    return TrainConfig(algo=algo, reward="ipf", scenario="3v3", episodes=1, seed=seed,
                       run_dir=str(run_dir), eval_every=16, eval_episodes=4, log_every=8,
                       checkpoint_every=8, progress=False, tensorboard=False)


def _weights(learner) -> dict[str, torch.Tensor]:
    return learner.training_tensors()


def _rows(path) -> list[dict[str, str]]:
    with path.open() as f:
        return list(csv.DictReader(f))


class _Crash(Exception):
    pass


def test_parse_curriculum_and_bad_values():
    assert parse_curriculum(" 3v3:10, 6v6:20 ") == [Stage("3v3", 10), Stage("6v6", 20)]
    assert parse_curriculum([("3v3", 5)]) == [Stage("3v3", 5)]
    assert [s.lifelong for s in parse_curriculum("warehouse-20:4,warehouse-30:2")] == [True] * 2
    for bad, match in (("", "at least one stage"), ("3v3", "SCENARIO:EPISODES"),
                       ("3v3:0", "positive integer|>= 1"), ("3v3:1.5", "positive integer"),
                       ("nope:10", "unknown scenario"),
                       ("3v3:10,warehouse-20:10", "all episodic or all lifelong"),
                       ("3v3:10:2", "positive integer")):
        with pytest.raises(ValueError, match=match):
            parse_curriculum(bad)
    with pytest.raises(ValueError, match="list of stages"):
        parse_curriculum(3)
    with pytest.raises(ValueError, match="do not depend on N"):
        train_curriculum(TrainConfig(algo="maddpg", progress=False), "3v3:4")


@pytest.mark.parametrize("algo", ["maddpg-e", "bicnet-e"])
def test_curriculum_carries_the_weights_and_resumes_bit_for_bit(tmp_path, algo):
    whole = train_curriculum(_config(tmp_path / "whole", algo), STAGES, TINY)
    first = tmp_path / "whole" / "stage-0-3v3"
    second = tmp_path / "whole" / "stage-1-5v5"
    assert (first / "done.json").is_file() and (second / "done.json").is_file()
    # stage 1 started from stage 0's weights and update count
    assert _rows(second / "progress.csv")[0]["updates"] > "0"
    assert whole.updates > json.loads((first / "done.json").read_text())["updates"] > 0
    assert (tmp_path / "whole" / "policy.safetensors").is_file()

    # killed right after stage 1's first periodic checkpoint, then resumed
    def crash(counters):
        if counters["episodes"] >= 8 and (tmp_path / "cut" / "stage-1-5v5").is_dir():
            raise _Crash

    with pytest.raises(_Crash):
        train_curriculum(_config(tmp_path / "cut", algo), STAGES, TINY, on_checkpoint=crash)
    assert not (tmp_path / "cut" / "stage-1-5v5" / "done.json").exists()
    resumed = train_curriculum(_config(tmp_path / "cut", algo), STAGES, TINY, resume=True)
    assert (resumed.episodes, resumed.env_steps, resumed.updates) == (
        whole.episodes, whole.env_steps, whole.updates)
    wa, wb = _weights(whole.learner), _weights(resumed.learner)
    for k in wa:
        assert torch.equal(wa[k], wb[k]), k
    for stage in ("stage-0-3v3", "stage-1-5v5"):
        keep = ("episode", "env_steps", "updates", "train_response_rate", "eval_response_rate")
        a = [{k: r[k] for k in keep} for r in _rows(tmp_path / "whole" / stage / "progress.csv")]
        b = [{k: r[k] for k in keep} for r in _rows(tmp_path / "cut" / stage / "progress.csv")]
        assert a == b

    # a stage appended on resume starts from the last one; everything else must match
    config, stages, learner = load_curriculum(tmp_path / "whole")
    assert stages == parse_curriculum(STAGES) and learner["hidden"] == TINY["hidden"]
    with pytest.raises(ValueError, match="keeps those stages"):
        train_curriculum(_config(tmp_path / "whole", algo), "3v3:16,6v6:16", TINY, resume=True)
    with pytest.raises(ValueError, match="different hyperparameters"):
        train_curriculum(_config(tmp_path / "whole", algo), STAGES, {**TINY, "hidden": 8},
                         resume=True)
    with pytest.raises(ValueError, match="seed"):
        train_curriculum(_config(tmp_path / "whole", algo, seed=3), STAGES, TINY, resume=True)
    with pytest.raises(ValueError, match="already holds a curriculum"):
        train_curriculum(_config(tmp_path / "whole", algo), STAGES, TINY)
    with pytest.raises(ValueError, match="nothing to resume"):
        train_curriculum(_config(tmp_path / "none", algo), STAGES, TINY, resume=True)


def test_init_from_checks_what_it_starts_from(tmp_path):
    first = _config(tmp_path / "a")
    first.episodes = 8
    base = train(first, TINY)
    ckpt = base.run_dir / "checkpoint.safetensors"
    other = _config(tmp_path / "b")
    other.episodes = 8
    with pytest.raises(ValueError, match="hidden=.*the same shape"):
        train(other, {**TINY, "hidden": TINY["hidden"] * 2}, init_from=ckpt)
    other.algo = "bicnet-e"
    with pytest.raises(ValueError, match="algo='maddpg-e'"):
        train(other, TINY, init_from=ckpt)
    plain = _config(tmp_path / "c")
    plain.algo = "maddpg"
    with pytest.raises(ValueError, match="algo='maddpg-e'"):
        train(plain, TINY, init_from=ckpt)
    started = _config(tmp_path / "d")
    started.scenario, started.episodes = "4v4", 8
    result = train(started, {**TINY, "tau": 0.5, "actor_lr": 1e-4}, init_from=ckpt)
    assert result.updates > base.updates  # the update count carried over
    # another reward only when asked for
    reward = _config(tmp_path / "e")
    reward.reward, reward.episodes = "greedy", 8
    with pytest.raises(ValueError, match=f"reward={first.reward!r}, this run has 'greedy'"):
        train(reward, TINY, init_from=ckpt)
    assert not (tmp_path / "e" / "checkpoint.safetensors").exists()
    changed = train(reward, TINY, init_from=ckpt, init_other_reward=True)
    assert changed.updates > base.updates
    with pytest.raises(ValueError, match="algo='maddpg-e'"):  # the algorithm still must match
        train(other, TINY, init_from=ckpt, init_other_reward=True)


def test_init_from_widens_a_checkpoint_for_the_parked_token(tmp_path):
    first = _config(tmp_path / "a", algo="bicnet-e")
    first.episodes = 8
    base = train(first, TINY)
    ckpt = base.run_dir / "checkpoint.safetensors"
    wide = _config(tmp_path / "b", algo="bicnet-e")
    wide.episodes = 8
    result = train(wide, {**TINY, "parked_token": True}, init_from=ckpt)
    assert result.updates > base.updates
    assert read_metadata(result.run_dir / "checkpoint.safetensors")["config"]["parked_token"]
    back = _config(tmp_path / "c", algo="bicnet-e")
    back.episodes = 8
    with pytest.raises(ValueError, match="without parked_token cannot start from one with it"):
        train(back, TINY, init_from=result.run_dir / "checkpoint.safetensors")


def test_init_from_a_curriculum_folder_takes_its_last_stage(tmp_path):
    from learners.curriculum import last_stage_checkpoint

    run = tmp_path / "cur"
    train_curriculum(_config(run), STAGES, TINY)
    last = last_stage_checkpoint(run)
    stages = sorted(run.glob("stage-*"))
    assert last == stages[-1] / "checkpoint.safetensors" and len(stages) == 2
    (stages[-1] / "checkpoint.safetensors").unlink()  # the stage before it is taken then
    assert last_stage_checkpoint(run) == stages[-2] / "checkpoint.safetensors"
    for stage in stages[:-1]:
        (stage / "checkpoint.safetensors").unlink()
    with pytest.raises(ValueError, match="no training checkpoint yet"):
        last_stage_checkpoint(run)
    with pytest.raises(ValueError, match="holds no curriculum"):
        last_stage_checkpoint(tmp_path)


def test_shield_in_the_loop_executes_the_shields_actions(tmp_path):
    """With shield=True the actions executed are the shield's: no training step has
    overlapping AGVs (the collision reward term stays 0), while the same exploration without
    the shield collides; the stored actions are the policy's intended ones (they differ
    between the two runs once the runs' states differ)."""
    from allocator import SafetyShield
    from learners.checkpoint import load_checkpoint

    out = {}
    for shield in (False, True):
        config = _config(tmp_path / f"s{shield}")
        config.scenario, config.episodes, config.log_every = "6v6", 16, 16
        result = train(config, {**TINY, "shield": shield, "learning_starts": 2000},
                       make_shield=SafetyShield)
        assert result.learner.config.shield is shield
        tensors, meta = load_checkpoint(result.run_dir / "checkpoint.safetensors")
        assert meta["config"]["shield"] is shield
        row = _rows(result.run_dir / "progress.csv")[-1]
        out[shield] = (float(row["train_term_collision"]), tensors["buffer.action"],
                       float(row["eval_collisions"]))
    assert out[False][0] < 0.0 and out[True][0] == 0.0
    assert out[False][2] > 0.0 and out[True][2] == 0.0  # evaluations run shielded too
    n = min(len(out[False][1]), len(out[True][1]))
    assert not torch.equal(out[False][1][:n], out[True][1][:n])
    assert out[True][1].abs().max() <= 1.0


def test_shield_penalty_charges_what_the_shield_changed(tmp_path):
    """Same seed, no updates: the same intended actions and executed steps, so the stored
    rewards differ only by the penalty, which is never positive and is charged somewhere."""
    from allocator import SafetyShield
    from learners.checkpoint import load_checkpoint

    out = {}
    for penalty in (0.0, 3.0):
        config = _config(tmp_path / f"p{penalty}")
        config.scenario, config.episodes, config.log_every = "6v6", 16, 16
        result = train(config, {**TINY, "shield": True, "shield_penalty": penalty,
                                "learning_starts": 2000}, make_shield=SafetyShield)
        tensors, meta = load_checkpoint(result.run_dir / "checkpoint.safetensors")
        assert meta["config"]["shield_penalty"] == penalty
        out[penalty] = tensors
    assert torch.equal(out[0.0]["buffer.action"], out[3.0]["buffer.action"])
    assert torch.equal(out[0.0]["buffer.next_obs"], out[3.0]["buffer.next_obs"])
    charged = out[0.0]["buffer.reward"] - out[3.0]["buffer.reward"]
    assert charged.min() >= 0.0 and charged.max() > 0.0
    assert charged.max() <= 3.0 * 2 * 2 ** 0.5 + 1e-5  # |a - a'| <= 2 sqrt(2)
    with pytest.raises(ValueError, match="it needs shield=True"):
        train(_config(tmp_path / "no-shield"), {**TINY, "shield_penalty": 1.0})
    with pytest.raises(ValueError, match="shield_penalty"):
        train(_config(tmp_path / "negative"), {**TINY, "shield": True, "shield_penalty": -1.0},
              make_shield=SafetyShield)


def test_agv_train_curriculum_cli(tmp_path, capsys):
    run_dir = tmp_path / "cli"
    args = ["--algo", "maddpg-e", "--reward", "ipf", "--curriculum", "3v3:8,4v4:8",
            "--run-dir", str(run_dir), "--eval-every", "8", "--eval-episodes", "2",
            "--checkpoint-every", "8", "--no-progress", "--set", "hidden=16",
            "--set", "batch_size=32", "--set", "num_envs=8", "--set", "learning_starts=64",
            "--set", "buffer_size=2000"]
    import argparse

    def cli(argv):
        parser = argparse.ArgumentParser()
        add_train_arguments(parser)
        return run_train(parser.parse_args(argv))

    assert cli(args) == 0
    assert (run_dir / "stage-1-4v4" / "done.json").is_file()
    assert cli(["--resume", str(run_dir), "--no-progress"]) == 0  # done: nothing to run
    assert cli(["--algo", "maddpg", "--curriculum", "3v3:8", "--run-dir",
                str(tmp_path / "x"), "--no-progress"]) == 2
    assert "do not depend on N" in capsys.readouterr().err
    assert cli(["--algo", "maddpg-e", "--curriculum", "3v3:x", "--run-dir",
                str(tmp_path / "y"), "--no-progress"]) == 2
    assert "positive integer" in capsys.readouterr().err
    assert cli(["--algo", "maddpg-e", "--curriculum", "3v3:8", "--scenario", "3v3",
                "--run-dir", str(tmp_path / "z"), "--no-progress"]) == 2
    assert "leave out --scenario" in capsys.readouterr().err


def test_shield_in_the_loop_without_a_shield_is_a_clear_error(tmp_path):
    """learners does not import allocator: the shield is handed in, and asked for by name."""
    with pytest.raises(ValueError, match="make_shield=allocator.SafetyShield"):
        train(_config(tmp_path / "run"), {**TINY, "shield": True})


def test_agv_train_hands_the_shield_in(tmp_path):
    """`agv train --set shield=true` trains through allocator/cli.py, which passes
    allocator.SafetyShield to learners (which cannot import it)."""
    from allocator.cli import main

    run_dir = tmp_path / "shielded"
    code = main(["train", "--algo", "maddpg-e", "--reward", "ipf", "--scenario", "3v3",
                 "--episodes", "8", "--run-dir", str(run_dir), "--eval-every", "0",
                 "--eval-episodes", "2", "--no-progress", "--set", "shield=true",
                 "--set", "hidden=16", "--set", "batch_size=32", "--set", "num_envs=8",
                 "--set", "learning_starts=64", "--set", "buffer_size=2000"])
    assert code == 0
    row = _rows(run_dir / "progress.csv")[-1]
    assert float(row["train_term_collision"]) == 0.0  # the shield drove: no overlap


LIFELONG_SMALL = {"hidden": 8, "batch_size": 16, "num_envs": 2, "learning_starts": 40,
                  "buffer_size": 400}


def _lifelong_config(run_dir) -> TrainConfig:
    return TrainConfig(algo="maddpg-e", reward="greedy", scenario="warehouse-20", episodes=1,
                       seed=1, run_dir=str(run_dir), eval_every=2, log_every=2,
                       checkpoint_every=2, window=15, eval_steps=20, progress=False,
                       tensorboard=False)


def test_lifelong_curriculum_goes_from_floor_to_floor(tmp_path):
    """warehouse-20 then warehouse-30 with one set of weights: the second floor starts from
    the first one's update count, and its done.json scores throughput."""
    result = train_curriculum(_lifelong_config(tmp_path / "run"),
                              "warehouse-20:4,warehouse-30:4", LIFELONG_SMALL)
    first = tmp_path / "run" / "stage-0-warehouse-20"
    second = tmp_path / "run" / "stage-1-warehouse-30"
    done = json.loads((first / "done.json").read_text())
    assert set(done) == {"episodes", "updates", "best_throughput"} and done["updates"] > 0
    rows = _rows(second / "progress.csv")
    # the count goes on from stage 0's (the new buffer fills first: no update in row 0)
    assert int(rows[0]["updates"]) == done["updates"] < int(rows[-1]["updates"])
    assert result.updates == int(rows[-1]["updates"]) and result.best_throughput >= 0
    assert (tmp_path / "run" / "best.safetensors").is_file()


def test_agv_train_init_from_goes_on_on_another_floor(tmp_path, capsys):
    import argparse

    def cli(argv):
        parser = argparse.ArgumentParser()
        add_train_arguments(parser)
        return run_train(parser.parse_args(argv + ["--no-progress", "--window", "15",
                                                   "--eval-steps", "20", "--eval-every", "0"]))

    small = [x for k, v in LIFELONG_SMALL.items() for x in ("--set", f"{k}={v}")]
    first = tmp_path / "w20"
    assert cli(["--algo", "maddpg-e", "--reward", "greedy", "--scenario", "warehouse-20",
                "--episodes", "4", "--run-dir", str(first)] + small) == 0
    updates = read_metadata(first / "checkpoint.safetensors")["updates"]
    second = tmp_path / "w30"
    assert cli(["--algo", "maddpg-e", "--reward", "greedy", "--scenario", "warehouse-30",
                "--episodes", "4", "--run-dir", str(second), "--init-from", str(first)]
               + small) == 0
    assert "throughput" in capsys.readouterr().out
    rows = _rows(second / "progress.csv")
    assert int(rows[-1]["updates"]) > updates  # the same run from scratch makes `updates`
    for argv, match in (
            (["--resume", str(second), "--init-from", str(first)], "--init-from starts a new"),
            (["--curriculum", "warehouse-30:2", "--run-dir", str(tmp_path / "c"), "--init-from",
              str(first)], "--init-from is for a single run"),
            (["--scenario", "warehouse-30", "--algo", "maddpg-e", "--reward", "greedy",
              "--episodes", "2", "--run-dir", str(tmp_path / "x"), "--init-from",
              str(tmp_path / "none")], "no checkpoint at"),
            (["--scenario", "warehouse-30", "--algo", "maddpg-e", "--reward", "greedy",
              "--episodes", "2", "--run-dir", str(tmp_path / "y"), "--init-from", str(first),
              "--set", "hidden=16"], "the same shape"),
            (["--scenario", "warehouse-30", "--algo", "maddpg-e", "--reward", "minidist",
              "--episodes", "2", "--run-dir", str(tmp_path / "z"), "--init-from", str(first)],
             "trained with reward='greedy'"),
            (["--scenario", "warehouse-30", "--algo", "maddpg-e", "--reward", "greedy",
              "--episodes", "2", "--run-dir", str(tmp_path / "v"), "--init-other-reward"],
             "--init-other-reward goes with --init-from")):
        assert cli(argv) == 2
        assert match in capsys.readouterr().err
    other = tmp_path / "w30-minidist"
    assert cli(["--algo", "maddpg-e", "--reward", "minidist", "--scenario", "warehouse-30",
                "--episodes", "4", "--run-dir", str(other), "--init-from", str(first),
                "--init-other-reward"] + small) == 0
    assert read_metadata(other / "checkpoint.safetensors")["reward"] == "minidist"
    assert int(_rows(other / "progress.csv")[-1]["updates"]) > updates


def test_lanes_in_the_loop_are_served_with_the_weights(tmp_path):
    """shield_keep_right: the training shield turns intended velocities by it, and a learned
    allocator serving the weights with shield=True uses the same angle; bad angles are
    refused."""
    from allocator import SafetyShield, make

    made = []

    def make_shield(controller, **kw):
        made.append(kw)
        return SafetyShield(controller, **kw)

    config = _lifelong_config(tmp_path / "lanes")
    config.episodes = 4
    result = train(config, {**LIFELONG_SMALL, "shield": True, "shield_keep_right": 0.3},
                   make_shield=make_shield)
    assert made and all(kw == {"keep_right": 0.3} for kw in made)
    solver = make("maddpg-greedy", scenario="warehouse-20",
                  checkpoint=result.run_dir / "policy.safetensors", shield=True)
    assert solver.safety.keep_right == 0.3
    wider = make("maddpg-greedy", scenario="warehouse-50", shield=True, keep_right=0.5,
                 checkpoint=result.run_dir / "policy.safetensors")
    assert wider.safety.keep_right == 0.5
    with pytest.raises(ValueError, match="needs shield=True"):
        make("maddpg-greedy", scenario="warehouse-20", keep_right=0.5,
             checkpoint=result.run_dir / "policy.safetensors")
    with pytest.raises(ValueError, match="keep_right must be an angle"):
        make("maddpg-greedy", scenario="warehouse-20", shield=True, keep_right=2.0,
             checkpoint=result.run_dir / "policy.safetensors")
    for bad in (-0.1, 1.6, "x"):
        with pytest.raises(ValueError, match="shield_keep_right"):
            train(_lifelong_config(tmp_path / "bad"), {**LIFELONG_SMALL,
                                                     "shield_keep_right": bad})


def _actor(learner) -> dict[str, torch.Tensor]:
    return {k: v.clone() for k, v in learner.policy_tensors().items()}


@pytest.mark.parametrize("algo", ["maddpg", "bicnet"])
def test_init_from_a_deployed_policy_with_a_critic_warmup(tmp_path, algo):
    """A shipped policy (actor only, any reward) starts a run: the actor carries over, the
    critic starts fresh and learns alone for ``critic_warmup`` updates, then the actor learns."""
    first = _config(tmp_path / "a", algo=algo)
    first.episodes = 8
    base = train(first, TINY)
    policy = base.run_dir / "policy.safetensors"
    start = _actor(base.learner)
    tuned = _config(tmp_path / "b", algo=algo)
    tuned.reward, tuned.episodes = "greedy", 16  # another reward: a policy holds no values
    tuned.critic_warmup = 10**6  # longer than the run: the actor never moves
    frozen = train(tuned, TINY, init_from=policy)
    assert frozen.updates > 0
    for key, value in _actor(frozen.learner).items():
        torch.testing.assert_close(value, start[key], rtol=0, atol=0)
    assert frozen.learner.actor_optimizer.param_groups[0]["lr"] == 0.0
    short = _config(tmp_path / "c", algo=algo)
    short.reward, short.episodes, short.critic_warmup = "greedy", 16, 3
    moved = train(short, TINY, init_from=policy)
    assert moved.updates > 3
    assert moved.learner.actor_optimizer.param_groups[0]["lr"] == TINY.get("actor_lr", 1e-3)
    assert any(not torch.equal(v, start[k]) for k, v in _actor(moved.learner).items())
    # the critic did not come from the first run (a policy has none)
    assert not torch.equal(moved.learner.critic.state_dict()[next(iter(
        moved.learner.critic.state_dict()))], base.learner.critic.state_dict()[next(iter(
            base.learner.critic.state_dict()))])


@pytest.mark.parametrize("algo", ["maddpg", "bicnet"])
def test_init_from_a_training_checkpoint_of_the_same_scenario(tmp_path, algo):
    """The paper's learners start from a long run's checkpoint (critic, targets, Adam moments
    and update count included) on the same scenario, and refuse another N by name."""
    first = _config(tmp_path / "a", algo=algo)
    first.episodes = 8
    base = train(first, TINY)
    ckpt = base.run_dir / "checkpoint.safetensors"
    frozen = _config(tmp_path / "b", algo=algo)
    frozen.episodes, frozen.critic_warmup = 1, 10**6
    frozen.eval_every = 0
    started = train(frozen, {**TINY, "learning_starts": TINY["buffer_size"]},
                    init_from=ckpt)  # one short episode: no update
    assert started.updates == base.updates  # the update count carried over
    for key, value in base.learner.training_tensors().items():
        if key.split(".", 1)[0] in ("actor", "critic", "target_actor", "target_critic"):
            torch.testing.assert_close(started.learner.training_tensors()[key], value,
                                       rtol=0, atol=0)
    elsewhere = _config(tmp_path / "c", algo=algo)
    elsewhere.scenario = "4v4"
    with pytest.raises(ValueError, match="networks depend on N.*same scenario"):
        train(elsewhere, TINY, init_from=ckpt)
    assert not (tmp_path / "c" / "checkpoint.safetensors").exists()


def test_init_from_a_policy_checks_its_scenario_and_shapes(tmp_path, capsys):
    first = _config(tmp_path / "a", algo="maddpg")
    first.episodes = 8
    policy = train(first, TINY).run_dir / "policy.safetensors"
    elsewhere = _config(tmp_path / "b", algo="maddpg")
    elsewhere.scenario = "4v4"  # MADDPG's per-agent actors fit only their scenario
    with pytest.raises(ValueError, match="fit only that scenario"):
        train(elsewhere, TINY, init_from=policy)
    wide = _config(tmp_path / "c", algo="maddpg")
    with pytest.raises(ValueError, match="hidden=.*the same shape"):
        train(wide, {**TINY, "hidden": TINY["hidden"] * 2}, init_from=policy)
    other = _config(tmp_path / "d", algo="bicnet")
    with pytest.raises(ValueError, match="algo='maddpg'"):
        train(other, TINY, init_from=policy)
    with pytest.raises(ValueError, match="critic_warmup must be"):
        TrainConfig(critic_warmup=-1)
    bic = _config(tmp_path / "f", algo="bicnet")
    bic.episodes = 8
    bic_policy = train(bic, TINY).run_dir / "policy.safetensors"
    grown = _config(tmp_path / "g", algo="bicnet")
    grown.scenario = "4v4"  # the observation size depends on N
    with pytest.raises(ValueError, match="fit only that scenario"):
        train(grown, TINY, init_from=bic_policy)
    # on the command line
    parser = __import__("argparse").ArgumentParser()
    add_train_arguments(parser)
    args = parser.parse_args(["--algo", "bicnet", "--reward", "ipf-time", "--scenario", "3v3",
                              "--episodes", "8", "--run-dir", str(tmp_path / "h"),
                              "--init-from", str(bic_policy), "--critic-warmup", "5",
                              "--eval-every", "8", "--eval-episodes", "4", "--no-progress",
                              "--set", f"hidden={TINY['hidden']}"])
    assert run_train(args) == 0
    assert read_metadata(tmp_path / "h" / "checkpoint.safetensors")["train_config"][
        "critic_warmup"] == 5
