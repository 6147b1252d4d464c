"""benchmarks/train_policies.py (tagged runs, settings from the reward search) and
benchmarks/reward_search.py (each reward's own settings) on tiny real runs."""

import csv
import json
from pathlib import Path

import pytest
from benchmark_scripts import load

train_policies = load("train_policies")
reward_search = load("reward_search")

SUMMARY_COLUMNS = ["algo", "reward", "scenario", "episodes", "eval_every", "eval_episodes",
                   "checkpoint_every", "actor_lr", "gamma", "tensorboard", "seeds",
                   "response_rate_mean", "response_rate_ci95", "avg_time_mean"]


def _sweep(folder: Path, rows: list[list]) -> Path:
    folder.mkdir(parents=True)
    with (folder / "summary.csv").open("w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(SUMMARY_COLUMNS)
        writer.writerows(rows)
    return folder


def test_reward_search_picks_each_methods_best_and_breaks_ties_by_time(tmp_path: Path) -> None:
    a = _sweep(tmp_path / "search", [
        ["maddpg", "minidist", "3v3", 3000, 0, 300, 1000, 0.001, 0.99, False, 2, 0.70, 0.01, 20.0],
        ["maddpg", "minidist", "3v3", 3000, 0, 300, 1000, 0.003, 0.9, False, 2, 0.80, 0.02, 19.0],
        ["maddpg", "ipf", "3v3", 3000, 0, 300, 1000, 0.003, 0.9, False, 2, 0.90, "", 12.0],
    ])
    b = _sweep(tmp_path / "base", [
        ["maddpg", "minidist", "3v3", 3000, 0, 300, 1000, 0.003, 0.95, False, 2, 0.80, 0.0, 18.0],
        ["maddpg", "ipf", "3v3", 3000, 0, 300, 1000, 0.003, 0.95, False, 2, 0.85, 0.0, 11.0],
    ])
    out = tmp_path / "out"
    assert reward_search.main([str(a), str(b), "--out", str(out)]) == 0
    record = json.loads((out / "reward_search.json").read_text())["methods"]
    assert record["maddpg-minidist"]["settings"] == {"actor_lr": 0.003, "gamma": 0.95}
    assert record["maddpg-minidist"]["sweep"] == "base"          # same response, less time
    assert record["maddpg-ipf"]["settings"] == {"actor_lr": 0.003, "gamma": 0.9}
    assert record["maddpg-ipf"]["candidates"] == 2
    md = (out / "reward_search.md").read_text()
    assert md.count("**yes**") == 2


def test_reward_search_without_a_summary_is_a_clear_error(tmp_path: Path, capsys) -> None:
    assert reward_search.main([str(tmp_path / "nothing"), "--out", str(tmp_path)]) == 2
    assert "holds no summary.csv" in capsys.readouterr().err


def test_settings_become_set_items_and_bad_records_are_refused(tmp_path: Path) -> None:
    path = tmp_path / "rs.json"
    path.write_text(json.dumps({"methods": {"bicnet-greedy": {
        "settings": {"gamma": 0.99, "reward_scale": 0.3}}}}))
    assert train_policies.chosen_settings(path, "bicnet-greedy") == ["gamma=0.99",
                                                                      "reward_scale=0.3"]
    assert train_policies.chosen_settings(None, "bicnet-greedy") == []
    with pytest.raises(ValueError, match="no settings for 'maddpg-ipf'"):
        train_policies.chosen_settings(path, "maddpg-ipf")
    path.write_text("not json")
    with pytest.raises(ValueError, match="--settings"):
        train_policies.chosen_settings(path, "bicnet-greedy")


@pytest.mark.parametrize("tag", ["../up", "a/b", " "])
def test_a_tag_that_is_not_a_plain_folder_name_is_refused(tag: str, capsys) -> None:
    with pytest.raises(SystemExit) as exc:
        train_policies.main(["--scenario", "3v3", "--algo", "maddpg", "--reward", "ipf",
                             "--episodes", "10", "--tag", tag])
    assert exc.value.code == 2
    assert "--tag" in capsys.readouterr().err


def test_a_tagged_run_trains_with_the_chosen_settings_and_ships_beside_the_default(
        tmp_path: Path, monkeypatch) -> None:
    for name, value in (("ROOT", tmp_path), ("WEIGHTS", tmp_path / "weights"),
                        ("TRAINING", tmp_path / "training")):
        monkeypatch.setattr(train_policies, name, value)
    settings = tmp_path / "rs.json"
    settings.write_text(json.dumps({"methods": {"maddpg-ipf": {"settings": {
        "gamma": 0.9, "num_envs": 8, "batch_size": 32, "learning_starts": 32}}}}))
    code = train_policies.main([
        "--scenario", "1v1", "--algo", "maddpg", "--reward", "ipf", "--seeds", "0",
        "--episodes", "24", "--eval-every", "12", "--eval-episodes", "4", "--tag", "budget",
        "--settings", str(settings), "--set", "batch_size=16"])
    assert code == 0
    config = json.loads((tmp_path / "training" / "1v1" / "budget"
                         / "maddpg-ipf-s0.config.json").read_text())
    learner = json.dumps(config)
    assert '"gamma": 0.9' in learner and '"batch_size": 16' in learner  # --set wins
    assert (tmp_path / "weights" / "1v1" / "budget" / "maddpg-ipf.safetensors").is_file()
    assert (tmp_path / "weights" / "1v1" / "budget" / "seeds"
            / "maddpg-ipf-s0.safetensors").is_file()
    assert not (tmp_path / "weights" / "1v1" / "maddpg-ipf.safetensors").exists()
    record = json.loads((tmp_path / "training" / "1v1" / "budget" / "maddpg-ipf.json")
                        .read_text())
    assert record["shipped_seed"] == 0
