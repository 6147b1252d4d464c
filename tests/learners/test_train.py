"""The training entry point: smoke runs, determinism, resume, bad input."""

from __future__ import annotations

import argparse
import csv

import pytest
import torch

from learners.cli import add_evaluate_arguments, add_train_arguments, run_evaluate, run_train
from learners.train import CSV_COLUMNS, TrainConfig, train
from tests.learners.conftest import TINY


def _cli(add, run, argv: list[str]) -> int:
    parser = argparse.ArgumentParser()
    add(parser)
    return run(parser.parse_args(argv))


def _tiny_args(algo: str, run_dir, episodes: int = 32) -> list[str]:
    sets = [f"--set={k}={v}" for k, v in TINY.items()]
    return ["--algo", algo, "--reward", "ipf", "--scenario", "3v3", "--episodes", str(episodes),
            "--seed", "0", "--run-dir", str(run_dir), "--eval-every", "16",
            "--eval-episodes", "8", "--checkpoint-every", "16", "--no-progress", *sets]


def _tiny_config(algo: str, run_dir, episodes: int, **kw) -> TrainConfig:
    return TrainConfig(algo=algo, reward="minidist", scenario="3v3", episodes=episodes, seed=3,
                       run_dir=str(run_dir), eval_every=16, eval_episodes=4, log_every=8,
                       checkpoint_every=16, progress=False, **kw)


@pytest.mark.parametrize("algo", ["maddpg", "bicnet"])
def test_agv_train_smoke_then_evaluate(tmp_path, algo, capsys):
    """`agv train` end to end on a tiny budget, then `agv evaluate` on what it wrote."""
    run_dir = tmp_path / "run"
    export = tmp_path / "weights" / f"{algo}-ipf.safetensors"
    assert _cli(add_train_arguments, run_train,
                [*_tiny_args(algo, run_dir), "--export", str(export)]) == 0
    for name in ("checkpoint", "policy", "best"):
        assert (run_dir / f"{name}.safetensors").is_file()
        assert (run_dir / f"{name}.json").is_file()
    assert export.is_file() and export.with_suffix(".json").is_file()
    with (run_dir / "progress.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert set(CSV_COLUMNS) <= set(rows[0]) and {"train_term_ipf", "train_term_goal"} <= set(
        rows[0])
    assert int(rows[-1]["episode"]) >= 32 and rows[-1]["eval_response_rate"] != ""
    capsys.readouterr()
    assert _cli(add_evaluate_arguments, run_evaluate, [str(export), "--episodes", "6"]) == 0
    out = capsys.readouterr().out
    assert "task response rate" in out and "average time" in out


def _weights(learner) -> dict[str, torch.Tensor]:
    return {k: v.clone() for k, v in learner.training_tensors().items()}


def test_same_seed_same_weights(tmp_path):
    a = train(_tiny_config("maddpg", tmp_path / "a", 40), TINY)
    b = train(_tiny_config("maddpg", tmp_path / "b", 40), TINY)
    assert a.updates == b.updates > 10
    wa, wb = _weights(a.learner), _weights(b.learner)
    for k in wa:
        assert torch.equal(wa[k], wb[k]), k
    other_seed = _tiny_config("maddpg", tmp_path / "c", 40)
    other_seed.seed = 4
    c = train(other_seed, TINY)
    assert not torch.equal(c.learner.actor.layers[0].weight, a.learner.actor.layers[0].weight)


class _Crash(Exception):
    pass


