"""The FIFO allocator: each task in turn takes its nearest free AGV (OpenTCS's default)."""

from __future__ import annotations

import numpy as np
import pytest

import allocator
import sim
from allocator.fifo import fifo_matching


def test_tasks_in_order_take_their_nearest_free_agv() -> None:
    cost = np.array([[1.0, 0.5, 9.0], [2.0, 0.4, 0.3]])
    rows, cols = fifo_matching(cost)
    # Task 0 takes AGV 0 (1.0 < 2.0); task 1 then takes AGV 1; task 2 is left unserved.
    assert rows.tolist() == [0, 1] and cols.tolist() == [0, 1]
    rows, cols = fifo_matching(np.array([[np.inf, 1.0], [np.inf, 2.0]]))
    assert rows.tolist() == [0] and cols.tolist() == [1]


def test_fifo_is_a_registry_allocator_on_both_modes() -> None:
    a = allocator.make("fifo")
    result = a.assign([[0.0, 0.0], [1.0, 0.0]], [[0.6, 0.0], [-1.0, 0.0]])
    assert result.task_of_agent.tolist() == [1, 0] and result.method == "fifo"
    m = sim.evaluate_lifelong(a, "warehouse-20", steps=150, seed=0)
    assert m.lost == 0 and m.delivered > 5


def test_fifo_refuses_bad_costs() -> None:
    with pytest.raises(ValueError):
        fifo_matching(np.array([[np.nan]]))
