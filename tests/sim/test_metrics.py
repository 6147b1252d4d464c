"""The paper's metrics on hand-made episodes whose answer is known."""

import numpy as np
import pytest
import torch

import sim
from sim.evaluate import metrics_from_episodes


def test_metrics_from_known_records() -> None:
    m = metrics_from_episodes(
        claims=np.array([3, 2, 3]), num_tasks=3, steps=np.array([10, 25, 14]),
        finished=np.array([True, False, True]), rewards=np.array([-10.0, -20.0, -30.0]),
        collisions=np.array([0, 2, 1]), task_of_agent=np.array([[0, 1, 2], [1, -1, 0], [2, 0, 1]]),
    )
    assert m.response_rate == pytest.approx(8 / 9)
    assert m.avg_time == pytest.approx(49 / 3)
    assert m.avg_time_finished == pytest.approx(12.0)
    assert m.avg_reward == pytest.approx(-20.0)
    assert m.collisions == pytest.approx(1.0)
    assert m.finished_rate == pytest.approx(2 / 3)
    pref = m.preference_matrix()
    assert pref[0].tolist() == pytest.approx([1 / 3, 1 / 3, 1 / 3])
    assert pref[1].tolist() == pytest.approx([1 / 3, 1 / 3, 0.0])


class _GoTo:
    """Drives every AGV straight at a fixed target per AGV (hand-made episode)."""

    def __init__(self, targets: torch.Tensor) -> None:
        self.targets = targets
        self.env = None

    def reset(self, env: sim.AGVEnv) -> None:
        self.env = env
        env.set_state(torch.tensor([[[-0.5, -0.5], [0.5, -0.5], [0.0, 0.6]]]).expand(
            env.num_envs, 3, 2), self.targets.expand(env.num_envs, 3, 2))

    def act(self, obs: torch.Tensor) -> torch.Tensor:
        return torch.zeros(*obs.shape[:2], 2)


def test_evaluate_known_episode_without_motion() -> None:
    # Nobody moves: no claims, the step limit is reached, R_t is constant and known.
    tasks = torch.tensor([[[-0.5, 0.0], [0.5, 0.0], [0.0, 0.0]]])
    m = sim.evaluate(_GoTo(tasks), "3v3", episodes=4, seed=0)
    assert m.response_rate == 0.0
    assert m.avg_time == 25.0
    assert np.isnan(m.avg_time_finished)
    # Distances to the nearest AGV: 0.5, 0.5 and 0.6 -> R_t = -1.6 for 25 steps.
    assert m.avg_reward == pytest.approx(-1.6 * 25, rel=1e-5)
    assert m.collisions == 0.0


def test_evaluate_known_episode_all_claimed_at_once() -> None:
    # Every task under an AGV: all claimed on the first step, time 1, reward -sum(d).
    tasks = torch.tensor([[[-0.5, -0.45], [0.5, -0.45], [0.0, 0.6]]])
    m = sim.evaluate(_GoTo(tasks), "3v3", episodes=3, seed=0)
    assert m.response_rate == 1.0
    assert m.avg_time == 1.0 and m.avg_time_finished == 1.0
    assert m.avg_reward == pytest.approx(-0.1, rel=1e-5)
    assert m.task_of_agent.tolist() == [[0, 1, 2]] * 3


def test_evaluate_is_seeded_and_batched_consistently() -> None:
    from sim.controllers import NearestTaskController

    a = sim.evaluate(NearestTaskController(), "6v6", episodes=40, seed=3, batch_size=40)
    b = sim.evaluate(NearestTaskController(), "6v6", episodes=40, seed=3, batch_size=40)
    assert a.response_rate == b.response_rate and a.avg_reward == b.avg_reward
    assert a.claims_per_episode.shape == (40,)
    with pytest.raises(ValueError, match="episodes"):
        sim.evaluate(NearestTaskController(), "3v3", episodes=0)
    with pytest.raises(ValueError, match="controller"):
        sim.evaluate(42, "3v3", episodes=2)
