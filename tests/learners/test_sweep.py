"""Sweeps on Ray Tune: the spec (parsing, expansion, every bad spec an error before any trial),
the tables (mean and 95% interval over seeds), the message without Ray, an evaluation sweep
with a retried trial on a local Ray, and (slow) the tiny training sweep killed with SIGKILL and
resumed, whose tables equal an uninterrupted sweep's."""

from __future__ import annotations

import csv
import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from learners import sweep
from learners.sweep import aggregate, load_spec, parse_spec

ROOT = Path(__file__).resolve().parents[2]
SWEEPS = ROOT / "benchmarks" / "sweeps"


def _spec(**tables: dict) -> dict:
    base = {"sweep": {"seeds": [0]}, "fixed": {"episodes": 10}, "grid": {"algo": ["maddpg"]}}
    base.update(tables)
    return base


# --------------------------------------------------------------------------- the spec


def test_tiny_spec_is_four_short_trials_in_canonical_order() -> None:
    spec = load_spec(SWEEPS / "tiny.toml")
    assert spec.mode == "train" and spec.name == "tiny"
    assert [t.trial_id for t in spec.trials] == ["0000-maddpg-s0", "0001-maddpg-s1",
                                                 "0002-bicnet-s0", "0003-bicnet-s1"]
    assert [t.index for t in spec.trials] == [0, 1, 2, 3]
    for trial in spec.trials:
        assert trial.settings["episodes"] <= 500 and trial.settings["scenario"] == "3v3"
        assert trial.train_fields()["seed"] == trial.seed
        assert trial.learner_fields() == {"batch_size": 128, "buffer_size": 5000,
                                          "learning_starts": 256}
    assert load_spec(SWEEPS / "tiny.toml").as_dict() == spec.as_dict()  # deterministic


def test_shipped_policy_specs_cover_the_former_sweep_job_list() -> None:
    # benchmarks/sweep_jobs.txt, which these specs replace: every method on 3v3 and 6v6 at
    # seed 0; the IPF and MiniDist ones at seeds 1 and 2 too; 5000 episodes each.
    expected = {(sc, algo, reward, 0) for sc in ("3v3", "6v6") for algo in ("maddpg", "bicnet")
                for reward in ("ipf", "minidist", "greedy")}
    expected |= {(sc, algo, reward, seed) for sc in ("3v3", "6v6")
                 for algo in ("maddpg", "bicnet") for reward in ("ipf", "minidist")
                 for seed in (1, 2)}
    found = []
    for name in ("policies.toml", "policies-greedy.toml"):
        for t in load_spec(SWEEPS / name).trials:
            assert t.settings["episodes"] == 5000
            found.append((t.settings["scenario"], t.settings["algo"], t.settings["reward"],
                          t.seed))
    assert len(found) == len(set(found)) == 28
    assert set(found) == expected


def test_evaluation_matrix_spec() -> None:
    spec = load_spec(SWEEPS / "paper-matrix.toml", mode="evaluate")
    assert spec.mode == "evaluate" and len(spec.trials) == 8 * 2 * 3
    assert spec.trials[0].settings == {"allocator": "hungarian", "scenario": "3v3",
                                       "episodes": 300}
    with pytest.raises(ValueError, match="--evaluate"):
        load_spec(SWEEPS / "paper-matrix.toml")
    with pytest.raises(ValueError, match=r"\[evaluate\] table"):
        load_spec(SWEEPS / "tiny.toml", mode="evaluate")


def test_unknown_field_is_an_error() -> None:
    with pytest.raises(ValueError, match=r"unknown field 'lr' in \[grid\]"):
        parse_spec(_spec(grid={"algo": ["maddpg"], "lr": [1e-3]}))
    with pytest.raises(ValueError, match=r"unknown field\(s\) \['sed'\] in \[sweep\]"):
        parse_spec(_spec(sweep={"sed": [0]}))
    with pytest.raises(ValueError, match=r"unknown table"):
        parse_spec({**_spec(), "grd": {"algo": ["maddpg"]}})
    # a field of one algorithm only, crossed with the other
    with pytest.raises(ValueError, match="'layers'"):
        parse_spec(_spec(grid={"algo": ["maddpg", "bicnet"], "layers": [2]}))


