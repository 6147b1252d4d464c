"""The ``assign`` term of ``IPFReward(assign_weight=...)`` and the batched min-sum assignment
behind it (issue 16): against scipy on random masked problems of every shape, both solver
paths, known values on hand-made scenes, bad values."""

from __future__ import annotations

import math

import pytest
import torch
from scipy.optimize import linear_sum_assignment

import sim
import sim.rewards.assignment as assignment
from sim.rewards import IPFReward
from sim.rewards.assignment import optimal_assignment


def _check_optimal(dist, free, open_, task) -> None:
    for e in range(dist.shape[0]):
        rows = free[e].nonzero().flatten()
        cols = open_[e].nonzero().flatten()
        pairs = [(i, int(task[e, i])) for i in range(dist.shape[1]) if task[e, i] >= 0]
        assert all(bool(free[e, i]) and bool(open_[e, j]) for i, j in pairs)
        assert len({j for _, j in pairs}) == len(pairs) == min(len(rows), len(cols))
        if pairs:
            sub = dist[e][rows][:, cols].numpy()
            r, c = linear_sum_assignment(sub)
            got = sum(float(dist[e, i, j]) for i, j in pairs)
            assert got == pytest.approx(float(sub[r, c].sum()), abs=1e-4)


@pytest.mark.parametrize("limit", [0, assignment.PERMUTATION_LIMIT], ids=["scipy", "batched"])
@pytest.mark.parametrize("n, m", [(1, 1), (3, 3), (4, 2), (2, 4), (3, 4), (6, 6), (9, 5)])
def test_the_assignment_is_a_min_sum_matching_of_maximum_size(n, m, limit, monkeypatch) -> None:
    monkeypatch.setattr(assignment, "PERMUTATION_LIMIT", limit)
    gen = torch.Generator().manual_seed(n * 10 + m)
    dist = torch.rand(64, n, m, generator=gen) * 5
    free = torch.rand(64, n, generator=gen) < 0.7
    open_ = torch.rand(64, m, generator=gen) < 0.7
    task = optimal_assignment(dist, free, open_)
    assert task.shape == (64, n) and task.dtype == torch.int64
    _check_optimal(dist, free, open_, task)


def test_both_paths_agree_on_problems_without_ties(monkeypatch) -> None:
    gen = torch.Generator().manual_seed(1)
    dist = torch.rand(32, 4, 4, generator=gen)
    free, open_ = torch.rand(32, 4, generator=gen) < 0.8, torch.rand(32, 4, generator=gen) < 0.8
    batched = optimal_assignment(dist, free, open_)
    monkeypatch.setattr(assignment, "PERMUTATION_LIMIT", 0)
    assert torch.equal(batched, optimal_assignment(dist, free, open_))


def test_the_assignment_is_not_the_nearest_task() -> None:
    # AGV 0 is nearest task 0 but AGV 1 can only reach task 0 cheaply: 1 + 1 beats 0.5 + 9.
    dist = torch.tensor([[[0.5, 1.0], [1.0, 9.0]]])
    task = optimal_assignment(dist, torch.ones(1, 2, dtype=torch.bool),
                              torch.ones(1, 2, dtype=torch.bool))
    assert task.tolist() == [[1, 0]]


@pytest.mark.parametrize("bad", [math.nan, math.inf, 1e400], ids=["nan", "inf", "huge"])
def test_distances_that_are_not_finite_are_refused(bad) -> None:
    dist = torch.ones(2, 3, 3)
    dist[1, 2, 0] = bad
    mask = torch.ones(2, 3, dtype=torch.bool)
    with pytest.raises(ValueError, match="dist must hold finite distances"):
        optimal_assignment(dist, mask, mask)


def test_masks_must_be_bool() -> None:
    with pytest.raises(ValueError, match="free and open_ must be bool masks, got torch.float32"):
        optimal_assignment(torch.ones(2, 3, 3), torch.ones(2, 3),
                           torch.ones(2, 3, dtype=torch.bool))


def test_empty_problems_and_bad_shapes() -> None:
    assert optimal_assignment(torch.zeros(2, 3, 0), torch.ones(2, 3, dtype=torch.bool),
                              torch.ones(2, 0, dtype=torch.bool)).tolist() == [[-1] * 3] * 2
    with pytest.raises(ValueError, match=r"expected dist \(B, N, M\), free \(B, N\)"):
        optimal_assignment(torch.zeros(2, 3, 3), torch.ones(2, 2, dtype=torch.bool),
                           torch.ones(2, 3, dtype=torch.bool))


def _env(n: int, m: int, reward) -> sim.AGVEnv:
    scenario = sim.Scenario(name="hand", world=sim.World(), num_agents=n, num_tasks=m)
    return sim.AGVEnv(scenario, num_envs=1, reward=reward, seed=0)


def test_each_idle_agv_is_charged_its_distance_to_its_assigned_task() -> None:
    # AGV 0 claims task 0 in the step (0 from then on); AGVs 1 and 2 share tasks 1 and 2, and
    # the assignment sends AGV 1 to task 2, not to its nearest (0.9 + 0.2 beats 0.3 + 1.4).
    env = _env(3, 3, IPFReward(assign_weight=2.0))
    env.set_state(torch.tensor([[[-0.5, -0.5], [0.0, 0.0], [0.0, 0.5]]]),
                  torch.tensor([[[-0.5, -0.5], [0.0, 0.3], [0.0, -0.9]]]))
    _, reward, _, info = env.step(torch.zeros(1, 3, 2))
    terms = {k: v[0] for k, v in info["reward_terms"].items()}
    torch.testing.assert_close(sum(info["reward_terms"].values()), reward)
    dist = torch.cdist(env.agent_pos, env.task_pos)[0]
    assert terms["assign"][0] == 0.0
    torch.testing.assert_close(terms["assign"][1:], -2.0 * torch.stack([dist[1, 2], dist[2, 1]]))


@pytest.mark.parametrize("bad", [-0.1, math.nan, math.inf, True, "1", None],
                         ids=["negative", "nan", "inf", "bool", "str", "None"])
def test_a_bad_assign_weight_is_refused(bad) -> None:
    with pytest.raises(ValueError, match=r"assign_weight must be a finite number >= 0"):
        IPFReward(assign_weight=bad)
