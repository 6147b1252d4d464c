"""Shared scenes for the allocator tests."""

from __future__ import annotations

import numpy as np
import pytest

from allocator.testing.plugin import make_world
from sim.world import World


def spaced_points(rng: np.random.Generator, k: int, world: World, gap: float,
                  clearance: float | None = None, avoid: np.ndarray | None = None) -> np.ndarray:
    """k free points of ``world``, at least ``gap`` apart (and from ``avoid``)."""
    xmin, ymin, xmax, ymax = world.bounds
    r = world.agent_radius if clearance is None else clearance
    out: list[np.ndarray] = []
    others = [] if avoid is None else list(avoid)
    for _ in range(20000):
        p = rng.uniform([xmin + r, ymin + r], [xmax - r, ymax - r])
        if not world.is_free(p[None], clearance=r)[0]:
            continue
        if any(np.linalg.norm(p - q) < gap for q in out + others):
            continue
        out.append(p)
        if len(out) == k:
            return np.array(out)
    raise RuntimeError("could not place the points")


@pytest.fixture(scope="session")
def shelf_world() -> World:
    """The shelf warehouse of the ``agv_world`` fixture, shared by the session."""
    return make_world("warehouse")


@pytest.fixture(scope="session")
def open_world() -> World:
    """The open MPE box of the ``agv_world`` fixture, shared by the session."""
    return make_world("open")
