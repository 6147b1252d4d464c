"""The public face of ``allocator.assign``, ``allocator.make`` and ``solve_cost_matrix``: every
bad input is a ValueError naming the argument, or a documented result."""

from __future__ import annotations

import inspect
import itertools
import subprocess
import sys
import textwrap

import numpy as np
import pytest

import allocator
from allocator.base import ALLOCATORS, CONTROLLER_OPTIONS, MAX_COORDINATE, make, option_names
from allocator.greedy import GreedyAllocator, greedy_matching
from allocator.hungarian import HungarianAllocator, solve_cost_matrix
from allocator.paths import travel_costs

METHODS = ["hungarian", "greedy", "fifo", "auction"]
AGENTS = [[0.0, 0.0], [1.0, 1.0]]
TASKS = [[1.0, 0.9], [0.1, 0.0]]


def best_plan(cost: np.ndarray, priorities: np.ndarray) -> tuple[int, int, float]:
    """Brute force: (pairs served, total priority, least cost) of the best plan."""
    n, m = cost.shape
    best = (0, 0, 0.0)
    for tasks in itertools.permutations(range(m), min(n, m)):
        agents = range(len(tasks))
        c = [cost[i, j] for i, j in zip(agents, tasks, strict=True)]
        if not all(np.isfinite(c)):
            continue
        key = (len(tasks), int(sum(int(priorities[j]) for j in tasks)), -float(sum(c)))
        best = max(best, key) if best != (0, 0, 0.0) else key
    return best[0], best[1], -best[2]


# ---------------------------------------------------------------------- coordinates
@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("scale", [1e154, 1e200, 1e300])
def test_assign_rejects_coordinates_that_would_overflow(method: str, scale: float) -> None:
    agents = np.array(AGENTS) * scale
    tasks = np.array(TASKS) * scale
    with pytest.raises(ValueError, match=r"agents rows \[1\].*overflow"):
        allocator.assign(agents, tasks, method=method)
    with pytest.raises(ValueError, match=r"tasks rows \[0, 1\].*overflow"):
        allocator.assign(AGENTS, tasks, method=method)


@pytest.mark.parametrize("method", METHODS)
def test_assign_plans_at_the_largest_accepted_coordinates(method: str) -> None:
    scale = MAX_COORDINATE / 2
    result = allocator.assign(np.array(AGENTS) * scale, np.array(TASKS) * scale, method=method)
    assert result.task_of_agent.tolist() == [1, 0] and not result.unserved
    assert np.isfinite(result.cost) and result.cost > 0


def test_travel_costs_reject_coordinates_that_would_overflow() -> None:
    with pytest.raises(ValueError, match="agents.*overflow"):
        travel_costs(np.array(AGENTS) * 1e200, TASKS)
    with pytest.raises(ValueError, match="tasks.*overflow"):
        travel_costs(AGENTS, [[np.nan, 0.0]])


# ---------------------------------------------------------------------- priorities
def test_priorities_near_1e16_are_handled_exactly() -> None:
    # 10**16 and 10**16 + 1 are the same float64: the higher one must still win.
    solver = allocator.make("hungarian")
    result = solver.assign([[0.0, 0.0]], [[1.0, 0.0], [5.0, 0.0]],
                           priorities=[10**16, 10**16 + 1])
    assert result.task_of_agent.tolist() == [1]
    result = solver.assign([[0.0, 0.0]], [[1.0, 0.0], [5.0, 0.0]],
                           priorities=np.array([10**16 + 1, 10**16], dtype=np.int64))
    assert result.task_of_agent.tolist() == [0]
    result = solver.assign([[0.0, 0.0]], [[1.0, 0.0], [5.0, 0.0]],
                           priorities=[10**30, 10**30 + 1])  # beyond int64: Python ints
    assert result.task_of_agent.tolist() == [1]