def test_empty_grid_is_an_error() -> None:
    with pytest.raises(ValueError, match=r"\[grid\] algo is empty"):
        parse_spec(_spec(grid={"algo": []}))
    with pytest.raises(ValueError, match="non-empty list of seeds"):
        parse_spec(_spec(sweep={"seeds": []}))
    with pytest.raises(ValueError, match="empty list"):
        parse_spec(_spec(sweep={"search": "random", "samples": 2}, random={"hidden": []}))


def test_value_outside_its_range_is_an_error() -> None:
    with pytest.raises(ValueError, match=r"gamma=1\.5.*gamma must be a finite number in \[0, 1\)"):
        parse_spec(_spec(grid={"algo": ["maddpg"], "gamma": [0.9, 1.5]}))
    with pytest.raises(ValueError, match="episodes must be an integer >= 1"):
        parse_spec(_spec(fixed={"episodes": 0}))
    with pytest.raises(ValueError, match="retries"):
        parse_spec(_spec(sweep={"seeds": [0], "retries": -1}))
    with pytest.raises(ValueError, match="loguniform needs low > 0"):
        parse_spec(_spec(sweep={"search": "random"}, random={"actor_lr": {"loguniform": [0, 1]}}))


def test_unknown_scenario_is_an_error() -> None:
    with pytest.raises(ValueError, match="9x9"):
        parse_spec(_spec(grid={"algo": ["maddpg"], "scenario": ["3v3", "9x9"]}))
    with pytest.raises(ValueError, match="9x9"):
        parse_spec({"evaluate": {"allocators": ["greedy"], "scenarios": ["9x9"]}},
                   mode="evaluate")
    with pytest.raises(ValueError, match="unknown algorithm 'ppo'"):
        parse_spec(_spec(grid={"algo": ["ppo"]}))


def test_random_search_is_seeded_and_inside_its_bounds() -> None:
    data = _spec(sweep={"search": "random", "samples": 6, "search_seed": 3, "seeds": [0, 1]},
                 random={"actor_lr": {"loguniform": [1e-4, 1e-2]},
                         "batch_size": {"randint": [64, 256]}, "hidden": [32, 64]})
    spec = parse_spec(data)
    assert len(spec.trials) == 12  # 6 samples x 2 seeds
    assert parse_spec(data).as_dict() == spec.as_dict()
    for t in spec.trials:
        assert 1e-4 <= t.settings["actor_lr"] <= 1e-2
        assert 64 <= t.settings["batch_size"] <= 256
        assert t.settings["hidden"] in (32, 64)
    assert [t.seed for t in spec.trials[:2]] == [0, 1]
    assert spec.trials[0].settings == spec.trials[1].settings
    other = parse_spec({**data, "sweep": {**data["sweep"], "search_seed": 4}})
    assert other.as_dict() != spec.as_dict()


def test_spec_file_errors(tmp_path: Path) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text("[grid\nalgo = 1\n")
    with pytest.raises(ValueError, match="not valid TOML"):
        load_spec(bad)
    with pytest.raises(FileNotFoundError):
        load_spec(tmp_path / "missing.toml")


# --------------------------------------------------------------------------- the tables


