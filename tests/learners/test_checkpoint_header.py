"""Checkpoint headers are checked against a schema, the pair checkpoint + sidecar stays
consistent, and interrupted writes leave nothing behind for ever.

Every tampered header below is written the way an editor would: the safetensors file is
rewritten with the same tensors and edited ``"agv"`` metadata (``sha256``, the tensors' digest,
stays valid, as it does not cover the header).
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import re
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import torch
from safetensors import safe_open
from safetensors.torch import load_file, save_file

import allocator
import sim
from learners.algorithms import make_learner
from learners.checkpoint import (
    load_checkpoint,
    read_metadata,
    save_checkpoint,
    tensor_digest,
    write_sidecar,
)
from learners.policy import LearnedPolicy
from learners.train import TrainConfig, load_run_config, train
from sim.io import atomic_write_bytes, clean_stale_temporaries
from tests.learners.conftest import TINY

ROOT = Path(__file__).resolve().parents[2]


def _policy_file(tmp_path: Path, name: str = "maddpg-ipf.safetensors") -> Path:
    env = sim.make_env("3v3", num_envs=1)
    torch.manual_seed(0)
    learner = make_learner("maddpg", env.obs_dim, env.state_dim, env.num_agents, {"hidden": 8})
    meta = {"kind": "policy", "algo": "maddpg", "reward": "ipf", "scenario": "3v3", "seed": 0,
            "num_agents": env.num_agents, "num_tasks": env.num_tasks, "obs_dim": env.obs_dim,
            "state_dim": env.state_dim, "config": dataclasses.asdict(learner.config),
            "episodes": 10, "env_steps": 250, "updates": 4, "seconds": 1.5,
            "best_response_rate": 0.5, "last_eval": {"response_rate": 0.5,
                                                     "avg_time_finished": math.nan}}
    return save_checkpoint(tmp_path / name, learner.policy_tensors(), meta)


def _header(path: Path) -> dict[str, Any]:
    with safe_open(str(path), framework="pt") as f:
        return json.loads(f.metadata()["agv"])


def _rewrite(path: Path, text: str, tensors: dict[str, torch.Tensor] | None = None) -> None:
    """Rewrite a checkpoint with the given raw header text (and tensors)."""
    save_file(tensors if tensors is not None else load_file(str(path)), str(path),
              metadata={"agv": text})


def _tamper(path: Path, edit: Callable[[dict[str, Any]], Any]) -> None:
    meta = _header(path)
    out = edit(meta)
    _rewrite(path, json.dumps(meta if out is None else out))


def _set(key: str, value: Any) -> Callable[[dict], None]:
    return lambda m: m.__setitem__(key, value)


def _drop(key: str) -> Callable[[dict], None]:
    def drop(meta: dict) -> None:
        del meta[key]

    return drop


def _set_config(key: str, value: Any) -> Callable[[dict], None]:
    return lambda m: m["config"].__setitem__(key, value)


def _drop_config(key: str) -> Callable[[dict], None]:
    def drop(meta: dict) -> None:
        del meta["config"][key]

    return drop


# (edit, words the message must hold); the field's name is always among them
TAMPERED = {
    "num_agents=0": (_set("num_agents", 0), "'num_agents'"),
    "num_agents=-1": (_set("num_agents", -1), "'num_agents'"),
    "num_agents=6": (_set("num_agents", 6), "'num_agents' is 6, but scenario '3v3'"),
    "num_agents='3'": (_set("num_agents", "3"), "'num_agents'"),
    "num_tasks=5": (_set("num_tasks", 5), "'num_tasks'"),
    "obs_dim=48": (_set("obs_dim", 48), "'obs_dim' is 48, but scenario '3v3' has obs_dim=24"),
    "obs_dim=0": (_set("obs_dim", 0), "'obs_dim'"),
    "state_dim=2.5": (_set("state_dim", 2.5), "'state_dim'"),
    "config removed": (_drop("config"), "'config' is missing"),
    "config null": (_set("config", None), "'config' must be a JSON object"),
    "config list": (_set("config", [1, 2]), "'config' must be a JSON object"),
    "config.hidden=0": (_set_config("hidden", 0), "hidden must be an integer >= 1"),
    "config.gamma=NaN": (_set_config("gamma", math.nan), "gamma must be a finite number"),
    "config.tau=5": (_set_config("tau", 5), "'config' is invalid: tau"),
    "config.terminal_value=bogus": (_set_config("terminal_value", "bogus"), "terminal_value"),
    "config.hidden removed": (_drop_config("hidden"), "'config' lacks"),
    "config.extra": (_set_config("hidden_size", 3), "unknown MADDPGConfig field"),
    "format_version='1'": (_set("format_version", "1"), "'format_version'"),
    "format_version=0": (_set("format_version", 0), "'format_version'"),
    "format_version=true": (_set("format_version", True), "'format_version'"),
    "format_version=2": (_set("format_version", 2), "format_version 2; this code reads up to 1"),
    "format_version removed": (_drop("format_version"), "'format_version' is missing"),
    "format bogus": (_set("format", "other"), "field 'format'"),
    "metadata a JSON list": (lambda m: [m], "must be a JSON object, got list"),
    "metadata a JSON number": (lambda m: 3, "must be a JSON object, got int"),
    "reward=dense": (_set("reward", "dense"), "'reward'"),
    "reward removed": (_drop("reward"), "'reward' is missing"),
    "scenario=bogus": (_set("scenario", "bogus"), "'scenario' is not a known scenario"),
    "scenario=6v6": (_set("scenario", "6v6"), "'num_agents' is 3, but scenario '6v6'"),
    "scenario=3": (_set("scenario", 3), "'scenario'"),
    "algo=ppo": (_set("algo", "ppo"), "'algo'"),
    "algo=bicnet": (_set("algo", "bicnet"), "'config'"),
    "kind=weights": (_set("kind", "weights"), "'kind'"),
    "sha256 short": (_set("sha256", "abc"), "'sha256'"),
    "seed=-1": (_set("seed", -1), "'seed'"),
    "seed='0'": (_set("seed", "0"), "'seed'"),
    "episodes=-1": (_set("episodes", -1), "'episodes'"),
    "updates=1.5": (_set("updates", 1.5), "'updates'"),
    "env_steps=-5": (_set("env_steps", -5), "'env_steps'"),
    "seconds=NaN": (_set("seconds", math.nan), "'seconds'"),
    "best_response_rate=2": (_set("best_response_rate", 2), "'best_response_rate'"),
    "last_eval a string": (_set("last_eval", "good"), "'last_eval'"),
    "last_eval of strings": (_set("last_eval", {"response_rate": "1"}), "'last_eval'"),
    "code_version=3": (_set("code_version", 3), "'code_version'"),
    "created=5": (_set("created", 5), "'created'"),
    "train_config null": (_set("train_config", None), "'train_config'"),
    "train_config of another reward": (_set("train_config", {"reward": "greedy"}),
                                       "'train_config' has reward='greedy'"),
    "unknown field": (_set("learning_rate", 0.1), "'learning_rate' is not a checkpoint field"),
    "seed edited (schema-valid)": (_set("seed", 7), "'header_sha256' does not match"),
    "episodes edited (schema-valid)": (_set("episodes", 99), "'header_sha256' does not match"),
}



def test_every_header_field_is_tampered_in_some_case(tmp_path):
    fields = set(_header(_policy_file(tmp_path))) | {"train_config"}
    tampered = {case.split("=")[0].split(" ")[0].split(".")[0] for case in TAMPERED}
    tampered.add("header_sha256")  # the schema-valid edits are caught by it
    assert fields <= tampered, sorted(fields - tampered)


LOADERS = {
    "read_metadata": read_metadata,
    "load_checkpoint": load_checkpoint,
    "LearnedPolicy.load": LearnedPolicy.load,
    "allocator.make": lambda p: allocator.make("maddpg-ipf", scenario="3v3", checkpoint=p),
}


@pytest.mark.parametrize("loader", LOADERS.values(), ids=LOADERS.keys())
@pytest.mark.parametrize("edit, words", TAMPERED.values(), ids=TAMPERED.keys())
def test_tampered_header_gives_a_value_error_naming_the_field(tmp_path, edit, words, loader):
    """num_agents=0 gave a ZeroDivisionError, -1 a negative dimension, config removed a
    KeyError, format_version "1" a TypeError, a JSON list an AttributeError; obs_dim,
    num_agents, config null, reward "dense", scenario "bogus" were accepted."""
    path = _policy_file(tmp_path)
    _tamper(path, edit)
    with pytest.raises(ValueError) as info:
        loader(path)
    assert words in str(info.value), str(info.value)
    assert str(path) in str(info.value)


def test_nan_actor_weights_with_a_recomputed_digest_are_refused(tmp_path):
    path = _policy_file(tmp_path)
    meta = _header(path)
    tensors = load_file(str(path))
    tensors["actor.layers.1.weight"][0, 0, 0] = math.nan
    meta["sha256"] = tensor_digest(tensors)
    meta.pop("header_sha256")
    _rewrite(path, json.dumps(meta), tensors)
    for loader in LOADERS.values():
        if loader is read_metadata:
            continue
        with pytest.raises(ValueError, match="'actor.layers.1.weight' holds NaN or infinite"):
            loader(path)


def test_weights_that_disagree_with_the_header_name_the_tensor_and_the_fields(tmp_path):
    """A header whose config.hidden says 16 over weights of width 8 (digests recomputed)."""
    path = _policy_file(tmp_path)
    meta = _header(path)
    meta["config"]["hidden"] = 16
    meta.pop("header_sha256")
    _rewrite(path, json.dumps(meta))
    with pytest.raises(ValueError, match=r"tensor 'actor.layers.0.weight' is torch.float32 of "
                                         r"shape \(3, 24, 8\), but the header .*config\) needs "
                                         r"torch.float32 of shape \(3, 24, 16\)"):
        LearnedPolicy.load(path)
    tensors = load_file(str(path))
    tensors["actor.extra"] = torch.zeros(2)
    meta["sha256"] = tensor_digest(tensors)
    meta["config"]["hidden"] = 8
    _rewrite(path, json.dumps(meta), tensors)
    with pytest.raises(ValueError, match=r"unexpected \['actor.extra'\]"):
        LearnedPolicy.load(path)


def test_header_without_header_digest_still_loads(tmp_path):
    """Files written before header_sha256 existed (the shipped weights) load as before."""
    path = _policy_file(tmp_path)
    _tamper(path, _drop("header_sha256"))
    policy = LearnedPolicy.load(path)
    assert policy.metadata["episodes"] == 10 and "header_sha256" not in policy.metadata


@pytest.mark.parametrize("name", ["maddpg-ipf", "bicnet-ipf", "maddpg-minidist",
                                  "bicnet-greedy"])
@pytest.mark.parametrize("scenario", ["3v3", "6v6"])
def test_shipped_weights_pass_the_header_schema(name, scenario):
    path = ROOT / "allocator" / "weights" / scenario / f"{name}.safetensors"
    if not path.exists():
        if os.environ.get("CI"):
            pytest.fail(f"shipped weights missing: {path}")
        pytest.skip(f"no shipped weights {path}")
    tensors, meta = load_checkpoint(path)
    assert meta["scenario"] == scenario and meta["kind"] == "policy" and tensors


def _training_run(tmp_path: Path) -> Path:
    run_dir = tmp_path / "run"
    train(TrainConfig(algo="maddpg", reward="minidist", scenario="3v3", episodes=16, seed=3,
                      run_dir=str(run_dir), eval_every=16, eval_episodes=4,
                      checkpoint_every=16, progress=False), TINY)
    return run_dir


TRAINING_TAMPERED = {
    "config null": (_set("config", None), "'config' must be a JSON object"),
    "train_config removed": (_drop("train_config"), "'train_config' is missing"),
    "episodes removed": (_drop("episodes"), "'episodes' is missing"),
    "last_eval removed": (_drop("last_eval"), "'last_eval' is missing"),
    "train_config.episodes=0": (lambda m: m["train_config"].__setitem__("episodes", 0),
                                "'train_config' is invalid: episodes must be"),
    "train_config.bogus": (lambda m: m["train_config"].__setitem__("bogus", 1),
                           "'train_config' holds unknown TrainConfig field(s) ['bogus']"),
}


@pytest.mark.parametrize("edit, words", TRAINING_TAMPERED.values(),
                         ids=TRAINING_TAMPERED.keys())
def test_tampered_training_header_is_refused_on_resume(tmp_path, edit, words):
    """config: null fell back to the default hyperparameters on resume."""
    run_dir = _training_run(tmp_path)
    ckpt = run_dir / "checkpoint.safetensors"

    def edit_and_drop_digest(meta):
        edit(meta)
        meta.pop("header_sha256")

    _tamper(ckpt, edit_and_drop_digest)
    with pytest.raises(ValueError, match=re.escape(words)):
        load_run_config(run_dir)
    with pytest.raises(ValueError, match=re.escape(words)):
        train(TrainConfig(algo="maddpg", reward="minidist", scenario="3v3", episodes=32,
                          seed=3, run_dir=str(run_dir), progress=False), resume=True)


def _strict_json(text: str) -> Any:
    def refuse(token: str) -> None:
        raise ValueError(f"not JSON: {token}")

    return json.loads(text, parse_constant=refuse)


def test_sidecar_and_header_are_strict_json_with_nan_as_null(tmp_path):
    """Sidecars held NaN, which JSON (e.g. JavaScript's JSON.parse) rejects."""
    path = _policy_file(tmp_path)
    sidecar = _strict_json(path.with_suffix(".json").read_text())
    assert sidecar["last_eval"]["avg_time_finished"] is None
    with safe_open(str(path), framework="pt") as f:
        assert _strict_json(f.metadata()["agv"])["last_eval"]["avg_time_finished"] is None
    assert math.isnan(read_metadata(path)["last_eval"]["avg_time_finished"])


def test_sidecar_left_behind_by_a_kill_between_the_two_writes_is_detected_and_rewritten(
        tmp_path):
    """A kill after the checkpoint and before its sidecar: loaders read the checkpoint alone
    (the sidecar is a derived view), and write_sidecar / resume make the pair agree again."""
    path = _policy_file(tmp_path)
    old_sidecar = path.with_suffix(".json").read_text()
    tensors = load_file(str(path))
    tensors["actor.layers.0.bias"] += 1.0
    meta = read_metadata(path)
    save_checkpoint(path, tensors, {**meta, "episodes": 20})
    path.with_suffix(".json").write_text(old_sidecar)  # as if killed before the sidecar
    _, loaded = load_checkpoint(path.with_suffix(".json"))
    assert loaded["episodes"] == 20
    assert json.loads(old_sidecar)["sha256"] != loaded["sha256"]  # the stale view is visible
    write_sidecar(path)
    fresh = _strict_json(path.with_suffix(".json").read_text())
    assert fresh["sha256"] == loaded["sha256"] and fresh["episodes"] == 20
    path.with_suffix(".json").unlink()
    write_sidecar(path)
    assert _strict_json(path.with_suffix(".json").read_text())["episodes"] == 20


def test_resume_rewrites_a_stale_sidecar(tmp_path):
    run_dir = _training_run(tmp_path)
    sidecar = run_dir / "checkpoint.json"
    sidecar.unlink()
    train(TrainConfig(algo="maddpg", reward="minidist", scenario="3v3", episodes=24, seed=3,
                      run_dir=str(run_dir), eval_every=16, eval_episodes=4,
                      checkpoint_every=1000, progress=False), resume=True)
    assert _strict_json(sidecar.read_text())["sha256"] == read_metadata(run_dir)["sha256"]


_KILLED_WRITER = """
import os, sys
from pathlib import Path
from sim.io import atomic_save

def half_then_die(tmp):
    Path(tmp).write_bytes(b"half a checkpoint")
    os._exit(9)  # killed in the middle of the write

atomic_save(half_then_die, sys.argv[1])
"""


def _killed_write(target: Path) -> None:
    proc = subprocess.run([sys.executable, "-c", _KILLED_WRITER, str(target)],
                          env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)},
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 9, proc.stderr


