"""FloorDistances: table distances, smoothed paths, next waypoints, validation."""

from __future__ import annotations

import time

import numpy as np
import pytest
from scipy.sparse import csgraph

import sim
from allocator.distances import FloorDistances, segments_clear
from allocator.paths import grid_for, path_length
from sim.world import World


@pytest.fixture(scope="module")
def floor() -> FloorDistances:
    return FloorDistances(sim.warehouse_floor(20))


def _free_points(world: World, n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    pts = rng.uniform(world.bounds[:2], world.bounds[2:], (20 * n, 2))
    return pts[world.is_free(pts)][:n]


def _dense_free(world: World, path: np.ndarray, samples: int = 400) -> bool:
    s = np.linspace(0.0, 1.0, samples)[:, None]
    pairs = zip(path[:-1], path[1:], strict=True)
    return all(world.is_free(p + (q - p) * s).all() for p, q in pairs)


def test_open_box_distance_is_near_euclidean() -> None:
    world = World(bounds=(0.0, 0.0, 4.0, 3.0))
    fd = FloorDistances(world)
    a, b = _free_points(world, 30, 0), _free_points(world, 20, 1)
    euclid = np.linalg.norm(a[:, None] - b[None], axis=-1)
    d = fd.distance(a, b)
    # 16-neighbour grid: at most 2.7% above a straight run, plus the connectors (< 1 cell).
    assert np.all(d >= euclid - 2 * fd.resolution)
    assert np.all(d <= 1.03 * euclid + 2 * fd.resolution)


def test_wall_forces_detour() -> None:
    # A wall across the floor with a gap at the top: left to right must go around it.
    world = World(bounds=(0.0, 0.0, 4.0, 4.0), obstacles=[[1.9, 0.0, 2.1, 3.2]])
    fd = FloorDistances(world)
    a, b = np.array([[1.0, 0.5]]), np.array([[3.0, 0.5]])
    # Over the wall's rounded top: two straight legs and the 0.2 of the wall's top.
    lower = 2 * np.hypot(1.0 - 0.15, 3.2 + 0.15 - 0.5) + 0.2
    d = fd.distance(a, b)[0, 0]
    p = fd.path(a[0], b[0])
    assert p is not None and _dense_free(world, p)
    assert lower <= path_length(p) <= d <= 1.05 * path_length(p) + 2 * fd.resolution


def test_unreachable_is_inf() -> None:
    # A wall from floor to ceiling: the right half is cut off.
    world = World(bounds=(0.0, 0.0, 4.0, 2.0), obstacles=[[1.9, 0.0, 2.1, 2.0]])
    fd = FloorDistances(world)
    d = fd.distance([[1.0, 1.0], [1.2, 1.0]], [[3.0, 1.0], [0.5, 0.5]])
    assert np.isinf(d[:, 0]).all() and np.isfinite(d[:, 1]).all()
    assert fd.path([1.0, 1.0], [3.0, 1.0]) is None
    wp = fd.next_waypoint([[1.0, 1.0]], [[3.0, 1.0]])
    np.testing.assert_allclose(wp, [[1.0, 1.0]])


def test_fixed_table_matches_on_demand_dijkstra(floor: FloorDistances) -> None:
    world = floor.world
    assert floor.fixed_in_table
    agents = _free_points(world, 40, 2)
    fast = floor.distance(agents, world.pickups)
    # The same distances by a fresh Dijkstra from each pickup's cell, not through the table.
    g = floor._grid
    cells, off = g.snap(world.pickups)
    fresh = csgraph.dijkstra(g.graph, directed=False, indices=cells)
    a_cells, a_off = g.snap(agents)
    np.testing.assert_allclose(fast, fresh[:, a_cells].T + a_off[:, None] + off[None])
    # Arbitrary targets go through the on-demand fields and agree with the table too.
    shifted = world.pickups[:5] + 1e-4
    np.testing.assert_allclose(floor.distance(agents, shifted), fast[:, :5], atol=1e-3)


def test_symmetric_and_triangle(floor: FloorDistances) -> None:
    p = _free_points(floor.world, 12, 3)
    d = floor.distance(p, p)
    off = np.array([floor._grid.snap(p)[1]])  # connectors counted twice on the diagonal
    np.testing.assert_allclose(d, d.T, atol=1e-9)
    np.testing.assert_allclose(np.diag(d), 2 * off[0], atol=1e-9)
    inner = d - off.T - off  # cell-to-cell grid distances obey the triangle inequality
    assert np.all(inner[:, None, :] <= inner[:, :, None] + inner[None, :, :] + 1e-9)


def test_paths_are_collision_free_and_close_to_gridmap(floor: FloorDistances) -> None:
    world = floor.world
    starts = _free_points(world, 10, 4)
    goals = world.pickups[np.random.default_rng(5).integers(len(world.pickups), size=10)]
    reference = grid_for(world)
    for a, b in zip(starts, goals, strict=True):
        p = floor.path(a, b)
        assert p is not None
        np.testing.assert_allclose(p[0], a)
        np.testing.assert_allclose(p[-1], b)
        assert _dense_free(world, p)
        assert segments_clear(p[:-1], p[1:], world).all()
        ref = reference.path(a, b)
        # Waypoints sit on cell centres: a corner can cost up to about one cell more.
        assert abs(path_length(p) - path_length(ref)) <= 0.05 * path_length(ref) \
            + floor.resolution
        d = floor.distance(a[None], b[None])[0, 0]
        assert path_length(p) <= d + 1e-9  # pulling the string never lengthens the path
        assert d <= 1.05 * path_length(p) + 2 * floor.resolution


def test_next_waypoint_is_visible_and_on_the_way(floor: FloorDistances) -> None:
    world = floor.world
    a = _free_points(world, 30, 6)
    b = world.pickups[np.random.default_rng(7).integers(len(world.pickups), size=30)]
    wp = floor.next_waypoint(a, b)
    assert wp.shape == (30, 2)
    assert segments_clear(a, wp, world).all()
    # Going to the waypoint first costs little more than the distance itself.
    via = np.linalg.norm(wp - a, axis=1) + np.diag(floor.distance(wp, b))
    direct = np.diag(floor.distance(a, b))
    assert np.all(via <= direct * 1.05 + 2 * floor.resolution)
    moved = np.linalg.norm(wp - a, axis=1)
    assert np.all(moved > 0)
    # In sight: the goal itself.
    near = world.pickups[:1] + np.array([[0.3, 0.0]])
    np.testing.assert_allclose(floor.next_waypoint(near, world.pickups[:1]), world.pickups[:1])


def test_table_is_built_once_per_floor() -> None:
    world = sim.warehouse_floor(20)
    first = FloorDistances(world)
    start = time.perf_counter()
    second = FloorDistances(sim.warehouse_floor(20))  # an equal floor, a new object
    assert time.perf_counter() - start < 0.5
    assert second._grid is first._grid


def test_fast_path_speed() -> None:
    world = sim.warehouse_floor(100)
    fd = FloorDistances(world)
    agents = _free_points(world, 100, 8)
    targets = np.concatenate([world.pickups, world.pickups[:84]])  # 300 pickups
    fd.distance(agents, targets)
    best = min(_timed(fd.distance, agents, targets) for _ in range(5))
    assert best < 5e-3, f"{best * 1e3:.2f} ms"


def _timed(fn, *args) -> float:  # noqa: ANN001
    start = time.perf_counter()
    fn(*args)
    return time.perf_counter() - start


@pytest.mark.parametrize(
    ("a", "b", "name"),
    [
        (np.zeros((3, 3)), np.zeros((2, 2)), "a"),
        ([[1.0, 1.0]], [[np.nan, 1.0]], "b"),
        ([[-5.0, 1.0]], [[1.0, 1.0]], "a"),
        ([[1.0, 1.0]], [[1.0, 99.0]], "b"),
        ([["x", "y"]], [[1.0, 1.0]], "a"),
    ],
)
def test_bad_points_name_the_argument(floor: FloorDistances, a, b, name: str) -> None:  # noqa: ANN001
    with pytest.raises(ValueError, match=rf"^{name}\b"):
        floor.distance(a, b)


def test_bad_arguments(floor: FloorDistances) -> None:
    with pytest.raises(ValueError, match="b must have shape"):
        floor.next_waypoint(np.ones((3, 2)), np.ones((2, 2)))
    with pytest.raises(ValueError, match="resolution"):
        FloorDistances(floor.world, resolution=1.0)
    with pytest.raises(ValueError, match="resolution"):
        FloorDistances(floor.world, resolution=-0.1)
    with pytest.raises(ValueError, match="connectivity"):
        FloorDistances(floor.world, connectivity=4)
    with pytest.raises(ValueError, match="world"):
        FloorDistances("warehouse-20")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="^a rows"):
        floor.path([np.inf, 0.0], [1.0, 1.0])


