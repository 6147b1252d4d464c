"""The ``agv`` command as a user runs it: every user error is one line on standard error with
exit status 2 and no traceback; help, choices, ``--version``; ``agv assign``; ``agv evaluate``
with a registry name; ``--eval-seed``."""

from __future__ import annotations

import argparse
import importlib.metadata
import io
import json
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

import allocator
import sim
from allocator.cli import build_parser, main

TINY_TRAIN = ["--set", "hidden=16", "--set", "batch_size=32", "--set", "num_envs=8",
              "--set", "learning_starts=64", "--set", "buffer_size=2000"]
"""A learner small enough for a run of a few episodes."""


def agv(*args: str, stdin: str | None = None, cwd: Path | None = None,
        code: str | None = None) -> subprocess.CompletedProcess[str]:
    """Run ``agv ARGS`` (``python -m allocator.cli``) in a fresh interpreter, or ``code``."""
    command = ["-c", code] if code is not None else ["-m", "allocator.cli", *args]
    return subprocess.run([sys.executable, *command], capture_output=True, text=True,
                          input=stdin, cwd=cwd, timeout=600)


def assert_user_error(proc: subprocess.CompletedProcess[str], command: str,
                      *fragments: str) -> str:
    """Exit status 2, no traceback, a last line ``agv COMMAND: error: ...`` holding
    ``fragments``; returns that line."""
    assert "Traceback" not in proc.stderr, proc.stderr
    assert proc.returncode == 2, (proc.returncode, proc.stderr)
    last = proc.stderr.strip().splitlines()[-1]
    assert last.startswith(f"agv {command}: error: "), last
    for fragment in fragments:
        assert fragment in last, (fragment, last)
    return last


def run_main(capsys: pytest.CaptureFixture[str], argv: list[str],
             stdin: str | None = None) -> tuple[int, str, str]:
    """``main(argv)`` in this process (an uncaught exception fails the test, as a traceback
    would): ``(exit status, stdout, stderr)``."""
    saved = sys.stdin
    if stdin is not None:
        sys.stdin = io.StringIO(stdin)
    try:
        code = main(argv)
    except SystemExit as exc:
        code = exc.code if isinstance(exc.code, int) else 1
    finally:
        sys.stdin = saved
    out, err = capsys.readouterr()
    return code, out, err


def user_error(capsys: pytest.CaptureFixture[str], argv: list[str],
               stdin: str | None = None) -> str:
    """Run ``main(argv)`` in this process, expect exit status 2; the last line of stderr."""
    code, _, err = run_main(capsys, argv, stdin)
    assert code == 2, err
    return err.strip().splitlines()[-1]


# ---------------------------------------------------------------------- the reported defects
def test_train_run_dir_below_a_file_is_a_clear_error(tmp_path) -> None:
    (tmp_path / "file").write_text("not a folder")
    proc = agv("train", "--run-dir", str(tmp_path / "file" / "run"), "--episodes", "2",
               "--no-progress", cwd=tmp_path)
    assert_user_error(proc, "train", "--run-dir", "is a file, not a folder")


def test_render_out_below_a_file_or_a_folder_is_a_clear_error(tmp_path) -> None:
    (tmp_path / "file").write_text("not a folder")
    assert_user_error(agv("render", "--out", str(tmp_path / "file" / "x.png"), cwd=tmp_path),
                      "render", "--out", "is a file, not a folder")
    assert_user_error(agv("render", "--out", str(tmp_path), cwd=tmp_path),
                      "render", "--out", "expected a file name")


def test_render_out_in_a_missing_folder_makes_the_folder(capsys, tmp_path) -> None:
    out = tmp_path / "new" / "deeper" / "scene.png"
    code, _, err = run_main(capsys, ["render", "--out", str(out)])
    assert code == 0, err
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_render_out_suffix_must_match_what_is_written(capsys, tmp_path) -> None:
    # A scene is always written as PNG, an episode as GIF: a mismatched name was a wrong file.
    line = user_error(capsys, ["render", "--out", str(tmp_path / "scene.gif")])
    assert line.startswith("agv render: error: --out") and ".png" in line, line
    line = user_error(capsys, ["render", "--gif", "--out", str(tmp_path / "ep.png")])
    assert line.startswith("agv render: error: --out") and ".gif" in line, line
    assert not list(tmp_path.iterdir())