def test_large_priorities_keep_the_cost_optimal() -> None:
    # Scaled by priorities of 1e15, the costs lost their digits and the plan was not optimal.
    rng = np.random.default_rng(0)
    for _ in range(20):
        cost = rng.uniform(0.0, 3.0, (3, 5))
        levels = rng.integers(0, 2, 5)
        priorities = levels * 10**15
        rows, cols = solve_cost_matrix(cost, priorities=priorities)
        served, total, least = best_plan(cost, priorities)
        assert len(rows) == served
        assert int(priorities[cols].sum()) == total
        assert float(cost[rows, cols].sum()) == pytest.approx(least, abs=1e-12)


def test_float_priorities_beyond_2_53_are_rejected() -> None:
    with pytest.raises(ValueError, match=r"priorities.*2\*\*53"):
        solve_cost_matrix(np.ones((1, 2)), priorities=[1e17, 0.0])
    for bad in ([0.5, 1], [-1, 0], [np.nan, 0], [True, False], ["1", "2"], [1j, 0], [1, 2, 3]):
        with pytest.raises(ValueError, match="priorities"):
            allocator.make("hungarian").assign(AGENTS, TASKS, priorities=bad)


def test_negative_costs_with_priorities_stay_optimal() -> None:
    rng = np.random.default_rng(1)
    for _ in range(20):
        cost = rng.uniform(-50.0, 1.0, (3, 4))
        priorities = rng.integers(0, 3, 4)
        rows, cols = solve_cost_matrix(cost, priorities=priorities)
        served, total, least = best_plan(cost, priorities)
        assert len(rows) == served and int(priorities[cols].sum()) == total
        assert float(cost[rows, cols].sum()) == pytest.approx(least, abs=1e-9)


def test_weights_that_overflow_the_cost_are_rejected() -> None:
    solver = allocator.make("hungarian")
    with pytest.raises(ValueError, match="weights.*overflow"):
        solver.assign([[0.0, 0.0]], [[1e10, 0.0], [2e10, 0.0]], weights=[1e300, 1e300])
    for bad in ([1j, 1], [0.0, 1.0], [np.inf, 1.0], [True, True], [1.0]):
        with pytest.raises(ValueError, match="weights"):
            solver.assign(AGENTS, TASKS, weights=bad)


# ---------------------------------------------------------------------- world
@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("world", ["warehouse", 3, {"bounds": (0, 0, 1, 1)}])
def test_a_world_that_is_not_a_world_raises_value_error_naming_world(
    method: str, world: object
) -> None:
    with pytest.raises(ValueError, match=r"world must be None or a sim\.world\.World"):
        allocator.assign(AGENTS, TASKS, method=method, world=world)


# ---------------------------------------------------------------------- array types
@pytest.mark.parametrize("method", METHODS)
def test_torch_tensor_with_requires_grad_is_accepted(method: str) -> None:
    torch = pytest.importorskip("torch")
    agents = torch.tensor(AGENTS, requires_grad=True)
    tasks = torch.tensor(TASKS, dtype=torch.float64, requires_grad=True)
    result = allocator.assign(agents, tasks, method=method)
    plain = allocator.assign(agents.detach().numpy(), TASKS, method=method)
    np.testing.assert_array_equal(result.task_of_agent, plain.task_of_agent)
    assert result.cost == plain.cost


@pytest.mark.parametrize("method", METHODS)
def test_complex_coordinates_are_rejected(method: str) -> None:
    with pytest.raises(ValueError, match="agents.*complex"):
        allocator.assign(np.array(AGENTS) + 1j, TASKS, method=method)
    with pytest.raises(ValueError, match="tasks.*complex"):
        allocator.assign(AGENTS, [[1.0 + 0j, 2.0], [0.0, 1j]], method=method)


