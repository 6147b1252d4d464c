"""benchmarks/detour_speed.py: the shield's detours timed, squares against discs."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from benchmark_scripts import load

speed = load("detour_speed")


def test_detour_speed_writes_three_timings_and_their_ratios(tmp_path: Path) -> None:
    speed.main(["--size", "10v10", "--episodes", "3", "--repeats", "2", "--out", str(tmp_path)])
    data = json.loads((tmp_path / "detour_speed.json").read_text())
    assert set(data["seconds"]) == {"False", "squares", "discs"}
    assert all(len(v) == 2 and min(v) > 0 for v in data["seconds"].values())
    assert data["ratio"]["False"] == 1.0 and data["ratio_per_step"]["False"] == 1.0
    assert data["ratio"]["discs"] == pytest.approx(data["median"]["discs"]
                                                   / data["median"]["False"])
    assert all(1 <= s <= 32 for s in data["batch_steps"].values())  # 10v10: 32-step limit
    text = (tmp_path / "detour_speed.md").read_text()
    assert "| yes + discs detour |" in text and "| yes + squares detour |" in text


@pytest.mark.parametrize("bad", [["--episodes", "0"], ["--repeats", "0"], ["--seed", "-1"],
                                 ["--size", "big"], ["--size", "warehouse-20"]])
def test_detour_speed_refuses_bad_arguments(tmp_path: Path, bad: list[str]) -> None:
    with pytest.raises(SystemExit):
        speed.main(bad + ["--out", str(tmp_path)])
