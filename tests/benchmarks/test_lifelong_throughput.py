"""benchmarks/lifelong_throughput.py runs end to end on a tiny row (--quick) and writes a
well-formed table and CSV with its configuration."""

import csv
import importlib.util
import math
from pathlib import Path

import pytest
from benchmark_scripts import load

bench = load("lifelong_throughput")


def _has_vmas() -> bool:
    return importlib.util.find_spec("vmas") is not None


@pytest.mark.parametrize("with_vmas", [False, pytest.param(True, marks=pytest.mark.skipif(
    not _has_vmas(), reason="vmas (the bench extra) is not installed"))])
def test_quick_run_writes_table_and_csv(tmp_path: Path, with_vmas: bool) -> None:
    argv = ["--quick", "--rows", "warehouse-20:2", "--seed", "3", "--out", str(tmp_path)]
    if not with_vmas:
        argv += ["--no-vmas", "--clock", "cpu"]
    assert bench.main(argv) == 0
    md = (tmp_path / "lifelong_throughput.md").read_text()
    table = [line for line in md.splitlines() if line.startswith("| ")]
    assert len(table) == 1 + 2  # header + breakdowns off and on
    assert all(line.count("|") == table[0].count("|") for line in table)
    assert "seed 3" in md and "--quick" in md
    with (tmp_path / "lifelong_throughput.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    assert [(r["scenario"], r["N"], r["B"]) for r in rows] == [("warehouse-20", "20", "2")] * 2
    assert rows[0]["faults"] == "none" and rows[1]["faults"].startswith("Breakdowns(")
    for r in rows:
        assert r["seed"] == "3" and r["threads"] == "1" and r["machine"] and r["date"]
        assert r["clock"] == ("wall" if with_vmas else "cpu")
        for key in ("lifelong_sps", "episodic_floor_sps", "episodic_floor_torch_sps",
                    "nvn_sps"):
            assert float(r[key]) > 0, key
        # The step time and the rate describe the same timing: B / seconds.
        assert float(r["lifelong_sps"]) == pytest.approx(2e6 / float(r["lifelong_step_us"]),
                                                         rel=0.01)
        overhead = float(r["episodic_floor_step_us"]) and (
            float(r["lifelong_step_us"]) / float(r["episodic_floor_step_us"]) - 1)
        assert float(r["overhead_vs_floor"]) == pytest.approx(overhead, rel=0.01, abs=0.01)
        vmas = float(r["vmas_sps"])
        if with_vmas:
            assert vmas > 0
            assert float(r["lifelong_over_vmas"]) == pytest.approx(
                float(r["lifelong_sps"]) / vmas, rel=0.01)
        else:
            assert math.isnan(vmas)
    assert not list(tmp_path.glob(".*"))  # nothing half-written left behind


def test_episodic_peer_matches_the_floor() -> None:
    import sim

    env = sim.make_env("warehouse-20", num_envs=2, seed=0)
    peer = bench.episodic_peer(env)
    assert peer.world is env.world
    assert (peer.num_agents, peer.num_tasks) == (20, 30)
    assert (peer.k_tasks, peer.k_agents) == (env.scenario.k_pickups, env.scenario.k_agents)
    episodic = sim.make_env(peer, num_envs=2, seed=0)
    assert not getattr(episodic, "lifelong", False)
    # Same depot: every AGV starts inside the floor's depot rectangles.
    depot = env.world.depot
    pos = episodic.agent_pos.reshape(-1, 2).numpy()
    inside = ((pos[:, None, 0] >= depot[None, :, 0]) & (pos[:, None, 0] <= depot[None, :, 2])
              & (pos[:, None, 1] >= depot[None, :, 1]) & (pos[:, None, 1] <= depot[None, :, 3]))
    assert inside.any(1).all()


@pytest.mark.parametrize("bad", ["warehouse-50", "warehouse-x:4", "3v3:4", "warehouse-5:0"])
def test_bad_row_is_refused(bad: str) -> None:
    with pytest.raises(ValueError, match="warehouse-<N>:<B>"):
        bench.parse_row(bad)