def test_segments_clear_exact_corner() -> None:
    world = World(bounds=(0.0, 0.0, 4.0, 4.0), obstacles=[[1.0, 1.0, 2.0, 2.0]], agent_radius=0.2)
    # Passing the corner (2, 2) diagonally at distance 0.19 vs 0.21 from it.
    for gap, expect in ((0.19, False), (0.21, True)):
        off = gap / np.sqrt(2)
        start = np.array([[2.0 + off - 1.0, 2.0 + off + 1.0]])
        end = np.array([[2.0 + off + 1.0, 2.0 + off - 1.0]])
        assert segments_clear(start, end, world)[0] == expect


def test_map_floor_at_its_own_cells(tmp_path) -> None:  # noqa: ANN001
    rows = ["r..e......", ".@@@@@@@..", ".@@@@@@@e.", "..........", "r.@@@@@@@.",
            "..@@@@@@@.", "...e......"]
    text = f"type octile\nheight {len(rows)}\nwidth {len(rows[0])}\nmap\n" + "\n".join(rows)
    path = tmp_path / "small.map"
    path.write_text(text + "\n")
    world = sim.load_floor(path, cell_size=0.3)
    fd = FloorDistances(world, resolution=0.3)
    assert fd.shape == (7, 10)
    d = fd.distance(world.stations, world.pickups)
    assert np.isfinite(d).all()
    # Station (0.15, 1.95) to the pickup (2.55, 1.65) right of the upper block: the aisles only.
    for a in world.stations:
        for b in world.pickups:
            p = fd.path(a, b)
            assert p is not None and _dense_free(world, p)