def test_aggregate_mean_and_student_t_interval() -> None:
    from scipy import stats

    rows = [{"a": 1, "seed": s, "x": v} for s, v in enumerate([0.2, 0.5, 0.4])]
    rows += [{"a": 2, "seed": 0, "x": 0.7}, {"a": 3, "seed": 0, "x": math.nan},
             {"a": 3, "seed": 1, "x": 1.0}]
    out = aggregate(rows, ["a"], ["x"])
    assert [r["a"] for r in out] == [1, 2, 3] and [r["seeds"] for r in out] == [3, 1, 2]
    values = [0.2, 0.5, 0.4]
    low, high = stats.t.interval(0.95, 2, loc=sum(values) / 3, scale=stats.sem(values))
    assert out[0]["x_mean"] == pytest.approx(sum(values) / 3, abs=1e-15)
    assert out[0]["x_ci95"] == pytest.approx((high - low) / 2, rel=1e-12)
    assert out[1]["x_mean"] == 0.7 and math.isnan(out[1]["x_ci95"])
    assert out[2]["x_mean"] == 1.0  # the NaN seed is left out
    with pytest.raises(ValueError, match="row 0 lacks"):
        aggregate([{"seed": 0}], ["a"], ["x"])


def test_results_folder_checks_come_before_any_trial(tmp_path: Path) -> None:
    spec = parse_spec(_spec())
    (tmp_path / "sweep.json").write_text(json.dumps(spec.as_dict()))
    with pytest.raises(ValueError, match="already holds a sweep"):
        sweep.run_sweep(spec, tmp_path)
    other = parse_spec(_spec(sweep={"seeds": [0, 1]}))
    with pytest.raises(ValueError, match="the spec differs"):
        sweep.run_sweep(other, tmp_path, resume=True)
    with pytest.raises(ValueError, match="nothing to resume"):
        sweep.run_sweep(spec, tmp_path / "empty", resume=True)
    with pytest.raises(ValueError, match="cpus sizes a local Ray"):
        sweep.run_sweep(spec, tmp_path / "x", address="127.0.0.1:6379", cpus=2)
    assert not (tmp_path / "trials").exists()


