"""benchmarks/scale_table.py runs end to end on a tiny configuration and writes its table,
its JSON and its figure."""

import json
from pathlib import Path

import pytest
from benchmark_scripts import load

bench = load("scale_table")


def test_tiny_run_writes_table_json_and_figure(tmp_path: Path) -> None:
    bench.main(["--sizes", "3", "--episodes", "4", "--floors", "warehouse-20",
                "--lifelong-steps", "30", "--seed", "2", "--out", str(tmp_path)])
    meta = json.loads((tmp_path / "scale.json").read_text())
    assert meta["seed"] == 2 and "--sizes 3" in meta["command"]
    rows = meta["rows"]
    episodic = [r for r in rows if r["kind"] == "episodic"]
    # 4 classical methods, 2 learned ones plain and shielded, and by default the shipped
    # any-N weights plain and shielded, the taught family's too
    from allocator.learned import any_n_weights_path

    any_n = [m for m in ("maddpg-ipf", "bicnet-ipf", "bicnet-dagger")
             if any_n_weights_path(*m.split("-")).is_file()]
    assert any_n, "the any-N weights ship (allocator/weights/any)"
    assert len(episodic) == 4 + 2 * 2 + 2 * len(any_n)
    assert {r["method"] for r in episodic if r["method"].endswith("any-N")} == \
        {f"{m} any-N" for m in any_n}
    assert all(0.0 <= r["response"] <= 1.0 for r in episodic)
    shielded = [r for r in episodic if r["shield"]]
    assert all(r["overlaps"] == 0 and r["interventions"] is not None for r in shielded)
    hung = next(r for r in episodic if r["method"] == "hungarian")
    assert hung["time_vs_hungarian"] == pytest.approx(1.0)
    lifelong = [r for r in rows if r["kind"] == "lifelong"]
    assert {r["method"] for r in lifelong} == {"hungarian", "fifo", "greedy", "auction",
                                              "hungarian+safe", "fifo+safe", "auction+safe",
                                              "maddpg-greedy (shipped)",
                                              "maddpg-dagger (shipped)"}
    assert all(r["lost"] == 0 for r in lifelong)
    # the shipped lifelong weights, plain and shielded: the shield leaves no overlap
    for name in ("maddpg-greedy (shipped)", "maddpg-dagger (shipped)"):
        shipped = {r["shield"]: r for r in lifelong if r["method"] == name}
        assert shipped[True]["overlaps_per_1000_steps"] == 0
        assert shipped[True]["interventions"] > 0
    safe = [r for r in lifelong if r["method"].endswith("+safe")]
    assert len(safe) == 3 and all(r["overlaps_per_1000_steps"] == 0 for r in safe)
    md = (tmp_path / "scale.md").read_text()
    table = [line for line in md.splitlines() if line.startswith("| 3v3")]
    assert len(table) == len(episodic)
    assert (tmp_path / "scale.png").stat().st_size > 1000


def test_no_any_n_leaves_the_any_n_rows_out(tmp_path: Path) -> None:
    bench.main(["--sizes", "3", "--episodes", "2", "--floors", "--no-any-n",
                "--methods", "hungarian", "maddpg-ipf", "--out", str(tmp_path)])
    rows = json.loads((tmp_path / "scale.json").read_text())["rows"]
    assert [(r["method"], r["shield"]) for r in rows] == [
        ("hungarian", False), ("maddpg-ipf", False), ("maddpg-ipf", True)]


def test_view_widens_every_row_but_the_papers_weights(tmp_path: Path) -> None:
    bench.main(["--sizes", "6", "--episodes", "2", "--floors", "--no-any-n", "--view", "10:3",
                "--methods", "hungarian", "bicnet-ipf", "--out", str(tmp_path)])
    rows = json.loads((tmp_path / "scale.json").read_text())["rows"]
    # capped at M = 6 tasks; the paper's 6v6 weights keep their 6:5 input
    assert [(r["method"], r["view"]) for r in rows] == [
        ("hungarian", "6:3"), ("bicnet-ipf", "6:5"), ("bicnet-ipf", "6:5")]


def test_detour_adds_a_shielded_detour_row_per_learned_method(tmp_path: Path) -> None:
    bench.main(["--sizes", "6", "--episodes", "2", "--floors", "--no-any-n", "--detour",
                "--methods", "hungarian", "bicnet-ipf", "--out", str(tmp_path)])
    rows = json.loads((tmp_path / "scale.json").read_text())["rows"]
    # a bare --detour is the squares model, as in the commands recorded before 2026-12-07
    assert [(r["method"], r["shield"], r["detour"]) for r in rows] == [
        ("hungarian", False, False), ("bicnet-ipf", False, False), ("bicnet-ipf", True, False),
        ("bicnet-ipf", True, "squares")]
    assert rows[-1]["overlaps"] == 0
    assert "| 6v6 | bicnet-ipf | yes + squares detour |" in (tmp_path / "scale.md").read_text()


def test_detour_discs_names_its_row(tmp_path: Path) -> None:
    bench.main(["--sizes", "6", "--episodes", "2", "--floors", "--no-any-n", "--detour",
                "discs", "--methods", "hungarian", "bicnet-ipf", "--out", str(tmp_path)])
    rows = json.loads((tmp_path / "scale.json").read_text())["rows"]
    assert [r["detour"] for r in rows] == [False, False, False, "discs"]
    assert rows[-1]["overlaps"] == 0
    assert "| 6v6 | bicnet-ipf | yes + discs detour |" in (tmp_path / "scale.md").read_text()
    with pytest.raises(SystemExit):
        bench.main(["--sizes", "6", "--episodes", "2", "--floors", "--detour", "circles",
                    "--out", str(tmp_path)])


def test_bad_arguments(tmp_path: Path) -> None:
    for view in ("10", "a:b", "0:3", "3:-1"):
        with pytest.raises(SystemExit):
            bench.main(["--sizes", "3", "--episodes", "1", "--floors", "--view", view,
                        "--out", str(tmp_path)])
    with pytest.raises(SystemExit):
        bench.main(["--sizes", "3", "6", "--episodes", "4", "--out", str(tmp_path)])
    with pytest.raises(SystemExit):
        bench.main(["--sizes", "0", "--out", str(tmp_path)])


def test_paper_weights_rows_are_left_out_where_their_input_does_not_fit(tmp_path: Path,
                                                                        capsys) -> None:
    """At 4v4 the 6v6 weights got 4 task slots and failed deep in the policy after the other
    rows had run; they are now left out there, with a line that says why."""
    assert [n for n in range(1, 8) if bench.paper_fits(n)] == [3, 6, 7]
    bench.main(["--sizes", "4", "--episodes", "2", "--floors", "--no-any-n",
                "--methods", "hungarian", "bicnet-ipf", "--out", str(tmp_path)])
    rows = json.loads((tmp_path / "scale.json").read_text())["rows"]
    assert [r["method"] for r in rows] == ["hungarian"]
    assert "no rows for the paper's weights (bicnet-ipf)" in capsys.readouterr().out