def test_bench_threads_zero_is_a_clear_error() -> None:
    assert_user_error(agv("bench", "--threads", "0"), "bench", "--threads",
                      "expected a positive integer")


def test_train_set_hidden_zero_is_a_clear_error(tmp_path) -> None:
    proc = agv("train", "--set", "hidden=0", "--episodes", "2", "--no-progress",
               "--run-dir", str(tmp_path / "run"), cwd=tmp_path)
    assert_user_error(proc, "train", "hidden")
    assert not (tmp_path / "run").exists()


def test_demo_episodes_zero_is_an_error(tmp_path) -> None:
    proc = agv("demo", "--episodes", "0", "--out", str(tmp_path / "demo"), cwd=tmp_path)
    assert_user_error(proc, "demo", "--episodes", "expected a positive integer")
    assert not (tmp_path / "demo").exists()


def test_run_demo_episodes_zero_is_an_error_from_python(tmp_path) -> None:
    from allocator.demo import run_demo

    args = argparse.Namespace(episodes=0, quick=False, out=str(tmp_path / "demo"), seed=0)
    with pytest.raises(ValueError, match="episodes"):
        run_demo(args)


def test_stop_response_nan_is_an_error(tmp_path) -> None:
    proc = agv("train", "--stop-response", "nan", "--episodes", "2", "--no-progress",
               "--run-dir", str(tmp_path / "run"), cwd=tmp_path)
    assert_user_error(proc, "train", "--stop-response", "[0, 1]")


_BAD_COUNTS = ["0", "-1", "nan", "inf", "x", "1.5", ""]
_BAD_SEEDS = ["-1", "nan", "inf", "x", "1.5", str(2**63)]
_NUMERIC_FLAGS = [
    (["demo"], "--episodes", _BAD_COUNTS),
    (["demo"], "--seed", _BAD_SEEDS),
    (["train"], "--episodes", _BAD_COUNTS),
    (["train"], "--seed", _BAD_SEEDS),
    (["train"], "--eval-every", ["-1", "nan", "inf", "x", "1.5"]),
    (["train"], "--eval-episodes", _BAD_COUNTS),
    (["train"], "--eval-seed", _BAD_SEEDS),
    (["train"], "--checkpoint-every", _BAD_COUNTS),
    (["train"], "--stop-response", ["-1", "nan", "inf", "-inf", "x", "1.5"]),
    (["train"], "--threads", _BAD_COUNTS),
    (["evaluate", "hungarian"], "--episodes", _BAD_COUNTS),
    (["evaluate", "hungarian"], "--seed", _BAD_SEEDS),
    (["bench"], "--envs", _BAD_COUNTS),
    (["bench"], "--threads", _BAD_COUNTS),
    (["render"], "--seed", _BAD_SEEDS),
    (["render", "--field"], "--agent", ["-1", "nan", "inf", "x", "1.5"]),
]


@pytest.mark.parametrize(("command", "flag", "values"), _NUMERIC_FLAGS,
                         ids=[f"{c[0]}{f}" for c, f, _ in _NUMERIC_FLAGS])
def test_numeric_flags_reject_zero_negative_nan_inf_and_strings(
    capsys, tmp_path, command: list[str], flag: str, values: list[str]
) -> None:
    for value in values:
        line = user_error(capsys, [*command, f"{flag}={value}"])
        assert line.startswith(f"agv {command[0]}: error: argument {flag}"), line
        assert repr(value) in line, line
    assert not list(tmp_path.iterdir())


def test_scenario_flags_name_the_valid_scenarios(capsys) -> None:
    for command in (["bench"], ["render"], ["train"], ["evaluate", "hungarian"]):
        line = user_error(capsys, [*command, "--scenario", "7x7"])
        assert "argument --scenario" in line and "'3v3'" in line and "NvM" in line, line
    line = user_error(capsys, ["bench", "--scenario", "0v3"])
    assert "at least one AGV" in line


