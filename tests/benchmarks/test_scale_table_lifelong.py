"""benchmarks/scale_table.py's learned lifelong rows (issue 17): a lifelong entity run's
weights, plain and shielded, beside the chosen baselines on the same seed."""

import json
from pathlib import Path

import pytest
from benchmark_scripts import load

from learners.train import TrainConfig, train

bench = load("scale_table")


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("ll") / "run"
    train(TrainConfig(algo="maddpg-e", reward="greedy", scenario="warehouse-20", episodes=2,
                      seed=0, run_dir=str(out), eval_every=0, window=10, eval_steps=10,
                      progress=False, tensorboard=False),
          {"hidden": 8, "batch_size": 16, "num_envs": 2, "learning_starts": 10,
           "buffer_size": 100})
    return out


def test_lifelong_weights_rows(tmp_path: Path, run_dir: Path) -> None:
    bench.main(["--sizes", "--floors", "warehouse-20", "--lifelong-steps", "20",
                "--dispatchers", "fifo", "nearest", "--lifelong-weights", str(run_dir),
                "--out", str(tmp_path)])
    rows = json.loads((tmp_path / "scale.json").read_text())["rows"]
    # the baselines, the shipped lifelong weights (allocator/weights/lifelong; the taught
    # family at its own view), then the run's
    assert [(r["method"], r["shield"], r["view"]) for r in rows] == [
        ("fifo", False, "4:4"), ("nearest", False, "4:4"),
        ("maddpg-greedy (shipped)", False, "4:4"), ("maddpg-greedy (shipped)", True, "4:4"),
        ("maddpg-dagger (shipped)", False, "16:16"), ("maddpg-dagger (shipped)", True, "16:16"),
        (f"maddpg-greedy ({run_dir})", False, "4:4"),
        (f"maddpg-greedy ({run_dir})", True, "4:4")]
    assert all(r["kind"] == "lifelong" and r["lost"] == 0 for r in rows)
    shielded = rows[-1]
    assert shielded["overlaps_per_1000_steps"] == 0 and shielded["interventions"] is not None
    assert rows[0]["interventions"] is None
    md = (tmp_path / "scale.md").read_text()
    assert "## Episodic" not in md and md.count("| warehouse-20 |") == 8


def test_bad_lifelong_weights(tmp_path: Path) -> None:
    with pytest.raises(SystemExit):
        bench.main(["--sizes", "--floors", "warehouse-20", "--lifelong-weights",
                    str(tmp_path / "none"), "--out", str(tmp_path)])
    with pytest.raises(SystemExit):
        bench.main(["--sizes", "--dispatchers", "dijkstra", "--out", str(tmp_path)])