BOOL_OR_TEXT = [
    ("bool array", np.array([[True, False], [False, True]]), "booleans"),
    ("numeric strings", [["0", "1"], ["1", "0"]], "strings"),
    ("bytes", np.array([[b"0", b"1"]]), "bytes"),
    ("dates", np.array([["2020-01-01", "2020-01-02"]], dtype="datetime64[D]"), "dates"),
    ("None inside", [[0.0, None]], "None"),
    ("masked", np.ma.masked_array(AGENTS, mask=[[True, False], [False, False]]), "masked"),
]


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("what, agents, message", BOOL_OR_TEXT, ids=[b[0] for b in BOOL_OR_TEXT])
def test_boolean_text_and_masked_positions_are_rejected(
    method: str, what: str, agents: object, message: str
) -> None:
    with pytest.raises(ValueError, match=f"agents.*{message}"):
        allocator.assign(agents, TASKS, method=method)


MALFORMED = [
    ("None", None, "got None"),
    ("empty list", [], "empty"),
    ("empty rows", np.zeros((0, 2)), "empty"),
    ("three columns", np.zeros((2, 3)), r"shape \([NM], 2\), got \(2, 3\)"),
    ("one point, flat", [0.0, 0.0], r"one point is \[\[x, y\]\]"),
    ("scalar", 3.0, r"shape \([NM], 2\)"),
    ("ragged", [[0.0, 0.0], [1.0]], "rows of equal length"),
    ("words", [["a", "b"]], "strings"),
    ("huge int", [[10**400, 0]], "too large"),
    ("NaN", [[np.nan, 0.0]], "NaN"),
]


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("what, agents, message", MALFORMED, ids=[b[0] for b in MALFORMED])
def test_malformed_positions_raise_value_error_naming_the_argument(
    method: str, what: str, agents: object, message: str
) -> None:
    with pytest.raises(ValueError, match=f"agents.*{message}"):
        allocator.assign(agents, TASKS, method=method)
    with pytest.raises(ValueError, match=f"tasks.*{message}"):
        allocator.assign(TASKS, agents, method=method)


@pytest.mark.parametrize("method", METHODS)
def test_exact_numbers_of_other_types_are_accepted(method: str) -> None:
    from fractions import Fraction

    plain = allocator.assign(AGENTS, TASKS, method=method)
    for agents in (np.array(AGENTS, dtype=object), np.array([[0, 0], [1, 1]], dtype=np.uint8),
                   [[Fraction(0), Fraction(0)], [Fraction(1), Fraction(1)]]):
        result = allocator.assign(agents, TASKS, method=method)
        np.testing.assert_array_equal(result.task_of_agent, plain.task_of_agent)


@pytest.mark.parametrize("method", METHODS)
def test_duplicate_agv_positions_give_an_optimal_plan(method: str) -> None:
    # Documented: AGVs sharing a position are interchangeable; the plan is deterministic.
    agents = [[0.0, 0.0], [0.0, 0.0], [2.0, 0.0]]
    tasks = [[0.0, 1.0], [2.0, 1.0], [0.0, -1.0]]
    result = allocator.assign(agents, tasks, method=method)
    assert result.num_served == 3
    assert result.task_of_agent[2] == 1 and sorted(result.task_of_agent[:2]) == [0, 2]
    assert result.cost == pytest.approx(3.0)
    again = allocator.assign(agents, tasks, method=method)
    np.testing.assert_array_equal(again.task_of_agent, result.task_of_agent)


# ---------------------------------------------------------------------- make and options
@pytest.mark.parametrize("name", [["hungarian"], ("hungarian",), None, 3, b"hungarian"])
def test_make_with_a_name_that_is_not_a_string_lists_the_registry(name: object) -> None:
    with pytest.raises(ValueError, match=r"unknown allocator .*expected a name.*'hungarian'"):
        make(name)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="unknown allocator"):
        allocator.assign(AGENTS, TASKS, method=name)  # type: ignore[arg-type]