@pytest.mark.parametrize("algo", ["maddpg", "bicnet"])
def test_resume_equals_uninterrupted_run(tmp_path, algo):
    whole = train(_tiny_config(algo, tmp_path / "whole", 48), TINY)

    def crash(counters):
        raise _Crash  # the process dies right after its first periodic checkpoint

    with pytest.raises(_Crash):
        train(_tiny_config(algo, tmp_path / "cut", 48), TINY, on_checkpoint=crash)
    resumed = train(_tiny_config(algo, tmp_path / "cut", 48), resume=True)
    assert (resumed.episodes, resumed.env_steps, resumed.updates) == (
        whole.episodes, whole.env_steps, whole.updates)
    wa, wb = _weights(whole.learner), _weights(resumed.learner)
    for k in wa:
        assert torch.equal(wa[k], wb[k]), k
    with (tmp_path / "whole" / "progress.csv").open() as f:
        whole_rows = [r["episode"] for r in csv.DictReader(f)]
    with (tmp_path / "cut" / "progress.csv").open() as f:
        cut_rows = [r["episode"] for r in csv.DictReader(f)]
    assert cut_rows == whole_rows


def test_resume_cli_continues_to_a_larger_budget(tmp_path):
    run_dir = tmp_path / "run"
    assert _cli(add_train_arguments, run_train, _tiny_args("maddpg", run_dir, 16)) == 0
    assert _cli(add_train_arguments, run_train,
                ["--resume", str(run_dir), "--episodes", "32", "--no-progress"]) == 0
    with (run_dir / "progress.csv").open() as f:
        assert int(list(csv.DictReader(f))[-1]["episode"]) >= 32


def test_bad_input_gives_clear_errors(tmp_path, capsys):
    with pytest.raises(ValueError, match="unknown algorithm 'ppo'"):
        train(TrainConfig(algo="ppo", run_dir=str(tmp_path / "x")))
    with pytest.raises(ValueError, match="unknown reward 'dense'"):
        train(TrainConfig(reward="dense", run_dir=str(tmp_path / "x")))
    with pytest.raises(ValueError, match="nothing to resume: expected a checkpoint at"):
        train(TrainConfig(run_dir=str(tmp_path / "empty")), resume=True)
    assert _cli(add_train_arguments, run_train, ["--resume", str(tmp_path / "empty")]) == 2
    assert "nothing to resume" in capsys.readouterr().err
    with pytest.raises(SystemExit):  # argparse names the valid choices
        _cli(add_train_arguments, run_train, ["--algo", "ppo"])
    assert "invalid choice: 'ppo'" in capsys.readouterr().err
    assert _cli(add_train_arguments, run_train,
                ["--set", "hidden_size=3", "--run-dir", str(tmp_path / "y")]) == 2
    assert "--set expects KEY=VALUE" in capsys.readouterr().err
    # a finished run is not overwritten by a new one
    train(_tiny_config("maddpg", tmp_path / "done", 8), TINY)
    with pytest.raises(ValueError, match="already holds a run"):
        train(_tiny_config("maddpg", tmp_path / "done", 8), TINY)
    with pytest.raises(ValueError, match="it was trained with algo='maddpg'"):
        train(_tiny_config("bicnet", tmp_path / "done", 16), resume=True)


def test_sigint_stops_cleanly_with_a_checkpoint_and_resumes_exactly(tmp_path):
    import os
    import signal

    whole = train(_tiny_config("maddpg", tmp_path / "whole", 48), TINY)

    def interrupt(counters):
        os.kill(os.getpid(), signal.SIGINT)  # Ctrl-C during training

    cut = train(_tiny_config("maddpg", tmp_path / "cut", 48), TINY, on_checkpoint=interrupt)
    assert cut.interrupted and cut.episodes < 48
    resumed = train(_tiny_config("maddpg", tmp_path / "cut", 48), resume=True)
    assert not resumed.interrupted
    wa, wb = _weights(whole.learner), _weights(resumed.learner)
    for k in wa:
        assert torch.equal(wa[k], wb[k]), k