def test_broken_import_inside_learners_surfaces() -> None:
    # A dependency of learners.cli that fails to import: `agv train` used to vanish silently
    # ("invalid choice: 'train'"); the ImportError must show instead.
    code = textwrap.dedent("""
        import importlib.abc, sys

        class Broken(importlib.abc.MetaPathFinder):
            def find_spec(self, name, path=None, target=None):
                if name == "learners.cli":
                    raise ImportError("No module named 'tqdm_missing'", name="tqdm_missing")
                return None

        sys.meta_path.insert(0, Broken())
        from allocator.cli import main
        sys.exit(main(["train", "--help"]))
    """)
    proc = agv(code=code)
    assert proc.returncode not in (0, 2), proc.stderr
    assert "ImportError" in proc.stderr and "tqdm_missing" in proc.stderr
    assert "invalid choice" not in proc.stderr


# ---------------------------------------------------------------------- help and choices
def _subparsers(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    action = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return dict(action.choices)


def test_every_subcommand_and_flag_has_a_description_and_help() -> None:
    subs = _subparsers(build_parser())
    assert set(subs) == {"assign", "demo", "train", "evaluate", "bench", "render", "sweep",
                         "serve"}
    for name, sub in subs.items():
        assert sub.description, name
        for action in sub._actions:
            assert action.help and action.help != argparse.SUPPRESS, (name, action.dest)


def test_registry_values_are_choices() -> None:
    from learners.algorithms import ALGORITHMS, REWARD_NAMES

    subs = _subparsers(build_parser())

    def choices(command: str, dest: str) -> list[str]:
        return sorted(next(a for a in subs[command]._actions if a.dest == dest).choices)

    assert choices("assign", "method") == sorted(allocator.ALLOCATORS)
    assert choices("train", "algo") == sorted(ALGORITHMS)
    assert choices("train", "reward") == sorted(REWARD_NAMES)
    assert choices("bench", "reward") == sorted(sim.REWARDS)


@pytest.mark.parametrize(("argv", "flags"), [
    (["render", "--field", "--gif"], ("--field", "--gif")),
    (["demo", "--quick", "--episodes", "3"], ("--quick", "--episodes")),
    (["train", "--run-dir", "a", "--resume", "b"], ("--run-dir", "--resume")),
])
def test_mutually_exclusive_flags_are_refused(capsys, argv: list[str],
                                              flags: tuple[str, str]) -> None:
    line = user_error(capsys, argv)
    assert "not allowed with argument" in line and all(f in line for f in flags), line


def test_render_agent_needs_field_and_a_valid_index(capsys, tmp_path, monkeypatch) -> None:
    monkeypatch.chdir(tmp_path)
    line = user_error(capsys, ["render", "--agent", "1"])
    assert line.startswith("agv render: error: --agent") and "--field" in line, line
    line = user_error(capsys, ["render", "--field", "--agent", "3"])
    assert line.startswith("agv render: error: --agent") and "[0, 2]" in line, line
    assert not list(tmp_path.iterdir())


def test_version() -> None:
    proc = agv("--version")
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == f"agv {importlib.metadata.version('agv-allocation')}"


# ---------------------------------------------------------------------- agv train / evaluate
@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory) -> Path:
    """A run folder of an 8-episode `agv train --eval-seed 77` (a barely trained policy)."""
    run_dir = tmp_path_factory.mktemp("train") / "run"
    proc = agv("train", "--reward", "minidist", "--episodes", "8", "--eval-every", "0",
               "--eval-episodes", "2", "--eval-seed", "77", "--no-progress",
               "--run-dir", str(run_dir), *TINY_TRAIN, cwd=run_dir.parent)
    assert proc.returncode == 0, proc.stderr
    return run_dir


def test_train_eval_seed_flag_sets_the_evaluation_seed(tiny_run) -> None:
    saved = json.loads((tiny_run / "config.json").read_text())
    assert saved["train"]["eval_seed"] == 77


def _reject_constant(name: str) -> None:
    raise AssertionError(f"{name} in the JSON output")


def test_evaluate_json_is_strict_json(capsys, tiny_run) -> None:
    # The barely trained policy finishes no episode: the average time over finished episodes
    # is NaN, which JSON does not have; it is written as null.
    code, out, err = run_main(capsys, ["evaluate", str(tiny_run / "policy.safetensors"),
                                       "--episodes", "2", "--json"])
    assert code == 0, err
    record = json.loads(out, parse_constant=_reject_constant)
    assert record["finished_rate"] == 0.0 and record["avg_time_finished"] is None


