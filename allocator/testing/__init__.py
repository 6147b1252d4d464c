"""Tests that users run on their own allocators, the way PettingZoo ships ``parallel_api_test``.

- :func:`check_allocator`: the conformance check every registry entry passes.
- Assertion helpers with messages that name the AGVs and tasks involved:
  :func:`assert_consistent_plan`, :func:`assert_optimal`, :func:`assert_equivariant`,
  :func:`assert_no_task_served_twice`, :func:`assert_serves_every_reachable_task`.
- Hypothesis strategies :func:`scenes` and :func:`worlds` (imported on first use; they need
  hypothesis, the rest does not).
- A pytest plugin (:mod:`allocator.testing.plugin`, registered as an entry point) with the
  fixtures ``agv_scenario`` and ``agv_world``.
- :func:`skip_or_fail_in_ci` and :func:`make_or_skip` for tests that need shipped files.

>>> import allocator
>>> from allocator.testing import check_allocator
>>> check_allocator(allocator.make("hungarian"), episodes=2, optimal=True, equivariant="both")
"""

from __future__ import annotations

from typing import Any

from allocator.testing.assertions import (
    MAX_BRUTE_FORCE,
    assert_consistent_plan,
    assert_equivariant,
    assert_is_assignment,
    assert_no_task_served_twice,
    assert_optimal,
    assert_serves_every_reachable_task,
)
from allocator.testing.ci import in_ci, make_or_skip, skip_or_fail_in_ci
from allocator.testing.conformance import CASES, check_allocator, check_plans

__all__ = [
    "check_allocator",
    "check_plans",
    "CASES",
    "assert_consistent_plan",
    "assert_optimal",
    "assert_equivariant",
    "assert_no_task_served_twice",
    "assert_serves_every_reachable_task",
    "assert_is_assignment",
    "MAX_BRUTE_FORCE",
    "in_ci",
    "skip_or_fail_in_ci",
    "make_or_skip",
]

_STRATEGIES = ("scenes", "worlds")
"""Imported on first access (they need hypothesis), so ``__all__`` leaves them out."""


def __dir__() -> list[str]:
    return sorted([*globals(), *_STRATEGIES])


def __getattr__(name: str) -> Any:
    if name in _STRATEGIES:
        from allocator.testing import strategies

        return getattr(strategies, name)
    raise AttributeError(f"module 'allocator.testing' has no attribute {name!r}")
