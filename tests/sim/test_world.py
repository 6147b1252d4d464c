"""World's floor fields (pickups, stations, depot): defaults, validation, read-only copies."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

import sim
from sim.ipf import ipf_grid

SHELF = np.array([[1.0, 1.0, 2.0, 1.5]])


def _floor(**fields: object) -> sim.World:
    base = dict(bounds=(0.0, 0.0, 4.0, 3.0), obstacles=SHELF, pickups=[[1.5, 0.8]],
                stations=[[0.3, 0.3]], depot=[[2.5, 0.0, 4.0, 1.0]])
    base.update(fields)
    return sim.World(**base)


def test_defaults_are_empty_and_the_paper_world_is_unchanged() -> None:
    world = sim.World()
    assert world.pickups.shape == (0, 2) and world.stations.shape == (0, 2)
    assert world.depot.shape == (0, 4)
    assert not world.is_floor
    assert world.bounds == (-1.0, -1.0, 1.0, 1.0) and world.obstacles.shape == (0, 4)
    assert world.agent_radius == 0.15 and world.capture_radius == 0.1
    # Without a depot, an AGV may start anywhere free.
    pts = np.array([[0.0, 0.0], [0.9, 0.0], [2.0, 0.0]])
    np.testing.assert_array_equal(world.in_depot(pts), world.is_free(pts))


def test_the_ipf_grids_world_call_keeps_working() -> None:
    world = sim.World(bounds=(0.0, 0.0, 4.0, 3.0), obstacles=SHELF.copy())
    assert ipf_grid(world, 0.25).obstacle.any()
    floor = _floor()  # a floor's grid is the grid of its bounds and shelves
    assert ipf_grid(floor, 0.25) is ipf_grid(world, 0.25)


def test_floor_fields_are_read_only_float_copies() -> None:
    pickups = np.array([[1.5, 0.8], [3.0, 2.5]])
    world = _floor(pickups=pickups, stations=[[1, 2]])  # ints become float64
    assert world.is_floor
    assert world.stations.dtype == np.float64 and world.stations.tolist() == [[1.0, 2.0]]
    for name in ("pickups", "stations", "depot"):
        with pytest.raises(ValueError, match="read-only"):
            getattr(world, name)[0, 0] = 9.0
    pickups[0, 0] = 3.5  # the caller's array stays writable and apart from the world
    assert world.pickups[0, 0] == 1.5


@pytest.mark.parametrize(("fields", "match"), [
    (dict(pickups=[1.0, 2.0]), r"pickups must be an \(K, 2\) array.*shape \(2,\)"),
    (dict(pickups=[[1.0, 2.0, 3.0]]), r"pickups must be an \(K, 2\).*shape \(1, 3\)"),
    (dict(stations=[[0.3, np.nan]]), r"stations rows \[0\] contain NaN"),
    (dict(stations=[[0.3, 0.3], [np.inf, 1.0]]), r"stations rows \[1\] contain NaN or infinite"),
    (dict(pickups=[["a", "b"]]), "pickups must hold real numbers"),
    (dict(pickups=[[True, False]]), "pickups must hold real numbers"),
    (dict(pickups=[[1.0, 2.0], [1.0]]), "pickups must be .* ragged rows"),
    (dict(depot=[[0.0, 0.0, 1.0]]), r"depot must be an \(K, 4\) array of rectangles"),
    (dict(depot=[[np.nan, 0.0, 1.0, 1.0]]), r"depot rows \[0\] contain NaN"),
])
def test_bad_shapes_and_values_name_the_field(fields: dict, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        _floor(**fields)


@pytest.mark.parametrize(("fields", "match"), [
    (dict(pickups=[[1.5, 0.8], [5.0, 1.0]]), r"pickups\[1\] at \(5, 1\): outside the world"),
    (dict(stations=[[0.3, -0.1]]), r"stations\[0\] at \(0.3, -0.1\): outside the world"),
    (dict(pickups=[[1.5, 1.2]]), r"pickups\[0\] at \(1.5, 1.2\): inside a shelf"),
    (dict(pickups=[[1.5, 0.9]]), r"pickups\[0\] at \(1.5, 0.9\): no room for an AGV disc"),
    (dict(stations=[[0.3, 0.3], [0.1, 2.0]]), r"stations\[1\] at \(0.1, 2\): no room"),
])
def test_points_must_be_free_and_errors_name_row_and_coordinates(fields: dict,
                                                                 match: str) -> None:
    with pytest.raises(ValueError, match=match):
        _floor(**fields)


def test_a_point_exactly_one_radius_from_a_shelf_is_free() -> None:
    world = _floor(pickups=[[1.5, 1.0 - 0.15]], stations=[[0.15, 0.15]])
    assert world.is_free(world.pickups).all()


@pytest.mark.parametrize(("depot", "match"), [
    ([[3.0, 0.0, 2.5, 1.0]], r"depot rows \[0\] need xmax > xmin"),
    ([[2.5, 0.0, 4.0, 1.0], [0.0, 2.0, 0.2, 3.0]], r"depot rows \[1\] are too small .* 0.3"),
    ([[2.5, -0.5, 4.0, 1.0]], r"depot rows \[0\] reach outside the world bounds"),
    ([[1.5, 0.0, 3.0, 1.2]], r"depot rows \[0\] overlap a shelf .* obstacle 0"),
])
def test_bad_depot(depot: list, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        _floor(depot=depot)


def test_a_depot_may_touch_a_shelf() -> None:
    world = _floor(depot=[[1.0, 0.0, 2.0, 1.0]])  # its top edge is the shelf's bottom edge
    assert world.in_depot(np.array([[1.5, 0.85]]))[0]


def test_in_depot_holds_the_whole_disc() -> None:
    world = _floor()
    pts = np.array([[3.0, 0.5], [2.6, 0.5], [3.0, 0.85], [3.0, 0.86], [0.3, 0.3]])
    assert world.in_depot(pts).tolist() == [True, False, True, False, False]
    assert world.in_depot(pts.reshape(1, 5, 2)).shape == (1, 5)


def test_replace_checks_again() -> None:
    world = _floor()
    moved = replace(world, pickups=np.array([[3.0, 2.5]]))
    assert moved.pickups.tolist() == [[3.0, 2.5]] and moved.stations.tolist() == [[0.3, 0.3]]
    with pytest.raises(ValueError, match=r"pickups\[0\] at \(1.5, 0.8\): inside a shelf"):
        replace(world, obstacles=np.array([[1.0, 0.5, 2.0, 1.5]]))
    # Dropping the floor's points gives a plain world with the same shelves.
    plain = replace(world, pickups=(), stations=(), depot=())
    assert not plain.is_floor and plain.depot.shape == (0, 4)


def test_obstacle_error_names_the_rows() -> None:
    with pytest.raises(ValueError, match=r"xmax > xmin and ymax > ymin \(rows \[1\]"):
        sim.World(obstacles=np.array([[0.0, 0.0, 0.1, 0.1], [0.5, 0.5, 0.4, 0.6]]))


def test_the_bucketed_shelf_distance_equals_obstacle_distance_near_the_shelves() -> None:
    # The point checks measure each point against the shelves of its bucket only (fast on grid
    # maps with thousands of shelves); near a shelf that must be the exact distance.
    gen = np.random.default_rng(7)
    for _ in range(100):
        width, height = gen.uniform(1.0, 8.0, 2)
        lo = gen.uniform([0.0, 0.0], [width, height], (int(gen.integers(1, 30)), 2))
        shelves = np.concatenate([lo, lo + gen.uniform(0.01, 2.0, lo.shape)], axis=1)
        r = gen.uniform(0.02, 0.3)
        if 2 * r >= min(width, height):
            continue
        world = sim.World(bounds=(0.0, 0.0, width, height), obstacles=shelves, agent_radius=r)
        points = gen.uniform([-0.2, -0.2], [width + 0.2, height + 0.2], (300, 2))
        fast, exact = world._near_obstacle_distance(points, r), world.obstacle_distance(points)
        near = exact < r
        np.testing.assert_allclose(fast[near], exact[near], rtol=0, atol=1e-12)
        assert np.all(fast[~near] >= r - 1e-12)