def test_evaluate_takes_a_registry_name() -> None:
    proc = agv("evaluate", "hungarian", "--scenario", "6v6", "--episodes", "4", "--json")
    assert proc.returncode == 0, proc.stderr
    got = json.loads(proc.stdout)
    want = sim.evaluate(allocator.make("hungarian"), "6v6", episodes=4, seed=0)
    assert got["method"] == "hungarian" and got["scenario"] == "6v6"
    assert got["response_rate"] == pytest.approx(want.response_rate)
    assert got["avg_reward"] == pytest.approx(want.avg_reward)


def test_evaluate_registry_name_prints_the_metrics_table(capsys) -> None:
    code, out, err = run_main(capsys, ["evaluate", "greedy", "--episodes", "2"])
    assert code == 0, err
    assert out.startswith("greedy on 3v3, 2 episodes, seed 0:") and "task response rate" in out


def test_evaluate_unknown_name_lists_the_allocators(capsys, tmp_path, monkeypatch) -> None:
    monkeypatch.chdir(tmp_path)
    line = user_error(capsys, ["evaluate", "hungarain"])
    assert line.startswith("agv evaluate: error: 'hungarain' is neither"), line
    assert "hungarian" in line and "checkpoint" in line


def test_evaluate_learned_name_without_weights_is_a_clear_error(capsys) -> None:
    line = user_error(capsys, ["evaluate", "bicnet-ipf", "--scenario", "4v4", "--episodes", "2"])
    assert line.startswith("agv evaluate: error: no trained weights") and "4v4" in line, line


# ---------------------------------------------------------------------- agv assign
SCENE = {"agents": [[0.0, 0.0], [1.0, 0.0], [2.0, 0.0]], "tasks": [[2.0, 0.5], [0.0, 0.5]]}
SCENE_CSV = "kind,x,y\nagent,0,0\nagent,1,0\nagent,2,0\ntask,2,0.5\ntask,0,0.5\n"


def test_assign_json_scene_prints_the_plan_as_a_table(tmp_path) -> None:
    path = tmp_path / "scene.json"
    path.write_text(json.dumps(SCENE))
    proc = agv("assign", str(path))
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.strip().splitlines()
    assert lines[0] == "hungarian: 3 AGVs, 2 tasks, 2 served, cost 1.0000"
    assert lines[1].split() == ["agent", "task", "distance"]
    assert [line.split() for line in lines[2:]] == [
        ["0", "1", "0.5000"], ["1", "-", "-"], ["2", "0", "0.5000"]]


def test_assign_csv_on_standard_input_as_json() -> None:
    proc = agv("assign", "-", "--json", stdin=SCENE_CSV)
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout)["plan"] == [{"agent": 0, "task": 1, "distance": 0.5},
                                               {"agent": 2, "task": 0, "distance": 0.5}]


def test_assign_csv_file_and_standard_input_match_the_library(capsys, tmp_path) -> None:
    path = tmp_path / "scene.csv"
    path.write_text(SCENE_CSV)
    (tmp_path / "scene.txt").write_text(json.dumps(SCENE))
    runs = [run_main(capsys, ["assign", str(path), "--json", "--method", "greedy"]),
            run_main(capsys, ["assign", "-", "--json", "--method", "greedy"], SCENE_CSV),
            run_main(capsys, ["assign", "-", "--json", "--method", "greedy"], json.dumps(SCENE)),
            run_main(capsys, ["assign", str(tmp_path / "scene.txt"), "--json", "--method",
                              "greedy"])]
    for code, _, err in runs:
        assert code == 0, err
    plans = [json.loads(out) for _, out, _ in runs]
    assert all(p == plans[0] for p in plans)
    plan = plans[0]
    want = allocator.assign(SCENE["agents"], SCENE["tasks"], method="greedy")
    assert plan["method"] == "greedy" and plan["agents"] == 3 and plan["tasks"] == 2
    assert plan["cost"] == pytest.approx(want.cost)
    assert [[p["agent"], p["task"]] for p in plan["plan"]] == want.pairs().tolist()
    agents, tasks = np.array(SCENE["agents"]), np.array(SCENE["tasks"])
    for p in plan["plan"]:
        assert p["distance"] == pytest.approx(np.linalg.norm(agents[p["agent"]]
                                                             - tasks[p["task"]]))
    assert plan["idle_agents"] == np.flatnonzero(want.task_of_agent < 0).tolist()


