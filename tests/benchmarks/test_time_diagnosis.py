"""``benchmarks/time_diagnosis.py`` (issue 16/17's look at where the time goes): its optimal
assignments against brute force, and a short run at a size whose permutations would not fit
in memory (its figure too)."""

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


def test_a_10v10_run_prints_a_row_and_draws_the_claims(capsys, tmp_path) -> None:
    # (10! permutations per episode is what the old enumeration would have had to hold)
    png = tmp_path / "claims.png"
    time_diagnosis.main(["--scenario", "10v10", "--seed", "3", "--episodes", "2",
                         "--hungarian", "--plot", str(png)])
    assert png.stat().st_size > 1000
    out = capsys.readouterr().out
    row = [line for line in out.splitlines() if line.startswith("| hungarian |")]
    assert len(row) == 1
    cells = [float(c) for c in row[0].strip("|").split("|")[1:]]
    resp, sum_opt = cells[0], cells[8]
    assert resp == 1.0 and sum_opt >= 1.0 - 1e-9


def test_the_claim_curve_counts_claims_and_keeps_a_finished_episode_s_state() -> None:
    claimed = np.zeros((3, 2, 2), dtype=bool)  # (T + 1, E, M): two steps recorded
    claimed[1:, 0, 0] = True
    claimed[2:, 1] = True
    curve = time_diagnosis._claim_curve(claimed, limit=4)
    np.testing.assert_allclose(curve, [0.0, 0.25, 0.75, 0.75, 0.75])


def test_plot_must_name_a_png(tmp_path) -> None:
    with pytest.raises(ValueError, match="--plot must name a .png file"):
        time_diagnosis.main(["--scenario", "3v3", "--episodes", "1", "--plot",
                             str(tmp_path / "x.pdf")])


@pytest.mark.parametrize("episodes", ["0", "-3", "2001"])
def test_episodes_out_of_range_is_a_clear_error(episodes) -> None:
    with pytest.raises(ValueError, match=r"--episodes must be in \[1, 2000\]"):
        time_diagnosis.main(["--scenario", "6v6", "--episodes", episodes, "--hungarian"])
