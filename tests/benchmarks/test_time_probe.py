"""``benchmarks/time_probe.py``'s ``--scenario``, ``--eval-every`` and reward weights (issue 16's
6v6 probes):
bad values are clear errors raised before any training or any file is written."""

from __future__ import annotations

from pathlib import Path

import pytest
from benchmark_scripts import load

time_probe = load("time_probe")


@pytest.mark.parametrize(("flags", "match"), [
    (["--scenario", "warehouse-20"], "is lifelong"),
    (["--scenario", "7x7"], "unknown scenario '7x7'"),
    (["--scenario", ""], "unknown scenario ''"),
    (["--eval-every", "-1"], "eval_every must be an integer >= 0"),
    (["--assign-weight", "-1"], "assign_weight must be a finite number >= 0"),
    (["--assign-weight", "nan"], "assign_weight must be a finite number >= 0"),
    (["--time-cost", "inf"], "time_cost must be a finite number >= 0"),
    (["--goal-weight", "0"], "goal_weight must be a finite number > 0"),
])
def test_bad_scenario_eval_every_or_weight_is_a_clear_error(tmp_path: Path, flags, match) -> None:
    run = tmp_path / "probe"  # an absolute NAME: runs/probes/NAME is then this folder
    with pytest.raises(ValueError, match=match):
        time_probe.main([str(run), "--episodes", "10", *flags])
    assert not run.exists()


def test_eval_every_must_be_an_integer(capsys) -> None:
    for value in ("nan", "1e99", ""):
        with pytest.raises(SystemExit) as exc:
            time_probe.main(["x", "--eval-every", value])
        assert exc.value.code == 2
        assert "--eval-every: invalid int value" in capsys.readouterr().err