@pytest.mark.parametrize("method", METHODS)
def test_make_rejects_unknown_options_and_lists_the_valid_ones(method: str) -> None:
    with pytest.raises(ValueError, match=r"unknown option 'avoidanse'.*valid options: .*"
                                         r"avoidance, .*planner, .*stuck_steps"):
        allocator.make(method, avoidanse=False)
    with pytest.raises(ValueError, match=r"unknown options 'a', 'b'"):
        allocator.make(method, a=1, b=2)
    cls = ALLOCATORS[method]
    with pytest.raises(ValueError, match=r"unknown option 'avoidanse'.*resolution"):
        cls(avoidanse=False)
    allocator.make(method, avoidance=False, planner="grid", resolution=0.1, stuck_steps=3)


@pytest.mark.parametrize("method", METHODS)
def test_assign_rejects_unknown_options(method: str) -> None:
    with pytest.raises(ValueError, match=r"unknown option 'plannr'.*planner"):
        allocator.assign(AGENTS, TASKS, method=method, plannr="grid")
    with pytest.raises(ValueError, match=r"unknown option 'prioritys'"):
        allocator.assign(AGENTS, TASKS, method=method, prioritys=[1, 0])
    # priorities is one of assign's plan options (DESIGN.md), not a solver option
    allocator.assign(AGENTS, TASKS, method=method, priorities=[1, 0])


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize(("option", "value"), [
    ("planner", 3), ("planner", "rrt"), ("planner", ["grid"]), ("resolution", 0.0),
    ("resolution", "fine"), ("resolution", np.nan), ("seed", 1.5), ("seed", True),
])
def test_bad_planner_options_raise_value_error_naming_them(
    method: str, option: str, value: object
) -> None:
    match = rf"{option} must be" + (r".*('grid'.*'prm'|'prm'.*'grid')" if option == "planner"
                                    else "")
    with pytest.raises(ValueError, match=match):
        allocator.make(method, **{option: value})


def test_controller_options_match_the_controller_signature() -> None:
    from allocator.controller import AllocatorController

    params = list(inspect.signature(AllocatorController).parameters)
    assert params[0] == "allocator"
    assert tuple(params[1:]) == CONTROLLER_OPTIONS
    assert set(CONTROLLER_OPTIONS) <= set(option_names(HungarianAllocator))
    assert {"planner", "resolution", "seed"} <= set(option_names(GreedyAllocator))


def test_make_checks_the_options_of_every_registered_class() -> None:
    class Strict:
        def __init__(self, depth: int = 1, *, width: int = 2) -> None:
            self.depth, self.width = depth, width

    class Loose:
        def __init__(self, **anything: object) -> None:
            self.anything = anything

    ALLOCATORS["test-strict"], ALLOCATORS["test-loose"] = Strict, Loose
    try:
        assert option_names(Strict) == ("depth", "width")
        assert option_names(Loose) is None
        assert make("test-strict", width=3).width == 3  # type: ignore[attr-defined]
        with pytest.raises(ValueError, match=r"unknown option 'height'.*valid options: "
                                             r"depth, width"):
            make("test-strict", height=3)
        assert make("test-loose", height=3).anything == {"height": 3}  # type: ignore[attr-defined]
    finally:
        del ALLOCATORS["test-strict"], ALLOCATORS["test-loose"]
    learned = next(name for name in ALLOCATORS if name not in METHODS)
    with pytest.raises(ValueError, match=r"unknown option 'scenari'.*checkpoint.*scenario"):
        make(learned, scenari="3v3")


# ---------------------------------------------------------------------- cost matrices
@pytest.mark.parametrize("solve", [solve_cost_matrix, greedy_matching])
@pytest.mark.parametrize("cost", [np.array([1.0, 2.0]), np.ones((2, 2, 2)), 5.0])
def test_cost_matrix_that_is_not_2d_is_rejected(solve, cost) -> None:
    with pytest.raises(ValueError, match=r"cost must be a 2-D \(N, M\) matrix"):
        solve(cost)


