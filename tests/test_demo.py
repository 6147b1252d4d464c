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
    assert (tmp_path / "table.md").exists()
    assert list(tmp_path.glob("*.gif")) and list(tmp_path.glob("*.png"))
    # The lifelong row: every dispatcher on warehouse-20, the same orders, none lost.
    lifelong = (tmp_path / "table_lifelong.md").read_text()
    for name in ("nearest-task", "hungarian", "fifo", "auction"):
        assert f"| warehouse-20 | {name} | 200 |" in lifelong
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
    assert main(["demo", "--episodes", "2", "--lifelong-steps", "0",
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
    assert [r["method"] for r in rows] == ["nearest-task", "hungarian", "fifo", "auction"]
    assert all(r["lost"] == 0 and r["throughput"] >= 0 for r in rows)
    assert (tmp_path / "table_lifelong.md").exists()
    with pytest.raises(SystemExit):
        main(["demo", "--lifelong-steps", "-1", "--out", str(tmp_path)])
