"""``best.safetensors`` is the evaluation with the highest task response and, among those, the
lowest average time (issue 16), the rule ``benchmarks/train_policies.py`` ranks runs by."""

from __future__ import annotations

import csv

from learners.checkpoint import read_metadata
from learners.train import TrainConfig, train
from tests.learners.conftest import TINY


def test_best_checkpoint_breaks_response_ties_by_time(tmp_path) -> None:
    run = tmp_path / "run"
    config = TrainConfig(algo="maddpg", reward="ipf", scenario="1v1", episodes=480, seed=0,
                         run_dir=str(run), eval_every=16, eval_episodes=2, log_every=16,
                         checkpoint_every=480, progress=False, tensorboard=False)
    train(config, dict(TINY))
    with (run / "progress.csv").open() as fh:
        evals = [(float(r["eval_response_rate"]), float(r["eval_avg_time"]), int(r["episode"]))
                 for r in csv.DictReader(fh) if r["eval_response_rate"]]
    top = max(resp for resp, _, _ in evals)
    tied = [(t, ep) for resp, t, ep in evals if resp == top]
    # the case the rule is for: the first evaluation at the top response is not the fastest
    assert len(tied) > 1 and min(tied)[0] < tied[0][0]
    best = read_metadata(run / "best.safetensors")
    fastest = min(tied)
    assert best["last_eval"]["response_rate"] == top
    assert best["last_eval"]["avg_time"] == fastest[0]