def test_write_killed_half_way_leaves_no_temporary_for_ever(tmp_path):
    target = tmp_path / "checkpoint.safetensors"
    other = tmp_path / "policy.safetensors"
    _killed_write(target)
    _killed_write(other)
    left = sorted(p.name for p in tmp_path.iterdir())
    assert len(left) == 2 and not target.exists(), left
    assert all(name.endswith(".tmp") and name.startswith(".") for name in left), left
    assert any(name.startswith(".checkpoint.safetensors.") for name in left), left
    atomic_write_bytes(target, b"whole")  # the next write of the same target cleans up
    assert target.read_bytes() == b"whole"
    assert sorted(p.name for p in tmp_path.iterdir() if p.name.startswith(".")) == [
        n for n in left if n.startswith(".policy.")]
    removed = clean_stale_temporaries(tmp_path)  # and a run folder can be cleaned whole
    assert [p.name for p in removed] == [n for n in left if n.startswith(".policy.")]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["checkpoint.safetensors"]


def test_temporary_of_a_live_writer_is_kept(tmp_path):
    live = tmp_path / f".checkpoint.safetensors.{os.getppid()}.abc123.tmp"
    live.write_bytes(b"being written by another process")
    atomic_write_bytes(tmp_path / "checkpoint.safetensors", b"x")
    assert clean_stale_temporaries(tmp_path) == [] and live.exists()