def test_without_ray_agv_sweep_says_how_to_install_it(tmp_path: Path) -> None:
    code = ("import sys; sys.modules['ray'] = None\n"  # Python's way to make an import fail
            "from learners.sweep_cli import main\n"
            f"sys.exit(main([{str(SWEEPS / 'tiny.toml')!r}, '--results', "
            f"{str(tmp_path / 'r')!r}]))\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          cwd=ROOT, timeout=120)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and 'pip install -e ".[sweep]"' in lines[0]
    assert not (tmp_path / "r").exists()


# --------------------------------------------------------------------------- on Ray


def flaky_make(name: str, **options: object) -> object:
    """``allocator.make`` that fails the second time it builds ``greedy`` (the first trial
    attempt after the driver's check), to exercise Tune's retry."""
    import allocator

    if name == "greedy":
        calls = Path(os.environ["AGV_SWEEP_TEST_CALLS"])
        with calls.open("a") as fh:
            fh.write(f"nice {os.nice(0)}\n")  # the priority the call runs at
        if len(calls.read_text().splitlines()) == 2:
            raise RuntimeError("a deliberate first-attempt failure")
    return allocator.make(name, **options)


def _read_csv(path: Path, drop: tuple[str, ...] = ()) -> list[dict[str, str]]:
    with path.open(newline="") as fh:
        return [{k: v for k, v in row.items() if k not in drop} for row in csv.DictReader(fh)]


def test_agv_sweep_evaluate_on_a_local_ray_retries_a_failed_trial(tmp_path: Path,
                                                                  monkeypatch) -> None:
    pytest.importorskip("ray.tune")
    import argparse

    import ray.cloudpickle

    import allocator
    import sim
    from learners.sweep_cli import add_sweep_parser

    ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])  # Ray's workers need it
    monkeypatch.setenv("AGV_SWEEP_TEST_CALLS", str(tmp_path / "calls.txt"))
    spec_path = tmp_path / "matrix.toml"
    spec_path.write_text('[sweep]\nname = "matrix"\nseeds = [0, 1]\nretries = 1\n'
                         '[evaluate]\nallocators = ["greedy", "maddpg-ipf"]\n'
                         'scenarios = ["3v3"]\nepisodes = 4\n')
    spec = load_spec(spec_path, mode="evaluate")
    results = tmp_path / "results"
    parser = argparse.ArgumentParser(prog="agv")  # as allocator/cli.py registers it
    add_sweep_parser(parser.add_subparsers(dest="command"), make_controller=flaky_make)
    args = parser.parse_args(["sweep", "--evaluate", str(spec_path), "--results", str(results),
                              "--cpus", "1", "--quiet"])
    assert args.func(args) == 0
    rows = _read_csv(results / "trials.csv")
    assert [r["trial"] for r in rows] == [t.trial_id for t in spec.trials]
    # each row is sim.evaluate of that controller, scenario and seed
    for row, trial in zip(rows, spec.trials, strict=True):
        name = trial.settings["allocator"]
        options = {"scenario": "3v3"} if name != "greedy" else {}
        m = sim.evaluate(allocator.make(name, **options), "3v3", episodes=4, seed=trial.seed)
        assert float(row["response_rate"]) == m.response_rate
        assert float(row["avg_reward"]) == pytest.approx(m.avg_reward, rel=1e-12)
    # the trials ran at the driver's priority, not at Ray's worker niceness (15)
    assert set((tmp_path / "calls.txt").read_text().splitlines()) == {f"nice {os.nice(0)}"}
    attempts = {r["trial"]: int(r["attempts"]) for r in rows}
    assert sorted(attempts.values()) == [1, 1, 1, 2]  # the failed greedy trial ran twice
    summary = _read_csv(results / "summary.csv")
    assert [(r["allocator"], r["seeds"]) for r in summary] == [("greedy", "2"),
                                                               ("maddpg-ipf", "2")]
    mean = (float(rows[0]["response_rate"]) + float(rows[1]["response_rate"])) / 2
    assert float(summary[0]["response_rate_mean"]) == pytest.approx(mean, abs=1e-15)
    # resuming a finished sweep runs nothing; running it again without --resume is refused
    again = sweep.run_sweep(spec, results, resume=True, make_controller=flaky_make)
    assert again.ran == [] and _read_csv(again.trials_csv) == rows
    assert args.func(args) == 2


def _pids(results: Path) -> set[int]:
    out = set()
    for log in results.glob("trials/*/attempts.log"):
        for line in log.read_text().splitlines():
            out.add(int(line.split(" pid ")[1].split(":")[0]))
    return out


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


def _driver(spec: Path, results: Path, *extra: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "learners.sweep_cli", str(spec),
                             "--results", str(results), "--cpus", "2", "--quiet", *extra],
                            cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


@pytest.mark.slow
def test_tiny_sweep_killed_and_resumed_equals_an_uninterrupted_one(tmp_path: Path) -> None:
    pytest.importorskip("ray.tune")
    spec_path = SWEEPS / "tiny.toml"
    spec = load_spec(spec_path)
    whole = tmp_path / "whole"
    assert _driver(spec_path, whole).wait(timeout=900) == 0

    cut = tmp_path / "cut"
    proc = _driver(spec_path, cut)
    deadline = time.monotonic() + 900
    late = [cut / "trials" / t.trial_id for t in spec.trials if t.settings["algo"] == "bicnet"]
    while not any((d / "checkpoint.safetensors").is_file() for d in late):
        assert proc.poll() is None, "the sweep ended before it could be killed"
        assert time.monotonic() < deadline
        time.sleep(0.2)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    while any(_alive(p) for p in _pids(cut)):  # Ray's workers share the driver's fate
        assert time.monotonic() < deadline, "trial workers outlived the killed driver"
        time.sleep(0.5)
    finished = {t.trial_id for t in spec.trials
                if (cut / "trials" / t.trial_id / "result.json").is_file()}
    started = {t.trial_id for t in spec.trials
               if (cut / "trials" / t.trial_id / "checkpoint.safetensors").is_file()} - finished
    assert finished and started  # killed part-way
    logs = {t: (cut / "trials" / t / "attempts.log").read_text() for t in finished}

    assert _driver(spec_path, cut, "--resume").wait(timeout=900) == 0
    for t in finished:  # no finished trial ran again
        assert (cut / "trials" / t / "attempts.log").read_text() == logs[t]
    for t in started:  # unfinished trials continued from their own checkpoints
        assert "resume from checkpoint" in (cut / "trials" / t / "attempts.log").read_text()
    timing = sweep.TIMING_COLUMNS
    assert _read_csv(cut / "trials.csv", timing) == _read_csv(whole / "trials.csv", timing)
    assert (cut / "summary.csv").read_bytes() == (whole / "summary.csv").read_bytes()


