"""Every registry entry passes the shared conformance check of :mod:`allocator.testing`."""

from __future__ import annotations

import pytest

import allocator
from allocator.learned import LIFELONG_ONLY, MissingWeightsError
from allocator.testing import check_allocator, make_or_skip
from sim.world import World

# What each solver promises beyond the common checks: (optimal, equivariant under ...).
# Greedy takes the AGVs in index order, so only a permutation of the tasks leaves it unchanged;
# a learned policy sees its K nearest tasks sorted by distance, whatever their order.
PROMISES = {"hungarian": (True, "both"), "greedy": (False, "tasks"), "fifo": (False, "agents")}
LEARNED_PROMISE = (False, "tasks")


@pytest.mark.parametrize("name", sorted(allocator.ALLOCATORS))
def test_registry_entry_conforms(name: str, shelf_world: World) -> None:
    if name in LIFELONG_ONLY:  # no episodic scenes, so no one-shot assign to check
        with pytest.raises(MissingWeightsError, match="lifelong floors"):
            allocator.make(name, scenario="3v3")
        return
    classical = issubclass(allocator.ALLOCATORS[name], allocator.ClassicalAllocator)
    optimal, equivariant = PROMISES.get(name, LEARNED_PROMISE)
    if classical:
        solver = allocator.make(name)
    else:  # a learned allocator, with the weights shipped for the scenario it was trained on
        solver = make_or_skip(name, scenario="3v3")
    # A centralized solver serves every task it can reach when AGVs suffice, at the cost of its
    # pairs, on the open box and on a shelf floor; a decentralized learned policy promises
    # neither (its unserved tasks carry a reason, its cost counts idle AGVs' travel too) and
    # runs on the floor it was trained on only.
    check_allocator(
        solver,
        scenario="3v3",
        episodes=2,
        complete=classical,
        optimal=optimal,
        equivariant=equivariant,
        world=shelf_world if classical else None,
    )


def test_registry_holds_the_classical_solvers() -> None:
    assert {"hungarian", "greedy"} <= set(allocator.ALLOCATORS)