@pytest.mark.parametrize("solve", [solve_cost_matrix, greedy_matching])
def test_nan_in_a_cost_matrix_is_rejected_naming_it(solve) -> None:
    with pytest.raises(ValueError, match=r"cost holds NaN at \(agent, task\) \[\(0, 1\)\].*\+inf"):
        solve(np.array([[1.0, np.nan], [2.0, 3.0]]))
    with pytest.raises(ValueError, match=r"cost holds -inf"):
        solve(np.array([[-np.inf, 2.0], [2.0, 3.0]]))


@pytest.mark.parametrize("solve", [solve_cost_matrix, greedy_matching])
@pytest.mark.parametrize(("cost", "why"), [
    (np.array([["a", "b"]]), "strings"), (np.array([[1j, 2.0]]), "complex"),
    (np.array([[True, False]]), "booleans"), ([[1.0, None]], "None"), (None, "None"),
])
def test_cost_matrix_of_non_real_numbers_is_rejected(solve, cost, why: str) -> None:
    with pytest.raises(ValueError, match=f"cost must be.*{why}"):
        solve(cost)


def test_solve_cost_matrix_documented_results() -> None:
    inf = np.inf
    # +inf is a forbidden pair, never matched; lists are accepted; empty sides match nothing.
    rows, cols = solve_cost_matrix([[1.0, inf], [inf, inf]])
    assert rows.tolist() == [0] and cols.tolist() == [0]
    for shape in ((0, 3), (3, 0)):
        rows, cols = solve_cost_matrix(np.zeros(shape))
        assert rows.dtype == np.int64 and rows.size == 0 and cols.size == 0
    rows, cols = greedy_matching([[inf, 1.0], [inf, inf]])
    assert rows.tolist() == [0] and cols.tolist() == [1]


# ---------------------------------------------------------------------- import
def _run(code: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", textwrap.dedent(code)], capture_output=True,
                          text=True, timeout=300)


def test_a_broken_learned_module_surfaces_on_import() -> None:
    # The old hook swallowed a missing allocator.learned and silently dropped its entries.
    out = _run("""
        import importlib.abc, sys

        class Missing(importlib.abc.MetaPathFinder):
            def find_spec(self, name, path, target=None):
                if name == "allocator.learned":
                    raise ModuleNotFoundError("no learned", name=name)

        sys.meta_path.insert(0, Missing())
        import allocator
        print(sorted(allocator.ALLOCATORS))
    """)
    assert out.returncode != 0 and "ModuleNotFoundError: no learned" in out.stderr


def test_import_allocator_registers_the_learned_allocators_without_torch() -> None:
    out = _run("""
        import sys
        import allocator
        print(len(allocator.ALLOCATORS), "torch" in sys.modules)
    """)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == [str(len(ALLOCATORS)), "False"]
    assert len(ALLOCATORS) > 2


@pytest.mark.parametrize("option, value", [
    ("avoidance", "no"), ("planner", "rrt"), ("planner", ["grid"]), ("max_speed", -1.0),
    ("max_speed", float("nan")), ("brake", 0), ("reassign_every", 2.5), ("avoid_tasks", 1),
    ("avoidance_options", "fast"), ("waypoint_tolerance", float("inf")), ("stuck_steps", 0),
    ("seed", -1), ("seed", True),
])
def test_make_rejects_a_bad_controller_option_value_when_the_allocator_is_made(
        option: str, value: object) -> None:
    """The controller checked some of its options only when the first episode started, inside
    ``sim.evaluate``, and others (``avoidance="no"``, ``max_speed=-1``) never."""
    for name in ("hungarian", "greedy"):
        # planner and seed are Hungarian's and greedy's own options (checked by them).
        with pytest.raises(ValueError, match=f"{option} must be"):
            allocator.make(name, **{option: value})


def test_make_accepts_the_controller_options_defaults() -> None:
    solver = allocator.make("hungarian", avoidance=False, planner="grid", max_speed=1.2, brake=3,
                            reassign_every=None, avoid_tasks=True, avoidance_options={},
                            waypoint_tolerance=0.1, stuck_steps=4, seed=3)
    assert solver.controller_options["max_speed"] == 1.2
