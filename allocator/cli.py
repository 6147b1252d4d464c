"""The ``agv`` command line: ``assign``, ``demo``, ``train``, ``evaluate``, ``bench``,
``render``.

Every user error (a bad value, a missing file, an unknown name) ends with a one-line
``agv <command>: error: ...`` on standard error and exit status 2, never a traceback.
"""

from __future__ import annotations

import argparse
import csv
import importlib.metadata
import io
import json
import math
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

import allocator
import sim
from learners.cli import (
    add_evaluate_arguments,
    add_train_arguments,
    non_negative_int,
    output_dir,
    output_file,
    positive_int,
    print_metrics,
    run_evaluate,
    run_train,
    scenario_name,
    seed,
)
from learners.sweep_cli import add_sweep_parser

__all__ = ["main", "build_parser", "read_scene", "read_floor"]

_SCENARIOS_HELP = f"{', '.join(sim.scenario_names())} or NvM (N AGVs, M tasks)"

SCENE_FORMATS = """\
scene formats:
  JSON  {"agents": [[x, y], ...], "tasks": [[x, y], ...]}
  CSV   a header row "kind,x,y", then one row per AGV or task, kind "agent" or "task":
          kind,x,y
          agent,0.0,0.0
          task,1.0,0.9
AGVs and tasks are numbered from 0 in the order they appear. The format follows the file's
suffix (.json, .csv); on standard input (SCENE "-") a first character "{" means JSON.

floor plan (--floor), JSON:
  {"bounds": [xmin, ymin, xmax, ymax], "shelves": [[xmin, ymin, xmax, ymax], ...],
   "agent_radius": 0.15}
  "shelves" and "agent_radius" are optional. With shelves, distances are obstacle-aware path
  lengths; every AGV and task must lie inside the bounds and outside the shelves.

output: one row per AGV with its task ("-": idle) and the travel distance to it (a straight
line, or the path around the shelves), then the unserved tasks with the reason; "cost" is the
solver's total (a learned method: the length of its simulated trajectories). --json prints
{"method", "agents", "tasks", "cost", "plan": [{"agent", "task", "distance"}, ...],
 "idle_agents": [...], "unserved_tasks": [{"task", "reason"}, ...]}.
"""


# ---------------------------------------------------------------------- scene files
def _read_text(path: str, what: str) -> str:
    if path == "-":
        return sys.stdin.read()
    try:
        return Path(path).read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise ValueError(f"{what} file {path!r} does not exist") from None
    except IsADirectoryError:
        raise ValueError(f"{what} {path!r} is a folder, expected a file") from None
    except PermissionError:
        raise ValueError(f"{what} file {path!r} cannot be read (permission denied)") from None
    except UnicodeDecodeError:
        raise ValueError(f"{what} file {path!r} is not a UTF-8 text file") from None


def _reject_constant(name: str) -> float:
    raise ValueError(f"{name} is not a number (JSON has no NaN or infinity)")


def _load_json(text: str, source: str) -> Any:
    try:
        return json.loads(text, parse_constant=_reject_constant)
    except json.JSONDecodeError as err:
        raise ValueError(f"{source} is not valid JSON: {err}") from None
    except ValueError as err:
        raise ValueError(f"{source}: {err}") from None