# --------------------------------------------------------------------------- without Ray


def _load_ship():
    import importlib.util

    spec = importlib.util.spec_from_file_location("sweep_ship", SWEEPS / "ship.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_a_training_trial_runs_once_and_its_best_seed_ships(tmp_path: Path) -> None:
    spec = parse_spec({"sweep": {"name": "mini", "seeds": [0, 1]},
                       "fixed": {"scenario": "3v3", "reward": "ipf", "episodes": 32,
                                 "eval_every": 0, "eval_episodes": 5, "checkpoint_every": 16,
                                 "hidden": 16, "batch_size": 32, "buffer_size": 1000,
                                 "learning_starts": 64},
                       "grid": {"algo": ["maddpg"]}})
    results = tmp_path / "r"
    (results).mkdir()
    (results / "sweep.json").write_text(json.dumps(spec.as_dict()))
    reports: list[dict] = []
    records = [sweep.run_training_trial(t, results, reports.append) for t in spec.trials]
    assert [r["counters"]["episodes_done"] for r in records] == [32, 32]
    assert reports[-1]["response_rate"] == records[-1]["metrics"]["response_rate"]
    # a finished trial is not run again: same record, no new attempt
    again = sweep.run_training_trial(spec.trials[0], results)
    assert again == records[0]
    log = results / "trials" / spec.trials[0].trial_id / "attempts.log"
    assert len(log.read_text().splitlines()) == 1
    trials_csv, summary_csv, finished = sweep.write_tables(spec, results)
    assert finished == 2 and [r["seed"] for r in _read_csv(trials_csv)] == ["0", "1"]
    (summary,) = _read_csv(summary_csv)
    assert summary["seeds"] == "2" and summary["algo"] == "maddpg"

    ship = _load_ship()
    weights, training = tmp_path / "weights", tmp_path / "training"
    (record,) = ship.ship([results], weights, training)
    scores = {int(s): v["response_rate"] for s, v in record["seeds"].items()}
    assert scores == pytest.approx(  # progress.csv keeps 6 digits
        {r["seed"]: r["metrics"]["response_rate"] for r in records}, abs=1e-6)
    assert scores[record["shipped_seed"]] == max(scores.values())
    assert (weights / "3v3" / "maddpg-ipf.safetensors").is_file()
    assert (weights / "3v3" / "seeds" / "maddpg-ipf-s1.json").is_file()
    assert (training / "3v3" / "maddpg-ipf-s0.csv").is_file()


def test_ray_temp_dir_fits_only_paths_short_enough_for_its_sockets() -> None:
    # Ray's plasma socket is TEMP + 64 characters; AF_UNIX paths hold at most 107 bytes.
    from learners.sweep import ray_temp_dir_fits

    assert ray_temp_dir_fits("/" + "a" * 42)        # 43 characters: 107 in all
    assert not ray_temp_dir_fits("/" + "a" * 43)    # 44: one too many
    # the results folder of a real sweep that Ray refused before this rule
    assert not ray_temp_dir_fits("/work/main/runs/sweeps/reward-search-maddpg-base/ray")