def test_assign_more_tasks_than_agents_lists_the_unserved(capsys) -> None:
    scene = json.dumps({"agents": [[0.0, 0.0]], "tasks": [[0.0, 1.0], [3.0, 3.0]]})
    code, out, err = run_main(capsys, ["assign", "-", "--json"], scene)
    assert code == 0, err
    plan = json.loads(out)
    assert plan["plan"] == [{"agent": 0, "task": 0, "distance": 1.0}]
    assert [u["task"] for u in plan["unserved_tasks"]] == [1]
    assert "no AGV left" in plan["unserved_tasks"][0]["reason"]
    code, out, err = run_main(capsys, ["assign", "-"], scene)
    assert code == 0, err
    assert "task 1 unserved: no AGV left" in out


def test_assign_floor_plan_makes_distances_go_around_shelves(capsys, tmp_path) -> None:
    floor = {"bounds": [-1, -1, 1, 1], "shelves": [[-0.6, 0.2, 0.6, 0.3]]}
    (tmp_path / "floor.json").write_text(json.dumps(floor))
    scene = {"agents": [[0.0, -0.5]], "tasks": [[0.0, 0.7]]}
    code, out, err = run_main(capsys, ["assign", "-", "--floor", str(tmp_path / "floor.json"),
                                       "--json"], json.dumps(scene))
    assert code == 0, err
    plan = json.loads(out)
    world = sim.World(bounds=(-1, -1, 1, 1), obstacles=np.array(floor["shelves"]))
    want = allocator.assign(scene["agents"], scene["tasks"], world=world)
    assert plan["cost"] == pytest.approx(want.cost)
    assert plan["plan"][0]["distance"] == pytest.approx(want.cost)
    assert want.cost > 1.2 + 0.5  # around the shelf, not through it


def test_assign_learned_method_uses_the_weights_of_the_scene_size(capsys) -> None:
    scene = {"agents": [[-0.5, -0.5], [0.5, -0.5], [0.0, 0.6]],
             "tasks": [[0.5, 0.5], [-0.5, 0.5], [0.0, -0.6]]}
    code, out, err = run_main(capsys, ["assign", "-", "--json", "--method", "bicnet-ipf"],
                              json.dumps(scene))
    assert code == 0, err
    plan = json.loads(out)
    want = allocator.make("bicnet-ipf", scenario="3v3").assign(scene["agents"], scene["tasks"])
    assert [[p["agent"], p["task"]] for p in plan["plan"]] == want.pairs().tolist()
    line = user_error(capsys, ["assign", "-", "--scenario", "3v3"], json.dumps(scene))
    assert "--scenario is only for a learned --method" in line


_ASSIGN_ERRORS = [
    ("missing-file", None, ["nowhere.json"], "does not exist"),
    ("folder", None, ["."], "is a folder"),
    ("bad-json", "{\"agents\": [[0, 0]], ", [], "not valid JSON"),
    ("json-nan", "{\"agents\": [[NaN, 0]], \"tasks\": [[1, 1]]}", [], "NaN"),
    ("json-huge", "{\"agents\": [[1e999, 0]], \"tasks\": [[1, 1]]}", [], "agents[0]"),
    ("json-string", "{\"agents\": [[\"0\", 0]], \"tasks\": [[1, 1]]}", [], "agents[0]"),
    ("json-bool", "{\"agents\": [[true, 0]], \"tasks\": [[1, 1]]}", [], "agents[0]"),
    ("json-triple", "{\"agents\": [[0, 0, 0]], \"tasks\": [[1, 1]]}", [], "[x, y] pair"),
    ("json-keys", "{\"agvs\": [[0, 0]], \"tasks\": [[1, 1]]}", [], "missing ['agents']"),
    ("json-list", "[[0, 0]]", ["--format", "json"], "JSON object"),
    ("json-no-tasks", "{\"agents\": [[0, 0]], \"tasks\": []}", [], "'tasks'"),
    ("csv-columns", "type,x,y\nagent,0,0\ntask,1,1\n", [], "kind, x, y"),
    ("csv-nan", "kind,x,y\nagent,nan,0\ntask,1,1\n", [], "line 2: x must be a finite"),
    ("csv-text", "kind,x,y\nagent,0,zero\ntask,1,1\n", [], "line 2: y must be a number"),
    ("csv-kind", "kind,x,y\nrobot,0,0\ntask,1,1\n", [], "line 2: kind must be"),
    ("csv-width", "kind,x,y\nagent,0\ntask,1,1\n", [], "line 2: expected 3 values"),
    ("csv-no-task", "kind,x,y\nagent,0,0\n", [], "no task rows"),
    ("empty", "", [], "empty"),
]


