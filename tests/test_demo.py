"""`agv demo --quick` end to end, and the shipped policies against a random policy."""

import pytest
import torch

import allocator
import sim
from allocator.cli import main
from allocator.learned import ALGOS, REWARDS
from sim.controllers import RandomController


@pytest.mark.slow
def test_demo_quick_end_to_end(tmp_path, capsys) -> None:
    assert main(["demo", "--quick", "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    for name in ("hungarian", "greedy", "bicnet-ipf", "maddpg-ipf"):
        assert name in out
    # a lifelong-only family is not tried on the paper's scenes, only in the lifelong rows
    assert "maddpg-dagger: skipped" not in out
    assert (tmp_path / "table.md").exists()
    assert list(tmp_path.glob("*.gif")) and list(tmp_path.glob("*.png"))
    # The lifelong row: every dispatcher on warehouse-20, the same orders, none lost.
    lifelong = (tmp_path / "table_lifelong.md").read_text()
    for name in ("nearest-task", "hungarian", "fifo", "auction", "hungarian + SafeDriver"):
        assert f"| warehouse-20 | {name} | 200 |" in lifelong
    assert "| warehouse-20 | maddpg-dagger (shielded) | 200 |" in lifelong
    # The scale headline: Hungarian and the shipped any-N weights, shielded, on 20v20.
    scale = (tmp_path / "table_scale.md").read_text()
    assert "| 20v20 | hungarian |" in scale and "maddpg-ipf (any-N, shielded)" in scale
    assert (tmp_path / "lifelong_throughput.png").stat().st_size > 1000


@pytest.fixture(scope="module")
def random_metrics() -> dict[str, sim.Metrics]:
    return {s: sim.evaluate(RandomController(seed=0), s, episodes=64, seed=7)
            for s in ("3v3", "6v6")}


@pytest.mark.parametrize("scenario", ["3v3", "6v6"])
@pytest.mark.parametrize("name", [f"{a}-{r}" for a in ALGOS for r in REWARDS])
def test_shipped_policy_beats_random(name: str, scenario: str, random_metrics) -> None:
    # Every shipped policy loads and is clearly better than random on the paper's average
    # reward (R_t: distances of tasks to their nearest AGV, minus overlaps).
    learned = sim.evaluate(allocator.make(name, scenario=scenario), scenario, episodes=64, seed=7)
    random = random_metrics[scenario]
    assert learned.avg_reward >= 0.9 * random.avg_reward  # rewards are negative: >= 10% better
    if name.endswith("-ipf"):  # the paper's method also claims far more tasks than random
        assert learned.response_rate >= random.response_rate + 0.5


def test_demo_reports_missing_weights(tmp_path, monkeypatch, capsys) -> None:
    import allocator.learned as learned

    monkeypatch.setattr(learned, "WEIGHTS_DIR", tmp_path / "nowhere")
    assert main(["demo", "--episodes", "2", "--lifelong-steps", "0", "--scale-episodes", "0",
                 "--out", str(tmp_path / "demo")]) == 0
    out = capsys.readouterr().out
    assert "bicnet-ipf" in out and "skipped" in out and "agv train" in out


def test_random_policy_is_weak() -> None:
    # Guards the previous test's yardstick: random motion rarely claims tasks.
    m = sim.evaluate(RandomController(seed=0), "3v3", episodes=32, seed=7)
    assert m.response_rate < 0.5
    assert torch.isfinite(torch.tensor(m.avg_reward))


def test_demo_lifelong_row_alone(tmp_path, capsys) -> None:
    from allocator.demo import run_lifelong

    rows = run_lifelong(tmp_path, steps=40, seed=1)
    names = [r["method"] for r in rows]
    assert names[:5] == ["nearest-task", "hungarian", "fifo", "auction",
                         "hungarian + SafeDriver"]
    assert all(r["lost"] == 0 and r["throughput"] >= 0 for r in rows)
    # SafeDriver and the shield never let two AGVs overlap
    assert all(r["overlaps"] == 0 for r in rows
               if r["method"].endswith("SafeDriver") or r["method"].endswith("(shielded)"))
    assert (tmp_path / "table_lifelong.md").exists()
    with pytest.raises(SystemExit):
        main(["demo", "--lifelong-steps", "-1", "--out", str(tmp_path)])


def test_demo_scale_headline_alone(tmp_path) -> None:
    from allocator.demo import run_scale

    rows = run_scale(tmp_path, episodes=2, seed=1)
    assert rows[0]["method"] == "hungarian" and rows[0]["time_vs_hungarian"] == 1.0
    shielded = [r for r in rows if r["method"].endswith("shielded)")]
    assert shielded and all(r["overlaps"] == 0 for r in shielded)
    assert "| 20v20 | hungarian |" in (tmp_path / "table_scale.md").read_text()
    with pytest.raises(SystemExit):
        main(["demo", "--scale-episodes", "-1", "--out", str(tmp_path)])
