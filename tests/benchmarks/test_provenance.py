"""The command a benchmark records repeats the run when pasted at the repository root."""

import pytest
from benchmark_scripts import ROOT, load

provenance = load("provenance")
SCRIPT = str(ROOT / "benchmarks" / "dagger_probe.py")


def test_a_run_from_the_root_is_recorded_as_it_was_typed(monkeypatch: pytest.MonkeyPatch):
    monkeypatch.chdir(ROOT)
    assert provenance.recorded_command(SCRIPT, ["--out", "a b", "--seed", "3"]) == (
        "python benchmarks/dagger_probe.py --out 'a b' --seed 3")


def test_a_run_from_elsewhere_is_recorded_with_its_cd(monkeypatch: pytest.MonkeyPatch):
    monkeypatch.chdir(ROOT / "benchmarks")
    assert provenance.recorded_command(SCRIPT, ["--start", "results/x"]) == (
        "cd benchmarks && python dagger_probe.py --start results/x")
    assert provenance.recorded_command(SCRIPT, [], env="OMP_NUM_THREADS=1") == (
        "cd benchmarks && OMP_NUM_THREADS=1 python dagger_probe.py")


def test_no_arguments_given_means_the_process_arguments(monkeypatch: pytest.MonkeyPatch):
    monkeypatch.chdir(ROOT)
    monkeypatch.setattr("sys.argv", ["whatever", "--sizes", "3"])
    assert provenance.recorded_command(SCRIPT) == "python benchmarks/dagger_probe.py --sizes 3"
