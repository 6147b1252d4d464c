"""The tables' code on a tiny run produces a well-formed table; the figures' helpers work."""

import csv
import math
from pathlib import Path

import numpy as np
import pytest
from benchmark_scripts import load

paper_tables = load("paper_tables")
paper_figures = load("paper_figures")


def test_tiny_table_is_well_formed(tmp_path: Path) -> None:
    methods = ["bicnet-ipf", "maddpg-ipf", "hungarian", "greedy"]
    code = paper_tables.main(["--episodes", "3", "--scenarios", "3v3", "--methods", *methods,
                              "--out", str(tmp_path)])
    assert code == 0
    md = (tmp_path / "paper_tables.md").read_text()
    table = [line for line in md.splitlines() if line.startswith("| ")]
    assert len(table) == 1 + len(methods)  # header + one row per method
    assert all(line.count("|") == table[0].count("|") for line in table)
    with (tmp_path / "paper_tables.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    assert [r["method"] for r in rows] == methods
    for r in rows:
        assert 0.0 <= float(r["response_rate"]) <= 1.0
        assert float(r["avg_time"]) >= 1.0
    hungarian = next(r for r in rows if r["method"] == "hungarian")
    assert float(hungarian["time_ratio_to_hungarian"]) == pytest.approx(1.0)
    ipf = next(r for r in rows if r["method"] == "bicnet-ipf")
    assert float(ipf["paper_response_rate"]) == pytest.approx(0.9758)
    assert not list(tmp_path.glob(".*"))  # nothing half-written left behind


def test_missing_policy_names_the_file(tmp_path: Path, monkeypatch, capsys) -> None:
    import allocator.learned as learned

    monkeypatch.setattr(learned, "WEIGHTS_DIR", tmp_path / "nowhere")
    code = paper_tables.main(["--episodes", "2", "--scenarios", "3v3", "--methods",
                              "maddpg-ipf", "--out", str(tmp_path)])
    err = capsys.readouterr().err
    assert code == 2
    assert "maddpg-ipf.safetensors" in err and "agv train" in err
    assert not (tmp_path / "paper_tables.md").exists()


def test_interval_over_seeds() -> None:
    class M:
        def __init__(self, v: float) -> None:
            self.response_rate = v

    row = paper_tables.Row("3v3", "x", M(0.9), [M(0.8), M(0.9), M(1.0)])
    mean, half = row.interval("response_rate")
    assert mean == pytest.approx(0.9)
    assert half == pytest.approx(4.302652729911275 * 0.1 / math.sqrt(3))
    assert math.isnan(paper_tables.Row("3v3", "x", M(0.9)).interval("response_rate")[1])


def test_preference_counts_sum_to_claims() -> None:
    import allocator

    by_index, by_rank = paper_figures.preference_counts(allocator.make("hungarian"), "3v3", 8, 0)
    assert by_index.shape == by_rank.shape == (3, 3)
    assert by_index.sum() == pytest.approx(by_rank.sum())
    assert np.all(by_index <= 1.0)


def test_paper_budget_seeds_are_scored_beside_the_5k_ones(tmp_path: Path, monkeypatch) -> None:
    import shutil

    import allocator

    shipped = Path(allocator.__file__).parent / "weights" / "3v3" / "seeds"
    budget = tmp_path / "allocator" / "weights" / "3v3" / paper_tables.BUDGET_TAG / "seeds"
    budget.mkdir(parents=True)
    for seed in (0, 1):
        for suffix in (".safetensors", ".json"):
            shutil.copyfile(shipped / f"maddpg-ipf-s{seed}{suffix}",
                            budget / f"maddpg-ipf-s{seed}{suffix}")
    monkeypatch.setattr(allocator, "__file__", str(tmp_path / "allocator" / "__init__.py"))
    row = paper_tables.evaluate_method("3v3", "maddpg-ipf", 3, 0)
    assert len(row.budget) == 2 and not row.seeds  # the 5k seeds are not under tmp_path
    mean, half = row.interval("response_rate", budget=True)
    assert mean == pytest.approx(np.mean([m.response_rate for m in row.budget]))
    assert not math.isnan(half)
    line = next(x for x in paper_tables.markdown([row], "#").splitlines()
                if x.startswith("| maddpg-ipf"))
    assert line.rstrip().endswith("| 2 |")
    none = paper_tables.Row("3v3", "greedy", row.shipped).interval("avg_time", budget=True)
    assert all(math.isnan(x) for x in none)  # no paper-budget seeds: no figure, not a zero


def test_training_figure_of_tagged_runs_reads_their_folder_only(tmp_path: Path) -> None:
    logs = Path(paper_figures.RESULTS) / "training" / "3v3"
    tagged = tmp_path / "training" / "3v3" / "paper-budget"
    tagged.mkdir(parents=True)
    (tagged / "maddpg-ipf-s0.csv").write_text((logs / "maddpg-ipf-s0.csv").read_text())
    curves = paper_figures.read_curves("3v3", tmp_path / "training", "paper-budget")
    assert list(curves) == ["maddpg-ipf"] and len(curves["maddpg-ipf"]) == 1
    assert not paper_figures.read_curves("3v3", tmp_path / "training")  # untagged: empty
    paper_figures.training_figure("3v3", tmp_path / "training", tmp_path, "paper-budget")
    assert (tmp_path / "fig9_training_3v3_paper-budget.png").stat().st_size > 1000