def _number(value: Any, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ValueError(f"{where} must be a number, got {value!r}")
    number = float(value)
    if not math.isfinite(number):
        raise ValueError(f"{where} must be a finite number, got {value!r}")
    return number


def _json_points(value: Any, key: str, source: str) -> np.ndarray:
    if not isinstance(value, list) or not value:
        raise ValueError(f"{source}: {key!r} must be a non-empty list of [x, y] pairs, got "
                         f"{value!r}")
    rows = []
    for i, row in enumerate(value):
        if not isinstance(row, list) or len(row) != 2:
            raise ValueError(f"{source}: {key}[{i}] must be an [x, y] pair, got {row!r}")
        rows.append([_number(v, f"{source}: {key}[{i}]") for v in row])
    return np.array(rows, dtype=np.float64)


def _scene_from_json(text: str, source: str) -> tuple[np.ndarray, np.ndarray]:
    data = _load_json(text, source)
    if not isinstance(data, dict):
        raise ValueError(f"{source}: expected a JSON object {{\"agents\": [[x, y], ...], "
                         f"\"tasks\": [[x, y], ...]}}, got a {type(data).__name__}")
    missing = sorted({"agents", "tasks"} - set(data))
    extra = sorted(set(data) - {"agents", "tasks"})
    if missing or extra:
        raise ValueError(f"{source}: expected the keys 'agents' and 'tasks'"
                         + (f"; missing {missing}" if missing else "")
                         + (f"; unknown {extra}" if extra else ""))
    return (_json_points(data["agents"], "agents", source),
            _json_points(data["tasks"], "tasks", source))


def _scene_from_csv(text: str, source: str) -> tuple[np.ndarray, np.ndarray]:
    reader = csv.reader(io.StringIO(text))
    header: list[str] | None = None
    points: dict[str, list[list[float]]] = {"agent": [], "task": []}
    for row in reader:
        if not any(cell.strip() for cell in row):
            continue
        where = f"{source}, line {reader.line_num}"
        if header is None:
            header = [cell.strip().lower() for cell in row]
            if sorted(header) != ["kind", "x", "y"]:
                raise ValueError(f"{where}: the header must name the columns kind, x, y "
                                 f"(in any order), got {row}")
            continue
        if len(row) != 3:
            raise ValueError(f"{where}: expected 3 values (kind, x, y), got {len(row)}: {row}")
        cells = dict(zip(header, (cell.strip() for cell in row), strict=True))
        kind = cells["kind"].lower()
        if kind not in points:
            raise ValueError(f"{where}: kind must be 'agent' or 'task', got {cells['kind']!r}")
        xy = []
        for axis in ("x", "y"):
            try:
                value = float(cells[axis])
            except ValueError:
                raise ValueError(f"{where}: {axis} must be a number, got "
                                 f"{cells[axis]!r}") from None
            if not math.isfinite(value):
                raise ValueError(f"{where}: {axis} must be a finite number, got "
                                 f"{cells[axis]!r}")
            xy.append(value)
        points[kind].append(xy)
    if header is None:
        raise ValueError(f"{source} is empty: expected a header row kind,x,y and one row per "
                         "AGV or task")
    for kind in ("agent", "task"):
        if not points[kind]:
            raise ValueError(f"{source} has no {kind} rows: expected at least one row "
                             f"'{kind},x,y'")
    return (np.array(points["agent"], dtype=np.float64),
            np.array(points["task"], dtype=np.float64))


def read_scene(path: str, fmt: str = "auto") -> tuple[np.ndarray, np.ndarray]:
    """Read AGV and task positions from a JSON or CSV file (``"-"``: standard input).

    Parameters
    ----------
    path : str
        The file, or ``"-"`` for standard input. The formats are described in
        ``agv assign --help``.
    fmt : {"auto", "json", "csv"}
        ``auto`` follows the suffix, or (for standard input and other suffixes) the first
        character: ``{`` means JSON.

    Returns
    -------
    agents : np.ndarray, shape (N, 2)
    tasks : np.ndarray, shape (M, 2)

    Raises
    ------
    ValueError
        For a missing or unreadable file, bad JSON, a wrong CSV header or row, a value that is
        not a finite number, or no AGV or no task; the message names the file and the line or
        entry.
    """
    source = "standard input" if path == "-" else repr(path)
    text = _read_text(path, "scene")
    if fmt == "auto":
        suffix = Path(path).suffix.lower()
        if suffix in (".json", ".csv"):
            fmt = suffix[1:]
        else:
            fmt = "json" if text.lstrip().startswith("{") else "csv"
    if fmt == "json":
        return _scene_from_json(text, source)
    if fmt == "csv":
        return _scene_from_csv(text, source)
    raise ValueError(f"format must be 'auto', 'json' or 'csv', got {fmt!r}")


_FLOOR_KEYS = ("bounds", "shelves", "agent_radius")


def read_floor(path: str) -> sim.World:
    """Build a :class:`sim.World` from a floor-plan JSON file.

    Parameters
    ----------
    path : str
        A JSON object with ``bounds`` ``[xmin, ymin, xmax, ymax]``, optional ``shelves``, a list
        of ``[xmin, ymin, xmax, ymax]`` rectangles, and optional ``agent_radius`` (default
        0.15).

    Returns
    -------
    sim.World

    Raises
    ------
    ValueError
        For a missing file, bad JSON, unknown or missing keys, or values that
        :class:`sim.World` refuses; the message names the file and the key.
    """
    source = repr(path)
    data = _load_json(_read_text(path, "floor plan"), source)
    if not isinstance(data, dict):
        raise ValueError(f"{source}: a floor plan is a JSON object with the keys "
                         f"{list(_FLOOR_KEYS)}, got a {type(data).__name__}")
    extra = sorted(set(data) - set(_FLOOR_KEYS))
    if extra or "bounds" not in data:
        raise ValueError(f"{source}: a floor plan needs 'bounds' and may have 'shelves' and "
                         f"'agent_radius'" + (f"; unknown {extra}" if extra else ""))
    bounds = data["bounds"]
    if not isinstance(bounds, list) or len(bounds) != 4:
        raise ValueError(f"{source}: 'bounds' must be [xmin, ymin, xmax, ymax], got {bounds!r}")
    box = tuple(_number(v, f"{source}: bounds[{i}]") for i, v in enumerate(bounds))
    shelves = data.get("shelves", [])
    if not isinstance(shelves, list):
        raise ValueError(f"{source}: 'shelves' must be a list of [xmin, ymin, xmax, ymax], got "
                         f"{shelves!r}")
    rects = []
    for k, shelf in enumerate(shelves):
        if not isinstance(shelf, list) or len(shelf) != 4:
            raise ValueError(f"{source}: shelves[{k}] must be [xmin, ymin, xmax, ymax], got "
                             f"{shelf!r}")
        rects.append([_number(v, f"{source}: shelves[{k}]") for v in shelf])
    options: dict[str, Any] = {}
    if "agent_radius" in data:
        options["agent_radius"] = _number(data["agent_radius"], f"{source}: agent_radius")
    try:
        return sim.World(bounds=box, obstacles=np.array(rects, dtype=np.float64).reshape(-1, 4),
                         **options)
    except ValueError as err:
        raise ValueError(f"{source}: {err}") from None


# ---------------------------------------------------------------------- subcommands
def _add_assign(sub: argparse._SubParsersAction) -> None:
    names = sorted(allocator.ALLOCATORS)
    p = sub.add_parser(
        "assign", help="assign AGVs to tasks for a scene read from a JSON or CSV file",
        description="Assign AGVs to tasks (allocator.assign) for one scene and print the plan.",
        epilog=SCENE_FORMATS, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("scene", metavar="SCENE",
                   help="JSON or CSV file of AGV and task positions, or - for standard input")
    p.add_argument("--floor", metavar="FLOOR.json", default=None,
                   help="floor plan (bounds and shelves); default an open floor")
    p.add_argument("--method", choices=names, default="hungarian", metavar="NAME",
                   help=f"allocator: {', '.join(names)} (default hungarian)")
    p.add_argument("--scenario", type=scenario_name, default=None,
                   help="for a learned --method: the scenario whose shipped weights it uses "
                        "(default NvM of the scene)")
    p.add_argument("--format", dest="fmt", choices=("auto", "json", "csv"), default="auto",
                   help="format of SCENE (default auto: the suffix, or '{' first for JSON)")
    p.add_argument("--json", action="store_true",
                   help="print the plan as JSON instead of a table")
    p.set_defaults(func=_run_assign)


def _run_assign(args: argparse.Namespace) -> int:
    from allocator.learned import LEARNED
    from allocator.paths import travel_costs

    agents, tasks = read_scene(args.scene, args.fmt)
    world = read_floor(args.floor) if args.floor is not None else None
    options: dict[str, Any] = {}
    if args.method in LEARNED:
        options["scenario"] = args.scenario or f"{len(agents)}v{len(tasks)}"
    elif args.scenario is not None:
        raise ValueError(f"--scenario is only for a learned --method, not {args.method!r}")
    solver = allocator.make(args.method, **options)
    result = solver.assign(agents, tasks, world=world)
    cost_of = getattr(solver, "cost_matrix", None)
    costs = (cost_of(agents, tasks, world) if callable(cost_of)
             else travel_costs(agents, tasks, world))
    plan = [{"agent": int(i), "task": int(j), "distance": float(costs[i, j])}
            for i, j in result.pairs()]
    idle = [int(i) for i in np.flatnonzero(result.task_of_agent < 0)]
    unserved = [{"task": int(j), "reason": result.unserved.get(int(j), "")}
                for j in np.flatnonzero(result.agent_of_task < 0)]
    if args.json:
        print(json.dumps({"method": args.method, "agents": len(agents), "tasks": len(tasks),
                          "cost": result.cost, "plan": plan, "idle_agents": idle,
                          "unserved_tasks": unserved}, indent=2, allow_nan=False))
        return 0
    print(f"{args.method}: {len(agents)} AGVs, {len(tasks)} tasks, {len(plan)} served, "
          f"cost {result.cost:.4f}")
    print(f"{'agent':>6} {'task':>6} {'distance':>10}")
    for i, j in enumerate(result.task_of_agent):
        if j < 0:
            print(f"{i:>6} {'-':>6} {'-':>10}")
        else:
            print(f"{i:>6} {j:>6} {costs[i, j]:>10.4f}")
    for row in unserved:
        print(f"task {row['task']} unserved: {row['reason']}")
    return 0


def _add_demo(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "demo", help="evaluate every method on the paper's scenarios and draw it",
        description="Evaluate every available method on 3v3 and 6v6, print the table beside "
                    "the paper's numbers, and write figures and animations; the scale "
                    "headline on 20v20; then run the dispatchers and the shipped lifelong "
                    "policy in lifelong operation on warehouse-20.")
    length = p.add_mutually_exclusive_group()
    length.add_argument("--quick", action="store_true",
                        help="30 test episodes per scenario (a smoke run)")
    length.add_argument("--episodes", type=positive_int, default=None,
                        help="test episodes per scenario (default 300)")
    p.add_argument("--out", type=output_dir, default="agv-demo",
                   help="folder for the table, figures and animations (default agv-demo)")
    p.add_argument("--seed", type=seed, default=0,
                   help="seed of the test episodes, in [0, 2**63) (default 0)")
    p.add_argument("--scale-episodes", type=non_negative_int, default=None,
                   help="episodes of the scale headline on 20v20 (default 50, 4 with --quick; "
                        "0 skips it)")
    p.add_argument("--lifelong-steps", type=non_negative_int, default=None,
                   help="steps of the lifelong row on warehouse-20 (default 500, 200 with "
                        "--quick; 0 skips it)")
    p.set_defaults(func=_run_demo)


def _run_demo(args: argparse.Namespace) -> int:
    from allocator.demo import run_demo

    return run_demo(args)


def _add_train(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "train", help="train a MADDPG or BiCNet policy",
        description="Train a MADDPG or BiCNet policy, evaluating it on seeded validation "
                    "scenes and writing resumable checkpoints to the run folder.")
    add_train_arguments(p)
    # learners does not import allocator: the shield of `--set shield=true` is handed in here
    p.set_defaults(func=run_train, make_shield=allocator.SafetyShield)


def _add_evaluate(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "evaluate", help="print the paper's metrics of an allocator or a checkpoint",
        description="Score an allocator of the registry (e.g. hungarian) or a trained "
                    "checkpoint on seeded test episodes: the paper's metrics.")
    add_evaluate_arguments(p, registry=sorted(allocator.ALLOCATORS))
    p.set_defaults(func=_run_evaluate)


def _run_evaluate(args: argparse.Namespace) -> int:
    from allocator.learned import LEARNED, scenario_to_run

    name = args.checkpoint
    if name not in allocator.ALLOCATORS:
        if not (Path(name).exists() or Path(name + ".safetensors").exists()):
            raise ValueError(f"{name!r} is neither an allocator "
                             f"({', '.join(sorted(allocator.ALLOCATORS))}) nor an existing "
                             "checkpoint file or run folder")
        return run_evaluate(args)
    scenario = args.scenario or "3v3"
    solver = allocator.make(name, **({"scenario": scenario} if name in LEARNED else {}))
    metrics = sim.evaluate(solver, scenario_to_run(solver, scenario), episodes=args.episodes,
                           seed=args.seed)
    print_metrics(name, {"method": name, "scenario": scenario}, metrics, args.seed, args.json)
    return 0


def _add_bench(sub: argparse._SubParsersAction) -> None:
    rewards = sorted(sim.REWARDS)
    p = sub.add_parser(
        "bench", help="quick simulator throughput (full benchmarks: benchmarks/)",
        description="Measure environment steps per second of the simulator for a few batch "
                    "sizes (the full comparison is benchmarks/sim_throughput.py).")
    p.add_argument("--scenario", type=scenario_name, default="6v6",
                   help=f"scenario: {_SCENARIOS_HELP} (default 6v6)")
    p.add_argument("--envs", type=positive_int, nargs="+", default=[1, 32, 1024],
                   metavar="B", help="batch sizes, parallel environments (default 1 32 1024)")
    p.add_argument("--reward", choices=rewards, default="minidist",
                   help=f"reward: {', '.join(rewards)} (default minidist)")
    p.add_argument("--threads", type=positive_int, default=1,
                   help="torch threads (default 1: steadier, and what the benchmarks use)")
    p.set_defaults(func=_run_bench)


def _run_bench(args: argparse.Namespace) -> int:
    import torch

    from sim import native
    from sim.throughput import measure

    torch.set_num_threads(args.threads)
    kernels = "fused kernels" if native.available() else "torch path"
    print(f"{args.scenario}, reward {args.reward}, {kernels}")
    print(f"{'B':>6} {'env steps/s':>14} {'step us':>10} {'reset us':>10} {'physics us':>11}"
          f" {'overhead':>9}")
    for b in args.envs:
        m = measure(args.scenario, b, reward=args.reward, physics=True)
        print(f"{b:>6} {m.steps_per_second:>14,.0f} {1e6 * m.step_seconds:>10,.0f} "
              f"{1e6 * m.reset_seconds:>10,.0f} {1e6 * m.physics_seconds:>11,.0f} "
              f"{m.overhead:>+9.0%}")
    return 0


def _lifelong_scenario(value: str) -> str:
    """An argparse type: the name of a lifelong scenario (``warehouse-20``, ``warehouse-N``)."""
    try:
        scenario = sim.get_scenario(value)
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err)) from None
    if getattr(scenario, "lifelong", False) is not True:
        raise argparse.ArgumentTypeError(
            f"{value!r} is an episodic scenario; a lifelong run needs a lifelong one such as "
            "warehouse-20, warehouse-50, warehouse-100 or warehouse-N")
    return value


