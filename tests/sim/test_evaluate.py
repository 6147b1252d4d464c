"""sim.evaluate: the test scenes do not depend on the batching, and bad input is named."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import sim
from sim.controllers import NearestTaskController
from sim.evaluate import evaluation_scenes


def _zero(obs: torch.Tensor) -> torch.Tensor:
    return torch.zeros(*obs.shape[:2], 2)


def _records(m: sim.Metrics) -> tuple:
    return (m.avg_reward, m.response_rate, m.avg_time, m.collisions,
            m.claims_per_episode.tolist(), m.task_of_agent.tolist(), m.episode_reward.tolist(),
            m.episode_time.tolist())


def test_evaluate_scenes_do_not_depend_on_batch_size() -> None:
    # The example: seed 3 gave -56.05 with the default batch and -57.09 with 7.
    runs = [sim.evaluate(_zero, "6v6", 20, seed=3, batch_size=b) for b in (1, 7, 20, 1024)]
    assert runs[0].avg_reward == pytest.approx(-56.047369873523714, rel=1e-6)
    for m in runs[1:]:
        assert _records(m) == _records(runs[0])


def test_evaluate_metrics_of_a_moving_controller_do_not_depend_on_batch_size() -> None:
    runs = [sim.evaluate(NearestTaskController(), "3v3", 20, seed=5, batch_size=b)
            for b in (1, 7, 20, 1024)]
    assert runs[0].response_rate > 0.5  # claims really happen
    for m in runs[1:]:
        assert m.claims_per_episode.tolist() == runs[0].claims_per_episode.tolist()
        assert m.task_of_agent.tolist() == runs[0].task_of_agent.tolist()
        np.testing.assert_allclose(m.episode_reward, runs[0].episode_reward, rtol=1e-6)


# Today's figures for the default batch size, measured on the code before this change with
#   cd /tmp && PYTHONPATH=/tmp/base python -c "
#   import sim, torch; from sim.controllers import NearestTaskController as C
#   z = lambda obs: torch.zeros(*obs.shape[:2], 2)
#   for c, s, e, seed in [(z, '6v6', 20, 3), (C(), '3v3', 300, 0), (C(), 'warehouse', 50, 1)]:
#       m = sim.evaluate(c, s, e, seed=seed)
#       print(repr(m.avg_reward), m.response_rate, m.avg_time, m.collisions,
#             m.claims_per_episode.sum())"
# The paper tables' calls (300 episodes, batch 1024) keep their scenes exactly.
@pytest.mark.parametrize(
    ("controller", "scenario", "episodes", "seed", "expected"),
    [
        ("zero", "6v6", 20, 3, (-56.047369873523714, 0.0, 25.0, 0.0, 0)),
        ("nearest", "3v3", 300, 0, (-18.284670800281067, 0.9611111111111111,
                                    15.693333333333333, 3.29, 865)),
        ("nearest", "warehouse", 50, 1, (-339.7139931809902, 0.6733333333333333, 78.36,
                                         59.24, 202)),
    ],
)
def test_evaluate_default_batch_keeps_todays_figures(
    controller: str, scenario: str, episodes: int, seed: int, expected: tuple
) -> None:
    ctrl = _zero if controller == "zero" else NearestTaskController()
    m = sim.evaluate(ctrl, scenario, episodes, seed=seed)
    reward, rate, steps, collisions, claims = expected
    assert m.avg_reward == pytest.approx(reward, rel=1e-6)
    assert m.response_rate == pytest.approx(rate, abs=1e-12)
    assert m.avg_time == pytest.approx(steps, abs=1e-12)
    assert m.collisions == pytest.approx(collisions, abs=1e-12)
    assert int(m.claims_per_episode.sum()) == claims


class _Recorder:
    """Records the scenes it sees in reset(env), and stands still."""

    def __init__(self) -> None:
        self.agents: list[torch.Tensor] = []
        self.tasks: list[torch.Tensor] = []

    def reset(self, env: sim.AGVEnv) -> None:
        self.agents.append(env.agent_pos.clone())
        self.tasks.append(env.task_pos.clone())

    def act(self, obs: torch.Tensor) -> torch.Tensor:
        return torch.zeros(*obs.shape[:2], 2)


def test_evaluate_controller_reset_sees_each_chunks_placed_scenes() -> None:
    from sim.evaluate import evaluation_scenes

    rec = _Recorder()
    sim.evaluate(rec, "6v6", 20, seed=3, batch_size=7)
    assert [len(a) for a in rec.agents] == [7, 7, 6]
    agents, tasks = evaluation_scenes(sim.get_scenario("6v6"), 20, 3)
    assert torch.equal(torch.cat(rec.agents), agents)
    assert torch.equal(torch.cat(rec.tasks), tasks)


def test_evaluate_accepts_every_seed_below_2_63() -> None:
    # seed * 1_000_003 used to overflow the generator seed.
    for seed in (2**62, 2**63 - 1):
        m = sim.evaluate(_zero, "3v3", 2, seed=seed)
        assert np.isfinite(m.avg_reward)
    a = sim.evaluate(_zero, "3v3", 2, seed=2**62)
    b = sim.evaluate(_zero, "3v3", 2, seed=2**62 + 1)
    assert a.avg_reward != b.avg_reward


@pytest.mark.parametrize("seed", [None, True, 1.5, "3", -1, 2**63, np.float64(2.0)])
def test_evaluate_rejects_a_bad_seed_by_name(seed: object) -> None:
    with pytest.raises(ValueError, match=r"seed must be an integer in \[0, 2\*\*63\)"):
        sim.evaluate(_zero, "3v3", 2, seed=seed)


def test_evaluate_accepts_numpy_integers() -> None:
    a = sim.evaluate(_zero, "3v3", np.int64(3), seed=np.int32(4), batch_size=np.int64(2))
    b = sim.evaluate(_zero, "3v3", 3, seed=4, batch_size=2)
    assert _records(a) == _records(b)


@pytest.mark.parametrize("batch_size", ["8", True, 8.0, 0, -2, None])
def test_evaluate_rejects_a_bad_batch_size_by_name(batch_size: object) -> None:
    with pytest.raises(ValueError, match="batch_size must be a positive integer"):
        sim.evaluate(_zero, "3v3", 2, batch_size=batch_size)


@pytest.mark.parametrize("episodes", ["8", True, 8.0, 0, None])
def test_evaluate_rejects_bad_episodes_by_name(episodes: object) -> None:
    with pytest.raises(ValueError, match="episodes must be a positive integer"):
        sim.evaluate(_zero, "3v3", episodes)


@pytest.mark.parametrize("scenario", [None, 3, ["3v3"], b"3v3", "bogus"])
def test_evaluate_rejects_a_bad_scenario_by_name(scenario: object) -> None:
    with pytest.raises(ValueError, match="scenario"):
        sim.evaluate(_zero, scenario, 2)


@pytest.mark.parametrize("device", ["bogus", 3, None])
def test_evaluate_rejects_a_bad_device_by_name(device: object) -> None:
    with pytest.raises(ValueError, match="device"):
        sim.evaluate(_zero, "3v3", 2, device=device)


@pytest.mark.skipif(torch.cuda.is_available(), reason="CUDA is available here")
def test_evaluate_rejects_cuda_without_cuda_by_name() -> None:
    with pytest.raises(ValueError, match="device 'cuda' is not usable here"):
        sim.evaluate(_zero, "3v3", 2, device="cuda")


@pytest.mark.parametrize("controller", [42, None, "hungarian"])
def test_evaluate_rejects_a_controller_that_cannot_act(controller: object) -> None:
    with pytest.raises(ValueError, match="controller must have an act"):
        sim.evaluate(controller, "3v3", 2)


def _returns(value: object):
    def controller(obs: torch.Tensor) -> object:
        return value

    return controller


@pytest.mark.parametrize(
    ("value", "what"),
    [
        (None, "returned None"),
        ("left", "returned a str 'left'"),
        ([["left", "right"]], "returned a list"),
        ({"agv_0": [0, 0]}, "returned a dict"),
        (torch.zeros(3, 2), r"shape \(3, 2\)"),
        (np.zeros((2, 3, 3)), r"shape \(2, 3, 3\)"),
        (torch.full((2, 3, 2), float("nan")), "NaN or infinite"),
        (np.full((2, 3, 2), np.inf), "NaN or infinite"),
        (torch.zeros(2, 3, 2, dtype=torch.complex64), "complex64"),
        (torch.zeros(2, 3, 2, dtype=torch.bool), "torch.bool"),
        (np.zeros((2, 3, 2), dtype=complex), "complex128"),
    ],
)
def test_evaluate_names_a_controller_returning_bad_actions(value: object, what: str) -> None:
    with pytest.raises(ValueError, match=r"controller .*controller .*" + what):
        sim.evaluate(_returns(value), "3v3", 2)


def test_evaluate_accepts_actions_that_numpy_reads_as_real_numbers() -> None:
    from_list = sim.evaluate(lambda obs: [[[0, 0]] * 3] * len(obs), "3v3", 2)
    from_tensor = sim.evaluate(_zero, "3v3", 2)
    assert _records(from_list) == _records(from_tensor)


@pytest.mark.parametrize("kwargs, match", [
    ({"scenario": 3}, "scenario"), ({"episodes": 0}, "episodes"), ({"episodes": 2.0}, "episodes"),
    ({"seed": -1}, "seed"), ({"seed": 2**63}, "seed"), ({"device": "gpu"}, "device"),
])
def test_evaluation_scenes_names_a_bad_argument(kwargs: dict, match: str) -> None:
    """The public scene draw passed its arguments straight to the spawner and the generator."""
    args = {"scenario": "3v3", "episodes": 4, "seed": 0, "device": "cpu", **kwargs}
    with pytest.raises(ValueError, match=match):
        evaluation_scenes(**args)


def test_evaluation_scenes_are_the_scenes_evaluate_runs() -> None:
    agents, tasks = evaluation_scenes("3v3", 5, seed=2)
    again, _ = evaluation_scenes(sim.get_scenario("3v3"), 5, seed=2)
    assert agents.shape == (5, 3, 2) and tasks.shape == (5, 3, 2) and torch.equal(agents, again)
