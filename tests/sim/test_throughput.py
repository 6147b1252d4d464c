"""The timing helpers behind ``agv bench`` and ``benchmarks/sim_throughput.py``."""

from __future__ import annotations

from sim.throughput import Throughput, measure


def test_measure_times_steps_resets_and_the_physics_in_turns() -> None:
    m = measure("3v3", 4, steps=30, repeats=2, physics=True)
    assert m.step_seconds > 0 and m.reset_seconds > 0 and m.physics_seconds > 0
    assert m.overhead == m.step_seconds / m.physics_seconds - 1
    assert m.steps_per_second == 4 / (m.step_seconds + m.reset_seconds)
    assert measure("3v3", 2, steps=5, repeats=1).overhead is None


def test_overhead_is_none_without_the_physics() -> None:
    assert Throughput(8, 2e-3, 1e-3).overhead is None
    assert Throughput(8, 3e-3, 0.0, 2e-3).overhead == 0.5


def test_agv_bench_prints_the_overhead(capsys) -> None:
    from allocator.cli import main

    assert main(["bench", "--scenario", "3v3", "--envs", "2"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert "overhead" in lines[1]
    row = lines[2].split()
    assert row[0] == "2" and row[-1].endswith("%")