def _fault_spec(value: str) -> tuple[float, int]:
    """An argparse type: ``RATE:REPAIR``, breakdowns per AGV-step and the steps a repair
    takes (checked as :class:`sim.Breakdowns` checks them)."""
    rate, sep, repair = value.partition(":")
    try:
        if not sep:
            raise ValueError("no ':' between RATE and REPAIR")
        try:
            number = float(rate)
        except ValueError:
            raise ValueError(f"RATE {rate!r} is not a number") from None
        try:
            steps = int(repair)
        except ValueError:
            raise ValueError(f"REPAIR {repair!r} is not an integer") from None
        faults = sim.Breakdowns(number, steps)
    except ValueError as err:
        raise argparse.ArgumentTypeError(
            f"expected RATE:REPAIR, a breakdown rate per AGV-step and the repair steps, e.g. "
            f"0.002:60, got {value!r}: {err}") from None
    return faults.rate, faults.repair_steps


def _add_render(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "render", help="draw a scene, an episode (GIF), an IPF field or a lifelong run (GIF)",
        description="Draw a scenario's start scene (PNG), an episode of the scripted "
                    "nearest-task controller (--gif), one AGV's IPF field (--field), or a "
                    "lifelong run of the nearest-task controller (--lifelong SCENARIO, a GIF; "
                    "with --plot also its throughput and waits over time).")
    p.add_argument("--scenario", type=scenario_name, default=None,
                   help=f"scenario: {_SCENARIOS_HELP} (default 3v3; not with --lifelong)")
    p.add_argument("--seed", type=seed, default=0,
                   help="seed of the scene or the lifelong run, in [0, 2**63) (default 0)")
    what = p.add_mutually_exclusive_group()
    what.add_argument("--field", action="store_true", help="draw AGV --agent's IPF heatmap")
    what.add_argument("--gif", action="store_true",
                      help="animate an episode of the scripted nearest-task controller")
    what.add_argument("--lifelong", metavar="SCENARIO", type=_lifelong_scenario, default=None,
                      help="animate a lifelong run of the scripted nearest-task controller on "
                           "SCENARIO (warehouse-20, warehouse-50, warehouse-100, warehouse-N)")
    p.add_argument("--agent", type=non_negative_int, default=None,
                   help="whose field, an AGV index (with --field; default 0)")
    p.add_argument("--steps", type=positive_int, default=None,
                   help="steps of the lifelong run (with --lifelong; default 200)")
    p.add_argument("--faults", type=_fault_spec, default=None, metavar="RATE:REPAIR",
                   help="breakdowns in the lifelong run (with --lifelong): RATE per AGV-step, "
                        "each repaired after REPAIR steps, e.g. 0.002:60 (default none)")
    p.add_argument("--plot", type=output_file, default=None, metavar="PATH",
                   help="with --lifelong: also write the throughput and wait over time of the "
                        "same run (sim.evaluate_lifelong, same seed, steps and faults) as an "
                        "image file")
    p.add_argument("--out", type=output_file, default=None,
                   help="output file, missing folders made: .png for a scene (default "
                        "scene_<scenario>.png), .gif with --gif (episode_<scenario>.gif), an "
                        "image file with --field (ipf_<scenario>_agent<i>.png), .gif with "
                        "--lifelong (lifelong_<scenario>.gif)")
    p.set_defaults(func=_run_render)


