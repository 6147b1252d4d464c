"""Paths around shelves: OMPL (RRTConnect, PRM) and the grid never cross a shelf."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from allocator.paths import GridMap, OMPLPlanner, path_is_free, path_length, segment_clear
from sim.world import World
from tests.allocator.conftest import spaced_points


@pytest.mark.parametrize("kind", ["rrtconnect", "prm"])
def test_ompl_paths_never_cross_a_shelf(shelf_world: World, kind: str) -> None:
    rng = np.random.default_rng(11)
    planner = OMPLPlanner(shelf_world, planner=kind, seed=1)
    starts = spaced_points(rng, 8, shelf_world, 0.3)
    goals = spaced_points(rng, 8, shelf_world, 0.3)
    for s, g in zip(starts, goals, strict=True):
        path = planner.plan(s, g)
        assert path is not None
        np.testing.assert_allclose(path[0], s)
        np.testing.assert_allclose(path[-1], g)
        assert path_is_free(path, shelf_world, shelf_world.agent_radius, step=0.002)
        assert path_length(path) >= np.linalg.norm(g - s) - 1e-9
    assert planner.stats["ompl"] > 0  # some queries needed OMPL, not only straight lines


def test_ompl_is_deterministic_with_a_seed() -> None:
    # OMPL seeds its RNG once per process, so compare two fresh processes.
    code = (
        "import numpy as np; from allocator.paths import OMPLPlanner;"
        "from sim.scenarios import warehouse_world;"
        "p = OMPLPlanner(warehouse_world(), seed=5)"
        ".plan(np.array([-0.95, -1.3]), np.array([-0.95, 0.3]));"
        "print(np.round(p, 9).tolist())"
    )
    runs = [
        subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
        .stdout for _ in range(2)
    ]
    assert runs[0] == runs[1] and runs[0].startswith("[[")


def test_grid_path_and_costs(shelf_world: World) -> None:
    grid = GridMap(shelf_world, 0.05)
    s, g = np.array([-0.95, -1.3]), np.array([-0.95, 0.3])
    assert not segment_clear(s, g, shelf_world, grid.clearance)
    path = grid.path(s, g)
    assert path is not None and path_is_free(path, shelf_world, shelf_world.agent_radius)
    cost = grid.cost_matrix(s[None], g[None])[0, 0]
    assert cost >= np.linalg.norm(g - s)
    assert cost == pytest.approx(path_length(path), rel=0.1)


def test_segment_clear_against_a_box() -> None:
    world = World(obstacles=np.array([[-0.2, -0.2, 0.2, 0.2]]))
    assert not segment_clear(np.array([-0.9, 0.0]), np.array([0.9, 0.0]), world, 0.1)
    assert segment_clear(np.array([-0.9, 0.5]), np.array([0.9, 0.5]), world, 0.1)
    assert not segment_clear(np.array([-0.9, 0.25]), np.array([0.9, 0.25]), world, 0.1)