@pytest.mark.parametrize(("text", "extra", "fragment"), [c[1:] for c in _ASSIGN_ERRORS],
                         ids=[c[0] for c in _ASSIGN_ERRORS])
def test_assign_bad_scene_is_a_clear_error(capsys, tmp_path, monkeypatch, text: str | None,
                                           extra: list[str], fragment: str) -> None:
    monkeypatch.chdir(tmp_path)
    argv = extra if text is None else ["-", *extra]
    line = user_error(capsys, ["assign", *argv], text or "")
    assert line.startswith("agv assign: error: ") and fragment in line, line


def test_assign_bad_scene_from_the_shell_is_one_line(tmp_path) -> None:
    proc = agv("assign", "-", stdin="kind,x,y\nagent,nan,0\ntask,1,1\n", cwd=tmp_path)
    assert_user_error(proc, "assign", "standard input, line 2: x must be a finite number")


_FLOOR_ERRORS = [
    ("missing", None, "does not exist"),
    ("no-bounds", {"shelves": []}, "needs 'bounds'"),
    ("unknown-key", {"bounds": [-1, -1, 1, 1], "walls": True}, "unknown ['walls']"),
    ("short-bounds", {"bounds": [-1, -1, 1]}, "'bounds' must be"),
    ("empty-area", {"bounds": [1, -1, -1, 1]}, "do not enclose an area"),
    ("bad-shelf", {"bounds": [-1, -1, 1, 1], "shelves": [[0, 0, 1]]}, "shelves[0]"),
    ("agent-in-shelf", {"bounds": [-1, -1, 1, 1], "shelves": [[-0.2, -0.2, 0.2, 0.2]]},
     "agents"),
]


@pytest.mark.parametrize(("floor", "fragment"), [c[1:] for c in _FLOOR_ERRORS],
                         ids=[c[0] for c in _FLOOR_ERRORS])
def test_assign_bad_floor_plan_is_a_clear_error(capsys, tmp_path, floor: dict | None,
                                                fragment: str) -> None:
    path = tmp_path / "floor.json"
    if floor is not None:
        path.write_text(json.dumps(floor))
    scene = json.dumps({"agents": [[0.0, 0.0]], "tasks": [[0.5, 0.5]]})
    line = user_error(capsys, ["assign", "-", "--floor", str(path)], scene)
    assert line.startswith("agv assign: error: ") and fragment in line, line


def test_assign_unknown_method_lists_the_registry(capsys) -> None:
    line = user_error(capsys, ["assign", "-", "--method", "hungarain"])
    assert "argument --method" in line and "'hungarian'" in line and "'greedy'" in line


# ---------------------------------------------------------------------- still working
def test_render_and_bench_still_work(capsys, tmp_path, monkeypatch) -> None:
    monkeypatch.chdir(tmp_path)
    for argv, out in ((["render", "--scenario", "3v3"], "scene_3v3.png"),
                      (["render", "--field", "--agent", "1"], "ipf_3v3_agent1.png")):
        code, _, err = run_main(capsys, argv)
        assert code == 0, err
        assert (tmp_path / out).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    code, out, err = run_main(capsys, ["bench", "--scenario", "3v3", "--envs", "2"])
    assert code == 0, err
    assert out.splitlines()[0].startswith("3v3, reward minidist")
    assert out.splitlines()[2].split()[0] == "2"