def test_fastest_keeps_the_least_time_at_the_response_floor(tmp_path):
    import math

    from learners.checkpoint import read_metadata

    result = train(_tiny_config("maddpg", tmp_path / "all", 64, fastest_min_response=0.0),
                   TINY)
    with open(result.run_dir / "progress.csv") as f:
        evals = [(float(r["eval_response_rate"]), float(r["eval_avg_time"]))
                 for r in csv.DictReader(f) if r["eval_response_rate"]]
    assert len(evals) >= 4
    fastest = read_metadata(result.run_dir / "fastest.safetensors")["last_eval"]
    assert fastest["avg_time"] == pytest.approx(min(t for _, t in evals), abs=1e-3)
    # at a floor only some evaluations reach, the least time among those (or no file)
    floor = sorted(r for r, _ in evals)[len(evals) // 2]
    again = train(_tiny_config("maddpg", tmp_path / "half", 64, fastest_min_response=floor),
                  TINY)
    qualifying = [t for r, t in evals if r >= floor]
    meta = read_metadata(again.run_dir / "fastest.safetensors")["last_eval"]
    assert meta["response_rate"] >= floor
    assert meta["avg_time"] == pytest.approx(min(qualifying), abs=1e-3)
    assert not math.isnan(meta["avg_time"])


@pytest.mark.parametrize("algo", ["maddpg", "bicnet"])
def test_portable_copy_drops_the_buffer_and_resumes(tmp_path, algo, capsys):
    """A run copied without its replay buffer is small, keeps everything else, and goes on
    from where it stopped with an empty buffer (and a warning that it is no longer bit for
    bit)."""
    from learners.checkpoint import load_checkpoint
    from learners.train import portable_copy

    run = train(_tiny_config(algo, tmp_path / "run", 32), TINY)
    target = tmp_path / "moved"
    assert _cli(add_train_arguments, run_train,
                ["--portable-copy", str(run.run_dir), str(target)]) == 0
    assert "without its replay buffer" in capsys.readouterr().out
    full, _ = load_checkpoint(run.run_dir / "checkpoint.safetensors")
    slim, meta = load_checkpoint(target / "checkpoint.safetensors", kind="training")
    assert any(k.startswith("buffer.") for k in full)
    assert not any(k.startswith("buffer.") for k in slim)
    assert set(slim) == {k for k in full if not k.startswith("buffer.")}
    for k, v in slim.items():
        assert torch.equal(v, full[k]), k
    assert meta["episodes"] == run.episodes
    for name in ("progress.csv", "config.json", "policy.safetensors", "policy.json",
                 "best.safetensors", "best.json"):
        assert (target / name).is_file(), name
    assert ((target / "checkpoint.safetensors").stat().st_size
            < (run.run_dir / "checkpoint.safetensors").stat().st_size)
    assert _cli(add_train_arguments, run_train,
                ["--resume", str(target), "--episodes", "40", "--no-progress"]) == 0
    err = capsys.readouterr().err
    assert "agv train: warning:" in err and "holds no replay buffer" in err
    again = portable_copy(run.run_dir, tmp_path / "again").parent
    with pytest.warns(UserWarning, match="holds no replay buffer"):
        resumed = train(_tiny_config(algo, again, 48), resume=True)
    assert resumed.episodes >= 48 and resumed.updates > run.updates
    with (again / "progress.csv").open() as f:
        episodes = [int(r["episode"]) for r in csv.DictReader(f)]
    assert episodes == sorted(episodes) and episodes[-1] >= 48
    # it can also start a fine-tune (same scenario), critic and all
    tuned = _tiny_config(algo, tmp_path / "tuned", 8)
    assert train(tuned, TINY, init_from=target).updates > run.updates
    # bad input
    with pytest.raises(ValueError, match="no run to copy"):
        portable_copy(tmp_path / "nothing", tmp_path / "x")
    with pytest.raises(ValueError, match="already holds a run"):
        portable_copy(run.run_dir, target)
    with pytest.raises(ValueError, match="the run folder itself"):
        portable_copy(run.run_dir, run.run_dir)
    assert _cli(add_train_arguments, run_train,
                ["--portable-copy", str(tmp_path / "nothing"), str(tmp_path / "y")]) == 2
    assert "no run to copy" in capsys.readouterr().err