def _image_suffixes() -> set[str]:
    from matplotlib.backend_bases import FigureCanvasBase

    return {f".{ext}" for ext in FigureCanvasBase.get_supported_filetypes()}


def _check_suffix(out: str, allowed: set[str], what: str, flag: str = "--out") -> None:
    if Path(out).suffix.lower() not in allowed:
        raise ValueError(f"{flag} {out!r}: {what} is written as {' or '.join(sorted(allowed))}, "
                         f"so the file name must end in it")


def _run_render_lifelong(args: argparse.Namespace) -> int:
    import torch

    if args.scenario is not None:
        raise ValueError("--lifelong names the scenario itself: drop --scenario")
    name = args.lifelong
    out = args.out or f"lifelong_{name}.gif"
    _check_suffix(out, {".gif"}, "a lifelong run")
    if args.plot is not None:
        _check_suffix(args.plot, _image_suffixes(), "the plot", "--plot")
        if Path(args.plot).absolute() == Path(out).absolute():
            raise ValueError(f"--plot {args.plot!r} is the GIF's own file: give another name")
    # One floor's tensors are small: one torch thread is faster than several, and far faster
    # on a busy machine (agv bench's default too). The caller's setting is restored after.
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        _write_lifelong(args, name, out)
    finally:
        torch.set_num_threads(threads)
    return 0


