"""``benchmarks/shield_stalls.py`` (issue 17's diagnosis of the shield's lost response): its
figures on a hand-made end state, a short run, and bad input."""

from __future__ import annotations

import pytest
import torch
from benchmark_scripts import load

import sim

shield_stalls = load("shield_stalls")


def test_an_idle_agv_pressed_against_a_parked_one_is_counted() -> None:
    scenario = sim.Scenario(name="hand", world=sim.World(), num_agents=3, num_tasks=3)
    env = sim.AGVEnv(scenario, num_envs=1, seed=0)
    # AGV 0 parks on task 0; AGV 1 touches it on its way to task 1; AGV 2 is far from all.
    env.set_state(torch.tensor([[[0.0, 0.0], [0.31, 0.0], [-0.8, 0.8]]]),
                  torch.tensor([[[0.0, 0.0], [-0.8, -0.8], [0.8, -0.8]]]))
    env.step(torch.zeros(1, 3, 2))
    assert env.agent_task[0].tolist()[0] == 0 and env.agent_task[0].tolist()[1:] == [-1, -1]
    intended = torch.tensor([[[0.0, 0.0], [-1.0, 0.0], [1.0, -1.0]]])
    out = shield_stalls.describe(env, intended)
    assert out["idle at the end"] == 2
    assert out["pressed"] == 0.5 and out["against parked"] == 0.5
    assert out["parked around (count: AGVs)"] == [1, 1]
    assert out["response"] == pytest.approx(1 / 3)


def test_a_short_run_prints_both_modes(capsys) -> None:
    shield_stalls.main(["--scenario", "6v6", "--episodes", "4"])
    out = capsys.readouterr().out
    assert "shield=False: {'response'" in out and "shield=True: {'response'" in out


@pytest.mark.parametrize(("flags", "match"), [
    (["--episodes", "0"], r"--episodes must be in \[1, 10000\]"),
    (["--episodes", "10001"], r"--episodes must be in \[1, 10000\]"),
    (["--episodes", "2", "--seed", "-1"], "seed must be an integer"),
    (["--episodes", "2", "--policy", "nope"], "unknown allocator 'nope'"),
    (["--scenario", ""], "unknown scenario ''"),
    (["--scenario", "warehouse-20"], "is lifelong"),
])
def test_bad_input_is_a_clear_error(flags, match) -> None:
    with pytest.raises(ValueError, match=match):
        shield_stalls.main(flags)
