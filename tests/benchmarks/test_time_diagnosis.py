"""``benchmarks/time_diagnosis.py`` (issue 16/17's look at where the time goes): its optimal
assignments against brute force, and a short run at a size whose permutations would not fit
in memory."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from benchmark_scripts import load

time_diagnosis = load("time_diagnosis")


@pytest.mark.parametrize(("n", "m"), [(1, 1), (3, 3), (5, 3), (3, 5), (6, 6)])
def test_min_sum_and_bottleneck_match_brute_force(n: int, m: int) -> None:
    rng = np.random.default_rng(n * 10 + m)
    for _ in range(20):
        dist = rng.uniform(0.0, 3.0, size=(n, m))
        dist[rng.uniform(size=(n, m)) < 0.2] = 1.0  # ties
        k = min(n, m)
        pairs = [list(zip(rows, cols, strict=True))
                 for rows in itertools.permutations(range(n), k)
                 for cols in itertools.combinations(range(m), k)]
        sums = [sum(dist[i, j] for i, j in p) for p in pairs]
        maxes = [max(dist[i, j] for i, j in p) for p in pairs]
        assert time_diagnosis._min_sum(dist) == pytest.approx(min(sums))
        assert time_diagnosis._bottleneck(dist) == pytest.approx(min(maxes))


def test_a_20v20_run_prints_a_row(capsys) -> None:
    time_diagnosis.main(["--scenario", "20v20", "--seed", "3", "--episodes", "2",
                         "--hungarian"])
    out = capsys.readouterr().out
    row = [line for line in out.splitlines() if line.startswith("| hungarian |")]
    assert len(row) == 1
    cells = [float(c) for c in row[0].strip("|").split("|")[1:]]
    resp, sum_opt = cells[0], cells[8]
    assert resp == 1.0 and sum_opt >= 1.0 - 1e-9