def test_training_cleans_temporaries_left_in_its_run_folder(tmp_path):
    run_dir = _training_run(tmp_path)
    _killed_write(run_dir / "best.safetensors.export")
    assert any(p.name.endswith(".tmp") for p in run_dir.iterdir())
    train(TrainConfig(algo="maddpg", reward="minidist", scenario="3v3", episodes=24, seed=3,
                      run_dir=str(run_dir), eval_every=16, eval_episodes=4,
                      checkpoint_every=1000, progress=False), resume=True)
    assert not any(p.name.endswith(".tmp") for p in run_dir.iterdir())


def test_folder_is_fsynced_after_the_rename(tmp_path, monkeypatch):
    """The rename is made durable: os.fsync is called on the folder after os.replace."""
    import stat

    events: list[str] = []
    real_fsync, real_replace = os.fsync, os.replace

    def fsync(fd: int) -> None:
        events.append("fsync-dir" if stat.S_ISDIR(os.fstat(fd).st_mode) else "fsync-file")
        real_fsync(fd)

    def replace(src: Any, dst: Any) -> None:
        events.append("replace")
        real_replace(src, dst)

    monkeypatch.setattr(os, "fsync", fsync)
    monkeypatch.setattr(os, "replace", replace)
    atomic_write_bytes(tmp_path / "a.bin", b"data")
    assert events == ["fsync-file", "replace", "fsync-dir"], events
