"""benchmarks/dispatch_bound.py: the transport bound, the cycle cover, and a tiny end-to-end run."""

import json
from pathlib import Path

import numpy as np
import pytest
from benchmark_scripts import load

bench = load("dispatch_bound")


def test_transport_bound_of_small_costs() -> None:
    # Two stations, two pickups, each station next to one pickup: nothing to travel.
    assert bench.transport_bound(np.array([[0.0, 2.0], [2.0, 0.0]])) == pytest.approx(0.0)
    # One station: every pickup is reached from it, the mean of the row.
    assert bench.transport_bound(np.array([[1.0, 3.0, 8.0]])) == pytest.approx(4.0)
    # Two stations for three pickups: station 0 takes pickup 0 and a third of pickup 1...
    cost = np.array([[0.0, 1.0, 5.0], [5.0, 2.0, 0.0]])
    # half the mass leaves each station; a third arrives at each pickup: station 0 sends 1/3
    # to pickup 0 (cost 0) and 1/6 to pickup 1 (cost 1), station 1 sends 1/6 to pickup 1
    # (cost 2) and 1/3 to pickup 2 (cost 0).
    assert bench.transport_bound(cost) == pytest.approx(1 / 6 + 2 / 6)


def test_transport_bound_with_column_weights() -> None:
    cost = np.array([[0.0, 1.0, 5.0], [5.0, 2.0, 0.0]])
    # Uniform weights are the default.
    assert bench.transport_bound(cost, np.ones(3)) == pytest.approx(bench.transport_bound(cost))
    # All the mass on pickup 1: half from each station.
    assert bench.transport_bound(cost, np.array([0, 7, 0])) == pytest.approx(1.5)
    # And all the row mass on station 1 as well: every pickup-1 unit from it.
    assert bench.transport_bound(cost, np.array([0, 7, 0]), np.array([0, 2])) \
        == pytest.approx(2.0)
    for bad in (np.ones(2), np.array([1.0, -1.0, 1.0]), np.zeros(3),
                np.array([1.0, np.nan, 1.0])):
        with pytest.raises(ValueError, match="weights"):
            bench.transport_bound(cost, bad)
    with pytest.raises(ValueError, match="row_weights"):
        bench.transport_bound(cost, None, np.ones(3))


def test_bounds_are_ordered_on_random_costs() -> None:
    rng = np.random.default_rng(3)
    cost = rng.uniform(1.0, 10.0, size=(4, 9))
    t = bench.transport_bound(cost)
    assert cost.min(axis=0).mean() - 1e-9 <= t <= cost.mean() + 1e-9
    # A large sample's cycle cover is near the transport bound (it is a sampled version).
    assert bench.cycle_cover(cost, 2000, seed=0) == pytest.approx(t, rel=0.1)


@pytest.mark.parametrize("bad", [np.zeros((0, 3)), np.array([1.0, 2.0]),
                                 np.array([[1.0, np.nan]]), np.array([[1.0, np.inf]])])
def test_transport_bound_refuses_bad_costs(bad) -> None:
    with pytest.raises(ValueError, match="cost"):
        bench.transport_bound(bad)


@pytest.mark.parametrize("bad", [1, 0, True, 2.5])
def test_cycle_cover_refuses_bad_samples(bad) -> None:
    with pytest.raises(ValueError, match="samples"):
        bench.cycle_cover(np.ones((2, 2)), bad, seed=0)


def test_tiny_run_writes_table_and_json(tmp_path: Path) -> None:
    bench.main(["--floor", "warehouse-20", "--steps", "300", "--samples", "200",
                "--out", str(tmp_path), "--name", "tiny"])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["tiny.json", "tiny.md"]
    data = json.loads((tmp_path / "tiny.json").read_text())
    assert "--floor warehouse-20" in data["command"]
    (row,) = data["rows"]
    m, q = row["model"], row["ratios"]
    # The bounds of the order model are ordered: nearest station <= transport <= random.
    assert m["nearest_station_empty_steps"] <= m["transport_empty_steps"] + 1e-9
    assert m["transport_empty_steps"] <= m["random_empty_steps"] + 1e-9
    assert set(row["runs"]) == {"fifo", "hungarian"}
    for r in row["runs"].values():
        assert r["empty_steps"] > 0 and r["loaded_steps"] > 0
        # The run's own pairing of drop-off stations and next pickups is one transport plan
        # between them: its mean is never below the optimum.
        assert r["empty_path"] >= r["served_transport_empty_path"] - 1e-9
        assert r["served_transport_empty_path"] >= r["served_nearest_station_path"] - 1e-9
    # Hungarian's empty trips are never shorter than their transport bound, so the ratio of an
    # optimal matching (same traffic, same loaded trips) is never below the measured cycles'.
    assert q["optimal_matching"] >= q["cycle_measured"] - 1e-9
    md = (tmp_path / "tiny.md").read_text()
    assert md.count("| warehouse-20 |") == 1 + 2 + 1
    # --report-only makes the same table from the stored JSON, without running anything.
    (tmp_path / "tiny.md").unlink()
    bench.main(["--report-only", "--out", str(tmp_path), "--name", "tiny"])
    assert (tmp_path / "tiny.md").read_text() == md


def test_bad_arguments(tmp_path: Path) -> None:
    with pytest.raises(SystemExit):
        bench.main(["--floor", "warehouse-20", "--steps", "50", "--out", str(tmp_path)])
    with pytest.raises(SystemExit):
        bench.main(["--floor", "warehouse-20", "--samples", "1", "--out", str(tmp_path)])
