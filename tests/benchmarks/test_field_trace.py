"""``benchmarks/field_trace.py`` (issue 17's look at the IPF field in the tail): the three
readings on a short Hungarian run, and bad input."""

from __future__ import annotations

import pytest
from benchmark_scripts import load

import allocator

field_trace = load("field_trace")


def test_the_three_readings_of_an_idle_agv() -> None:
    out = field_trace.trace(allocator.make("hungarian"), "6v6", seed=0, episodes=2,
                            episode=0, agv=0, step=0)
    assert list(out) == list(field_trace.READINGS)
    for r in out.values():
        assert len(r["lines"]) == 6 and len(r["quantiles"]) == 5
        for line in r["lines"].values():
            assert len(line) == 11 and line[-1] == pytest.approx(5.0)
    # at step 0 nobody is parked: the three readings are one field
    paper, zero, out_ = (out[k] for k in field_trace.READINGS)
    assert paper["here"] == zero["here"] == out_["here"]


def test_main_prints_each_reading(capsys) -> None:
    field_trace.main(["--policy", "hungarian", "--scenario", "3v3", "--episodes", "1",
                      "--episode", "0", "--agv", "1", "--step", "1"])
    out = capsys.readouterr().out
    assert all(reading in out for reading in field_trace.READINGS)
    assert "to the task at (" in out


@pytest.mark.parametrize(("kw", "match"), [
    ({"episode": 2}, r"--episode must be in \[0, 1\]"),
    ({"agv": 6}, r"--agv must be in \[0, 5\]"),
    ({"step": 999}, r"--step must be in"),
    ({"episodes": 0}, r"--episodes must be in \[1, 2000\]"),
    ({"episodes": 10**8}, r"--episodes must be in \[1, 2000\]"),
])
def test_out_of_range_is_a_clear_error(kw, match) -> None:
    args = {"seed": 0, "episodes": 2, "episode": 0, "agv": 0, "step": 0, **kw}
    with pytest.raises(ValueError, match=match):
        field_trace.trace(allocator.make("hungarian"), "6v6", **args)


def test_a_parked_agv_is_refused() -> None:
    with pytest.raises(ValueError, match="is parked at step"):
        # by the last recorded step of a finished Hungarian episode every AGV is parked
        field_trace.trace(allocator.make("hungarian"), "3v3", seed=0, episodes=1,
                          episode=0, agv=0, step=6)
