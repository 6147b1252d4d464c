"""The service's floor and dispatcher from their command-line names (no web imports)."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

__all__ = ["load_world", "make_dispatcher"]


def load_world(floor: str) -> Any:
    """A floor from a file (``.map``/JSON) or a lifelong scenario name."""
    import sim

    if re.fullmatch(r"[A-Za-z][A-Za-z0-9_-]*", floor) and not Path(floor).is_file():
        scen = sim.get_scenario(floor)
        world = getattr(scen, "world", None)
        if world is None or not getattr(world, "is_floor", False):
            raise ValueError(f"--floor {floor}: not a lifelong floor (use a floor file or a "
                             "warehouse-N scenario)")
        return world
    try:
        return sim.load_floor(floor)
    except OSError as err:
        raise ValueError(f"--floor {floor}: {err}") from None


def make_dispatcher(method: str) -> Any:
    """The lifelong dispatcher of an allocator name."""
    import allocator

    try:
        solver = allocator.make(method)
    except (ValueError, TypeError) as err:
        raise ValueError(f"--method {method}: {err}") from None
    make = getattr(solver, "lifelong_dispatcher", None)
    if make is None:
        raise ValueError(f"--method {method}: this allocator has no lifelong dispatcher "
                         "(use hungarian, fifo or greedy)")
    return make()