def _write_lifelong(args: argparse.Namespace, name: str, out: str) -> None:
    """The GIF of ``agv render --lifelong`` and, with ``--plot``, its plot."""
    from sim.controllers import NearestTaskController
    from sim.render import plot_lifelong, render_lifelong

    steps = args.steps or 200
    faults = sim.Breakdowns(*args.faults) if args.faults is not None else None
    physics = sim.get_scenario(name).world.physics
    render_lifelong(name, NearestTaskController(physics), steps=steps, seed=args.seed,
                    path=out, faults=faults)
    print(f"wrote {out}")
    if args.plot is None:
        return
    metrics = sim.evaluate_lifelong(NearestTaskController(physics), name, steps=steps,
                                    seed=args.seed, faults=faults, window=max(10, steps // 20))
    broken = "" if faults is None else \
        f", breakdowns {faults.rate:g}/AGV-step, repair {faults.repair_steps} steps"
    plot_lifelong({"nearest task": metrics}, path=args.plot,
                  title=f"{name}, seed {args.seed}{broken}")
    print(f"{name}: {metrics.delivered} orders delivered in {steps} steps, throughput "
          f"{metrics.throughput:.0f} per 1000 steps (bound {metrics.throughput_bound:.0f}), "
          f"mean wait {metrics.wait_mean:.0f} steps")
    print(f"wrote {args.plot}")


def _run_render(args: argparse.Namespace) -> int:
    from sim.controllers import NearestTaskController

    if args.agent is not None and not args.field:
        raise ValueError("--agent chooses whose IPF field to draw: use it with --field")
    if args.lifelong is not None:
        return _run_render_lifelong(args)
    for flag, value in (("--steps", args.steps), ("--faults", args.faults),
                        ("--plot", args.plot)):
        if value is not None:
            raise ValueError(f"{flag} is for a lifelong run: use it with --lifelong SCENARIO")
    scenario = args.scenario or "3v3"
    if getattr(sim.get_scenario(scenario), "lifelong", False) is True:
        raise ValueError(f"--scenario {scenario} is a lifelong scenario (orders, no fixed "
                         f"tasks): draw a run of it with --lifelong {scenario}")
    env = sim.make_env(scenario, num_envs=1, seed=args.seed)
    if args.field:
        import matplotlib.pyplot as plt

        agent = args.agent or 0
        if agent >= env.num_agents:
            raise ValueError(f"--agent must be an AGV index in [0, {env.num_agents - 1}] for "
                             f"{scenario}, got {agent}")
        out = args.out or f"ipf_{scenario}_agent{agent}.png"
        _check_suffix(out, _image_suffixes(), "the field")
        fig = sim.render_field(env.agent_pos[0].numpy(), env.task_pos[0].numpy(), agent=agent,
                               world=env.world, out=out)
        plt.close(fig)
    elif args.gif:
        out = args.out or f"episode_{scenario}.gif"
        _check_suffix(out, {".gif"}, "an episode")
        sim.render_episode(NearestTaskController(env.world.physics), scenario,
                           seed=args.seed, path=out)
    else:
        out = args.out or f"scene_{scenario}.png"
        _check_suffix(out, {".png"}, "a scene")
        sim.render_scene(env, path=out)
    print(f"wrote {out}")
    return 0


def _version() -> str:
    try:
        return importlib.metadata.version("agv-allocation")
    except importlib.metadata.PackageNotFoundError:
        return "unknown (agv-allocation is not installed)"


def build_parser() -> argparse.ArgumentParser:
    """The ``agv`` argument parser with every subcommand.

    Returns
    -------
    argparse.ArgumentParser
        Parsing sets ``command`` and ``func``, the subcommand's entry point (``func(args)``
        returns the exit status).
    """
    parser = argparse.ArgumentParser(
        prog="agv", description="Multi-AGV task allocation: simulator, learners and solvers.")
    parser.add_argument("--version", action="version", version=f"%(prog)s {_version()}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for add in (_add_assign, _add_demo, _add_train, _add_evaluate, _add_bench, _add_render):
        add(sub)
    # Sweeps on Ray Tune (learners/sweep_cli.py); evaluation sweeps build allocators by name.
    add_sweep_parser(sub, make_controller=allocator.make)
    # The fleet service (allocator/serve; FastAPI is imported only when it runs).
    from allocator.serve.cli import add_serve_parser

    add_serve_parser(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``agv`` console script.

    Parameters
    ----------
    argv : sequence of str, optional
        The arguments (default ``sys.argv[1:]``).

    Returns
    -------
    int
        The exit status: 0 done, 2 bad input (with a one-line message on standard error), 130
        a training run interrupted. Argument errors exit through argparse with status 2.
    """
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except ValueError as err:
        print(f"agv {args.command}: error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
