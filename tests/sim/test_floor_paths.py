"""``FloorWaypoints`` with round obstacles (``discs``), as the shield's discs detour uses it."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import sim
from sim.floor_paths import FloorWaypoints


def _box() -> sim.World:
    return sim.get_scenario("20v20").world


def _length(paths: FloorWaypoints, a, b) -> float:
    return float(paths.query(torch.tensor([a]), torch.tensor([b]))[1][0])


def test_a_gap_between_discs_is_open_only_when_wider_than_twice_the_clearance() -> None:
    world = _box()
    discs = np.array([[0.0, 0.35], [0.0, -0.35]])  # 0.7 apart, across the line y = 0
    a, b = [-0.8, 0.0], [0.8, 0.0]
    open_ = FloorWaypoints(world, resolution=0.025, discs=discs, disc_clearance=0.311)
    closed = FloorWaypoints(world, resolution=0.025, discs=discs, disc_clearance=0.36)
    assert _length(open_, a, b) == pytest.approx(1.6, abs=0.05)   # through the gap
    assert _length(closed, a, b) > 1.9                            # round the pair
    assert _length(FloorWaypoints(world, resolution=0.025), a, b) == pytest.approx(1.6, abs=0.05)


def test_waypoints_keep_the_clearance_from_every_disc() -> None:
    world = _box()
    discs = np.array([[0.0, y] for y in np.arange(-0.6, 0.61, 0.3)])  # a wall with no gap
    paths = FloorWaypoints(world, resolution=0.025, lookahead=4, discs=discs,
                           disc_clearance=0.32)
    point, goal = torch.tensor([[-0.8, 0.0]]), torch.tensor([[0.8, 0.0]])
    for _ in range(200):
        wp, _ = paths.query(point, goal)
        step = wp - point
        point = point + step * min(1.0, 0.05 / max(float(step.norm()), 1e-9))
        gap = np.linalg.norm(discs - point.double().numpy(), axis=-1).min()
        assert gap >= 0.32 - 0.025 * 1.5  # cells are free at 0.32; points between them
        if float((point - goal).norm()) < 1e-6:
            break
    assert float((point - goal).norm()) < 1e-6


@pytest.mark.parametrize("discs,clearance,word", [
    (np.zeros((3,)), 0.1, "discs"), (np.zeros((2, 3)), 0.1, "discs"),
    (np.array([[np.nan, 0.0]]), 0.1, "discs"), (np.zeros((1, 2)), -0.1, "disc_clearance"),
    (np.zeros((1, 2)), float("inf"), "disc_clearance"), (np.zeros((1, 2)), "0.3",
                                                         "disc_clearance"),
])
def test_bad_discs_name_the_problem(discs, clearance, word) -> None:
    with pytest.raises(ValueError, match=word):
        FloorWaypoints(_box(), discs=discs, disc_clearance=clearance)


def test_a_clearance_wider_than_the_floor_blocks_every_cell_without_a_huge_window() -> None:
    with pytest.raises(ValueError, match="no cell of this floor holds an AGV"):
        FloorWaypoints(_box(), discs=np.array([[0.0, 0.0]]), disc_clearance=1e300)
    # a disc far off the floor with a wide clearance: the dense check, cells near it blocked
    paths = FloorWaypoints(_box(), resolution=0.025, discs=np.array([[9.0, 0.0]]),
                           disc_clearance=10.0)
    gap = np.linalg.norm(paths._centres - [9.0, 0.0], axis=-1)
    assert np.array_equal(paths._clear_of(np.array([[9.0, 0.0]]), 10.0), gap >= 10.0)
    assert not (gap >= 10.0).all() and (gap >= 10.0).any()


@pytest.mark.parametrize("clearance", [0.0, 0.05, 0.311, 1.0])
def test_free_cells_are_exactly_those_at_the_clearance_from_every_disc(clearance) -> None:
    world = _box()
    rng = np.random.default_rng(3)
    discs = rng.uniform(-2.5, 2.5, (25, 2))  # some beyond the floor's walls (+-1.83)
    paths = FloorWaypoints(world, resolution=0.025, discs=discs, disc_clearance=clearance)
    centres = paths._centres
    gap = np.linalg.norm(centres[:, None] - discs[None], axis=-1).min(1)
    expected = world.is_free(centres) & (gap >= clearance)
    got = np.asarray(paths._graph.sum(1)).ravel() > 0  # cells with a free neighbour
    assert np.array_equal(paths._clear_of(discs, clearance), gap >= clearance)
    assert not (got & ~expected).any()  # no blocked cell joins the graph
