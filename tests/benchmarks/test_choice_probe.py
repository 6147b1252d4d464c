"""benchmarks/choice_probe.py: the student-against-teacher curves of a choice-head policy."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
from benchmark_scripts import ROOT, load

probe = load("choice_probe")
CHOICE = ROOT / "benchmarks/results/scale/entity/dagger-choice-w1/dagger.safetensors"
PARKED = ROOT / "benchmarks/results/scale/entity/bicnet-e-parked/parked.safetensors"


def _strict(text: str) -> dict:
    def refuse(name: str) -> float:
        raise ValueError(f"{name} in the JSON")
    return json.loads(text, parse_constant=refuse)


def test_choice_probe_writes_its_table_curves_and_figure(tmp_path: Path) -> None:
    probe.main(["--policy", str(CHOICE), "--size", "6v6", "--episodes", "3",
                "--seed", "5", "--out", str(tmp_path)])
    data = _strict((tmp_path / "choice.json").read_text())
    assert [r["controller"] for r in data["rows"]] == ["teacher", "student",
                                                       "student + shield"]
    assert data["rows"][0]["response"] == 1.0  # the teacher finishes 6v6
    assert data["rows"][2]["overlaps"] == 0.0
    c = data["curves"]
    assert c["idle"][0] == c["teacher_idle"][0] == 6.0  # every AGV idle at the start
    assert len(c["agreement"]) == len(c["clashes"]) == len(c["idle"])
    shares = [v for v in c["agreement"] + c["clashes"] if v is not None]
    assert shares and all(0.0 <= v <= 1.0 for v in shares)
    assert 0.0 <= data["summary"]["agreement"] <= 1.0
    assert not math.isnan(data["summary"]["clashes_first_step"])
    assert (tmp_path / "choice.png").stat().st_size > 0
    assert "python" in data["command"] and "choice.png" in (tmp_path / "choice.md").read_text()


def test_choice_probe_runs_the_same_on_the_same_seed(tmp_path: Path) -> None:
    args = ["--policy", str(CHOICE), "--size", "6v6", "--episodes", "2", "--seed", "9"]
    probe.main([*args, "--out", str(tmp_path / "a")])
    probe.main([*args, "--out", str(tmp_path / "b")])
    a, b = (_strict((tmp_path / d / "choice.json").read_text()) for d in "ab")
    assert a["rows"] == b["rows"] and a["curves"] == b["curves"]


@pytest.mark.parametrize("bad", [
    ["--policy", str(PARKED)],  # an MLP head: no pointer to probe
    ["--policy", str(CHOICE), "--episodes", "0"],
    ["--policy", str(CHOICE), "--size", "6v"],
    ["--policy", "no/such/file.safetensors"],
])
def test_choice_probe_refuses_bad_input_with_a_clear_message(bad, tmp_path, capsys):
    with pytest.raises(SystemExit):
        probe.main([*bad, "--out", str(tmp_path)])
    assert "error:" in capsys.readouterr().err


def test_intent_speed_writes_both_timings_and_their_ratio(tmp_path: Path) -> None:
    speed = load("intent_speed")
    speed.main(["--size", "6v6", "--batch", "4", "--repeats", "2", "--out", str(tmp_path)])
    data = _strict((tmp_path / "intent_speed.json").read_text())
    assert set(data["seconds"]) == {"0", "2"} and all(len(v) == 2 for v in
                                                      data["seconds"].values())
    assert data["ratio"] == data["median"]["2"] / data["median"]["0"] > 0
    assert "| 2 |" in (tmp_path / "intent_speed.md").read_text() and data["regret"] is False
    speed.main(["--size", "6v6", "--batch", "4", "--repeats", "1", "--rounds", "1",
                "--regret", "--out", str(tmp_path)])
    data = _strict((tmp_path / "intent_speed.json").read_text())
    assert data["regret"] is True and set(data["seconds"]) == {"0", "1"}
    assert "| 1 (with regrets) |" in (tmp_path / "intent_speed.md").read_text()
    speed.main(["--size", "6v6", "--batch", "4", "--repeats", "1", "--sinkhorn", "3",
                "--out", str(tmp_path)])
    data = _strict((tmp_path / "intent_speed.json").read_text())
    assert data["sinkhorn"] == 3 and data["regret"] is False
    assert "| 2, 3 assignment rounds |" in (tmp_path / "intent_speed.md").read_text()
    for bad in (["--rounds", "0"], ["--batch", "0"], ["--size", "big"], ["--sinkhorn", "-1"],
                ["--sinkhorn", "257"]):
        with pytest.raises(SystemExit):
            speed.main([*bad, "--out", str(tmp_path)])
